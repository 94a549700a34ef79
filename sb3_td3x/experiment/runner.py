"""The task function: train, evaluate and checkpoint one run described by a composed config.

``run.py`` calls :func:`run_experiment` under ``@hydra.main``; the Optuna sweeps call it directly with configs
from ``hydra.compose``. It does not read Hydra's global state: the run folder is ``cfg.run_dir`` (``run.py``
sets it to Hydra's output folder), or ``cfg.resume`` when continuing a run.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment.algos import algorithm_class, build_algorithm
from sb3_td3x.experiment.callbacks import Checkpointer, DivergenceCheck, PeriodicEvaluation, ProgressBar, StopOnSignal
from sb3_td3x.experiment.checkpoints import load_checkpoint, resume_checkpoint
from sb3_td3x.experiment.envs import make_eval_env, make_train_env
from sb3_td3x.experiment.loggers import build_logger, start_wandb
from sb3_td3x.experiment.plotting import LEARNING_CURVE_PNG, plot_learning_curve, record_video
from sb3_td3x.experiment.schemas import check_config, public_config

log = logging.getLogger(__name__)

CONFIG_FILE = "config.yaml"
SUMMARY_FILE = "summary.json"
PROVENANCE_FILE = "provenance.jsonl"


def run_experiment(cfg: DictConfig, report: Callable[[int, float], None] | None = None) -> float:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.total_timesteps`` steps and return the final evaluation mean return.

    Writes to the run folder (``cfg.run_dir``, or ``cfg.resume`` when set): ``config.yaml`` (resolved, without
    credentials), ``evaluations.csv``/``.json``, ``checkpoints/{last,best}``, ``tb/`` (TensorBoard), ``wandb/``,
    ``learning_curve.png``, ``summary.json`` and, with ``video=final``, ``video.gif``.

    :param cfg: a config composed from ``conf/`` (``hydra.compose(config_name="config", overrides=[...])``)
    :param report: called as ``report(num_timesteps, mean_eval_return)`` after every evaluation, including the
        final one; if it raises (e.g. ``optuna.TrialPruned``), a checkpoint is written, envs and loggers are closed
        and the exception propagates unchanged
    :raises ConfigError: the config cannot be run (bad value, unknown id, missing checkpoint); nothing is trained
    :raises TrainingDiverged: a training loss or an evaluation return became NaN or infinite
    :raises TrainingInterrupted: SIGINT or SIGTERM arrived; a checkpoint was written first
    """
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))  # a private copy; the caller's cfg stays as is
    if cfg.resume is not None:
        cfg.run_dir = str(cfg.resume)
    OmegaConf.resolve(cfg)  # pins ${now:...} and the env defaults once
    check_config(cfg)
    run_dir = Path(cfg.run_dir)
    resume_from = resume_checkpoint(run_dir) if cfg.resume is not None else None
    run_dir.mkdir(parents=True, exist_ok=True)
    config = public_config(cfg)
    (run_dir / CONFIG_FILE).write_text(OmegaConf.to_yaml(OmegaConf.create(config)))
    if cfg.torch_threads is not None:
        torch.set_num_threads(cfg.torch_threads)

    train_env = make_train_env(cfg.env, cfg.n_envs, cfg.seed)
    eval_env = make_eval_env(cfg.env)
    closers: list[Callable[[], object]] = [train_env.close, eval_env.close]
    evaluation: PeriodicEvaluation | None = None
    succeeded = False
    started = time.time()
    try:
        if resume_from is None:
            model = build_algorithm(cfg, train_env)
            experiment_state = None
        else:
            model, experiment_state = load_checkpoint(resume_from, algorithm_class(cfg.algo), train_env, cfg.device)
            log.info("Resuming %s at step %d from %s", run_dir, model.num_timesteps, resume_from)
        if cfg.algo.learning_starts >= cfg.total_timesteps:
            log.warning(
                "algo.learning_starts=%d >= total_timesteps=%d: the whole run takes uniformly random actions and never "
                "trains. Lower algo.learning_starts or raise total_timesteps.",
                cfg.algo.learning_starts,
                cfg.total_timesteps,
            )

        with open(run_dir / PROVENANCE_FILE, "a") as file:  # one line per session: a run may span several
            record = {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "at_step": int(model.num_timesteps), **provenance()}
            file.write(json.dumps(redact(record)) + "\n")

        run_name = f"{cfg.env.name}_{cfg.algo.name}_seed{cfg.seed}"
        wandb_run = start_wandb(cfg.logger.wandb, run_dir, run_name, config) if cfg.logger.wandb is not None else None
        if wandb_run is not None:
            closers.append(lambda: wandb_run.finish(exit_code=0 if succeeded else 1))
        logger = build_logger(cfg.logger, run_dir, wandb_run)
        closers.insert(0, logger.close)
        model.set_logger(logger)

        progress = ProgressBar(cfg.total_timesteps, run_name) if cfg.progress_bar else None
        if progress is not None:
            closers.insert(0, progress.close)
        evaluation = PeriodicEvaluation(
            eval_env,
            run_dir,
            cfg.eval.freq,
            cfg.eval.n_episodes,
            cfg.seed + cfg.eval.seed_offset,
            cfg.eval.deterministic,
            value_bias=cfg.eval.value_bias,
            value_horizon_tolerance=cfg.eval.value_horizon_tolerance,
        )
        checkpointer = Checkpointer(
            run_dir,
            cfg.checkpoint.freq,
            experiment_state=lambda: {"evaluation": evaluation.state_dict()},
            save_best=cfg.checkpoint.save_best,
            best_replay_buffer=cfg.checkpoint.best_replay_buffer,
        )
        if experiment_state is not None:
            evaluation.load_state_dict(experiment_state["evaluation"])
            checkpointer.best_mean_return = evaluation.best_mean_return
        evaluation.listeners.append(checkpointer.on_evaluation)
        if progress is not None:
            evaluation.listeners.append(progress.on_evaluation)
        if report is not None:
            evaluation.listeners.append(_reporting(report, checkpointer))

        log.info(
            "Training %s (%s) on %s for %d steps, seed %d, device %s; run folder: %s",
            type(model).__name__,
            cfg.algo.name,
            cfg.env.id,
            cfg.total_timesteps,
            cfg.seed,
            model.device,
            run_dir,
        )
        remaining = cfg.total_timesteps - model.num_timesteps
        if remaining > 0:
            callbacks = [DivergenceCheck(), evaluation, checkpointer] + ([progress] if progress is not None else [])
            with StopOnSignal(checkpointer):
                model.learn(
                    total_timesteps=remaining,
                    callback=callbacks,
                    log_interval=cfg.logger.log_interval,
                    reset_num_timesteps=resume_from is None,
                )
        if progress is not None:
            progress.close()  # before the last log lines
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
            # How TD3X's update ran and why (sb3_td3x.td3x.update_paths.choose); None for SB3's TD3
            "update_path": getattr(model, "update_path", None),
            "update_reason": getattr(model, "update_reason", None),
            "exploration_path": getattr(model, "exploration_path", None),
            "wall_time_s_this_session": time.time() - started,
            "provenance": provenance(),
        }
        (run_dir / SUMMARY_FILE).write_text(json.dumps(redact(summary), indent=2))
        if cfg.video is not None:
            path = record_video(
                model, cfg.env, cfg.video, run_dir / f"video.{cfg.video.format}", cfg.seed + cfg.eval.seed_offset
            )
            log.info("Video of the final policy: %s", path)
        log.info(
            "Done: final evaluation %.2f ± %.2f at step %d (best %.2f). Run folder: %s",
            final["mean_return"],
            final["std_return"],
            final["timesteps"],
            evaluation.best_mean_return,
            run_dir,
        )
        succeeded = True
        return float(final["mean_return"])
    finally:
        for close in closers:
            try:
                close()
            except Exception as error:  # a failing close must not hide the exception that ended the run
                log.warning("Closing %s failed: %s", close, error)
        if evaluation is not None and evaluation.history:
            plot_learning_curve(
                evaluation.history, run_dir / LEARNING_CURVE_PNG, f"{cfg.algo.name} on {cfg.env.id}, seed {cfg.seed}"
            )


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
