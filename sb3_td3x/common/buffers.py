"""A replay buffer kept as torch tensors on the training device, sampled by index."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize


def _storage_dtype(np_dtype: np.dtype) -> th.dtype:
    """float64 is stored as float32 (what the networks read); other dtypes (uint8 images...) are kept."""
    if np.issubdtype(np_dtype, np.floating):
        return th.float32
    return th.from_numpy(np.zeros(0, dtype=np_dtype)).dtype


class TensorReplayBuffer(ReplayBuffer):
    """
    SB3's ``ReplayBuffer`` (same constructor, same ``add``/``sample`` contract, same samples) stored as torch tensors.

    Transitions are written once into preallocated tensors on ``device`` and a batch is gathered there by index: no
    numpy-to-torch copy per batch and, on a GPU, no host-to-device transfer per batch. Floating-point observations
    are stored as float32 (the dtype the networks read), which halves the memory of float64 spaces such as MuJoCo's.
    Box observation spaces only; SB3's Dict, n-step and HER buffers are used for the rest.

    With a ``VecNormalize`` env, samples are normalised with the env's current statistics, as SB3 does.
    """

    # The storage tensors (``next_observations`` is None with ``optimize_memory_usage``).
    STORAGE = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
    ):
        if not isinstance(observation_space, spaces.Box):
            raise ValueError(
                f"TensorReplayBuffer stores Box observations, got {observation_space!r}; "
                "use SB3's DictReplayBuffer for Dict observations (replay_buffer_class=None picks it)."
            )
        if optimize_memory_usage and handle_timeout_termination:
            raise ValueError(
                "ReplayBuffer does not support optimize_memory_usage = True and handle_timeout_termination = True "
                "simultaneously: pass replay_buffer_kwargs=dict(handle_timeout_termination=False)."
            )
        # BaseBuffer's set-up (shapes, device, pos/full), without ReplayBuffer's numpy arrays.
        super(ReplayBuffer, self).__init__(buffer_size, observation_space, action_space, device, n_envs=n_envs)
        self.buffer_size = max(buffer_size // n_envs, 1)
        self.optimize_memory_usage = optimize_memory_usage
        self.handle_timeout_termination = handle_timeout_termination
        self._allocate(get_device(device))

    def _allocate(self, device: th.device) -> None:
        size, n = self.buffer_size, self.n_envs
        obs_dtype = _storage_dtype(self.observation_space.dtype)

        def zeros(*shape: int, dtype: th.dtype = th.float32) -> th.Tensor:
            if device.type == "cpu":
                # numpy's zeros take zero pages from the OS lazily: a 1M-transition buffer costs nothing until filled
                # (torch.zeros writes every byte up front, seconds for MuJoCo sizes).
                return th.from_numpy(np.zeros(shape, dtype=th.empty(0, dtype=dtype).numpy().dtype))
            return th.zeros(shape, dtype=dtype, device=device)

        self.observations = zeros(size, n, *self.obs_shape, dtype=obs_dtype)
        self.next_observations = None if self.optimize_memory_usage else zeros(size, n, *self.obs_shape, dtype=obs_dtype)
        self.actions = zeros(size, n, self.action_dim)
        self.rewards = zeros(size, n)
        self.dones = zeros(size, n)
        self.timeouts = zeros(size, n)
        self._device = device

    # The device can be changed after loading (SB3 does ``replay_buffer.device = model.device``): move the storage.
    @property
    def device(self) -> th.device:
        return self._device

    @device.setter
    def device(self, device: th.device | str) -> None:
        device = get_device(device)
        if hasattr(self, "observations") and device != self._device:
            for name in self.STORAGE:
                tensor = getattr(self, name)
                if tensor is not None:
                    setattr(self, name, tensor.to(device))
            self.__dict__.pop("_views", None)
        self._device = device

    def nbytes(self) -> int:
        """Bytes held by the storage tensors."""
        tensors = (getattr(self, name) for name in self.STORAGE)
        return sum(t.numel() * t.element_size() for t in tensors if t is not None)

    @th.no_grad()
    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        pos = self.pos
        next_pos = (pos + 1) % self.buffer_size
        timeouts = [info.get("TimeLimit.truncated", False) for info in infos] if self.handle_timeout_termination else None
        if self._device.type == "cpu":
            # numpy views of the CPU tensors: one cast-and-copy per field, no tensor created per step.
            views = self._numpy_views()
            views["observations"][pos] = np.reshape(obs, views["observations"].shape[1:])
            if self.optimize_memory_usage:
                views["observations"][next_pos] = np.reshape(next_obs, views["observations"].shape[1:])
            else:
                views["next_observations"][pos] = np.reshape(next_obs, views["next_observations"].shape[1:])
            views["actions"][pos] = np.reshape(action, (self.n_envs, self.action_dim))
            views["rewards"][pos] = np.reshape(reward, self.n_envs)
            views["dones"][pos] = np.reshape(done, self.n_envs)
            if timeouts is not None:
                views["timeouts"][pos] = np.asarray(timeouts, dtype=np.float32).reshape(self.n_envs)
        else:

            def put(tensor: th.Tensor, index: int, value: Any) -> None:
                tensor[index].copy_(th.as_tensor(np.asarray(value)).reshape(tensor.shape[1:]), non_blocking=True)

            put(self.observations, pos, obs)
            if self.optimize_memory_usage:
                put(self.observations, next_pos, next_obs)
            else:
                put(self.next_observations, pos, next_obs)  # type: ignore[arg-type]
            put(self.actions, pos, action)
            put(self.rewards, pos, reward)
            put(self.dones, pos, done)
            if timeouts is not None:
                put(self.timeouts, pos, np.asarray(timeouts, dtype=np.float32))

        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True
            self.pos = 0

    def _numpy_views(self) -> dict[str, np.ndarray]:
        """numpy arrays sharing memory with the CPU storage tensors (rebuilt after a move or a load)."""
        views = self.__dict__.get("_views")
        if views is None or views["_owner"] is not self.observations:
            views = {name: getattr(self, name).numpy() for name in self.STORAGE if getattr(self, name) is not None}
            views["_owner"] = self.observations
            self._views = views
        return views

    def enable_static_sampling(self) -> None:
        """Sample with bounds held in device tensors, so that a captured CUDA graph samples the buffer as it grows.

        Call :meth:`refresh_static_bounds` before each replay; indices are ``(offset + floor(u * span)) % size``.
        """
        self._static_offset = th.zeros((), dtype=th.long, device=self._device)
        self._static_span = th.ones((), dtype=th.float32, device=self._device)
        self.refresh_static_bounds()

    def disable_static_sampling(self) -> None:
        """Sample as SB3 does again (indices from numpy's generator, bounds read at each call): for a model whose
        update no longer runs in CUDA graphs, where nothing would refresh the static bounds."""
        for name in ("_static_offset", "_static_span"):
            self.__dict__.pop(name, None)

    def refresh_static_bounds(self) -> None:
        """Write the current valid index range into the static bound tensors (asynchronous fills, no sync)."""
        offset, span = self._valid_range()
        self._static_offset.fill_(offset)
        self._static_span.fill_(max(span, 1))

    def _valid_range(self) -> tuple[int, int]:
        """The transitions that can be sampled: indices ``(offset + k) % buffer_size`` for ``k`` in ``[0, span)``."""
        if self.optimize_memory_usage and self.full:
            # Index ``pos`` holds the newest next-observation, not a valid transition: skip it (as SB3 does).
            return self.pos + 1, self.buffer_size - 1
        return 0, self.buffer_size if self.full else self.pos

    @property
    def static_sampling(self) -> bool:
        return "_static_span" in self.__dict__

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        """Uniform sample of ``batch_size`` transitions.

        Indices are drawn with numpy's global generator exactly as SB3's ``ReplayBuffer`` draws them (same calls, same
        order), so a seeded run samples the same transitions as SB3, and as SB3's Dict buffer for Dict observations;
        the gather itself happens on the storage device. With static sampling (CUDA graphs) they are drawn on the device.
        """
        if self.static_sampling:
            u = th.rand(batch_size, device=self._device)
            steps = th.minimum((u * self._static_span).long(), self._static_span.long() - 1)
            batch_inds = (self._static_offset + steps) % self.buffer_size
            env_inds = th.randint(0, self.n_envs, (batch_size,), device=self._device)
            return self._gather(batch_inds, env_inds, env)
        # numpy's randint(0, span) draws what SB3's randint(0, upper) / randint(1, buffer_size) draw.
        offset, span = self._valid_range()
        np_inds = (offset + self._np_random().randint(0, span, size=batch_size)) % self.buffer_size
        return self._get_samples(np_inds, env=env)

    def _np_random(self) -> Any:
        """The numpy generator indices are drawn from: the owning model's stream (``TD3X.random_streams``, numpy's
        global generator unless detached), else numpy's global one."""
        streams = self.__dict__.get("random_streams")
        return np.random if streams is None else streams.numpy

    def _get_samples(self, batch_inds: np.ndarray | th.Tensor, env: VecNormalize | None = None) -> ReplayBufferSamples:
        # Drawn as SB3 draws them, one env (always 0) included: the generator moves on as in SB3.
        env_inds = self._np_random().randint(0, high=self.n_envs, size=(len(batch_inds),))
        batch = th.as_tensor(batch_inds, device=self._device)
        return self._gather(batch, None if self.n_envs == 1 else th.as_tensor(env_inds, device=self._device), env)

    def _gather(self, batch_inds: th.Tensor, env_inds: th.Tensor | None, env: VecNormalize | None) -> ReplayBufferSamples:
        # One flat row index per transition and ``index_select`` on (buffer_size * n_envs, ...) views: a third of the
        # time of indexing with the two index tensors. One env (``env_inds`` None): the row is the index.
        rows = batch_inds if env_inds is None else batch_inds * self.n_envs + env_inds

        def take(storage: th.Tensor, index: th.Tensor = rows) -> th.Tensor:
            return storage.view(-1, *storage.shape[2:]).index_select(0, index)

        if self.optimize_memory_usage:
            next_rows = (batch_inds + 1) % self.buffer_size * self.n_envs
            next_obs = take(self.observations, next_rows if env_inds is None else next_rows + env_inds)
        else:
            next_obs = take(self.next_observations)  # type: ignore[arg-type]
        obs = take(self.observations)
        # Only use dones that are not due to timeouts
        dones = (take(self.dones) * (1 - take(self.timeouts))).unsqueeze(1)
        rewards = take(self.rewards).unsqueeze(1)
        if env is not None:
            obs, next_obs = self._normalize(obs, env), self._normalize(next_obs, env)
            rewards = self._normalize_rew(rewards, env)
        return ReplayBufferSamples(obs, take(self.actions), next_obs, dones, rewards)

    def _normalize(self, obs: th.Tensor, env: VecNormalize) -> th.Tensor:
        normalized = env.normalize_obs(obs.cpu().numpy())
        return th.as_tensor(normalized, dtype=th.float32, device=self._device)

    def _normalize_rew(self, rewards: th.Tensor, env: VecNormalize) -> th.Tensor:
        normalized = env.normalize_reward(rewards.cpu().numpy()).astype(np.float32)
        return th.as_tensor(normalized, device=self._device)

    def __getstate__(self) -> dict[str, Any]:
        # Saved on the CPU so that a buffer saved on a GPU machine loads anywhere.
        state = self.__dict__.copy()
        for name in self.STORAGE:
            if state.get(name) is not None:
                state[name] = state[name].cpu()
        state["_device"] = th.device("cpu")
        # Views, static sampling bounds and the model's streams belong to this process; the loader sets them up again.
        for name in ("_views", "_static_offset", "_static_span", "random_streams"):
            state.pop(name, None)
        return state
