"""A replay buffer kept as torch tensors on the training device, sampled by index: uniformly as SB3 samples, or in
proportion to priorities; with one-step or n-step returns."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize

from sb3_td3x.common.sum_tree import SumTree


class TensorReplayBufferSamples(NamedTuple):
    """A batch of :class:`TensorReplayBuffer`: SB3's ``ReplayBufferSamples`` fields first and in order (code written
    for SB3's batches reads it as one), then where each transition sits in the buffer and its importance weight."""

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    #: n-step returns: gamma ** (the steps summed in ``rewards``), shape (batch_size, 1); None for one-step returns.
    discounts: th.Tensor | None = None
    #: the row of each transition, ``position * n_envs + env``, shape (batch_size,): what
    #: :meth:`TensorReplayBuffer.update_priorities` takes.
    indices: th.Tensor | None = None
    #: prioritised sampling with ``beta > 0``: the importance-sampling weights, shape (batch_size, 1), the largest 1;
    #: None where every weight is 1 (uniform sampling, or ``beta=0`` as LAP).
    weights: th.Tensor | None = None


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
    Box observation spaces only; SB3's Dict and HER buffers are used for the rest.

    With a ``VecNormalize`` env, samples are normalised with the env's current statistics, as SB3 does. A batch is a
    :class:`TensorReplayBufferSamples`: SB3's fields, then the rows sampled (``indices``) and importance weights.

    **n-step returns** (``n_steps > 1``, what ``TD3X(n_steps=...)`` sets up, as SB3 sets up its
    ``NStepReplayBuffer``): the same batches as SB3's ``NStepReplayBuffer`` from the same transitions and indices.
    ``rewards`` is ``sum_k gamma^k r_{t+k}`` over the steps up to the first termination, truncation or the newest
    transition (at most ``n_steps``), ``next_observations`` and ``dones`` are those of that last step, and
    ``discounts`` is ``gamma ** (steps summed)``, by which the TD target discounts the bootstrapped value.

    **Prioritised sampling** (``alpha`` set): transition ``i`` is drawn with probability proportional to
    ``max(p_i, min_priority) ** alpha``, through a sum tree on the device
    (:class:`~sb3_td3x.common.sum_tree.SumTree`), from the owning model's torch stream. Priorities ``p`` are written by
    :meth:`update_priorities` (TD3X's ``update_priorities`` hook, after each critic step); a new transition gets the
    largest ``max(p, min_priority) ** alpha`` written so far (1 at first), as in TD7's LAP buffer (sfujim/TD7,
    buffer.py, lines 35, 48 and 73). With ``max_priority_reset_interval=k`` that largest value is set back to the
    largest one in the buffer every ``k`` updates, as TD7 does every 250 training steps (TD7.py, line 290). With
    ``beta > 0`` a batch carries importance-sampling weights ``(N P(i)) ** -beta``, divided by the batch's largest
    (Schaul et al. 2016). The priorities are pickled with the buffer (``save_replay_buffer``), so a resumed run
    samples what the run never stopped samples.

    :param n_steps: the number of steps summed into each return (1: one-step TD, SB3's ``ReplayBuffer``)
    :param gamma: the discount of the n-step returns (ignored with ``n_steps=1``)
    :param alpha: the priority exponent; ``None`` (the default) samples uniformly, as SB3 does
    :param beta: the importance-sampling exponent of prioritised sampling; 0 gives no weights (LAP)
    :param min_priority: priorities are raised to at least this before the exponent (LAP: 1; a small epsilon for
        proportional prioritised replay, so that no transition gets probability 0)
    :param max_priority_reset_interval: every this many :meth:`update_priorities`, the priority of new transitions is
        set back to the largest in the buffer (TD7: 250); 0 never does (it only grows)
    """

    # The storage tensors (``next_observations`` is None with ``optimize_memory_usage``).
    STORAGE = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
    # Defaults for buffers pickled before these options existed.
    n_steps = 1
    gamma = 0.99
    alpha: float | None = None
    beta = 0.0
    min_priority = 1e-6
    max_priority_reset_interval = 0
    priorities: SumTree | None = None

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_steps: int = 1,
        gamma: float = 0.99,
        alpha: float | None = None,
        beta: float = 0.0,
        min_priority: float = 1e-6,
        max_priority_reset_interval: int = 0,
    ):
        self._check_options(optimize_memory_usage, n_steps, gamma, alpha, beta, min_priority, max_priority_reset_interval)
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
        self.n_steps, self.gamma = n_steps, gamma
        self.alpha, self.beta, self.min_priority = alpha, beta, min_priority
        self.max_priority_reset_interval = max_priority_reset_interval
        self._allocate(get_device(device))

    @staticmethod
    def _check_options(
        optimize_memory_usage: bool, n_steps: int, gamma: float, alpha: float | None, beta: float, min_priority: float,
        max_priority_reset_interval: int,
    ) -> None:  # fmt: skip
        def fail(message: str) -> None:
            raise ValueError(f"TensorReplayBuffer: {message}")

        if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
            fail(f"n_steps={n_steps!r} must be an integer >= 1 (1: one-step returns)")
        if n_steps > 1 and optimize_memory_usage:
            fail(
                "n-step returns (n_steps > 1) need the next observations: pass optimize_memory_usage=False "
                "(as SB3's NStepReplayBuffer)"
            )
        if not 0.0 <= gamma <= 1.0:
            fail(f"gamma={gamma!r} must be in [0, 1]")
        if alpha is None:
            if beta != 0.0 or min_priority != 1e-6 or max_priority_reset_interval != 0:
                fail(
                    "beta, min_priority and max_priority_reset_interval are options of prioritised sampling, which "
                    "samples uniformly without alpha: pass alpha (e.g. 0.6) too"
                )
            return
        if optimize_memory_usage:
            fail(
                "prioritised sampling (alpha) needs optimize_memory_usage=False: the newest row's transition is not "
                "stored whole"
            )
        if not (np.isfinite(alpha) and alpha >= 0):
            fail(f"alpha={alpha!r} must be a finite float >= 0 (None: uniform sampling)")
        if not (np.isfinite(beta) and beta >= 0):
            fail(f"beta={beta!r} must be a finite float >= 0 (0: no importance weights)")
        if not (np.isfinite(min_priority) and min_priority > 0):
            fail(f"min_priority={min_priority!r} must be a finite float > 0, so that every transition can be drawn")
        if (
            isinstance(max_priority_reset_interval, bool)
            or not isinstance(max_priority_reset_interval, (int, np.integer))
            or max_priority_reset_interval < 0
        ):
            fail(f"max_priority_reset_interval={max_priority_reset_interval!r} must be an integer >= 0 (0: never)")

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
        if self.alpha is not None:
            # One leaf per row (position * n_envs + env): max(p, min_priority) ** alpha, 0 where nothing is stored.
            self.priorities = SumTree(size * n, device, with_maxima=self.max_priority_reset_interval > 0)
            self.max_priority = th.ones((), device=device)  # what a new transition gets (TD7: 1 at first)
            self.priority_updates = th.zeros((), dtype=th.long, device=device)

    @property
    def prioritized(self) -> bool:
        """Whether batches are drawn in proportion to priorities (``alpha`` set)."""
        return self.priorities is not None

    # The device can be changed after loading (SB3 does ``replay_buffer.device = model.device``): move the storage.
    @property
    def device(self) -> th.device:
        return self._device

    @device.setter
    def device(self, device: th.device | str) -> None:
        device = get_device(device)
        if hasattr(self, "observations") and device != self._device:
            self.__dict__.update(self._tensors_on(device))
            self.__dict__.pop("_views", None)
        self._device = device

    def _tensors_on(self, device: th.device) -> dict[str, Any]:
        """The storage tensors and the priorities, moved to ``device``, by attribute name."""
        moved: dict[str, Any] = {}
        for name in self.STORAGE:
            tensor = getattr(self, name)
            if tensor is not None:
                moved[name] = tensor.to(device)
        if self.priorities is not None:
            moved["priorities"] = self.priorities.to(device)
            moved["max_priority"] = self.max_priority.to(device)
            moved["priority_updates"] = self.priority_updates.to(device)
        return moved

    def nbytes(self) -> int:
        """Bytes held by the storage tensors and the priorities."""
        tensors = (getattr(self, name) for name in self.STORAGE)
        priorities = 0 if self.priorities is None else self.priorities.nbytes()
        return sum(t.numel() * t.element_size() for t in tensors if t is not None) + priorities

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
        if self.priorities is not None:  # each new transition: the largest priority so far (TD7's buffer.py, line 48)
            rows = th.arange(pos * self.n_envs, (pos + 1) * self.n_envs, device=self._device)
            self.priorities.set(rows, self.max_priority.expand(self.n_envs))

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
        self._static_newest = th.zeros((), dtype=th.long, device=self._device)
        self._discount_powers()  # made now: a host-to-device copy cannot happen inside a capture
        self.refresh_static_bounds()

    def disable_static_sampling(self) -> None:
        """Sample as SB3 does again (indices from numpy's generator, bounds read at each call): for a model whose
        update no longer runs in CUDA graphs, where nothing would refresh the static bounds."""
        for name in ("_static_offset", "_static_span", "_static_newest"):
            self.__dict__.pop(name, None)

    def refresh_static_bounds(self) -> None:
        """Write the current valid index range into the static bound tensors (asynchronous fills, no sync)."""
        offset, span = self._valid_range()
        self._static_offset.fill_(offset)
        self._static_span.fill_(max(span, 1))
        self._static_newest.fill_((self.pos - 1) % self.buffer_size)

    def _valid_range(self) -> tuple[int, int]:
        """The transitions that can be sampled: indices ``(offset + k) % buffer_size`` for ``k`` in ``[0, span)``."""
        if self.optimize_memory_usage and self.full:
            # Index ``pos`` holds the newest next-observation, not a valid transition: skip it (as SB3 does).
            return self.pos + 1, self.buffer_size - 1
        return 0, self.buffer_size if self.full else self.pos

    @property
    def static_sampling(self) -> bool:
        return "_static_span" in self.__dict__

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> TensorReplayBufferSamples:  # type: ignore[override]
        """Uniform sample of ``batch_size`` transitions.

        Indices are drawn with numpy's global generator exactly as SB3's ``ReplayBuffer`` draws them (same calls, same
        order), so a seeded run samples the same transitions as SB3, and as SB3's Dict buffer for Dict observations;
        the gather itself happens on the storage device. With static sampling (CUDA graphs) they are drawn on the device.
        Prioritised sampling (``alpha`` set) draws one uniform number per transition from the model's torch stream
        instead (:meth:`_sample_prioritized`).
        """
        if self.priorities is not None:
            return self._sample_prioritized(batch_size, env)
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

    def _torch_generator(self) -> th.Generator | None:
        """The torch generator prioritised draws come from: the owning model's own stream where its streams are
        detached (a SeedBatch's model), else None: torch's global generator of the device, which is the model's."""
        streams = self.__dict__.get("random_streams")
        return None if streams is None or streams.bound else streams.torch(self._device)

    def _sample_prioritized(self, batch_size: int, env: VecNormalize | None) -> TensorReplayBufferSamples:
        """``batch_size`` rows drawn in proportion to their priority, as TD7's LAP buffer draws them (buffer.py, lines
        56-58: a uniform number times the total, searched in the cumulative sums), with their importance weights."""
        priorities = self.priorities
        assert priorities is not None
        u = th.rand(batch_size, device=self._device, generator=self._torch_generator())
        rows = priorities.find(u * priorities.total)
        weights = None
        if self.beta > 0:  # (N P(i)) ** -beta over its largest in the batch: (p_i / min_j p_j) ** -beta
            mass = priorities.leaves[rows]
            weights = (mass / mass.min()).pow(-self.beta).unsqueeze(1)
        if self.n_envs == 1:
            return self._gather(rows, None, env, weights)
        return self._gather(rows // self.n_envs, rows % self.n_envs, env, weights)

    @th.no_grad()
    def update_priorities(self, indices: th.Tensor, priorities: th.Tensor) -> None:
        """Set the priorities of the transitions at ``indices`` (a batch's ``indices``): each is drawn in proportion to
        ``max(p, min_priority) ** alpha`` from now on. As TD7's LAP buffer (sfujim/TD7, buffer.py, lines 71-77, with
        TD7.py line 262 computing the exponent): the priority given to new transitions becomes the largest written so
        far, and with ``max_priority_reset_interval=k`` it is set back to the largest in the buffer every ``k`` calls.
        Tensor operations only (no host synchronisation): a transition drawn twice in the batch keeps the larger.

        :param indices: shape (batch_size,), the rows ``position * n_envs + env``
        :param priorities: shape (batch_size,) or (batch_size, 1), e.g. the largest |TD error| of the critics
        """
        if self.priorities is None:
            raise ValueError(
                "update_priorities: this TensorReplayBuffer samples uniformly; pass alpha (replay_buffer_kwargs="
                "{'alpha': 0.6}) for prioritised sampling"
            )
        mass = priorities.detach().float().reshape(-1).clamp(min=self.min_priority).pow(self.alpha)
        self.priorities.set(indices, mass)
        th.maximum(self.max_priority, mass.max(), out=self.max_priority)
        if self.max_priority_reset_interval:
            self.priority_updates.add_(1)
            reset = self.priority_updates % self.max_priority_reset_interval == 0
            self.max_priority.copy_(th.where(reset, self.priorities.max, self.max_priority))

    def reset_max_priority(self) -> None:
        """The priority of new transitions set back to the largest in the buffer (TD7's buffer.py, lines 76-77)."""
        if self.priorities is None:
            raise ValueError("reset_max_priority: this TensorReplayBuffer samples uniformly (no alpha)")
        self.max_priority.copy_(self.priorities.leaves.max())

    def _get_samples(self, batch_inds: np.ndarray | th.Tensor, env: VecNormalize | None = None) -> TensorReplayBufferSamples:
        # Drawn as SB3 draws them, one env (always 0) included: the generator moves on as in SB3.
        env_inds = self._np_random().randint(0, high=self.n_envs, size=(len(batch_inds),))
        batch = th.as_tensor(batch_inds, device=self._device)
        return self._gather(batch, None if self.n_envs == 1 else th.as_tensor(env_inds, device=self._device), env)

    def _gather(
        self, batch_inds: th.Tensor, env_inds: th.Tensor | None, env: VecNormalize | None, weights: th.Tensor | None = None
    ) -> TensorReplayBufferSamples:
        # One flat row index per transition and ``index_select`` on (buffer_size * n_envs, ...) views: a third of the
        # time of indexing with the two index tensors. One env (``env_inds`` None): the row is the index.
        rows = batch_inds if env_inds is None else batch_inds * self.n_envs + env_inds
        if self.n_steps > 1:
            return self._gather_n_steps(batch_inds, env_inds, rows, env, weights)

        take = self._take
        if self.optimize_memory_usage:
            next_rows = (batch_inds + 1) % self.buffer_size * self.n_envs
            next_obs = take(self.observations, next_rows if env_inds is None else next_rows + env_inds)
        else:
            next_obs = take(self.next_observations, rows)  # type: ignore[arg-type]
        obs = take(self.observations, rows)
        dones = self._terminations(rows)
        rewards = take(self.rewards, rows).unsqueeze(1)
        if env is not None:
            obs, next_obs = self._normalize(obs, env), self._normalize(next_obs, env)
            rewards = self._normalize_rew(rewards, env)
        return TensorReplayBufferSamples(obs, take(self.actions, rows), next_obs, dones, rewards, None, rows, weights)

    @staticmethod
    def _take(storage: th.Tensor, rows: th.Tensor) -> th.Tensor:
        """The ``rows`` of a (buffer_size, n_envs, ...) storage tensor, through its (buffer_size * n_envs, ...) view."""
        return storage.view(-1, *storage.shape[2:]).index_select(0, rows)

    def _terminations(self, rows: th.Tensor) -> th.Tensor:
        """Shape (len(rows), 1): 1 where the transition ended its episode by a termination (a done that is not a
        time-limit truncation), 0 otherwise."""
        return (self._take(self.dones, rows) * (1 - self._take(self.timeouts, rows))).unsqueeze(1)

    def _gather_n_steps(
        self,
        batch_inds: th.Tensor,
        env_inds: th.Tensor | None,
        rows: th.Tensor,
        env: VecNormalize | None,
        weights: th.Tensor | None,
    ) -> TensorReplayBufferSamples:
        """The n-step transitions starting at ``rows``: SB3's ``NStepReplayBuffer._get_samples`` (SB3 2.7) in tensor
        operations, with the same arithmetic in the same order (float32, the powers of gamma computed as SB3 computes
        them): the same bits as SB3's for ``n_steps < 8`` (numpy sums 8 terms or more pairwise: to float rounding)."""
        n = self.n_steps
        steps = th.arange(n, device=self._device)
        sequence = (batch_inds.unsqueeze(1) + steps) % self.buffer_size  # (batch, n): positions, wrapping around
        sequence_rows = sequence if env_inds is None else sequence * self.n_envs + env_inds.unsqueeze(1)
        rewards = self.rewards.view(-1)[sequence_rows]  # (batch, n)
        if env is not None:
            rewards = self._normalize_rew(rewards, env)
        # A sequence stops at the first termination or truncation, and at the newest transition (SB3 marks it
        # truncated for the time of the call, so that no sequence runs from the newest into the oldest).
        stop = (self.dones.view(-1)[sequence_rows] > 0) | (self.timeouts.view(-1)[sequence_rows] > 0)
        stop = stop | (sequence == self._newest_position())
        stop_count = stop.to(th.int32).cumsum(1)
        kept = (stop_count - stop.to(th.int32)) == 0  # (batch, n): the steps up to and including the first stop
        n_kept = kept.sum(1)  # (batch,), in [1, n]
        powers = self._discount_powers()  # (n + 1,): gamma ** k
        terms = rewards * powers[:n] * kept  # (batch, n)
        n_step_returns = terms[:, :1]  # (batch, 1): summed in order, as numpy sums fewer than 8 terms (the same bits)
        for k in range(1, n):
            n_step_returns = n_step_returns + terms[:, k : k + 1]
        discounts = powers[n_kept].unsqueeze(1)  # (batch, 1): gamma ** (steps summed)
        last = (batch_inds + n_kept - 1) % self.buffer_size
        last_rows = last if env_inds is None else last * self.n_envs + env_inds
        next_obs = self._take(self.next_observations, last_rows)  # type: ignore[arg-type]
        dones = self._terminations(last_rows)
        obs = self._take(self.observations, rows)
        if env is not None:
            obs, next_obs = self._normalize(obs, env), self._normalize(next_obs, env)
        return TensorReplayBufferSamples(
            obs, self._take(self.actions, rows), next_obs, dones, n_step_returns, discounts, rows, weights
        )

    def _newest_position(self) -> th.Tensor | int:
        """The position of the newest transition: a device tensor with static sampling (CUDA graphs)."""
        if self.static_sampling:
            return self._static_newest
        return (self.pos - 1) % self.buffer_size

    def _discount_powers(self) -> th.Tensor:
        """``gamma ** k`` for k in [0, n_steps], float32 on the device, computed as SB3's NStepReplayBuffer does."""
        cached = self.__dict__.get("_powers")
        if cached is None or cached.device != self._device:
            powers = self.gamma ** np.arange(self.n_steps + 1, dtype=np.float32)
            cached = self._powers = th.as_tensor(powers, device=self._device)
        return cached

    def _normalize(self, obs: th.Tensor, env: VecNormalize) -> th.Tensor:
        normalized = env.normalize_obs(obs.cpu().numpy())
        return th.as_tensor(normalized, dtype=th.float32, device=self._device)

    def _normalize_rew(self, rewards: th.Tensor, env: VecNormalize) -> th.Tensor:
        normalized = env.normalize_reward(rewards.cpu().numpy()).astype(np.float32)
        return th.as_tensor(normalized, device=self._device)

    def __getstate__(self) -> dict[str, Any]:
        # Saved on the CPU so that a buffer saved on a GPU machine loads anywhere.
        state = self.__dict__.copy()
        state.update(self._tensors_on(th.device("cpu")))
        state["_device"] = th.device("cpu")
        # Views, static sampling bounds, cached powers and the model's streams belong to this process; the loader sets
        # them up again.
        for name in ("_views", "_static_offset", "_static_span", "_static_newest", "_powers", "random_streams"):
            state.pop(name, None)
        return state
