"""``run.py``'s jobs, as Hydra launches them: one run in this process, or a multirun's jobs through the Hydra launcher
plugin that ``hydra/launcher`` chooses (``joblib_cores`` by default: conf/hydra/launcher/).

The plugin starts the jobs; this module says what that means for the machine (:class:`HydraJobs`, a
:class:`~sb3_td3x.experiment.launch.launcher.Launcher`): how many jobs run side by side on it, hence their torch
threads and CUDA MPS around the launch. It reads the same launcher config in the process that launches
(``hydra.launcher`` composed before Hydra starts) and in each job (``HydraConfig.get().launcher``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from sb3_td3x.experiment import jobs
from sb3_td3x.experiment.launch.launcher import Launcher, jobs_at_once

#: The plugins' classes (``hydra.launcher._target_``) whose jobs run on this machine, side by side.
JOBLIB = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
SUBMITIT_LOCAL = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
SUBMITIT_SLURM = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"


class HydraJobs(Launcher):
    """The jobs of one ``run.py`` launch.

    :param launcher: the composed ``hydra.launcher`` config (its ``_target_``, ``n_jobs``, ``cpus_per_task``)
    :param multirun: ``-m``: a multirun, whose jobs the plugin starts; else one run in this process
    :param n_runs: how many runs the multirun's sweep makes (the product of its overrides' values)
    :param main: what starts them: Hydra's main function
    """

    def __init__(self, launcher: Any, multirun: bool, n_runs: int = 1, main: Callable[[], Any] | None = None) -> None:
        self.target = str(launcher.get("_target_", ""))
        self.n_jobs = launcher.get("n_jobs")
        self.cpus_per_task = launcher.get("cpus_per_task")
        self.multirun = multirun
        self.n_runs = n_runs
        self.main = main

    @property
    def side_by_side(self) -> int:
        if not self.multirun:
            return 1
        if self.target == JOBLIB:
            return min(self.n_runs, jobs_at_once(int(self.n_jobs), jobs.available_cores()))
        if self.target == SUBMITIT_LOCAL:
            return self.n_runs  # submitit's local executor starts every job at once
        if self.target == SUBMITIT_SLURM:
            return 0  # the cluster places them (docs/cluster.md: ask SLURM for MPS there)
        return 1  # Hydra's basic launcher: one job after the other

    def threads_per_process(self, cores: int) -> int | None:
        """A job's torch threads when its config leaves ``torch_threads`` unset (docs/experiments.md): in a SLURM job
        the cores it was given (``--cpus-per-task``); where the launcher says its cores per job (``cpus_per_task`` of
        submitit's launchers), those; in a joblib multirun the machine's cores shared among the jobs that run at once;
        else None: torch's default, every core, for a single run."""
        given = jobs.job_cores()
        if given is not None:
            return given
        if not self.multirun:
            return None
        if self.cpus_per_task is not None:
            return int(self.cpus_per_task)
        if self.target == JOBLIB:
            return threads_per_job(int(self.n_jobs), cores)
        return None

    def start(self) -> Any:
        assert self.main is not None, "HydraJobs(main=...) starts the jobs"
        return self.main()


def threads_per_job(n_jobs: int | None, cores: int) -> int | None:
    """Torch threads for one job of a joblib multirun: the cores shared among the jobs that run at once.

    :param n_jobs: the launcher's ``n_jobs`` (joblib's meaning: -1 one job per core, -2 all cores but one, ...), or
        None for a launcher that runs one job at a time (Hydra's basic launcher)
    :return: the thread count, or None to leave torch's default (all cores) when jobs do not run side by side
    """
    if n_jobs is None:
        return None
    return max(1, cores // jobs_at_once(n_jobs, cores))
