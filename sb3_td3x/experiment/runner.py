"""The task function: train, evaluate and checkpoint what a composed config describes.

``run.py`` calls :func:`run_experiment` under ``@hydra.main``; the Optuna sweeps call it directly with configs
from ``hydra.compose``. It does not read Hydra's global state: the run folder is ``cfg.run_dir`` (``run.py``
sets it to Hydra's output folder), or ``cfg.resume`` when continuing a run.

It decides where the run starts (:func:`~sb3_td3x.experiment.run.folder.where_to_start`), checks the config, and hands
the training to a :class:`~sb3_td3x.experiment.launch.launcher.Launcher`: :class:`InThisProcess` (one seed, or
``seeds=[...]`` together: :mod:`~sb3_td3x.experiment.run.train`, :mod:`~sb3_td3x.experiment.run.seeds`), or
:class:`~sb3_td3x.experiment.launch.seed_processes.SeedProcesses`.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from sb3_td3x.experiment import jobs
from sb3_td3x.experiment.analysis.statistics import STATISTICS
from sb3_td3x.experiment.configs.compose import check_config
from sb3_td3x.experiment.errors import ConfigError, RunFilesNotWritten
from sb3_td3x.experiment.launch.launcher import Launcher
from sb3_td3x.experiment.launch.seed_processes import SeedProcesses, processes_for
from sb3_td3x.experiment.run.checkpoints import last_step
from sb3_td3x.experiment.run.folder import REQUEUED, RESTARTED, where_to_start
from sb3_td3x.experiment.run.seeds import run_seeds
from sb3_td3x.experiment.run.train import run_one

log = logging.getLogger(__name__)


def run_experiment(
    cfg: DictConfig,
    report: Callable[[int, float], None] | None = None,
    seeds_aggregate: str = "mean",
    report_seeds: Callable[[int, dict[int, float]], None] | None = None,
) -> float:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.total_timesteps`` steps and return the final evaluation mean return.

    Writes to the run folder (``cfg.run_dir``, or ``cfg.resume`` when set): ``config.yaml`` (resolved, without
    credentials), ``evaluations.csv``/``.json``, ``checkpoints/{last,best}``, ``tb/`` (TensorBoard), ``wandb/``,
    ``learning_curve.png``, ``summary.json`` and, with ``video=final``, ``video.gif``.

    With ``cfg.seeds`` (``seeds=[0,1,2]``), the seeds train together (:class:`~sb3_td3x.SeedBatch`; on a CPU in one
    process per core, :mod:`~sb3_td3x.experiment.launch.seed_processes`, unless ``report`` or ``report_seeds`` is given:
    spawned, so a script that calls this does so under ``if __name__ == "__main__":``, or sets ``seed_processes=1``),
    each computing what its lone ``seed=`` run computes and writing the same run folder, at ``cfg.seed_run_dirs``
    (``run.py`` sets them: ``runs/<env>/<algo>/seed<s>/<date>``) or else ``<run_dir>/seed<s>``. The return value is
    then the ``seeds_aggregate`` ("mean" or "iqm") of the seeds' final mean returns.

    :param cfg: a config composed from ``conf/`` (``hydra.compose(config_name="config", overrides=[...])``)
    :param report: called as ``report(num_timesteps, mean_eval_return)`` after every evaluation, including the
        final one (with seeds: once every seed still training has evaluated at that step, with their aggregate); if
        it raises (e.g. ``optuna.TrialPruned``), a checkpoint is written (of every seed), envs and loggers are
        closed and the exception propagates unchanged
    :param report_seeds: with seeds, called as ``report_seeds(num_timesteps, {seed: mean_return})`` before
        ``report``
    :raises ConfigError: the config cannot be run (bad value, unknown id, missing checkpoint); nothing is trained
    :raises TrainingDiverged: a training loss or an evaluation return became NaN or infinite (with seeds: of one
        seed, after the others finished)
    :raises TrainingInterrupted: SIGINT or SIGTERM arrived; a checkpoint was written first
    """
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))  # a private copy; the caller's cfg stays as is
    if cfg.resume is not None:
        cfg.run_dir = str(cfg.resume)
    OmegaConf.resolve(cfg)  # pins ${now:...} and the env defaults once
    start = where_to_start(cfg)  # a requeued job continues its own folder (sb3_td3x.experiment.run.folder)
    if start.how in (REQUEUED, RESTARTED):
        log.info(
            "This job (SLURM job %s) started again after a requeue: %s in %s",
            jobs.current_job().name,  # type: ignore[union-attr]
            "it resumes its run" if start.resume is not None else "its earlier start left no checkpoint, so it starts afresh",
            start.run_dir,
        )
    cfg.run_dir, cfg.resume = str(start.run_dir), (str(start.resume) if start.resume is not None else None)
    if start.seed_run_dirs is not None:
        cfg.seed_run_dirs = [str(d) for d in start.seed_run_dirs]
    check_config(cfg)
    if seeds_aggregate not in STATISTICS:
        raise ConfigError(f"seeds_aggregate={seeds_aggregate!r} must be one of {', '.join(STATISTICS)}")
    if cfg.torch_threads is not None:
        torch.set_num_threads(cfg.torch_threads)
    launch = _launcher(cfg, start.how, report, seeds_aggregate, report_seeds)
    try:
        return launch.run(str(cfg.device), bool(cfg.mps), say=log.info)
    except RunFilesNotWritten as error:
        raise RunFilesNotWritten(_not_written(cfg, str(error))) from error
    except OSError as error:
        if error.errno not in _DISK_ERRORS:
            raise
        raise RunFilesNotWritten(_not_written(cfg, f"writing {error.filename or 'a file'} failed ({error.strerror})")) from error


# Errors of a file system that cannot take more: the run stops with a message instead of a traceback.
_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


def _not_written(cfg: DictConfig, what: str) -> str:
    run_dir = Path(cfg.seed_run_dirs[0] if cfg.seeds is not None else cfg.run_dir)
    step = last_step(run_dir)
    if step is None:
        return f"The run in {run_dir} stopped: {what}. It had written no checkpoint yet: free some space and start it again in a new run_dir."
    return (
        f"The run in {run_dir} stopped: {what}. Its checkpoint of step {step} is whole, so nothing trained before it is "
        f"lost: free some space, then continue with: python run.py resume={run_dir}"
    )


def _launcher(
    cfg: DictConfig,
    how: str,
    report: Callable[[int, float], None] | None,
    statistic: str,
    report_seeds: Callable[[int, dict[int, float]], None] | None,
) -> Launcher:
    """Where the config trains: ``cfg.seeds`` in one process per core (unless a sweep's trial reports: it reports from
    one process), else this process."""
    if cfg.seeds is not None and report is None and report_seeds is None and (processes := processes_for(cfg)) > 1:
        return SeedProcesses(cfg, how, statistic, processes)
    return InThisProcess(cfg, how, report, statistic, report_seeds)


class InThisProcess(Launcher):
    """The run (or ``cfg.seeds``, together in one :class:`~sb3_td3x.SeedBatch`) in this process; :meth:`start` returns
    the final mean return (of the seeds: their ``statistic``)."""

    def __init__(
        self,
        cfg: DictConfig,
        how: str,
        report: Callable[[int, float], None] | None,
        statistic: str,
        report_seeds: Callable[[int, dict[int, float]], None] | None,
    ) -> None:
        self.cfg, self.how, self.report, self.statistic, self.report_seeds = cfg, how, report, statistic, report_seeds

    @property
    def side_by_side(self) -> int:
        return 1

    def start(self) -> float:
        if self.cfg.seeds is not None:
            return run_seeds(self.cfg, self.how, self.report, self.statistic, self.report_seeds)
        return run_one(self.cfg, self.how, self.report)
