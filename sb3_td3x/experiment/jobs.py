"""The scheduler job this process runs in: who it is, how many cores it was given, and what its signals mean.

A SLURM job keeps its id when it is requeued (``scontrol requeue``, a preemption with requeue, submitit's requeue at
the time limit); ``SLURM_RESTART_COUNT`` counts how often it started again. That id, not the clock, is how a job that
starts again finds the run folder it trained in (:mod:`sb3_td3x.experiment.run_folder`).

Signals (docs/cluster.md):

- SIGTERM: SLURM sends it before it kills a job that is cancelled, preempted or requeued (then SIGKILL after the
  cluster's ``KillWait``, 30 s by default). The run checkpoints at its next rollout boundary and exits with 143.
  Inside a SLURM job it leaves no result for submitit to collect: the scheduler says how the job ends (started
  again after a requeue, or CANCELLED), and whoever waits on it follows it there.
- submitit's signal (``SIGUSR2`` unless ``SUBMITIT_PREEMPT_SIGNAL`` says otherwise): sent ``signal_delay_s`` before
  the time limit (or by ``scancel --signal=USR2``). The run checkpoints first, then hands over to submitit's own
  handler, which resubmits the job's function and requeues the job, at most ``max_num_timeout`` times for a time-out.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
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


def requeue_signal() -> signal.Signals | None:
    """submitit's time-out and preemption signal, in a function submitit runs on SLURM; None elsewhere."""
    if not in_submitit_job() or current_job() is None:
        return None
    return getattr(signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2"), None)


def stop_signals() -> tuple[signal.Signals, ...]:
    """The signals that make a run checkpoint and stop: SIGINT, SIGTERM, and submitit's in a submitit job."""
    extra = requeue_signal()
    return (signal.SIGINT, signal.SIGTERM) + ((extra,) if extra is not None else ())


class _Stops:
    """What this process was told to do by a signal, for the job's top level to act on once its checkpoint is written."""

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self.scheduler_handler: Callable[[int, Any], Any] | None = None  # submitit's, replaced by ours


_stops = _Stops()


def keep_handler(signum: int, handler: Any) -> None:
    """Called with the handler ours replaced: submitit's handler of its signal is kept, to hand over to later."""
    if signum == requeue_signal() and callable(handler) and not getattr(handler, "_sb3_td3x", False):
        _stops.scheduler_handler = handler


def ours(handler: Callable[..., Any]) -> Callable[..., Any]:
    """Mark a signal handler (a function, or the function of a method) as this package's, so that
    :func:`keep_handler` never keeps one of ours."""
    handler._sb3_td3x = True  # type: ignore[attr-defined]
    return handler


def note_signal(signum: int) -> None:
    """A stop signal arrived (the first one counts)."""
    if _stops.received is None:
        _stops.received = signal.Signals(signum)


def received() -> signal.Signals | None:
    return _stops.received


def killed_by_its_own_requeue(error: subprocess.CalledProcessError) -> bool:
    """Whether ``error`` is submitit's ``scontrol requeue`` killed by SIGTERM or SIGKILL (what SLURM sends to the
    processes of a job it requeues)."""
    command = [str(part) for part in error.cmd] if isinstance(error.cmd, (list, tuple)) else str(error.cmd).split()
    return command[:2] == ["scontrol", "requeue"] and error.returncode in (-signal.SIGTERM, -signal.SIGKILL)


def after_stop(exit_code: int, message: str) -> None:
    """The top level of a run or a sweep worker stopped on a signal, its checkpoint written: end the process.

    - submitit's signal: hand over to submitit's handler, which resubmits the function and requeues the job (or,
      after ``max_num_timeout`` time-outs, ends it with an error); it exits this process. Its ``scontrol requeue``
      stopped by the requeue's own SIGTERM exits this process too, without a result.
    - SIGTERM or SIGINT inside a SLURM job: exit without a result (``SystemExit``), so that submitit reads the
      result of the job that SLURM starts again after a requeue, or sees a cancelled job end without one.
    - otherwise: return; the caller exits as it always did.
    """
    got = _stops.received
    if got is None:
        return
    if got == requeue_signal() and _stops.scheduler_handler is not None:
        print(f"{message} Handing over to submitit to requeue the job.", file=sys.stderr, flush=True)
        try:
            _stops.scheduler_handler(int(got), None)
        except subprocess.CalledProcessError as error:
            if not killed_by_its_own_requeue(error):
                raise
            # SLURM signals every process of a job it requeues, submitit's `scontrol requeue` among them when it has
            # not returned yet (seen on a loaded machine): the requeue was taken. submitit would raise, and its
            # process_job would write that error as the job's result, which whoever waits on the job reads as its
            # end. Exit without a result instead, as submitit does after a requeue: the job's next start writes it.
            print(
                f"`{' '.join(map(str, error.cmd))}` was stopped by {signal.Signals(-error.returncode).name}, as SLURM "
                "stops every process of a job it requeues: the job is requeued (or, at its time limit, ended); this "
                "start exits without a result.",
                file=sys.stderr,
                flush=True,
            )
            raise SystemExit(-1) from None
        return
    if current_job() is not None:
        print(message, file=sys.stderr, flush=True)
        raise SystemExit(exit_code)

