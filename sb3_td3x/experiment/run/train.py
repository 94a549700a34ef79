"""One run: a seed's run folder claimed, its model built (or loaded from the checkpoint it resumes), trained with its
evaluations and checkpoints, and its records finished.

:func:`run_one` trains a lone ``seed=`` run; :mod:`~sb3_td3x.experiment.run.seeds` prepares and finishes each seed of
``seeds=[...]`` with the same :func:`prepare` and :func:`finish`, so that a seed's folder is its lone run's.
"""

from __future__ import annotations

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
from omegaconf import DictConfig

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment.configs.algos import algorithm_class, build_algorithm
from sb3_td3x.experiment.layout import LAST, LEARNING_CURVE_PNG
from sb3_td3x.experiment.run.callbacks import Checkpointer, CoreWaitsCheck, DivergenceCheck, PeriodicEvaluation, ProgressBar
from sb3_td3x.experiment.run.checkpoints import checkpoint_dir, load_checkpoint, load_resumable
from sb3_td3x.experiment.run.envs import make_eval_env, make_train_env, record_video
from sb3_td3x.experiment.run.folder import RunFolder, check_resume, public_config, saved_config
from sb3_td3x.experiment.run.loggers import build_logger, start_wandb
from sb3_td3x.experiment.stops import StopOnSignal

log = logging.getLogger(__name__)


def run_one(cfg: DictConfig, how: str, report: Callable[[int, float], None] | None) -> float:
    run = prepare(cfg, how)
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
        return finish(run)
    finally:
        close_run(run)


@dataclass
class Run:
    """One seed's run, up to ``learn()``: what :func:`finish` and :func:`close_run` need."""

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
    #: How the update ran in the sessions before this one (from the checkpoint resumed), oldest first.
    earlier_sessions: list[dict[str, Any]] = field(default_factory=list)
    session_start: int = 0  # the step this session started at
    #: Where this session's code came from, taken when it started (provenance.jsonl's line): summary.json repeats it,
    #: so a commit made while the run trained is not credited with it.
    provenance: dict[str, Any] = field(default_factory=dict)

    def update_sessions(self) -> list[dict[str, Any]]:
        """How the update ran in each session of the run, oldest first: the step it started at, its ``update_path``
        and ``update_reason`` (None before its first ``train()``, and for SB3's TD3). Saved with each checkpoint, so
        a resumed run's records name every session's, as far as the weights it resumed go."""
        model = self.model
        now = {
            "from_step": self.session_start,
            "update_path": getattr(model, "update_path", None),
            "update_reason": getattr(model, "update_reason", None),
        }
        return [*self.earlier_sessions, now]


def prepare(cfg: DictConfig, how: str) -> Run:
    """Everything a run does before ``model.learn``: own the folder, build or load the model, then (once the
    checkpoint has loaded and the config is accepted) the records, loggers and callbacks. On an error, what was
    opened is closed and nothing of the run's records has been written.

    :param how: how the run starts in its folder (:func:`~sb3_td3x.experiment.run.folder.where_to_start`): a new
        run refuses a folder that holds a run; ``RESTARTED`` starts afresh in a folder whose earlier session left no
        checkpoint (a requeued job, or a seed of a resumed batch, stopped before its first checkpoint)
    """
    run = Run(cfg, Path(cfg.run_dir), time.time())
    run.folder = RunFolder.claim(run.run_dir, how)
    try:
        config = public_config(cfg)
        train_env = make_train_env(cfg.env, cfg.n_envs, cfg.seed)
        run.closers.append(train_env.close)
        eval_env = make_eval_env(cfg.env)
        run.closers.append(eval_env.close)
        experiment_state, session = _model(run, config, train_env)
        model = run.model
        run.provenance = provenance()
        run.folder.start_session(config, model.num_timesteps, session, run.provenance)
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
        close_run(run)
        raise


def _model(run: Run, config: dict[str, Any], train_env: Any) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """Build the model, or load it from the run's newest whole checkpoint and check the config against the one it
    trained with. Returns the experiment state to restore and what this session's provenance line adds."""
    cfg = run.cfg
    if cfg.resume is None:
        run.model = build_algorithm(cfg, train_env)
        _warn_never_trains(cfg)
        return None, {}
    cls = algorithm_class(cfg.algo)
    resumed = load_resumable(run.run_dir, lambda path: load_checkpoint(path, cls, train_env, cfg.device))
    run.model, run.resume_from = resumed.model, checkpoint_dir(run.run_dir, LAST)
    changes = check_resume(saved_config(run.run_dir, run.resume_from), config, run.run_dir)
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


def _loggers(run: Run, config: dict[str, Any]) -> None:
    cfg = run.cfg
    wandb_run = start_wandb(cfg.logger.wandb, run.run_dir, run.run_name, config) if cfg.logger.wandb is not None else None
    if wandb_run is not None:
        run.closers.append(lambda: wandb_run.finish(exit_code=0 if run.succeeded else 1))
    logger = build_logger(cfg.logger, run.run_dir, wandb_run)
    run.closers.insert(0, logger.close)
    run.model.set_logger(logger)


def _callbacks(run: Run, eval_env: Any, config: dict[str, Any], experiment_state: dict[str, Any] | None) -> None:
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
    run.session_start = run.model.num_timesteps
    checkpointer = run.checkpointer = Checkpointer(
        run.run_dir,
        cfg.checkpoint.freq,
        experiment_state=lambda: {"evaluation": evaluation.state_dict(), "update_sessions": run.update_sessions()},
        save_best=cfg.checkpoint.save_best,
        best_replay_buffer=cfg.checkpoint.best_replay_buffer,
        config=config,
    )
    if experiment_state is not None:
        evaluation.load_state_dict(experiment_state["evaluation"])
        # A checkpoint written before the sessions were kept has none: the record then starts at this session.
        run.earlier_sessions = list(experiment_state.get("update_sessions", []))
        checkpointer.best_mean_return = evaluation.best_mean_return
    evaluation.listeners.append(checkpointer.on_evaluation)
    if run.progress is not None:
        evaluation.listeners.append(run.progress.on_evaluation)
    run.callbacks = [DivergenceCheck(), CoreWaitsCheck(), evaluation, checkpointer]
    run.callbacks += [run.progress] if run.progress is not None else []


def finish(run: Run) -> float:
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
        # How TD3X's update ran and why (sb3_td3x.td3x.update_paths.choose, or the seed batch's), in this session and
        # in each session of a resumed run; None for SB3's TD3
        "update_path": getattr(model, "update_path", None),
        "update_reason": getattr(model, "update_reason", None),
        "update_sessions": run.update_sessions(),
        "exploration_path": getattr(model, "exploration_path", None),
        "wall_time_s_this_session": time.time() - run.started,
        "provenance": run.provenance,
    }
    if evaluation.value_notes:  # why value columns are NaN, and what to change (the log says it in one line)
        summary["value_measurement_notes"] = evaluation.value_notes
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


def close_run(run: Run) -> None:
    for close in run.closers:
        try:
            close()
        except Exception as error:  # a failing close must not hide the exception that ended the run
            log.warning("Closing %s failed: %s", close, error)
    run.closers = []
    if run.evaluation is not None and run.evaluation.history:
        try:
            # Imported here: matplotlib costs 0.75 s at start-up, which a run that stops early (bad input) never needs.
            from sb3_td3x.experiment.analysis.plots import plot_learning_curve

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


def provenance() -> dict[str, object]:
    """Where a result came from: the command (its secrets masked, :func:`~sb3_td3x.common.redaction.redact`), the
    package's git commit (``-dirty`` with uncommitted changes; None outside a git checkout), the machine and the
    library versions. Goes into ``summary.json``."""
    import stable_baselines3

    root = Path(__file__).resolve().parents[3]

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
