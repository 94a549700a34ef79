"""``seeds=[...]`` trained together in this process: each seed's run prepared as its lone run is (its folder, envs,
model and callbacks: :mod:`~sb3_td3x.experiment.run.train`), then one :class:`~sb3_td3x.SeedBatch` learns them all, and
each seed's folder is finished as a lone run's. Each seed computes what its lone run computes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from sb3_td3x.common.random_streams import RandomStreams, detached_streams
from sb3_td3x.experiment.analysis.statistics import STATISTICS, seed_statistic
from sb3_td3x.experiment.errors import TrainingDiverged, TrainingInterrupted
from sb3_td3x.experiment.layout import LOG_FORMAT, RUN_LOG
from sb3_td3x.experiment.run.checkpoints import last_step
from sb3_td3x.experiment.run.folder import NEW, RESTARTED
from sb3_td3x.experiment.run.train import Run, close_run, finish, prepare
from sb3_td3x.experiment.stops import StopOnSignal
from sb3_td3x.seeds import SeedBatch, acting_as, current_seed

log = logging.getLogger(__name__)


class _SeedReports:
    """The evaluations of a batch's seeds, step by step: ``report`` gets their aggregate once every seed still
    training has evaluated at a step. When ``report`` raises, every seed is asked to stop: each checkpoints at its
    next rollout boundary, with its own random state (as a signal would), and the exception is kept for the caller."""

    def __init__(
        self,
        seeds: list[int],
        runs: list[Run],
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


def run_seeds(
    cfg: DictConfig,
    how: str,
    report: Callable[[int, float], None] | None,
    statistic: str,
    report_seeds: Callable[[int, dict[int, float]], None] | None,
) -> float:
    """``cfg.seeds`` trained together: each seed's run prepared as its lone run is (folder, envs, model, callbacks),
    then one :class:`~sb3_td3x.SeedBatch` learns them all; each seed's folder is finished as a lone run's."""
    seeds, dirs = [int(s) for s in cfg.seeds], [Path(d) for d in cfg.seed_run_dirs]
    finals, errors = train_seed_group(cfg, how, list(range(len(seeds))), statistic, report, report_seeds)
    return end_of_batch(seeds, dirs, finals, errors, statistic)


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
    :class:`~sb3_td3x.SeedBatch`), each in its folder of ``cfg.seed_run_dirs``, each folder finished as a lone
    run's. Every seed's ``config.yaml`` lists all of ``cfg.seeds`` and their folders, so that ``resume=`` of any
    continues them all. Returns each finished seed's final mean return and what stopped each other one (keyed by
    seed); raises what ``report`` raised."""
    all_seeds, all_dirs = [int(s) for s in cfg.seeds], [Path(d) for d in cfg.seed_run_dirs]
    seeds, dirs = [all_seeds[i] for i in indices], [all_dirs[i] for i in indices]
    runs: list[Run] = []
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
                    finals[seeds[index]] = finish(run)
        return finals, {seeds[index]: error for index, error in errors.items()}
    finally:
        RandomStreams().set_state(caller)
        for run in runs:
            close_run(run)
        for handler in handlers:
            logging.getLogger().removeHandler(handler)
            handler.close()


def _prepare_seeds(
    cfg: DictConfig,
    how: str,
    seeds: list[int],
    dirs: list[Path],
    all_dirs: list[Path],
    runs: list[Run],
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
        resumes = cfg.resume is not None and last_step(run_dir) is not None
        if cfg.resume is not None and not resumes:
            log.warning("Seed %d has no checkpoint in %s: it starts from the beginning (as its lone run would).", seed, run_dir)
        seed_cfg.resume = str(run_dir) if resumes else None
        if (handler := _seed_log_file(run_dir, index)) is not None:
            handlers.append(handler)
        with acting_as(index):
            runs.append(prepare(seed_cfg, how if resumes else (NEW if how == NEW else RESTARTED)))
            runs[-1].trained_together = list(seeds)
            streams.append(detached_streams(runs[-1].model))
    return streams


def _train_seeds(
    cfg: DictConfig, runs: list[Run], streams: list[RandomStreams], seeds: list[int], reports: _SeedReports
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
    ``python -m sb3_td3x.experiment.analysis.aggregate`` prints it."""
    from sb3_td3x.experiment.analysis.aggregate import aggregate, load_runs, to_markdown

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


