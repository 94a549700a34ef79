"""SB3 callbacks of a run: periodic evaluation, checkpoints, divergence check, progress bar, the core-waits check of
a model that does not make it itself.

Everything that looks at or saves the model runs at a *rollout boundary* (``_on_rollout_start``, after the
previous ``train()`` and before the next environment step). Inside ``_on_step`` the environment has stepped
but SB3 has not stored the transition nor updated ``_last_obs`` yet, so a checkpoint written there could not
resume exactly. This is also why :class:`PeriodicEvaluation` is not SB3's ``EvalCallback``, which evaluates in
``_on_step``; it uses the same machinery (``evaluate_policy``, ``sync_envs_normalization``).
With the default ``train_freq=1`` step a boundary comes after every step; with ``train_freq_unit=episode``
evaluations and checkpoints wait for the end of the episode.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv, sync_envs_normalization
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from sb3_td3x.common.core_waits import CoreWaits
from sb3_td3x.experiment.errors import TrainingDiverged, TrainingInterrupted
from sb3_td3x.experiment.layout import (
    BEST,
    EVALUATION_FIELDS,
    EVALUATIONS_CSV,
    EVALUATIONS_JSON,
    LAST,
    VALUE_FIELDS,
)
from sb3_td3x.experiment.run.checkpoints import checkpoint_dir, save_checkpoint
from sb3_td3x.experiment.run.folder import write_atomically
from sb3_td3x.experiment.run.value_bias import Episode, EpisodeRecorder, cut_at_time_limit, measure_value_bias
from sb3_td3x.td3x import TD3X

log = logging.getLogger(__name__)


class PeriodicEvaluation(BaseCallback):
    """Evaluate the deterministic policy every ``freq`` environment steps and once more at the end of training.

    Each evaluation runs ``n_episodes`` on ``eval_env``, re-seeded with ``eval_seed`` first, so all evaluations
    start from the same states. The history is rewritten to ``evaluations.csv`` and ``evaluations.json`` in
    ``run_dir`` after each evaluation, logged as ``eval/*`` to SB3's logger, and handed to ``listeners``
    (progress bar, best checkpoint, the caller's ``report``) in order.

    With ``value_bias`` (``eval.value_bias``, on by default) the same episodes also measure the critic's value
    estimate against the true discounted return (:mod:`sb3_td3x.experiment.run.value_bias`): the columns
    ``value_estimate``, ``true_value``, ``overestimation``, ``normalized_bias`` and ``value_states``, logged as
    ``eval/<column>``. Off, neither the columns nor the metrics exist. Rows of an earlier run without them (a resumed
    run) are written with empty cells.

    :raises TrainingDiverged: when the mean return is NaN or infinite
    """

    def __init__(
        self,
        eval_env: VecEnv,
        run_dir: Path,
        freq: int,
        n_episodes: int,
        eval_seed: int,
        deterministic: bool = True,
        listeners: list[Callable[[dict[str, float]], None]] | None = None,
        value_bias: bool = True,
        value_horizon_tolerance: float = 0.01,
    ) -> None:
        super().__init__()
        self.eval_env = eval_env
        self.run_dir = run_dir
        self.freq = freq
        self.n_episodes = n_episodes
        self.eval_seed = eval_seed
        self.deterministic = deterministic
        self.listeners = list(listeners or [])
        self.value_bias = value_bias
        self.value_horizon_tolerance = value_horizon_tolerance
        self.history: list[dict[str, float]] = []
        self.timing: dict[str, float] = {}  # seconds of the last evaluation: episodes, value measurement
        self._said_value_reasons: set[str] = set()  # kinds of NaN already logged
        #: why value columns were NaN (once per kind: the step, whether the configuration explains it, the reason)
        self.value_notes: list[dict[str, Any]] = []

    @property
    def last_timesteps(self) -> int:
        return int(self.history[-1]["timesteps"]) if self.history else 0

    @property
    def best_mean_return(self) -> float:
        return max((row["mean_return"] for row in self.history), default=-math.inf)

    def state_dict(self) -> dict[str, Any]:
        return {"history": [dict(row) for row in self.history]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.history = [dict(row) for row in state["history"]]
        self._write_history()  # drops rows a killed run wrote after its last checkpoint; they will come again

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        if self.num_timesteps // self.freq > self.last_timesteps // self.freq:
            self.evaluate()

    def _on_training_end(self) -> None:
        if self.num_timesteps > self.last_timesteps:
            self.evaluate()

    def evaluate(self) -> dict[str, float]:
        sync_envs_normalization(self.training_env, self.eval_env)
        self.eval_env.seed(self.eval_seed)
        recorder = EpisodeRecorder() if self.value_bias else None
        started = time.perf_counter()
        returns, lengths = evaluate_policy(
            self.model,
            self.eval_env,
            n_eval_episodes=self.n_episodes,
            deterministic=self.deterministic,
            return_episode_rewards=True,
            callback=recorder,
        )
        self.timing = {"episodes_s": time.perf_counter() - started}
        result = {
            "timesteps": self.num_timesteps,
            "mean_return": float(np.mean(returns)),
            "std_return": float(np.std(returns)),
            "mean_length": float(np.mean(lengths)),
            "wall_time": time.time(),
        }
        if not math.isfinite(result["mean_return"]):
            raise TrainingDiverged("the evaluation mean return", result["mean_return"], self.num_timesteps)
        if recorder is not None:
            started = time.perf_counter()
            values, reason = measure_value_bias(self.model, recorder.episodes, self.value_horizon_tolerance)
            self.timing["value_bias_s"] = time.perf_counter() - started
            result.update(values)
            if reason is not None:
                self._say_value_reason(values, recorder.episodes, reason)
        self.history.append(result)
        self._write_history()
        self.logger.record("eval/mean_reward", result["mean_return"])
        self.logger.record("eval/std_reward", result["std_return"])
        self.logger.record("eval/mean_ep_length", result["mean_length"])
        self.logger.record("eval/best_mean_reward", self.best_mean_return)
        for key in VALUE_FIELDS:
            if key in result:
                self.logger.record(f"eval/{key}", result[key])
        self.logger.dump(self.num_timesteps)
        for listener in self.listeners:
            listener(result)
        return result

    def _say_value_reason(self, values: dict[str, float], episodes: list[Episode], reason: str) -> None:
        """Log why a value column is NaN, once per run and kind; :attr:`value_notes` keeps the whole reason (and what to
        change) for the run's ``summary.json``.

        No state kept because every episode ran to the evaluation env's time limit, which is shorter than a state
        needs for its return to be known to the tolerance (Pendulum-v1's 200 steps with gamma 0.99, the README's first
        run), follows from the configuration: said at INFO. Any other NaN (episodes cut before their time limit, the
        normalised bias of returns that cancel) is a WARNING.
        """
        expected = values["value_states"] == 0 and cut_at_time_limit(episodes, self._time_limit())
        kind = "expected" if expected else "unexpected"
        if kind in self._said_value_reasons:
            return
        self._said_value_reasons.add(kind)
        self.value_notes.append({"step": int(self.num_timesteps), "expected": expected, "why": reason})
        if expected:
            log.info(
                "Value measurement at step %d: no value columns, the episodes end at their time limit too soon "
                "(summary.json says why)",
                self.num_timesteps,
            )
        else:
            log.warning("Value measurement at step %d gives NaN: %s (said once per run)", self.num_timesteps, reason)

    def _time_limit(self) -> int | None:
        """The evaluation env's time limit (its spec's ``max_episode_steps``), None when it has none."""
        spec = self.eval_env.get_attr("spec", indices=[0])[0]
        return None if spec is None else spec.max_episode_steps

    def _write_history(self) -> None:
        # NaN (a value measurement without states) as null: strict JSON readers refuse NaN
        rows = [{key: None if isinstance(v, float) and math.isnan(v) else v for key, v in row.items()} for row in self.history]
        write_atomically(self.run_dir / EVALUATIONS_JSON, json.dumps(rows, indent=1))
        # the value columns when any row has them; rows without them (before a resume) get empty cells
        fields = EVALUATION_FIELDS + tuple(key for key in VALUE_FIELDS if any(key in row for row in self.history))
        tmp = self.run_dir / (EVALUATIONS_CSV + ".tmp")
        with open(tmp, "w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=fields)
            writer.writeheader()
            writer.writerows(self.history)
        os.replace(tmp, self.run_dir / EVALUATIONS_CSV)


class Checkpointer(BaseCallback):
    """Write ``checkpoints/last`` every ``freq`` steps, at the end of training and when a stop is requested;
    ``checkpoints/best`` when an evaluation beats the best so far (use :meth:`on_evaluation` as a listener).

    A stop (SIGINT/SIGTERM: :class:`~sb3_td3x.experiment.stops.StopOnSignal`) is honoured at the next rollout
    boundary: the checkpoint is written, then :class:`TrainingInterrupted` is raised out of ``learn()``.

    :param experiment_state: returns the picklable state saved next to the model (evaluation history, ...)
    :param config: the run's resolved config, kept in each checkpoint's ``meta.json`` (what a resume is checked against)
    """

    def __init__(
        self,
        run_dir: Path,
        freq: int,
        experiment_state: Callable[[], dict[str, Any]],
        save_best: bool = True,
        best_replay_buffer: bool = False,
        config: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.run_dir = run_dir
        self.config = config
        self.freq = freq
        self.experiment_state = experiment_state
        self.save_best = save_best
        self.best_replay_buffer = best_replay_buffer
        self.last_saved_timesteps = -1
        self.best_mean_return = -math.inf
        self.stop_signal: tuple[str, int] | None = None

    def request_stop(self, signal_name: str, exit_code: int) -> None:
        self.stop_signal = (signal_name, exit_code)

    def _on_training_start(self) -> None:
        # A resumed run must not write again the checkpoint it started from.
        self.last_saved_timesteps = self.num_timesteps

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        if self.num_timesteps // self.freq > self.last_saved_timesteps // self.freq:
            self.save_last()
        if self.stop_signal is not None:
            if self.last_saved_timesteps != self.num_timesteps:
                self.save_last()
            raise TrainingInterrupted(*self.stop_signal, num_timesteps=self.num_timesteps, run_dir=str(self.run_dir))

    def _on_training_end(self) -> None:
        self.save_last()

    def save_last(self) -> Path:
        self.last_saved_timesteps = self.num_timesteps
        return save_checkpoint(checkpoint_dir(self.run_dir, LAST), self.model, self.experiment_state(), config=self.config)

    def on_evaluation(self, result: dict[str, float]) -> None:
        if self.save_best and result["mean_return"] > self.best_mean_return:
            self.best_mean_return = result["mean_return"]
            save_checkpoint(
                checkpoint_dir(self.run_dir, BEST), self.model, self.experiment_state(), self.best_replay_buffer, self.config
            )


class DivergenceCheck(BaseCallback):
    """Raise :class:`TrainingDiverged` as soon as a training loss recorded by ``train()`` is NaN or infinite."""

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        for key, value in self.logger.name_to_value.items():
            if key.startswith("train/") and key.endswith("loss") and not math.isfinite(value):
                raise TrainingDiverged(key, value, self.num_timesteps)


class CoreWaitsCheck(BaseCallback):
    """The check of TD3X's ``train()`` (:class:`~sb3_td3x.common.core_waits.CoreWaits`: a warning, once, when the torch
    threads wait for cores that other work holds), for a model on a CPU that does not make it itself (SB3's ``TD3`` run
    as a peer, ``algo=sb3_td3``, collapses alike beside busy cores): at each rollout boundary, after ``train()``."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: CoreWaits | None = None

    def _on_training_start(self) -> None:
        if not isinstance(self.model, TD3X) and self.model.device.type == "cpu":
            self.waits = CoreWaits()

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        if self.waits is not None:
            self.waits.warn_once()


class ProgressBar(BaseCallback):
    """A tqdm bar over environment steps, with steps/s and the latest evaluation (``on_evaluation`` listener)."""

    def __init__(self, total_timesteps: int, description: str) -> None:
        super().__init__()
        self.total_timesteps = total_timesteps
        self.description = description
        self.bar: tqdm | None = None

    def _on_training_start(self) -> None:
        self.bar = tqdm(
            total=self.total_timesteps,
            initial=self.num_timesteps,
            desc=self.description,
            unit="step",
            dynamic_ncols=True,
            mininterval=0.5,
        )
        _console_through_bars.open()

    def _on_step(self) -> bool:
        assert self.bar is not None
        self.bar.update(self.num_timesteps - self.bar.n)
        return True

    def on_evaluation(self, result: dict[str, float]) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(
                f"eval {result['mean_return']:.1f} ± {result['std_return']:.1f} @ {int(result['timesteps'])}"
            )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
            _console_through_bars.close()


class _ConsoleThroughBars:
    """While a progress bar is open in this process (one per seed of a batch), the console's log lines go through
    ``tqdm.write`` (tqdm's ``logging_redirect_tqdm``), which clears the bars, writes the line and draws them again: a
    line never cuts a bar. The console handlers come back when the last bar closes; a log file is left as it is."""

    def __init__(self) -> None:
        self.bars = 0
        self.redirect: contextlib.ExitStack | None = None

    def open(self) -> None:
        self.bars += 1
        consoles = [handler for handler in logging.root.handlers if _is_console(handler)]
        if self.redirect is None and consoles:  # no console handler (a script without logging): nothing to redirect
            self.redirect = contextlib.ExitStack()
            self.redirect.enter_context(logging_redirect_tqdm())

    def close(self) -> None:
        self.bars = max(0, self.bars - 1)
        if self.bars == 0 and self.redirect is not None:
            self.redirect.close()
            self.redirect = None


def _is_console(handler: logging.Handler) -> bool:
    return isinstance(handler, logging.StreamHandler) and getattr(handler, "stream", None) in (sys.stdout, sys.stderr)


_console_through_bars = _ConsoleThroughBars()
