"""The scheduler job this process runs in: who it is, and how many cores it was given.

A SLURM job keeps its id when it is requeued (``scontrol requeue``, a preemption with requeue, submitit's requeue at
the time limit); ``SLURM_RESTART_COUNT`` counts how often it started again. That id, not the clock, is how a job that
starts again finds the run folder it trained in (:mod:`sb3_td3x.experiment.run.folder`).

What its signals make a run do (checkpoint, then requeue or exit) is :mod:`sb3_td3x.experiment.stops`'s.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class Job:
    """A SLURM job, as its environment describes it."""

    scheduler: str
    cluster: str | None
    job_id: str  #: ``SLURM_JOB_ID``: unique per job, and per task of an array
    name: str  #: how squeue and submitit show it: ``<array job>_<task>`` for a task of an array, else the id
    restarts: int  #: ``SLURM_RESTART_COUNT``: 0 the first time, one more each time it starts again

    def record(self) -> dict[str, Any]:
        """What a run folder's provenance keeps of the job."""
        return asdict(self)

    def is_earlier_run_of_this_job(self, record: Any) -> bool:
        """Whether ``record`` (a :meth:`record` read back) was written by this job before it started again."""
        if not isinstance(record, dict):
            return False
        same = (record.get("scheduler"), record.get("cluster"), str(record.get("job_id"))) == (
            self.scheduler,
            self.cluster,
            self.job_id,
        )
        earlier = record.get("restarts")
        return same and isinstance(earlier, int) and earlier < self.restarts


def current_job(environ: dict[str, str] | None = None) -> Job | None:
    """The SLURM job this process runs in, or None outside one."""
    env = os.environ if environ is None else environ
    job_id = env.get("SLURM_JOB_ID")
    if not job_id:
        return None
    array, task = env.get("SLURM_ARRAY_JOB_ID"), env.get("SLURM_ARRAY_TASK_ID")
    try:
        restarts = int(env.get("SLURM_RESTART_COUNT", "0"))
    except ValueError:
        restarts = 0
    return Job("slurm", env.get("SLURM_CLUSTER_NAME"), job_id, f"{array}_{task}" if array and task else job_id, restarts)


def job_cores(environ: dict[str, str] | None = None) -> int | None:
    """The cores SLURM gave this job's task (``--cpus-per-task``, else the job's CPUs on this node); None outside a
    job. On a node shared with other jobs, the affinity mask may show more cores than the job was given."""
    env = os.environ if environ is None else environ
    for name in ("SLURM_CPUS_PER_TASK", "SLURM_CPUS_ON_NODE"):
        try:
            value = int(env.get(name, ""))
        except ValueError:
            continue
        if value >= 1:
            return value
    return None


def available_cores() -> int:
    """The CPUs this process may run on (its affinity mask where the OS has one, as joblib counts them)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def in_submitit_job() -> bool:
    """Whether this process runs a function submitit submitted (its ``process_job`` sets ``SUBMITIT_FOLDER``)."""
    return bool(os.environ.get("SUBMITIT_FOLDER"))
