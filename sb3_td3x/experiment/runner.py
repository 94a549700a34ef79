"""The task function: train, evaluate and checkpoint one run described by a composed config.

``run.py`` calls :func:`run_experiment` under ``@hydra.main``; the Optuna sweeps call it directly with configs
from ``hydra.compose``. It does not read Hydra's global state: the run folder is ``cfg.run_dir`` (``run.py``
sets it to Hydra's output folder), or ``cfg.resume`` when continuing a run.
"""

from __future__ import annotations

import errno
import logging
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from sb3_td3x.common.random_streams import RandomStreams, detached_streams
from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment import jobs
from sb3_td3x.experiment.algos import algorithm_class, build_algorithm
from sb3_td3x.experiment.callbacks import (
    Checkpointer,
    DivergenceCheck,
    PeriodicEvaluation,
    ProgressBar,
    StopOnSignal,
)
from sb3_td3x.experiment.checkpoints import (
    LAST,
    checkpoint_dir,
    find_checkpoint,
    load_checkpoint,
    load_resumable,
)
from sb3_td3x.experiment.envs import make_eval_env, make_train_env
from sb3_td3x.experiment.errors import ConfigError, RunFilesNotWritten, TrainingDiverged, TrainingInterrupted
from sb3_td3x.experiment.loggers import build_logger, start_wandb
from sb3_td3x.experiment.plotting import LEARNING_CURVE_PNG, plot_learning_curve, record_video
from sb3_td3x.experiment.resume import check_resume, saved_config
from sb3_td3x.experiment.run_folder import (
    CONFIG_FILE,
    NEW,
    REQUEUED,
    RESTARTED,
    RUN_LOG,
    RunFolder,
    checkpoint_step,
    seed_run_dirs,
    where_to_start,
)
from sb3_td3x.experiment.schemas import check_config, public_config
from sb3_td3x.experiment.statistics import STATISTICS, seed_statistic
from sb3_td3x.td3x.seed_batch import SeedBatch, acting_as, current_seed

log = logging.getLogger(__name__)

LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"  # Hydra's, as run.py's own lines



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
    process per core, :mod:`~sb3_td3x.experiment.seed_processes`, unless ``report`` or ``report_seeds`` is given:
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
    start = where_to_start(cfg)  # a requeued job continues its own folder (sb3_td3x.experiment.run_folder)
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
    try:
        if cfg.seeds is not None:
            if report is None and report_seeds is None:  # a sweep's trial reports from one process
                from sb3_td3x.experiment.seed_processes import processes_for, run_in_processes

                if (processes := processes_for(cfg)) > 1:
                    return run_in_processes(cfg, start.how, seeds_aggregate, processes)
            return _run_seeds(cfg, start.how, report, seeds_aggregate, report_seeds)
        return _run_one(cfg, start.how, report)
    except RunFilesNotWritten as error:
        raise RunFilesNotWritten(_not_written(cfg, str(error))) from error
    except OSError as error:
        if error.errno not in _DISK_ERRORS:
            raise
        raise RunFilesNotWritten(_not_written(cfg, f"writing {error.filename or 'a file'} failed ({error.strerror})")) from error


# Errors of a file system that cannot take more: the run stops with a message instead of a traceback.
_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


def _not_written(cfg: DictConfig, what: str) -> str:
    run_dir = seed_run_dirs(cfg)[0] if cfg.seeds is not None else Path(cfg.run_dir)
    step = checkpoint_step(find_checkpoint(checkpoint_dir(run_dir, LAST)))
    if step is None:
        return f"The run in {run_dir} stopped: {what}. It had written no checkpoint yet: free some space and start it again in a new run_dir."
    return (
        f"The run in {run_dir} stopped: {what}. Its checkpoint of step {step} is whole, so nothing trained before it is "
        f"lost: free some space, then continue with: python run.py resume={run_dir}"
    )


def _run_one(cfg: DictConfig, how: str, report: Callable[[int, float], None] | None) -> float:
    run = _prepare(cfg, how)
    try:
        if report is not None:
            run.evaluation.listeners.append(_reporting(report, run.checkpointer))
        if run.remaining > 0:
            with StopOnSignal(run.checkpointer):
                run.model.learn(
                    total_timesteps=run.remaining,
                    callback=run.callbacks,
                    log_interval=cfg.logger.log_interval,
                    reset_num_timesteps=run.resume_from is None,
                )
        return _finish(run)
    finally:
        _close(run)


@dataclass
class _Run:
    """One seed's run, up to ``learn()``: what :func:`_finish` and :func:`_close` need."""

    cfg: DictConfig
    run_dir: Path
    started: float
    closers: list[Callable[[], object]] = field(default_factory=list)
    folder: RunFolder | None = None
    resume_from: Path | None = None
    model: Any = None
    evaluation: PeriodicEvaluation | None = None
    checkpointer: Checkpointer | None = None
    progress: ProgressBar | None = None
    callbacks: list[Any] = field(default_factory=list)
    remaining: int = 0
    run_name: str = ""
    succeeded: bool = False
    trained_together: list[int] | None = None  # the seeds of its process's SeedBatch


def _prepare(cfg: DictConfig, how: str) -> _Run:
    """Everything a run does before ``model.learn``: own the folder, build or load the model, then (once the
    checkpoint has loaded and the config is accepted) the records, loggers and callbacks. On an error, what was
    opened is closed and nothing of the run's records has been written.

    :param how: how the run starts in its folder (:func:`~sb3_td3x.experiment.run_folder.where_to_start`): a new
        run refuses a folder that holds a run; ``RESTARTED`` starts afresh in a folder whose earlier session left no
        checkpoint (a requeued job, or a seed of a resumed batch, stopped before its first checkpoint)
    """
    run = _Run(cfg, Path(cfg.run_dir), time.time())
    run.folder = RunFolder.claim(run.run_dir, how)
    try:
        config = public_config(cfg)
        train_env = make_train_env(cfg.env, cfg.n_envs, cfg.seed)
        run.closers.append(train_env.close)
        eval_env = make_eval_env(cfg.env)
        run.closers.append(eval_env.close)
        experiment_state, session = _model(run, config, train_env)
        model = run.model
        run.folder.start_session(config, model.num_timesteps, session, provenance())
        run.run_name = f"{cfg.env.name}_{cfg.algo.name}_seed{cfg.seed}"
        _loggers(run, config)
        _callbacks(run, eval_env, config, experiment_state)
        log.info(
            "Training %s (%s) on %s for %d steps, seed %d, device %s; run folder: %s",
            type(model).__name__,
            cfg.algo.name,
            cfg.env.id,
            cfg.total_timesteps,
            cfg.seed,
            model.device,
            run.run_dir,
        )
        run.remaining = cfg.total_timesteps - model.num_timesteps
        return run
    except BaseException:
        _close(run)
        raise


def _model(run: _Run, config: dict[str, Any], train_env: Any) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """Build the model, or load it from the run's newest whole checkpoint and check the config against the one it
    trained with. Returns the experiment state to restore and what this session's provenance line adds."""
    cfg = run.cfg
    if cfg.resume is None:
        check_buffer_fits(cfg, train_env)
        run.model = build_algorithm(cfg, train_env)
        _warn_never_trains(cfg)
        return None, {}
    cls = algorithm_class(cfg.algo)
    resumed = load_resumable(run.run_dir, lambda path: load_checkpoint(path, cls, train_env, cfg.device))
    run.model, run.resume_from = resumed.model, checkpoint_dir(run.run_dir, LAST)
    changes = check_resume(saved_config(run.run_dir, run.resume_from, CONFIG_FILE), config, run.run_dir)
    log.info("Resuming %s at step %d from %s", run.run_dir, run.model.num_timesteps, resumed.path)
    for key, change in changes.items():
        log.info("Changed on resume, from step %d: %s = %r (was %r)", run.model.num_timesteps, key, change["to"], change["from"])
    _warn_never_trains(cfg)
    session: dict[str, Any] = {"resumed_from": str(resumed.path.relative_to(run.run_dir))}
    if changes:
        session["changes"] = changes
    if resumed.skipped:
        session["skipped_checkpoints"] = {str(path.relative_to(run.run_dir)): why for path, why in resumed.skipped}
    return resumed.experiment_state, session


def _warn_never_trains(cfg: DictConfig) -> None:
    if cfg.algo.learning_starts >= cfg.total_timesteps:
        log.warning(
            "algo.learning_starts=%d >= total_timesteps=%d: the whole run takes uniformly random actions and never "
            "trains. Lower algo.learning_starts or raise total_timesteps.",
            cfg.algo.learning_starts,
            cfg.total_timesteps,
        )


def _loggers(run: _Run, config: dict[str, Any]) -> None:
    cfg = run.cfg
    wandb_run = start_wandb(cfg.logger.wandb, run.run_dir, run.run_name, config) if cfg.logger.wandb is not None else None
    if wandb_run is not None:
        run.closers.append(lambda: wandb_run.finish(exit_code=0 if run.succeeded else 1))
    logger = build_logger(cfg.logger, run.run_dir, wandb_run)
    run.closers.insert(0, logger.close)
    run.model.set_logger(logger)


def _callbacks(run: _Run, eval_env: Any, config: dict[str, Any], experiment_state: dict[str, Any] | None) -> None:
    cfg = run.cfg
    run.progress = ProgressBar(cfg.total_timesteps, run.run_name) if cfg.progress_bar else None
    if run.progress is not None:
        run.closers.insert(0, run.progress.close)
    evaluation = run.evaluation = PeriodicEvaluation(
        eval_env,
        run.run_dir,
        cfg.eval.freq,
        cfg.eval.n_episodes,
        cfg.seed + cfg.eval.seed_offset,
        cfg.eval.deterministic,
        value_bias=cfg.eval.value_bias,
        value_horizon_tolerance=cfg.eval.value_horizon_tolerance,
    )
    checkpointer = run.checkpointer = Checkpointer(
        run.run_dir,
        cfg.checkpoint.freq,
        experiment_state=lambda: {"evaluation": evaluation.state_dict()},
        save_best=cfg.checkpoint.save_best,
        best_replay_buffer=cfg.checkpoint.best_replay_buffer,
        config=config,
    )
    if experiment_state is not None:
        evaluation.load_state_dict(experiment_state["evaluation"])
        checkpointer.best_mean_return = evaluation.best_mean_return
    evaluation.listeners.append(checkpointer.on_evaluation)
    if run.progress is not None:
        evaluation.listeners.append(run.progress.on_evaluation)
    run.callbacks = [DivergenceCheck(), evaluation, checkpointer] + ([run.progress] if run.progress is not None else [])


def check_buffer_fits(cfg: DictConfig, env: Any) -> None:
    """A :class:`ConfigError` when the replay buffer alone would need more memory than the machine has."""
    import numpy as np
    from gymnasium import spaces

    def nbytes(space: Any) -> int:
        if isinstance(space, spaces.Dict):
            return sum(nbytes(sub) for sub in space.spaces.values())
        return int(np.prod(space.shape or (1,))) * np.dtype(space.dtype or np.float32).itemsize

    per_transition = nbytes(env.observation_space) * (1 if cfg.algo.optimize_memory_usage else 2)
    per_transition += nbytes(env.action_space) + 3 * 4  # rewards, dones, timeouts
    needed = int(cfg.algo.buffer_size) * per_transition
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not a POSIX system: nothing to compare with
        return
    if needed > memory:
        raise ConfigError(
            f"algo.buffer_size={cfg.algo.buffer_size} needs about {needed / 2**30:.1f} GiB for the replay buffer "
            f"({per_transition} bytes per transition of {cfg.env.id}), more than this machine's {memory / 2**30:.1f} GiB "
            "of memory. Lower algo.buffer_size (the paper's is 1000000)."
        )


def _finish(run: _Run) -> float:
    """After ``learn``: ``summary.json``, the video, the last log line. Returns the final mean return."""
    cfg, evaluation, model = run.cfg, run.evaluation, run.model
    assert evaluation is not None
    if run.progress is not None:
        run.progress.close()  # before the last log lines
    if not evaluation.history:
        raise RuntimeError("The run ended without any evaluation")  # learn() always evaluates at its end
    final = evaluation.history[-1]
    summary = {
        "env_id": cfg.env.id,
        "algo": cfg.algo.name,
        "seed": cfg.seed,
        "total_timesteps": int(final["timesteps"]),
        "final_mean_return": final["mean_return"],
        "final_std_return": final["std_return"],
        "best_mean_return": evaluation.best_mean_return,
        # How TD3X's update ran and why (sb3_td3x.td3x.update_paths.choose, or the seed batch's); None for SB3's TD3
        "update_path": getattr(model, "update_path", None),
        "update_reason": getattr(model, "update_reason", None),
        "exploration_path": getattr(model, "exploration_path", None),
        "wall_time_s_this_session": time.time() - run.started,
        "provenance": provenance(),
    }
    if cfg.seeds is not None:
        summary["trained_with_seeds"] = list(cfg.seeds)  # launched together (seeds=[...])
        summary["trained_together"] = run.trained_together  # in one process, one sb3_td3x.SeedBatch
    assert run.folder is not None
    run.folder.write_summary(summary)
    if cfg.video is not None:
        path = record_video(
            model, cfg.env, cfg.video, run.run_dir / f"video.{cfg.video.format}", cfg.seed + cfg.eval.seed_offset
        )
        log.info("Video of the final policy: %s", path)
    log.info(
        "Done: final evaluation %.2f ± %.2f at step %d (best %.2f). Run folder: %s",
        final["mean_return"],
        final["std_return"],
        final["timesteps"],
        evaluation.best_mean_return,
        run.run_dir,
    )
    run.succeeded = True
    return float(final["mean_return"])


def _close(run: _Run) -> None:
    for close in run.closers:
        try:
            close()
        except Exception as error:  # a failing close must not hide the exception that ended the run
            log.warning("Closing %s failed: %s", close, error)
    run.closers = []
    if run.evaluation is not None and run.evaluation.history:
        try:
            plot_learning_curve(
                run.evaluation.history,
                run.run_dir / LEARNING_CURVE_PNG,
                f"{run.cfg.algo.name} on {run.cfg.env.id}, seed {run.cfg.seed}",
            )
        except OSError as error:  # a full disk: the curve is in evaluations.csv, and the error that ended the run goes on
            log.warning("The learning curve could not be drawn: %s", error)
    if run.folder is not None:
        run.folder.release()
        run.folder = None


# Many seeds in one process ------------------------------------------------------------------------------------------
class _SeedReports:
    """The evaluations of a batch's seeds, step by step: ``report`` gets their aggregate once every seed still
    training has evaluated at a step. When ``report`` raises, every seed is asked to stop: each checkpoints at its
    next rollout boundary, with its own random state (as a signal would), and the exception is kept for the caller."""

    def __init__(
        self,
        seeds: list[int],
        runs: list[_Run],
        statistic: str,
        report: Callable[[int, float], None] | None,
        report_seeds: Callable[[int, dict[int, float]], None] | None,
    ) -> None:
        self.seeds, self.runs, self.statistic = seeds, runs, statistic
        self.report, self.report_seeds = report, report_seeds
        self.pending: dict[int, dict[int, float]] = {}
        self.training: set[int] = set()
        self.error: BaseException | None = None
        self.interrupted = False

    def listener(self, index: int) -> Callable[[dict[str, float]], None]:
        return lambda result: self.on_result(index, result)

    def stopped(self, index: int, error: BaseException) -> None:
        """Seed ``index`` stopped early. Diverged (or failed): the aggregates go on over the others. Interrupted (a
        signal, or ``report`` raised): the whole batch is stopping, so no aggregate of the seeds that evaluated
        before the others stopped is reported."""
        if isinstance(error, TrainingInterrupted):
            self.interrupted = True
            return
        self.training.discard(index)
        self._flush()

    def on_result(self, index: int, result: dict[str, float]) -> None:
        self.pending.setdefault(int(result["timesteps"]), {})[index] = float(result["mean_return"])
        self._flush()

    def _flush(self) -> None:
        if self.interrupted:
            return
        for step in sorted(self.pending):
            values = self.pending[step]
            if not self.training or not self.training <= values.keys():
                return
            del self.pending[step]
            if self.error is not None:
                continue
            per_seed = {self.seeds[i]: values[i] for i in sorted(values)}
            try:
                if self.report_seeds is not None:
                    self.report_seeds(step, per_seed)
                if self.report is not None:
                    self.report(step, seed_statistic(self.statistic, list(per_seed.values())))
            except BaseException as error:
                self.error = error
                for run in self.runs:
                    assert run.checkpointer is not None
                    run.checkpointer.request_stop(f"report ({type(error).__name__})", 0)


def _run_seeds(
    cfg: DictConfig,
    how: str,
    report: Callable[[int, float], None] | None,
    statistic: str,
    report_seeds: Callable[[int, dict[int, float]], None] | None,
) -> float:
    """``cfg.seeds`` trained together: each seed's run prepared as its lone run is (folder, envs, model, callbacks),
    then one :class:`~sb3_td3x.SeedBatch` learns them all; each seed's folder is finished as a lone run's."""
    seeds, dirs = [int(s) for s in cfg.seeds], seed_run_dirs(cfg)
    check_batch_resumable(cfg, dirs)
    finals, errors = train_seed_group(cfg, how, list(range(len(seeds))), statistic, report, report_seeds)
    return end_of_batch(seeds, dirs, finals, errors, statistic)


def check_batch_resumable(cfg: DictConfig, dirs: list[Path]) -> None:
    """A resumed batch needs a checkpoint in one of its seeds' folders at least (a seed without one starts afresh)."""
    if cfg.resume is not None and not any(find_checkpoint(checkpoint_dir(d, LAST)) for d in dirs):
        raise ConfigError(
            f"resume={cfg.resume}: none of the batch's seed folders ({', '.join(map(str, dirs))}) has a checkpoint, "
            "so there is nothing to resume; start the batch again without resume=."
        )


def end_of_batch(
    seeds: list[int], dirs: list[Path], finals: dict[int, float], errors: dict[int, BaseException], statistic: str
) -> float:
    """What stopped a seed, raised (:func:`_raise_first`); else the seeds' aggregate, logged with its table."""
    _raise_first(errors, seeds, dirs)
    value = seed_statistic(statistic, list(finals.values()))
    _log_seed_aggregate(dirs, seeds, finals, statistic, value)
    return value


def train_seed_group(
    cfg: DictConfig,
    how: str,
    indices: list[int],
    statistic: str = "mean",
    report: Callable[[int, float], None] | None = None,
    report_seeds: Callable[[int, dict[int, float]], None] | None = None,
) -> tuple[dict[int, float], dict[int, BaseException]]:
    """The seeds ``cfg.seeds[i]`` for ``i`` in ``indices`` trained together in this process (one
    :class:`~sb3_td3x.SeedBatch`), each in its folder of ``seed_run_dirs(cfg)``, each folder finished as a lone
    run's. Every seed's ``config.yaml`` lists all of ``cfg.seeds`` and their folders, so that ``resume=`` of any
    continues them all. Returns each finished seed's final mean return and what stopped each other one (keyed by
    seed); raises what ``report`` raised."""
    all_seeds, all_dirs = [int(s) for s in cfg.seeds], seed_run_dirs(cfg)
    seeds, dirs = [all_seeds[i] for i in indices], [all_dirs[i] for i in indices]
    runs: list[_Run] = []
    handlers: list[logging.Handler] = []
    caller = RandomStreams().state()
    try:
        streams = _prepare_seeds(cfg, how, seeds, dirs, all_dirs, runs, handlers)
        RandomStreams().set_state(caller)
        reports = _SeedReports(seeds, runs, statistic, report, report_seeds)
        for index, run in enumerate(runs):
            assert run.evaluation is not None
            run.evaluation.listeners.append(reports.listener(index))
        errors = _train_seeds(cfg, runs, streams, seeds, reports)
        if reports.error is not None:
            raise reports.error
        finals = {}
        for index, run in enumerate(runs):
            if index not in errors:
                with acting_as(index):
                    finals[seeds[index]] = _finish(run)
        return finals, {seeds[index]: error for index, error in errors.items()}
    finally:
        RandomStreams().set_state(caller)
        for run in runs:
            _close(run)
        for handler in handlers:
            logging.getLogger().removeHandler(handler)
            handler.close()


def _prepare_seeds(
    cfg: DictConfig,
    how: str,
    seeds: list[int],
    dirs: list[Path],
    all_dirs: list[Path],
    runs: list[_Run],
    handlers: list[logging.Handler],
) -> list[RandomStreams]:
    """Each seed's run prepared as its lone run is (into ``runs``, its log file into ``handlers``); returns each
    model's random streams, detached where its lone run stands when it calls learn(). A seed of a batch that
    continues (resumed, or requeued) but has no checkpoint starts afresh in its folder."""
    streams = []
    for index, (seed, run_dir) in enumerate(zip(seeds, dirs)):
        seed_cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
        seed_cfg.seed, seed_cfg.run_dir = seed, str(run_dir)
        seed_cfg.seed_run_dirs = [str(d) for d in all_dirs]
        resumes = cfg.resume is not None and find_checkpoint(checkpoint_dir(run_dir, LAST)) is not None
        if cfg.resume is not None and not resumes:
            log.warning("Seed %d has no checkpoint in %s: it starts from the beginning (as its lone run would).", seed, run_dir)
        seed_cfg.resume = str(run_dir) if resumes else None
        if (handler := _seed_log_file(run_dir, index)) is not None:
            handlers.append(handler)
        with acting_as(index):
            runs.append(_prepare(seed_cfg, how if resumes else (NEW if how == NEW else RESTARTED)))
            runs[-1].trained_together = list(seeds)
            streams.append(detached_streams(runs[-1].model))
    return streams


def _train_seeds(
    cfg: DictConfig, runs: list[_Run], streams: list[RandomStreams], seeds: list[int], reports: _SeedReports
) -> dict[int, BaseException]:
    """The seeds with steps left trained by one SeedBatch; returns seed index -> what stopped it."""
    training = [i for i, run in enumerate(runs) if run.remaining > 0]
    reports.training = set(training)
    if not training:
        return {}
    batch = SeedBatch.from_models(
        [runs[i].model for i in training], [streams[i] for i in training], [seeds[i] for i in training]
    )
    if len(training) > 1:
        log.info("Training seeds %s together in one process, each with its own update", [seeds[i] for i in training])
    with StopOnSignal(*[runs[i].checkpointer for i in training]):  # type: ignore[misc]
        batch.learn(
            total_timesteps=[runs[i].remaining for i in training],
            callback=[runs[i].callbacks for i in training],
            log_interval=cfg.logger.log_interval,
            reset_num_timesteps=[runs[i].resume_from is None for i in training],
            keep_going=True,
            on_error=lambda position, error: reports.stopped(training[position], error),
        )
    return {training[position]: error for position, error in batch.errors.items()}


def _raise_first(errors: dict[int, BaseException], seeds: list[int], dirs: list[Path]) -> None:
    """What stopped a seed (``errors`` maps a seed to it), if any: an interruption first (the batch resumes), then a
    divergence, then the rest; among seeds of one kind, the first in ``seeds``."""
    for kind in (TrainingInterrupted, TrainingDiverged, BaseException):
        failed = [(seed, errors[seed]) for seed in seeds if isinstance(errors.get(seed), kind)]
        if failed:
            seed, error = failed[0]
            if isinstance(error, TrainingInterrupted):
                # Resume the batch from any seed's folder (each config.yaml lists them all).
                raise TrainingInterrupted(error.signal_name, error.exit_code, error.num_timesteps, str(dirs[0])) from error
            log.error("Seed %d failed: %s", seed, error)
            raise error


class _SeedFilter(logging.Filter):
    def __init__(self, index: int) -> None:
        super().__init__()
        self.index = index

    def filter(self, record: logging.LogRecord) -> bool:
        return current_seed.get() in (None, self.index)


def _seed_log_file(run_dir: Path, index: int) -> logging.Handler | None:
    """``<run_dir>/run.log``, as a lone ``run.py`` run has (Hydra's): the lines of seed ``index`` and those of the
    batch as a whole. None where a handler writes that file already (Hydra's, in the folder it was given: the first
    seed's, which then holds every seed's lines)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = (run_dir / RUN_LOG).resolve()
    for existing in logging.getLogger().handlers:
        if isinstance(existing, logging.FileHandler) and Path(existing.baseFilename).resolve() == path:
            return None
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    handler.addFilter(_SeedFilter(index))
    logging.getLogger().addHandler(handler)
    return handler


def _log_seed_aggregate(dirs: list[Path], seeds: list[int], finals: dict[int, float], statistic: str, value: float) -> None:
    """The aggregate across seeds (mean and IQM, each with its 95% bootstrap interval), as
    ``python -m sb3_td3x.experiment.aggregate`` prints it."""
    from sb3_td3x.experiment.aggregate import aggregate, load_runs, to_markdown

    per_seed = ", ".join(f"seed {seed}: {finals[seed]:.2f}" for seed in seeds if seed in finals)
    log.info("Seeds' final evaluations: %s; %s %.2f", per_seed, statistic, value)
    try:
        runs = load_runs([d for d in dirs if d.is_dir()])
        for stat in STATISTICS:
            table, _ = aggregate(runs, stat)
            shown = table[["env_id", "algo", "n_runs", "timesteps", f"final_{stat}", "ci_low", "ci_high"]]
            log.info("Across seeds (%s, 95%% bootstrap CI):\n%s", stat, to_markdown(shown))
    except (FileNotFoundError, ValueError, KeyError) as error:  # the summary above stands without the table
        log.warning("Could not aggregate the seeds' evaluations: %s", error)


def provenance() -> dict[str, object]:
    """Where a result came from: the command (its secrets masked, :func:`~sb3_td3x.common.redaction.redact`), the
    package's git commit (``-dirty`` with uncommitted changes; None outside a git checkout), the machine and the
    library versions. Goes into ``summary.json``."""
    import stable_baselines3

    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, check=True)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip()

    commit = git("rev-parse", "HEAD")
    if commit is not None and git("status", "--porcelain", "--untracked-files=no"):
        commit += "-dirty"
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            cpu = next(line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "command": " ".join(redact([Path(sys.argv[0]).name, *sys.argv[1:]])),
        "commit": commit,
        "machine": {"cpu": cpu, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "os": platform.platform()},
        "versions": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "stable_baselines3": stable_baselines3.__version__,
        },
    }


def _reporting(report: Callable[[int, float], None], checkpointer: Checkpointer) -> Callable[[dict[str, float]], None]:
    """An evaluation listener calling ``report``; when it raises, the run is checkpointed before the exception goes on."""

    def listener(result: dict[str, float]) -> None:
        try:
            report(int(result["timesteps"]), float(result["mean_return"]))
        except BaseException:
            checkpointer.save_last()
            raise

    return listener
