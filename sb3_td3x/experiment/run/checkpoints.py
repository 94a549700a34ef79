"""Checkpoints that let a killed run continue exactly where it stopped.

A checkpoint is a folder (``<run_dir>/checkpoints/last`` or ``.../best``) holding

- ``model.zip``: SB3's save (networks, optimizers, step counters, the observation that starts the next step),
- ``replay_buffer.pkl``: SB3's replay buffer save, of the filled rows only,
- ``vecnormalize.pkl``: the ``VecNormalize`` statistics, when observations or rewards are normalised,
- ``state.pkl``: what SB3's save leaves out and an exact continuation needs: the random number generators
  (python, numpy, torch, the action space's sampler), the state of every training environment *within* its
  episode (wrappers, MuJoCo's ``MjData``) and the experiment's own state (evaluation history, best return),
- ``meta.json``: the step count, the config the run trained with, and each file's size and SHA-256, written last.

Writing survives any single fault. Everything goes to ``<name>.tmp`` first and is flushed to disk; then the
older ``<name>.prev`` is removed, ``<name>`` becomes ``<name>.prev``, ``<name>.tmp`` becomes ``<name>``, and the
folder's entries are flushed. So besides the newest checkpoint the one before it is kept, with its replay buffer.
Loading (:func:`load_resumable`) checks every file against ``meta.json`` and takes the newest checkpoint that is
whole: ``<name>``, a complete ``<name>.tmp`` (a save cut between its renames) or ``<name>.prev``.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import pickle
import shutil
import time
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize

from sb3_td3x.common.random_streams import RandomStreams
from sb3_td3x.experiment.errors import ConfigError, RunFilesNotWritten
from sb3_td3x.experiment.layout import LAST

log = logging.getLogger(__name__)

MODEL_FILE = "model.zip"
REPLAY_BUFFER_FILE = "replay_buffer.pkl"
VECNORMALIZE_FILE = "vecnormalize.pkl"
STATE_FILE = "state.pkl"
META_FILE = "meta.json"
DAMAGED = ".damaged"  # suffix of a checkpoint found damaged, kept for inspection


def checkpoint_dir(run_dir: Path, name: str) -> Path:
    """The folder of checkpoint ``name`` (:data:`~sb3_td3x.experiment.layout.LAST` or ``BEST``) of ``run_dir``."""
    return run_dir / "checkpoints" / name


def _sibling(target: Path, suffix: str) -> Path:
    return target.with_name(target.name + suffix)


def save_checkpoint(
    target: Path,
    model: OffPolicyAlgorithm,
    experiment_state: dict[str, Any],
    replay_buffer: bool = True,
    config: dict[str, Any] | None = None,
) -> Path:
    """Write a complete checkpoint of ``model`` to the folder ``target`` (see the module docstring for the order).

    :param experiment_state: picklable state of the experiment (evaluation history, ...), returned by
        :func:`load_checkpoint` as is
    :param replay_buffer: also save the replay buffer (needed to resume training, not to deploy the policy)
    :param config: the run's resolved config, stored in ``meta.json``: what a resume is checked against
    :raises RunFilesNotWritten: the files could not be written (a full disk); the previous checkpoint is intact
    """
    tmp = _sibling(target, ".tmp")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        files = _write_checkpoint_files(tmp, model, experiment_state, replay_buffer)
        meta = {
            "num_timesteps": model.num_timesteps,
            "saved_at": time.time(),
            "files": files,
            "sha256": {name: _digest(tmp / name) for name in files},
            "sizes": {name: (tmp / name).stat().st_size for name in files},
            "config": config,
        }
        with open(tmp / META_FILE, "w") as file:
            file.write(json.dumps(meta, indent=2))
            file.flush()
            os.fsync(file.fileno())
        _fsync_dir(tmp)
    except OSError as error:
        shutil.rmtree(tmp, ignore_errors=True)
        raise RunFilesNotWritten(
            f"writing the checkpoint of step {model.num_timesteps} to {tmp} failed ({error.strerror or error})"
        ) from error
    _promote(target)
    return target


def _write_checkpoint_files(folder: Path, model: OffPolicyAlgorithm, experiment_state: dict[str, Any], replay_buffer: bool) -> list[str]:
    files = [MODEL_FILE, STATE_FILE]
    model.save(folder / MODEL_FILE)
    buffer_arrays: list[str] = []
    if replay_buffer:
        buffer_arrays = _save_filled_replay_buffer(model, folder / REPLAY_BUFFER_FILE)
        files.append(REPLAY_BUFFER_FILE)
    vec_normalize = model.get_vec_normalize_env()
    if vec_normalize is not None:
        vec_normalize.save(str(folder / VECNORMALIZE_FILE))
        files.append(VECNORMALIZE_FILE)
    state = {
        "rng": _rng_state(model),
        "env": _capture_env_state(model.get_env()),
        "vecnormalize_returns": None if vec_normalize is None else vec_normalize.returns.copy(),
        "replay_buffer_arrays": buffer_arrays,
        "experiment": experiment_state,
    }
    with open(folder / STATE_FILE, "wb") as file:
        pickle.dump(state, file)
    for name in files:
        _fsync(folder / name)
    return files


def _promote(target: Path) -> None:
    """Move a complete ``<target>.tmp`` into place, keeping the checkpoint it replaces as ``<target>.prev``."""
    tmp, previous = _sibling(target, ".tmp"), _sibling(target, ".prev")
    if target.exists():
        shutil.rmtree(previous, ignore_errors=True)
        os.replace(target, previous)
    os.replace(tmp, target)
    _fsync_dir(target.parent)


def _candidates(target: Path) -> list[Path]:
    """The folders that may hold a complete checkpoint of ``target``, newest first: by step, then ``<target>``
    before ``<target>.tmp`` before ``<target>.prev``. Only those with a readable ``meta.json``."""
    found = []
    for rank, candidate in enumerate((target, _sibling(target, ".tmp"), _sibling(target, ".prev"))):
        meta = _read_meta(candidate)
        if meta is not None:
            found.append((-int(meta.get("num_timesteps", -1)), rank, candidate))
    return [candidate for *_, candidate in sorted(found)]


def find_checkpoint(target: Path) -> Path | None:
    """The newest folder at ``target``, ``target.tmp`` or ``target.prev`` with a readable ``meta.json``; whether its
    files are whole is checked when it is loaded (:func:`load_resumable`)."""
    candidates = _candidates(target)
    return candidates[0] if candidates else None


def _read_meta(folder: Path) -> dict[str, Any] | None:
    try:
        meta = json.loads((folder / META_FILE).read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) else None


def checkpoint_step(folder: Path | None) -> int | None:
    """The step of the checkpoint in ``folder`` (one :func:`find_checkpoint` found); None without a readable one."""
    meta = None if folder is None else _read_meta(folder)
    try:
        return None if meta is None else int(meta["num_timesteps"])
    except (KeyError, TypeError, ValueError):
        return None


def last_step(run_dir: Path) -> int | None:
    """The step of the newest ``last`` checkpoint of ``run_dir``; None when it has none."""
    return checkpoint_step(find_checkpoint(checkpoint_dir(run_dir, LAST)))


def checkpoint_config(folder: Path) -> dict[str, Any] | None:
    """The config a checkpoint was trained with (``meta.json``), or None for a checkpoint written before it was kept."""
    meta = _read_meta(folder)
    return None if meta is None else meta.get("config")


def verify_checkpoint(folder: Path, need_buffer: bool = True) -> str | None:
    """What is wrong with the checkpoint in ``folder``, or None when every file is there and matches ``meta.json``."""
    meta = _read_meta(folder)
    if meta is None:
        return f"{META_FILE} is missing or unreadable"
    files = list(meta.get("files", []))
    if need_buffer and REPLAY_BUFFER_FILE not in files:
        return "it has no replay buffer, so training cannot continue from it"
    for name in files:
        path = folder / name
        if not path.is_file():
            return f"{name} is missing"
        size = meta.get("sizes", {}).get(name)
        if size is not None and path.stat().st_size != size:
            return f"{name} has {path.stat().st_size} bytes where {size} were written (cut short or damaged)"
        digest = meta.get("sha256", {}).get(name)
        if digest is not None and _digest(path) != digest:
            return f"{name} does not match its SHA-256 in {META_FILE} (damaged)"
        if digest is None and name == MODEL_FILE and not zipfile.is_zipfile(path):
            return f"{name} is not a readable zip file"
    return None


@dataclass
class Resumed:
    """What :func:`load_resumable` loaded: the model, the experiment state, the folder it came from, and the newer
    checkpoints it passed over with what was wrong with each."""

    model: OffPolicyAlgorithm
    experiment_state: dict[str, Any]
    path: Path
    skipped: list[tuple[Path, str]] = field(default_factory=list)


def load_resumable(run_dir: Path, load: Callable[[Path], tuple[OffPolicyAlgorithm, dict[str, Any]]]) -> Resumed:
    """Load the newest whole ``last`` checkpoint of ``run_dir`` with ``load(folder)``, falling back to older ones.

    The one loaded is then made ``checkpoints/last`` (a damaged newer one is renamed ``<name>.damaged``, never
    deleted), so that the run's next save keeps it as ``last.prev``.
    :raises ConfigError: no checkpoint could be loaded; the message lists each one and what was wrong
    """
    target = checkpoint_dir(run_dir, LAST)
    skipped: list[tuple[Path, str]] = []
    for candidate in _candidates(target):
        problem = verify_checkpoint(candidate)
        if problem is None:
            try:
                model, state = load(candidate)
            except (OSError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError, KeyError) as error:
                problem = f"loading it failed ({type(error).__name__}: {error})"
        if problem is not None:
            skipped.append((candidate, problem))
            continue
        for path, why in skipped:
            log.warning("Checkpoint %s is not usable: %s", path, why)
        if skipped:
            log.warning("Resuming from the older checkpoint %s (step %d) instead", candidate, model.num_timesteps)
        _settle(target, candidate, [path for path, _ in skipped])
        return Resumed(model, state, candidate, skipped)
    if not skipped:
        raise ConfigError(
            f"resume={run_dir}: this folder has no complete checkpoint ({target}/{META_FILE} is missing). A run writes "
            "one every checkpoint.freq steps, at the end and on SIGINT/SIGTERM; a run killed before its first "
            "checkpoint cannot be resumed: start it again in a new run_dir."
        )
    problems = "; ".join(f"{path.name}: {why}" for path, why in skipped)
    raise ConfigError(
        f"resume={run_dir}: no checkpoint of this run could be loaded ({problems}). The files are left as they are; "
        "a run cannot continue without a whole checkpoint, start it again in a new run_dir."
    )


def _settle(target: Path, loaded: Path, damaged: list[Path]) -> None:
    """Make the checkpoint ``loaded`` the ``target`` folder: finish a save cut between its renames, and move damaged
    newer checkpoints aside as ``<name>.damaged``."""
    for path in damaged:
        if path != loaded:
            aside = _sibling(path, DAMAGED)
            shutil.rmtree(aside, ignore_errors=True)
            os.replace(path, aside)
    if loaded == _sibling(target, ".tmp"):
        _promote(target)
    elif loaded != target:
        if target.exists():  # newer but without a readable meta.json: a partial leftover, kept aside
            aside = _sibling(target, DAMAGED)
            shutil.rmtree(aside, ignore_errors=True)
            os.replace(target, aside)
        os.replace(loaded, target)
        _fsync_dir(target.parent)


def resume_checkpoint(run_dir: Path) -> Path:
    """The newest ``last`` checkpoint of ``run_dir`` (whole or not: :func:`load_resumable` checks); a
    :class:`ConfigError` saying what is missing otherwise."""
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
            "before its first checkpoint cannot be resumed: start it again in a new run_dir."
        )
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


def _fsync_dir(folder: Path) -> None:
    """Flush a folder's entries (creations, renames) to disk."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as error:  # some file systems cannot sync a directory; the renames are still atomic there
        if error.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def _digest(path: Path) -> str:
    sha = hashlib.sha256()
    with open(path, "rb") as file:
        while chunk := file.read(1 << 20):
            sha.update(chunk)
    return sha.hexdigest()


# Random number generators -------------------------------------------------------------------------------------------
def _streams(model: OffPolicyAlgorithm) -> RandomStreams:
    """The generators ``model`` draws from: its own streams (TD3X), else the global generators (SB3's algorithms)."""
    streams = getattr(model, "random_streams", None)
    return streams if isinstance(streams, RandomStreams) else RandomStreams(model.device)


def _rng_state(model: OffPolicyAlgorithm) -> dict[str, Any]:
    return {**_streams(model).state(), "action_space": model.action_space.np_random.bit_generator.state}


def _set_rng_state(model: OffPolicyAlgorithm, rng: dict[str, Any]) -> None:
    _streams(model).set_state(rng)
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
