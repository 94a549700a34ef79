"""Checkpoints that let a killed run continue exactly where it stopped.

A checkpoint is a folder (``<run_dir>/checkpoints/last`` or ``.../best``) holding

- ``model.zip``: SB3's save (networks, optimizers, step counters, the observation that starts the next step),
- ``replay_buffer.pkl``: SB3's replay buffer save, of the filled rows only,
- ``vecnormalize.pkl``: the ``VecNormalize`` statistics, when observations or rewards are normalised,
- ``state.pkl``: what SB3's save leaves out and an exact continuation needs: the random number generators
  (python, numpy, torch, the action space's sampler), the state of every training environment *within* its
  episode (wrappers, MuJoCo's ``MjData``) and the experiment's own state (evaluation history, best return),
- ``meta.json``: the step count and the file list, written last.

Writing is atomic: everything goes to ``<name>.tmp`` first, then ``<name>`` is moved to ``<name>.prev``, the
new folder takes its place, and ``.prev`` is removed. Whatever moment the process dies at, a complete
checkpoint exists under ``<name>`` or, between the two renames, under ``<name>.prev``; :func:`find_checkpoint`
looks at both.
"""

from __future__ import annotations

import json
import os
import pickle
import random
import shutil
import time
import warnings
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize

from sb3_td3x.experiment.errors import ConfigError

LAST = "last"
BEST = "best"

MODEL_FILE = "model.zip"
REPLAY_BUFFER_FILE = "replay_buffer.pkl"
VECNORMALIZE_FILE = "vecnormalize.pkl"
STATE_FILE = "state.pkl"
META_FILE = "meta.json"


def checkpoint_dir(run_dir: Path, name: str) -> Path:
    return run_dir / "checkpoints" / name


def seed_run_dir(run_dir: Path | str, seed: int) -> Path:
    """The folder of seed ``seed`` of a batch of seeds run in ``run_dir`` (``run.py seeds=[...]`` with a
    ``run_dir=`` of its own, a multirun job, a sweep trial)."""
    return Path(run_dir) / f"seed{seed}"


def save_checkpoint(target: Path, model: OffPolicyAlgorithm, experiment_state: dict[str, Any], replay_buffer: bool = True) -> Path:
    """Write a complete checkpoint of ``model`` to the folder ``target``, atomically (see the module docstring).

    :param experiment_state: picklable state of the experiment (evaluation history, ...), returned by
        :func:`load_checkpoint` as is
    :param replay_buffer: also save the replay buffer (needed to resume training, not to deploy the policy)
    """
    tmp = target.with_name(target.name + ".tmp")
    previous = target.with_name(target.name + ".prev")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)

    files = [MODEL_FILE, STATE_FILE]
    model.save(tmp / MODEL_FILE)
    buffer_arrays: list[str] = []
    if replay_buffer:
        buffer_arrays = _save_filled_replay_buffer(model, tmp / REPLAY_BUFFER_FILE)
        files.append(REPLAY_BUFFER_FILE)
    vec_normalize = model.get_vec_normalize_env()
    if vec_normalize is not None:
        vec_normalize.save(str(tmp / VECNORMALIZE_FILE))
        files.append(VECNORMALIZE_FILE)
    state = {
        "rng": _rng_state(model),
        "env": _capture_env_state(model.get_env()),
        "vecnormalize_returns": None if vec_normalize is None else vec_normalize.returns.copy(),
        "replay_buffer_arrays": buffer_arrays,
        "experiment": experiment_state,
    }
    with open(tmp / STATE_FILE, "wb") as file:
        pickle.dump(state, file)
    meta = {"num_timesteps": model.num_timesteps, "saved_at": time.time(), "files": files}
    (tmp / META_FILE).write_text(json.dumps(meta, indent=2))
    for name in files + [META_FILE]:
        _fsync(tmp / name)

    shutil.rmtree(previous, ignore_errors=True)
    if target.exists():
        os.replace(target, previous)
    os.replace(tmp, target)
    shutil.rmtree(previous, ignore_errors=True)
    return target


def find_checkpoint(target: Path) -> Path | None:
    """The complete checkpoint at ``target``, or at ``target.prev`` when a save was cut between its two renames."""
    for candidate in (target, target.with_name(target.name + ".prev")):
        if (candidate / META_FILE).is_file():
            return candidate
    return None


def resume_checkpoint(run_dir: Path) -> Path:
    """The ``last`` checkpoint of ``run_dir``; a :class:`ConfigError` saying what is missing otherwise."""
    if not run_dir.is_dir():
        raise ConfigError(
            f"resume={run_dir}: no such folder. Pass the run folder of an earlier run, "
            "e.g. resume=runs/pendulum/td3/seed0/2026-01-01_12-00-00 (it holds config.yaml and checkpoints/)."
        )
    found = find_checkpoint(checkpoint_dir(run_dir, LAST))
    if found is None:
        raise ConfigError(
            f"resume={run_dir}: this folder has no complete checkpoint ({checkpoint_dir(run_dir, LAST)}/{META_FILE} is "
            "missing). A run writes one every checkpoint.freq steps, at the end and on SIGINT/SIGTERM; a run killed "
            "before its first checkpoint cannot be resumed, start it again instead."
        )
    if not (found / REPLAY_BUFFER_FILE).is_file():
        raise ConfigError(f"resume={run_dir}: the checkpoint {found} has no replay buffer, so training cannot continue.")
    return found


def load_checkpoint(path: Path, cls: type[OffPolicyAlgorithm], env: VecEnv, device: str) -> tuple[OffPolicyAlgorithm, dict[str, Any]]:
    """Rebuild the model saved in ``path`` on ``env`` (a fresh training env of the same config), exactly as it was.

    Restores the environments within their episodes, the normalisation statistics, the replay buffer and the
    random generators, so that ``model.learn(..., reset_num_timesteps=False)`` continues the interrupted run.
    :return: the model and the ``experiment_state`` given to :func:`save_checkpoint`
    """
    with open(path / STATE_FILE, "rb") as file:
        state = pickle.load(file)
    resumes_episode = _restore_env_state(env, state["env"])
    if isinstance(env, VecNormalize):
        env = VecNormalize.load(str(path / VECNORMALIZE_FILE), env.venv)
        env.returns = state["vecnormalize_returns"]
    # ``load`` seeds the env again, which only sets the seeds of its next explicit reset(); with force_reset=False
    # there is none, so the restored episodes go on.
    model = cls.load(path / MODEL_FILE, env=env, device=device, force_reset=not resumes_episode)
    model.load_replay_buffer(path / REPLAY_BUFFER_FILE)
    _regrow_replay_buffer(model.replay_buffer, state["replay_buffer_arrays"])
    _set_rng_state(model, state["rng"])
    return model, state["experiment"]


# Replay buffer ------------------------------------------------------------------------------------------------------
# SB3 preallocates the buffer and pickles it whole: 850 MB for Ant's 1M transitions after 3000 steps. Only the filled
# rows are saved here (SB3's own save, with the arrays cut for the time of the call) and the arrays are grown back to
# buffer_size on load, so an early checkpoint costs what it holds.
def _buffer_arrays(buffer: ReplayBuffer) -> dict[str, Any]:
    """The public attributes of ``buffer`` holding one row per transition: numpy arrays or torch tensors (sb3_td3x's
    TensorReplayBuffer), or dicts of them (DictReplayBuffer). Private ones are caches (TensorReplayBuffer's views)."""

    def per_transition(value: Any) -> bool:
        if isinstance(value, dict):
            return bool(value) and all(per_transition(v) for v in value.values())
        return isinstance(value, (np.ndarray, torch.Tensor)) and value.ndim >= 1 and value.shape[0] == buffer.buffer_size

    return {name: value for name, value in vars(buffer).items() if not name.startswith("_") and per_transition(value)}


def _first_rows(array: np.ndarray | torch.Tensor, n_rows: int) -> np.ndarray | torch.Tensor:
    # A tensor slice is a view, and pickling a view writes its whole storage: clone it.
    return array[:n_rows].clone() if isinstance(array, torch.Tensor) else array[:n_rows]


def _save_filled_replay_buffer(model: OffPolicyAlgorithm, path: Path) -> list[str]:
    """Save the filled rows; return the names of the arrays that were cut, for :func:`_regrow_replay_buffer`."""
    buffer = model.replay_buffer
    # One row more than the filled ones: with optimize_memory_usage, row ``pos`` holds the last next-observation.
    n_kept = min(buffer.pos + 1, buffer.buffer_size) if not buffer.full else buffer.buffer_size
    arrays = _buffer_arrays(buffer)
    try:
        for name, value in arrays.items():
            cut = (
                {k: _first_rows(v, n_kept) for k, v in value.items()}
                if isinstance(value, dict)
                else _first_rows(value, n_kept)
            )
            setattr(buffer, name, cut)
        model.save_replay_buffer(path)
    finally:
        vars(buffer).update(arrays)
    return sorted(arrays)


def _regrow_replay_buffer(buffer: ReplayBuffer, names: list[str]) -> None:
    def regrow(array: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        shape = (buffer.buffer_size, *array.shape[1:])
        if isinstance(array, torch.Tensor):
            full = torch.zeros(shape, dtype=array.dtype, device=array.device)
        else:
            full = np.zeros(shape, dtype=array.dtype)
        full[: array.shape[0]] = array
        return full

    for name in names:
        value = getattr(buffer, name)
        setattr(buffer, name, {k: regrow(v) for k, v in value.items()} if isinstance(value, dict) else regrow(value))


def _fsync(path: Path) -> None:
    with open(path, "rb") as file:
        os.fsync(file.fileno())


# Random number generators -------------------------------------------------------------------------------------------
def _rng_state(model: OffPolicyAlgorithm) -> dict[str, Any]:
    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
        "torch_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        "action_space": model.action_space.np_random.bit_generator.state,
    }


def _set_rng_state(model: OffPolicyAlgorithm, rng: dict[str, Any]) -> None:
    random.setstate(rng["python"])
    np.random.set_state(rng["numpy"])
    torch.set_rng_state(rng["torch"])
    if rng["torch_cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(rng["torch_cuda"])
    model.action_space.np_random.bit_generator.state = rng["action_space"]


# Environments within their episodes ---------------------------------------------------------------------------------
# Gymnasium's MuJoCo envs pickle as their constructor arguments (EzPickle), so pickling one gives a fresh env at
# the start of an episode. The state is taken layer by layer instead: every wrapper's and the base env's
# attributes, except the link to the wrapped env, MuJoCo's constant model and the renderer; MuJoCo's MjData is
# copied in place with mj_copyData.
_NOT_STATE = ("env", "model", "mujoco_renderer")


def _layers(env: Any) -> list[Any]:
    layers = [env]
    while hasattr(layers[-1], "env"):
        layers.append(layers[-1].env)
    return layers


def _capture_env_state(venv: VecEnv) -> list[list[dict[str, Any]]] | None:
    base = venv.venv if isinstance(venv, VecNormalize) else venv
    if not isinstance(base, DummyVecEnv):
        return None
    states = [[{k: v for k, v in vars(layer).items() if k not in _NOT_STATE} for layer in _layers(env)] for env in base.envs]
    try:
        pickle.dumps(states)
    except Exception as error:  # an env holding a handle (a socket, a simulator process) cannot be saved this way
        warnings.warn(f"The training env's state cannot be saved ({error}); a resumed run starts a new episode.")
        return None
    return states


def _restore_env_state(venv: VecEnv, states: list[list[dict[str, Any]]] | None) -> bool:
    """Put the saved episode state back into ``venv``; False when there is none (the caller then resets)."""
    base = venv.venv if isinstance(venv, VecNormalize) else venv
    if states is None or not isinstance(base, DummyVecEnv) or len(states) != len(base.envs):
        return False
    for env, env_states in zip(base.envs, states):
        layers = _layers(env)
        if len(layers) != len(env_states):
            return False
        for layer, layer_state in zip(layers, env_states):
            saved_data = layer_state.pop("data", None)
            vars(layer).update(layer_state)
            if isinstance(saved_data, mujoco.MjData):
                mujoco.mj_copyData(layer.data, layer.model, saved_data)
            elif saved_data is not None:
                layer.data = saved_data
    return True
