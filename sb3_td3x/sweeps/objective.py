"""One trial: draw the parameters, compose the same config ``run.py`` would, train, and report evaluations.

The trial's Hydra overrides are the sweep file's ``overrides``, the command line's, one ``path=value`` per searched
parameter, ``seed=<sweep seed + trial number>`` and ``run_dir=<study folder>/trial_NNNN``. They are stored on the
trial (``user_attrs``, secrets masked) before training starts, so every trial, finished or not, can be re-run by
hand::

    python run.py <the trial's overrides>

With ``seeds_per_trial: K`` above 1, trial ``n`` trains the K seeds ``sweep seed + n*K + j`` (``j < K``) together in
its process: its overrides say ``seed=<the first>`` and ``seeds=[...]``, each seed writes its run folder
``trial_NNNN/seed<s>``, the pruner sees the seeds' aggregate (``seeds_aggregate``) at every evaluation, and the
trial's value is the aggregate. The trial's user attributes add ``seeds``, ``seeds_aggregate``, ``seed_values``
(``{"<seed>": mean return}``, each seed's latest evaluation: its final one when the trial completes) and
``seed_values_step`` (the step of those evaluations). An interrupted trial resumes with
``resume=trial_NNNN/seed<first seed>``, which resumes all its seeds.
"""

from __future__ import annotations

import logging
import math
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import optuna
from omegaconf import DictConfig

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment import jobs
from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.sweeps.errors import SweepSpecError
from sb3_td3x.sweeps.spec import SweepSpec, override_value

logger = logging.getLogger(__name__)

#: ``run_experiment(cfg, report)``: trains, calls ``report(num_timesteps, mean_return)`` after every evaluation,
#: returns the final evaluation's mean return. A trial of several seeds also passes ``seeds_aggregate`` and
#: ``report_seeds(num_timesteps, {seed: mean_return})``; ``report`` then gets the seeds' aggregate, as does the return.
TrainFn = Callable[..., float]

DEFAULT_CONFIG_DIR = Path(__file__).resolve().parents[2] / "conf"

#: Settings every trial gets: no progress bar interleaving with other workers' output.
TRIAL_DEFAULTS = ["progress_bar=false"]

#: User attribute of a trial stopped cleanly by Ctrl-C/SIGTERM; its queued copy inherits it and resumes the run.
RESUMABLE = "resumable"

#: User attributes of a trial of several seeds that its run writes: each seed's latest evaluation and its step.
SEED_VALUES, SEED_VALUES_STEP = "seed_values", "seed_values_step"


def seed_overrides(seeds: list[int], run_dir: Path, resume: bool = False) -> list[str]:
    """A trial's own overrides: its seed (and ``seeds=[...]`` for several), its folder, and ``resume`` for the copy
    of an interrupted trial (several seeds resume from the first seed's folder)."""
    from sb3_td3x.experiment.run.folder import seed_folders

    if len(seeds) == 1:
        return [f"seed={seeds[0]}", f"run_dir={run_dir}"] + ([f"resume={run_dir}"] if resume else [])
    own = [f"seed={seeds[0]}", f"seeds={override_value(seeds)}", f"run_dir={run_dir}"]
    return own + ([f"resume={seed_folders(run_dir, seeds[:1])[0]}"] if resume else [])


def override_key(override: str) -> str:
    """The config path or group an override sets: ``algo.tau`` for ``algo.tau=0.01``, ``env`` for ``env=ant``."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create().parse_override(override).key_or_group


def check_composes(spec: SweepSpec, config_dir: Path, extra_overrides: list[str]) -> None:
    """Compose one trial's config before any trial runs, so that a wrong path fails now with a clear message."""
    from hydra.errors import HydraException, OverrideParseException
    from omegaconf.errors import OmegaConfBaseException

    from sb3_td3x.experiment.configs.compose import check_config
    from sb3_td3x.experiment.errors import ConfigError

    fixed = spec.overrides + extra_overrides
    try:
        fixed_keys = {override_key(o).lstrip("+~") for o in fixed}
    except OverrideParseException as err:
        raise SweepSpecError(f"an override of {spec.source} or of the command line is not in Hydra's syntax: {err}") from None
    clash = sorted(fixed_keys & set(spec.searched_paths))
    if clash:
        raise SweepSpecError(
            f"{spec.source}: {', '.join(clash)} is both searched (search_space) and fixed (the overrides of the file or the command line); remove one of the two"
        )
    for reserved in ("seed", "seeds", "run_dir", "resume"):
        if reserved in spec.searched_paths or reserved in fixed_keys:
            raise SweepSpecError(
                f"{spec.source}: {reserved} is set by the sweep for every trial (seed = sweep seed + trial number, "
                f"seeds = seeds_per_trial seeds from there, run_dir = the trial's folder, resume = an interrupted "
                "trial's folder); remove it from the overrides/search_space (set seeds_per_trial for several seeds)"
            )
    example = [p.override(p.example_value()) for p in spec.params]
    own = seed_overrides(spec.trial_seeds(0), Path("/tmp/sweep-check"))
    try:
        cfg = compose_config(fixed + example + TRIAL_DEFAULTS + own, config_dir)
        check_config(cfg)
    except (HydraException, OmegaConfBaseException, ConfigError) as err:
        message = str(err).strip().splitlines()
        raise SweepSpecError(
            f"{spec.source}: the overrides and search-space paths do not compose with {config_dir}: "
            f"{' '.join(message[:3])}. Search-space keys must be existing config paths (see python run.py --cfg job)."
        ) from None


def worker_id() -> str:
    """This worker as the records name it: ``host:pid``."""
    return f"{socket.gethostname()}:{os.getpid()}"


class TrialFinishedElsewhere(Exception):
    """The trial was finished by another worker (marked FAIL as stale while this one was cut off): stop training."""

    def __init__(self, num_timesteps: int | None, mean_return: float | None) -> None:
        self.num_timesteps = num_timesteps
        self.mean_return = mean_return
        super().__init__(f"trial already finished by another worker (found at step {num_timesteps})")


@dataclass
class TrialResult:
    """What :class:`TrialObjective` hands back to the worker, which tells it to Optuna."""

    state: optuna.trial.TrialState
    value: float | None = None
    reason: str | None = None  #: why a trial was pruned or failed; stored as the trial's ``fail_reason``
    interrupted: bool = False  #: stopped by Ctrl-C / SIGTERM: the worker re-queues the trial and stops
    crashed: bool = False  #: raised an error other than divergence: its traceback is in the trial folder
    step: int | None = None  #: the step of the trial's last evaluation, if it had one
    finished_elsewhere: bool = False  #: another worker had finished the trial: the result is kept as a late result


class TrialObjective:
    """Runs one trial of a sweep and turns every way it can end into a :class:`TrialResult`.

    :param spec: the sweep file
    :param config_dir: the ``conf/`` folder ``run.py`` composes
    :param extra_overrides: overrides given on the sweep's command line, applied after the sweep file's
    :param study_dir: the study folder; trial ``k`` trains in ``study_dir/trial_000k``
    :param train_fn: the training function; :func:`sb3_td3x.experiment.runner.run_experiment` by default
    """

    def __init__(
        self,
        spec: SweepSpec,
        config_dir: Path,
        extra_overrides: list[str],
        study_dir: Path,
        train_fn: TrainFn | None = None,
    ) -> None:
        self.spec = spec
        self.config_dir = config_dir
        self.extra_overrides = list(extra_overrides)
        self.study_dir = study_dir
        self.train_fn = train_fn

    def overrides(self, values: dict[str, Any], seeds: list[int], run_dir: Path, resume: bool = False) -> list[str]:
        searched = [param.override(values[param.path]) for param in self.spec.params]
        return self.spec.overrides + self.extra_overrides + searched + TRIAL_DEFAULTS + seed_overrides(seeds, run_dir, resume)

    def run_dir(self, number: int) -> Path:
        return (self.study_dir / f"trial_{number:04d}").resolve()

    def __call__(self, trial: optuna.Trial) -> TrialResult:
        try:
            return self._run(trial)
        except optuna.exceptions.UpdateFinishedTrialError:  # finished elsewhere before training began
            return TrialResult(optuna.trial.TrialState.FAIL, reason="finished by another worker", finished_elsewhere=True)

    def _record_start(self, trial: optuna.Trial, overrides: list[str], seeds: list[int], run_dir: Path) -> None:
        """What the trial runs, as its user attributes."""
        # a queued copy inherits its original's attributes; these describe how the original ended
        for inherited in ("fail_reason", "prune_reason", RESUMABLE, SEED_VALUES, SEED_VALUES_STEP):
            if trial.user_attrs.get(inherited) is not None:
                trial.set_user_attr(inherited, None)
        trial.set_user_attr("overrides", redact(overrides))  # secrets masked: the study is a record too
        trial.set_user_attr("seed", seeds[0])
        if len(seeds) > 1:
            trial.set_user_attr("seeds", seeds)
            trial.set_user_attr("seeds_aggregate", self.spec.seeds_aggregate)
        trial.set_user_attr("run_dir", str(run_dir))
        trial.set_user_attr("worker", worker_id())
        job = jobs.current_job()
        trial.set_user_attr("job", job.record() if job is not None else None)  # a requeued worker finds its trials

    def _run(self, trial: optuna.Trial) -> TrialResult:
        from sb3_td3x.experiment.errors import TrainingDiverged, TrainingInterrupted

        values = {param.path: param.suggest(trial) for param in self.spec.params}
        resume_dir = self._resumable_run_dir(trial)
        if resume_dir is not None:  # the queued copy of a trial stopped by Ctrl-C/SIGTERM: continue its run
            seeds, run_dir = self._recorded_seeds(trial), resume_dir
        else:
            seeds, run_dir = self.spec.trial_seeds(trial.number), self.run_dir(trial.number)
        overrides = self.overrides(values, seeds, run_dir, resume=resume_dir is not None)
        self._record_start(trial, overrides, seeds, run_dir)
        if resume_dir is not None:
            logger.info("trial %d resumes the run of the trial it repeats, in %s, from its checkpoint", trial.number, run_dir)
        else:
            logger.info("trial %d started in %s", trial.number, run_dir)

        evaluations: list[float] = []
        steps: list[int] = []
        what = "mean return" if len(seeds) == 1 else f"{self.spec.seeds_aggregate} return of seeds {seeds}"

        def report(num_timesteps: int, mean_return: float) -> None:
            evaluations.append(mean_return)
            steps.append(num_timesteps)
            try:
                trial.report(mean_return, step=num_timesteps)
            except optuna.exceptions.UpdateFinishedTrialError:  # failed as stale while this worker was cut off
                raise TrialFinishedElsewhere(num_timesteps, mean_return) from None
            if trial.should_prune():
                raise optuna.TrialPruned(
                    f"pruned by {type(trial.study.pruner).__name__} at step {num_timesteps} "
                    f"(evaluation {what} {mean_return:.2f})"
                )

        seed_values: dict[str, float] = {}

        def report_seeds(num_timesteps: int, returns: dict[int, float]) -> None:
            seed_values.update({str(seed): float(value) for seed, value in returns.items()})  # JSON keys are text
            try:
                trial.set_user_attr(SEED_VALUES, dict(sorted(seed_values.items(), key=lambda item: int(item[0]))))
                trial.set_user_attr(SEED_VALUES_STEP, int(num_timesteps))
            except optuna.exceptions.UpdateFinishedTrialError:
                raise TrialFinishedElsewhere(num_timesteps, None) from None

        seed_options = {} if len(seeds) == 1 else {"seeds_aggregate": self.spec.seeds_aggregate, "report_seeds": report_seeds}
        try:
            cfg = compose_config(overrides, self.config_dir)
            if cfg.torch_threads is None:  # workers may share a machine: one thread each unless the spec says
                cfg.torch_threads = 1
            final_return = self.train(cfg, report, **seed_options)
        except optuna.TrialPruned as pruned:
            return TrialResult(optuna.trial.TrialState.PRUNED, reason=str(pruned), step=steps[-1] if steps else None)
        except TrialFinishedElsewhere as late:
            return TrialResult(
                optuna.trial.TrialState.FAIL,
                value=late.mean_return,
                reason=str(late),
                step=late.num_timesteps,
                finished_elsewhere=True,
            )
        except TrainingDiverged as err:
            return TrialResult(
                optuna.trial.TrialState.FAIL, reason=f"diverged: {err.what} became {err.value} at step {err.num_timesteps}"
            )
        except (KeyboardInterrupt, TrainingInterrupted) as err:
            signal_name = getattr(err, "signal_name", "SIGINT")
            return TrialResult(optuna.trial.TrialState.FAIL, reason=f"interrupted by {signal_name}", interrupted=True)
        except Exception as err:  # noqa: BLE001  (any crash in one trial is recorded on it; the study goes on)
            self._write_traceback(run_dir)
            first_line = (str(err).strip().splitlines() or [""])[0]
            return TrialResult(optuna.trial.TrialState.FAIL, reason=f"{type(err).__name__}: {first_line}", crashed=True)

        value = max(evaluations) if self.spec.metric == "eval/best_mean_return" and evaluations else final_return
        if value is None or not math.isfinite(value):
            return TrialResult(optuna.trial.TrialState.FAIL, reason=f"diverged: the metric {self.spec.metric} is {value}")
        return TrialResult(optuna.trial.TrialState.COMPLETE, value=float(value), step=steps[-1] if steps else None)

    @staticmethod
    def _recorded_seeds(trial: optuna.Trial) -> list[int]:
        """The seeds the original of a queued copy trained (its ``seeds``, or its one ``seed``)."""
        if trial.user_attrs.get("seeds") is not None:
            return [int(seed) for seed in trial.user_attrs["seeds"]]
        return [int(trial.user_attrs["seed"])]

    @classmethod
    def _resumable_run_dir(cls, trial: optuna.Trial) -> Path | None:
        """The run folder to resume: set when this trial is the queued copy of one that stopped cleanly on
        Ctrl-C/SIGTERM and left a complete checkpoint (of its first seed, for several). A copy of a trial failed by
        the heartbeat starts afresh in its own folder instead, since its first worker may still be writing to the
        old one."""
        from sb3_td3x.experiment.errors import ConfigError
        from sb3_td3x.experiment.run.checkpoints import resume_checkpoint
        from sb3_td3x.experiment.run.folder import seed_folders

        if not trial.user_attrs.get(RESUMABLE):
            return None
        run_dir = Path(trial.user_attrs["run_dir"])
        seeds = cls._recorded_seeds(trial)
        try:
            resume_checkpoint(run_dir if len(seeds) == 1 else seed_folders(run_dir, seeds[:1])[0])
        except ConfigError:  # stopped before its first checkpoint: start again
            return None
        return run_dir

    def train(self, cfg: DictConfig, report: Callable[[int, float], None], **seed_options: Any) -> float:
        """Train ``cfg``; ``seed_options`` (``seeds_aggregate``, ``report_seeds``) only for a trial of several seeds,
        so that a one-seed trial calls the training function exactly as before."""
        if self.train_fn is None:
            from sb3_td3x.experiment.runner import run_experiment

            self.train_fn = run_experiment
        return self.train_fn(cfg, report=report, **seed_options)

    @staticmethod
    def _write_traceback(run_dir: Path) -> None:
        import traceback

        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "sweep_error.txt").write_text(redact(traceback.format_exc()))
