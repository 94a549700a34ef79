"""Start sweep workers as cluster jobs with submitit, configured like Hydra's submitit launcher.

A launcher file is a ``hydra/launcher`` config of ``hydra-submitit-launcher`` (``sweeps/launcher/slurm.yaml``,
``sweeps/launcher/local.yaml``): the same ``_target_`` and fields, checked against the plugin's own schema
(``SlurmQueueConf`` / ``LocalQueueConf``) and turned into submitit parameters the way the plugin does. What differs
is what a job runs: not one Hydra job per override combination, but one sweep worker
(:func:`sb3_td3x.sweeps.worker.run_worker`), which takes trials from the shared study until its budget is spent.
Hydra's launcher cannot run that: its jobs never see the Optuna trial, so they could not report or be pruned.

A worker job that SLURM requeues (``scontrol requeue``, a preemption with requeue, or submitit's requeue
``signal_delay_s`` before the time limit, at most ``max_num_timeout`` times) resumes the trial it was training from
the trial folder's checkpoint when it starts again, and only its last start gives submitit a result: ``--wait``
follows each job to its real end (:func:`wait_for_workers`).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sb3_td3x.experiment import stops
from sb3_td3x.experiment.launch.launcher import Launcher
from sb3_td3x.sweeps.errors import SweepSpecError
from sb3_td3x.sweeps.spec import check_readable_file

try:
    from submitit.helpers import Checkpointable
except ImportError:  # without the cluster extra: load_launcher says what to install
    Checkpointable = object  # type: ignore[assignment,misc]

_LAUNCHERS = {
    "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher": "slurm",
    "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher": "local",
}


def load_launcher(path: str | Path, job_folder: Path, job_name: str) -> tuple[str, dict[str, Any]]:
    """Read a launcher file; return the submitit cluster (``slurm`` or ``local``) and its executor parameters.

    :param job_folder: where submitit writes job scripts and logs (``%j`` is the job id)
    :param job_name: the jobs' name in the queue
    """
    source = Path(path)
    try:
        from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf, LocalQueueConf, SlurmQueueConf
    except ImportError:
        raise SweepSpecError("--launcher needs hydra-submitit-launcher: pip install 'sb3-td3x[cluster]'") from None
    check_readable_file(source, "launcher file", "the ready ones are in sweeps/launcher/")
    try:
        loaded = OmegaConf.load(source)
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise SweepSpecError(f"launcher file {source} is not valid YAML: {err}") from None
    except OSError as err:
        raise SweepSpecError(f"launcher file {source} cannot be read: {err.strerror}") from None
    target = loaded.get("_target_") if isinstance(loaded, DictConfig) else None
    if target not in _LAUNCHERS:
        raise SweepSpecError(f"{source}: _target_ must be one of {sorted(_LAUNCHERS)}, as in Hydra's submitit launcher")
    cluster = _LAUNCHERS[target]
    schema = SlurmQueueConf if cluster == "slurm" else LocalQueueConf
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), loaded)
        merged.submitit_folder = str(job_folder / "%j")  # the plugin's defaults interpolate ${hydra:...}
        merged.name = job_name
        params = OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as err:
        raise SweepSpecError(f"{source}: {str(err).splitlines()[0]}") from None
    assert isinstance(params, dict)
    params.pop("_target_")
    # As in hydra_submitit_launcher.submitit_launcher.BaseSubmititLauncher.launch: shared fields keep their
    # names, the cluster's own fields get its prefix (partition -> slurm_partition).
    base = set(OmegaConf.structured(BaseQueueConf).keys())
    executor_params: dict[str, Any] = {"folder": params.pop("submitit_folder")}
    if "max_num_timeout" in params:
        executor_params[f"{cluster}_max_num_timeout"] = params.pop("max_num_timeout")
    executor_params["parameters"] = {key if key in base else f"{cluster}_{key}": value for key, value in params.items()}
    return cluster, executor_params


class WorkerJob(Checkpointable):
    """One sweep worker as a submitit job: ``worker(argv)`` (``python -m sb3_td3x.sweeps <argv>``'s main).
    Checkpointable, so that submitit requeues it at its time limit (what a running trial needs is in its checkpoint
    and in the study)."""

    def __init__(self, worker: Callable[[list[str]], int]) -> None:
        self.worker = worker

    def __call__(self, argv: list[str]) -> int:
        code = self.worker(argv)
        if stops.received() is not None:  # stopped by a signal: SLURM (or submitit) says how the job goes on
            stops.after_stop(code, "The sweep worker stopped on a signal; its trial was queued again.")
        return code


class SweepWorkers(Launcher):
    """``n_workers`` sweep workers as submitit jobs (a :class:`~sb3_td3x.experiment.launch.launcher.Launcher`): local
    processes side by side on this machine, or SLURM jobs that the cluster places. :meth:`start` submits them and
    prints where their logs go; with ``wait`` it follows each to its real end and returns :func:`wait_for_workers`'s
    ends, else None.

    :param worker: what each job runs with ``argv``: the sweep command's main
    :param study_dir: the study's folder (the jobs' logs are in its ``jobs/``)
    """

    def __init__(
        self,
        cluster: str,
        executor_params: dict[str, Any],
        n_workers: int,
        argv: list[str],
        worker: Callable[[list[str]], int],
        wait: bool,
        study_dir: Path,
    ) -> None:
        self.cluster, self.executor_params, self.n_workers, self.argv = cluster, executor_params, n_workers, argv
        self.worker, self.wait, self.study_dir = worker, wait, study_dir
        self.not_waiting = None if wait else "without --wait nothing would stop it (pass --wait)"

    @property
    def side_by_side(self) -> int:
        return self.n_workers if self.cluster == "local" else 0

    def start(self) -> list[dict[str, Any]] | None:
        jobs = submit_workers(self.cluster, self.executor_params, self.n_workers, self.argv, self.worker)
        print(f"submitted {len(jobs)} {self.cluster} worker job(s): {', '.join(str(job.job_id) for job in jobs)}")
        print(f"job logs: {self.study_dir / 'jobs'}; the last worker writes the results into {self.study_dir}")
        if not self.wait:
            return None
        return wait_for_workers(jobs)  # each job to its real end, through requeues


def submit_workers(
    cluster: str, executor_params: dict[str, Any], n_workers: int, argv: list[str], worker: Callable[[list[str]], int]
) -> list[Any]:
    """Submit ``n_workers`` jobs that each run ``worker(argv)``; return submitit's job handles."""
    import submitit

    from sb3_td3x.experiment.launch import job_watch

    job_watch.install()
    params = dict(executor_params)
    parameters = params.pop("parameters")
    executor = submitit.AutoExecutor(cluster=cluster, **params)
    executor.update_parameters(**parameters)
    return executor.map_array(WorkerJob(worker), [list(argv) for _ in range(n_workers)])


def wait_for_workers(jobs: list[Any]) -> list[dict[str, Any]]:
    """Wait for each job's real end (through requeues) and print it; returns :func:`job_watch.job_end` of each."""
    from sb3_td3x.experiment.launch.job_watch import job_end

    ends = []
    for job in jobs:
        end = job_end(job)
        requeued = f", requeued {end['requeued']} time(s)" if end["requeued"] else ""
        outcome = f"exit {end['result']}" if "error" not in end else f"no result: {end['error']}"
        print(f"worker job {end['job']}: {end['state']}{requeued}, {outcome}", file=sys.stdout, flush=True)
        ends.append(end)
    return ends
