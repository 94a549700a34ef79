"""Many seeds in one process: the gradient steps of N independent TD3X models computed together (issue 17).

:class:`SeedStackedMlpUpdate` trains N :class:`~sb3_td3x.TD3X` models, each one a full SB3 model with its own
replay buffer, optimizers, logger, ``save`` and ``load``, so that seed ``i`` computes what the lone model ``i``
computes with :class:`~.mlp.MlpUpdate` (its default update): the same sampled transitions, the same target smoothing
noise, the same weights and optimizer states to float rounding. Only the arithmetic is shared:

- each role's weights (actor, actor target, critics, critic targets) of all N models live in one
  :class:`~.mlp.MlpStack`, a leading axis of N seeds (times ``n_critics`` for the critics); every model's Parameters
  are views of it, so its optimizers, target updates, ``save`` and ``load`` see its own parameters as before;
- each layer of every seed's network runs in one batched product (``baddbmm``/``bmm``), forward and backward;
- the optimizers are each model's own, and so are the target updates (its ``update_critic_target`` and
  ``update_actor_target`` hooks). With ``fuse=True`` (the default), the fused Adam (or AdamW) steps of all seeds with
  equal options are one kernel call, and the stock target updates of all seeds with equal ``tau`` one
  ``_foreach_lerp_``: both are elementwise, so each tensor gets what its own model's call gives it, to the bit
  (``tests/equivalence/test_seed_stack.py`` checks it); anything else steps per seed. ``should_update_actor``,
  ``_n_updates``, ``_n_actor_updates``, the learning-rate schedules and the logged statistics are each model's, as
  :meth:`TD3X.train` keeps them.

**Random numbers.** A lone TD3X draws from the global generators that SB3's ``set_random_seed`` seeds: step 4's
indices from numpy's (``np.random.randint``, in the replay buffer), step 6's noise from torch's (``th.randn``), and a
``sample_batch`` of the user's may draw from any of them, or from Python's ``random``. So each seed keeps its own
:class:`GlobalRandomState` (Python's, numpy's and torch's generator states, and the CUDA generator's on a GPU), and
its draws run with that state swapped in: ``model.sample_batch(batch_size)`` then the noise, drawn exactly as
``MlpUpdate`` draws it. What the lone model's code draws, it draws from the same state, in the same order, whatever
it draws with. The caller's global state is put back after each ``train()`` call. Swapping costs a state copy per
generator per seed and step (numpy's is the dearest, tens of microseconds); per-seed ``th.Generator`` objects would
be cheaper for the noise, but a ``sample_batch`` drawing from torch's global generator would then silently draw
from a stream shared by all seeds.

**What it assumes.** Every model is one ``MlpUpdate`` would train (:meth:`SeedStackedMlpUpdate.requirements`: the
hooks ``MlpUpdate`` replaces as written, SB3's ReLU MLP actor and critics...), in fp32, uncompiled, without CUDA
graphs; the models share what enters the batched arithmetic (the architecture, the device, ``gamma``, ``n_steps``,
the target smoothing and clipped double-Q settings, ``flush_denormals``). Anything else (learning rates and their
schedules, ``tau``, the optimizers, ``policy_delay`` or an overridden ``should_update_actor``, ``sample_batch``, the
target-update hooks) runs per model and may differ. Otherwise :class:`SeedStackedMlpUpdate` refuses with every
reason (:meth:`SeedStackedMlpUpdate.why_not_together`).

The N random states are the caller's to give: the global state each model's lone run would hold when its training
starts (:meth:`GlobalRandomState.capture` right after building the model and filling its buffer).
"""

from __future__ import annotations

import contextlib
import random
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th
from torch import nn

from sb3_td3x.common import denormals
from sb3_td3x.td3x.hooks import changed_hooks
from sb3_td3x.td3x.update_paths import requirements
from sb3_td3x.td3x.update_paths.mlp import (
    MlpStack,
    MlpUpdate,
    _matmul,
    _relu_backward,
    _tanh_backward,
    fused_adam_call,
    optimizer_step,
    run_fused_adam,
)
from sb3_td3x.td3x.update_paths.requirements import relu_mlp_layers

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]
Weights = tuple[list[th.Tensor], list[th.Tensor]]

# What enters the batched arithmetic: it must be the same in every model.
SHARED_SETTINGS = (
    "gamma",
    "n_steps",
    "target_policy_smoothing",
    "target_policy_noise",
    "target_noise_clip",
    "clipped_double_q",
    "flush_denormals",
)


@dataclass
class GlobalRandomState:
    """The states of the global generators SB3's ``set_random_seed`` seeds: Python's ``random``, numpy's, torch's
    CPU generator, and the CUDA generator of ``cuda_device`` when there is one."""

    python: Any
    numpy: Any
    torch: th.Tensor
    cuda: th.Tensor | None = None
    cuda_device: int | None = None

    @classmethod
    def capture(cls, device: th.device | str = "cpu") -> GlobalRandomState:
        """The current global state (and the CUDA generator's of ``device`` when it is a GPU)."""
        device = th.device(device)
        cuda_device = None
        if device.type == "cuda":
            cuda_device = device.index if device.index is not None else th.cuda.current_device()
        return cls(
            python=random.getstate(),
            numpy=np.random.get_state(),
            torch=th.get_rng_state(),
            cuda=None if cuda_device is None else th.cuda.get_rng_state(cuda_device),
            cuda_device=cuda_device,
        )

    def restore(self) -> None:
        """Make this the global state."""
        random.setstate(self.python)
        np.random.set_state(self.numpy)
        th.set_rng_state(self.torch)
        if self.cuda is not None:
            th.cuda.set_rng_state(self.cuda, self.cuda_device)


class SeedRandomStreams:
    """One :class:`GlobalRandomState` per seed: seed ``i``'s draws run with its state as the global one.

    Swaps are lazy: a seed's state stays the global one after its block until another seed's block (or the end of
    :meth:`kept_apart`) needs the generators, so one seed alone, or the same seed twice in a row, costs no swap.
    Code that runs inside :meth:`kept_apart` but outside every :meth:`seed` block must not draw random numbers (it
    would draw from the last seed's stream)."""

    def __init__(self, states: Sequence[GlobalRandomState], device: th.device | str = "cpu"):
        self.states = list(states)
        self.device = th.device(device)
        self._owner: int | None = None  # the seed whose state is the global one now, not yet captured

    def _release(self) -> None:
        if self._owner is not None:
            self.states[self._owner] = GlobalRandomState.capture(self.device)
            self._owner = None

    @contextlib.contextmanager
    def seed(self, i: int) -> Iterator[None]:
        """Seed ``i``'s state as the global one inside; what it draws is kept as seed ``i``'s state (in
        ``states[i]`` at the latest when another seed's block starts or :meth:`kept_apart` ends). The caller's state
        is not put back (:meth:`kept_apart` does that once around many blocks)."""
        if self._owner != i:
            self._release()
            self.states[i].restore()
            self._owner = i
        yield

    @contextlib.contextmanager
    def kept_apart(self) -> Iterator[None]:
        """The caller's global state, put back at the end (every seed's state kept in ``states`` first)."""
        outer_owner = self._owner
        self._release()  # nested: the live state of the outer block's seed is kept first (and is the "caller's")
        caller = GlobalRandomState.capture(self.device)
        try:
            yield
        finally:
            self._release()
            if outer_owner is None:
                caller.restore()
            else:  # the outer block's seed goes on from where the inner blocks left its stream
                self.states[outer_owner].restore()
                self._owner = outer_owner


def _per_critic(x: th.Tensor, n_critics: int) -> th.Tensor:
    """(N, batch, in) -> (N * n_critics, batch, in): each seed's input for each of its critics, seed-major."""
    return x.repeat_interleave(n_critics, dim=0)


def _first_critic(weights: Weights, n_critics: int) -> Weights:
    """Each seed's first critic, (N, out, in), from all critics' stacked (N * n_critics, out, in) weights."""
    return (
        [w.unflatten(0, (-1, n_critics))[:, 0] for w in weights[0]],
        [b.unflatten(0, (-1, n_critics))[:, 0] for b in weights[1]],
    )


def seed_critic_gradients(
    batch: tuple[th.Tensor, ...],
    discounts: th.Tensor | float,
    noise: th.Tensor | None,
    noise_clip: float,
    clipped_double_q: bool,
    n_critics: int,
    actor_target: Weights,
    critic_target: Weights,
    critic: Weights,
) -> tuple[list[th.Tensor], list[th.Tensor], dict[str, th.Tensor]]:
    """Steps 5 to 11 and the critics' gradients of N seeds at once: :func:`~.mlp.critic_gradients` with a seed axis.

    :param batch: (observations, actions, next_observations, rewards, dones), each (N, batch, dim)
    :param discounts: gamma, or the n-step discounts (N, batch, 1)
    :param noise: the target policy smoothing noise before clipping (N, batch, action_dim), or None
    :return: the critics' weight and bias gradients (stacked like the weights, (N * n_critics, ...)) and the
        statistics, one entry per seed: ``critic_loss`` and ``target_q`` (N,), ``q`` (N, n_critics)
    """
    obs, actions, next_obs, rewards, dones = batch
    n_seeds, batch_size = obs.shape[:2]
    next_actions, _ = MlpStack.forward(next_obs, *actor_target)  # step 5: (N, batch, action_dim)
    next_actions = next_actions.tanh_()
    if noise is not None:  # step 6
        next_actions = next_actions + noise.clamp(-noise_clip, noise_clip)
    next_actions = next_actions.clamp(-1.0, 1.0)
    next_q, _ = MlpStack.forward(_per_critic(th.cat([next_obs, next_actions], dim=2), n_critics), *critic_target)
    next_q = next_q.unflatten(0, (n_seeds, n_critics))  # step 7: (N, n_critics, batch, 1)
    next_q = next_q.min(dim=1).values if clipped_double_q else next_q[:, 0]  # step 8: (N, batch, 1)
    target_q = rewards + (1.0 - dones) * discounts * next_q  # step 9
    current_q, inputs = MlpStack.forward(_per_critic(th.cat([obs, actions], dim=2), n_critics), *critic)  # step 10
    td_errors = current_q.unflatten(0, (n_seeds, n_critics)) - target_q.unsqueeze(1)  # (N, n_critics, batch, 1)
    loss = td_errors.square().mean(dim=(2, 3)).sum(dim=1)  # step 11, per seed: (N,)
    # d loss / d Q_i = 2 (Q_i - y) / batch
    weight_grads, bias_grads = MlpStack.backward((td_errors * (2.0 / batch_size)).flatten(0, 1), inputs, critic[0])
    info = {
        "critic_loss": loss,
        "target_q": target_q.mean(dim=(1, 2)),
        "q": current_q.unflatten(0, (n_seeds, n_critics)).mean(dim=(2, 3)),
    }
    return weight_grads, bias_grads, info


def seed_actor_gradients(
    obs: th.Tensor, n_critics: int, actor: Weights, critic: Weights
) -> tuple[list[th.Tensor], list[th.Tensor], th.Tensor]:
    """Step 13's gradient of N seeds at once: :func:`~.mlp.actor_gradients` with a seed axis.

    :param obs: (N, batch, obs_dim)
    :return: the actors' weight and bias gradients (stacked like the weights, (N, ...)) and the losses (N,)
    """
    batch_size, obs_dim = obs.shape[1:]
    actions, actor_inputs = MlpStack.forward(obs, *actor)  # (N, batch, action_dim)
    actions = actions.tanh_()
    weights, biases = _first_critic(critic, n_critics)
    q, critic_inputs = MlpStack.forward(th.cat([obs, actions], dim=2), weights, biases)  # (N, batch, 1)
    loss = -q.mean(dim=(1, 2))
    # d J / d Q_1 = -1 / batch, back through each seed's first critic to its input
    grad = th.full_like(q, -1.0 / batch_size)
    for depth in range(len(weights) - 1, 0, -1):
        grad = _relu_backward(_matmul(grad, weights[depth]), critic_inputs[depth], 0)
    grad = th.bmm(grad, weights[0][:, :, obs_dim:])  # d J / d a: the action columns of the first layer only
    grad = _tanh_backward(grad, actions)
    weight_grads, bias_grads = MlpStack.backward(grad, actor_inputs, actor[0])
    return weight_grads, bias_grads, loss


def _compact_state_dict(module: nn.Module, state_dict: dict[str, Any], prefix: str, local_metadata: Any) -> None:
    """A state-dict post-hook: a tensor that is a view of a larger storage (here, of every seed's weights) is
    replaced by a copy of itself, so that ``torch.save`` (``model.save``) writes this model's weights only."""
    for name in ("weight", "bias"):
        key = prefix + name
        value = state_dict.get(key)
        if (
            isinstance(value, th.Tensor)
            and not isinstance(value, nn.Parameter)  # state_dict(keep_vars=True): the Parameters themselves
            and value.untyped_storage().nbytes() > value.numel() * value.element_size()
        ):
            state_dict[key] = value.clone()


class SeedStackedMlpUpdate(requirements.FastPath):
    """The gradient steps of N TD3X models computed together, each as its lone ``MlpUpdate`` computes it (see the
    module's docstring).

    :param models: the N models, one per seed (distinct, each one ``MlpUpdate`` would train, sharing
        :data:`SHARED_SETTINGS` and the architecture)
    :param random_states: each model's global random state at the start of its training, as its lone run would hold
        it (:meth:`GlobalRandomState.capture`); kept up to date in ``self.streams.states``. Or a
        :class:`SeedRandomStreams`, used as it is (its states are then the caller's too)
    :param fuse: the seeds' fused Adam steps and stock target updates in one call each where that computes the same
        (see the module's docstring); ``False`` steps each model's optimizers and calls its target-update hooks
    :param seeds_per_product: how many seeds' matrix products run as one batched call (default: all on a GPU, one
        on a CPU, where a larger call's operands outgrow the caches); the optimizer steps and target updates run
        over all seeds either way
    :raises ValueError: with every reason, when the models cannot be trained together exactly
    """

    replaces = MlpUpdate.replaces

    def __init__(
        self,
        models: Sequence[TD3X],
        random_states: Sequence[GlobalRandomState] | SeedRandomStreams,
        fuse: bool = True,
        seeds_per_product: int | None = None,
    ):
        reason = self.why_not_together(models)
        if reason is not None:
            raise ValueError(f"SeedStackedMlpUpdate cannot train these models together: {reason}.")
        streams = random_states if isinstance(random_states, SeedRandomStreams) else None
        if streams is not None:
            random_states = streams.states
        if len(random_states) != len(models):
            raise ValueError(f"SeedStackedMlpUpdate: {len(models)} models but {len(random_states)} random states.")
        self.models = list(models)
        self.fuse = fuse
        self.device = self.models[0].device
        if self.device.type == "cuda" and any(state.cuda is None for state in random_states):
            raise ValueError(
                f"SeedStackedMlpUpdate: the models are on {self.device}, so each random state needs the CUDA "
                "generator's too: GlobalRandomState.capture(model.device)."
            )
        # Shared with the caller when it gave its streams (SeedBatch: collection draws from the same ones).
        self.streams = streams if streams is not None else SeedRandomStreams(random_states, self.device)
        self.n_critics = len(self.models[0].critic.q_networks)
        if seeds_per_product is None:
            # On a CPU the products of all seeds in one call outgrow the caches (measured on Hopper, [400, 300],
            # 8 seeds: 4.6 ms of products per seed-step against 3.4 for one seed's); a GPU wants one large call.
            seeds_per_product = len(self.models) if self.device.type == "cuda" else 1
        if seeds_per_product < 1:
            raise ValueError(f"SeedStackedMlpUpdate: seeds_per_product={seeds_per_product} must be >= 1.")
        self.seeds_per_product = seeds_per_product
        self.actor = MlpStack([relu_mlp_layers(m.actor.mu, nn.Tanh) for m in self.models])  # type: ignore[misc]
        self.actor_target = MlpStack([relu_mlp_layers(m.actor_target.mu, nn.Tanh) for m in self.models])  # type: ignore[misc]
        # Seed-major: network s * n_critics + k is seed s's critic k.
        self.critic = MlpStack([relu_mlp_layers(q, None) for m in self.models for q in m.critic.q_networks])  # type: ignore[misc]
        self.critic_target = MlpStack(
            [relu_mlp_layers(q, None) for m in self.models for q in m.critic_target.q_networks]  # type: ignore[misc]
        )
        for stack in self._stacks():
            for lin in {id(lin): lin for net in stack.layers for lin in net}.values():
                if _compact_state_dict not in lin._state_dict_hooks.values():
                    lin.register_state_dict_post_hook(_compact_state_dict)

    # ------------------------------------------------------------------------------------------------------------
    @classmethod
    def requirements(cls, model: TD3X) -> list[str]:
        """Every assumption that ``model`` breaks (empty: its lone update would be ``MlpUpdate``, in fp32)."""
        reasons = MlpUpdate.requirements(model)
        # The batched update replaces the model's train() and what it calls around the gradient steps.
        reasons += changed_hooks(model, ("train", "_update_learning_rate", "_log_train_infos"))
        if not getattr(model, "mlp_update", True):
            reasons.append("mlp_update=False")
        if model.bf16:
            reasons.append("bf16=True (the seed-stacked update runs in fp32 only)")
        if model.compile_update:
            reasons.append("compile_update=True (the seed-stacked update is not compiled)")
        if model.cuda_graph:
            reasons.append("cuda_graph=True")
        return reasons

    @classmethod
    def why_not_together(cls, models: Sequence[TD3X]) -> str | None:
        """Why these models cannot be trained together exactly (every reason, joined), or ``None``."""
        if not models:
            return "no models"
        reasons = [f"model {i}: {reason}" for i, m in enumerate(models) if (reason := cls.why_not(m)) is not None]
        if reasons:
            return "; ".join(reasons)
        params = [p.data_ptr() for m in models for p in m.policy.parameters()]
        if len({id(m) for m in models}) != len(models):
            reasons.append("a model is given twice")
        elif len(set(params)) != len(params):
            reasons.append("models share parameters")
        first = models[0]
        shapes = cls._architecture(first)
        for i, m in enumerate(models[1:], start=1):
            if cls._architecture(m) != shapes:
                reasons.append(f"model {i}'s networks differ from model 0's ({cls._architecture(m)} != {shapes})")
            if m.device != first.device:
                reasons.append(f"model {i} is on {m.device}, model 0 on {first.device}")
            for name in SHARED_SETTINGS:
                if getattr(m, name, None) != getattr(first, name, None):
                    reasons.append(
                        f"model {i}'s {name} is {getattr(m, name, None)!r}, model 0's {getattr(first, name, None)!r}"
                    )
        return "; ".join(reasons) if reasons else None

    @staticmethod
    def _architecture(model: TD3X) -> dict[str, list[tuple[int, ...]]]:
        return {
            "actor": [tuple(lin.weight.shape) for lin in relu_mlp_layers(model.actor.mu, nn.Tanh)],  # type: ignore[union-attr]
            "critics": [
                [tuple(lin.weight.shape) for lin in relu_mlp_layers(q, None)]  # type: ignore[union-attr]
                for q in model.critic.q_networks
            ],
        }

    def _stacks(self) -> tuple[MlpStack, ...]:
        return (self.actor, self.actor_target, self.critic, self.critic_target)

    # ------------------------------------------------------------------------------------------------------------
    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """``model.train(gradient_steps, batch_size)`` for every model, the gradient steps computed together."""
        for model in self.models:
            model.policy.set_training_mode(True)
            model._update_learning_rate([model.actor.optimizer, model.critic.optimizer])
        critic_infos: list[list[dict[str, th.Tensor]]] = [[] for _ in self.models]
        actor_infos: list[list[dict[str, th.Tensor]]] = [[] for _ in self.models]
        flush = self.device.type == "cpu" and bool(getattr(self.models[0], "flush_denormals", True))
        with denormals.flush_denormals(flush), self.streams.kept_apart():
            for _ in range(gradient_steps):
                update_actor = []
                for model in self.models:
                    model._n_updates += 1
                    update_actor.append(model.should_update_actor(model._n_updates))  # step 13: delayed updates
                infos = self._step(batch_size, update_actor)
                for i, (model, (critic_info, actor_info)) in enumerate(zip(self.models, infos)):
                    critic_infos[i].append(critic_info)
                    if update_actor[i]:
                        model._n_actor_updates += 1
                        actor_infos[i].append(actor_info)
        for model, critic_info_list, actor_info_list in zip(self.models, critic_infos, actor_infos):
            model._log_train_infos(critic_info_list, actor_info_list)

    def step(self, batch_size: int, update_actor: Sequence[bool]) -> list[Infos]:
        """One gradient step (steps 4 to 15) of every model; ``update_actor[i]`` says whether model ``i``'s actor
        and targets are updated. Returns each model's statistics, as ``MlpUpdate`` does."""
        with self.streams.kept_apart():
            return self._step(batch_size, update_actor)

    def _step(self, batch_size: int, update_actor: Sequence[bool]) -> list[Infos]:
        for stack in self._stacks():
            stack.ensure_bound()
        batches, noises = self._draw(batch_size)
        with th.no_grad():
            critic_infos = self._update_critics(batches, noises)  # steps 5-12
            actor_infos: list[dict[str, th.Tensor]] = [{} for _ in self.models]
            if any(update_actor):
                actor_infos = self._update_actors(th.stack([b.observations for b in batches]), update_actor)  # step 13
        self._update_targets([model for model, update in zip(self.models, update_actor) if update])  # steps 14-15
        return list(zip(critic_infos, actor_infos))

    def _step_optimizers(self, optimizers: list[th.optim.Optimizer]) -> None:
        """Each optimizer's step; with ``fuse``, the fused Adams of equal options as one kernel call."""
        groups: dict[tuple[Any, ...], list[Any]] = {}
        for optimizer in optimizers:
            call = fused_adam_call(optimizer) if self.fuse else None
            if call is None:
                optimizer_step(optimizer)
            else:
                kernel, options, _ = call
                groups.setdefault((kernel, *sorted(options.items())), []).append(call)
        for calls in groups.values():
            run_fused_adam(calls)

    def _update_targets(self, models: list[TD3X]) -> None:
        """Steps 15 and 14 of ``models``: their own hooks; with ``fuse``, the stock ones of equal ``tau`` as one
        ``_foreach_lerp_`` (what each model's ``_polyak`` calls; no batch norm here, so nothing else to copy)."""
        groups: dict[float, tuple[list[th.Tensor], list[th.Tensor]]] = {}
        for model in models:
            if self.fuse and not changed_hooks(model, ("update_critic_target", "update_actor_target")):
                targets, params = groups.setdefault(float(model.tau), ([], []))
                targets += [*model._critic_target_params, *model._actor_target_params]
                params += [*model._critic_params, *model._actor_params]
            else:
                model.update_critic_target()  # step 15
                model.update_actor_target()  # step 14
        with th.no_grad():
            for tau, (targets, params) in groups.items():
                th._foreach_lerp_(targets, params, tau)

    def _draw(self, batch_size: int) -> tuple[list[Any], list[th.Tensor] | None]:
        """Each seed's batch (step 4) and target smoothing noise (step 6), from its own random stream, in the lone
        run's order: ``sample_batch``, then ``th.randn`` as ``MlpUpdate`` draws it."""
        batches, noises = [], []
        action_dim = self.actor_target.weights[-1].shape[1]
        for i, model in enumerate(self.models):
            with self.streams.seed(i):
                batch = model.sample_batch(batch_size)
                batches.append(batch)
                if model.target_policy_smoothing:
                    shape = (batch.next_observations.shape[0], action_dim)
                    noises.append(th.randn(shape, dtype=th.float32, device=batch.rewards.device) * model.target_policy_noise)
        return batches, (noises or None)

    def _update_critics(self, batches: list[Any], noises: list[th.Tensor] | None) -> list[dict[str, th.Tensor]]:
        """Steps 5 to 12 of every seed: the gradients together, each model's own critic optimizer."""
        first = self.models[0]
        stacked = tuple(
            th.stack([getattr(b, field) for b in batches])
            for field in ("observations", "actions", "next_observations", "rewards", "dones")
        )
        discounts: th.Tensor | float = first.gamma
        if getattr(batches[0], "discounts", None) is not None:
            discounts = th.stack([b.discounts for b in batches])
        noise = None if noises is None else th.stack(noises)
        nc = self.n_critics
        parts = [
            seed_critic_gradients(
                tuple(x[a:b] for x in stacked),
                discounts if isinstance(discounts, float) else discounts[a:b],
                None if noise is None else noise[a:b],
                float(first.target_noise_clip),
                bool(first.clipped_double_q),
                nc,
                _seeds(self.actor_target, a, b, 1),
                _seeds(self.critic_target, a, b, nc),
                _seeds(self.critic, a, b, nc),
            )
            for a, b in self._chunks()
        ]
        weight_grads, bias_grads, info = _joined(parts)
        self.critic.assign_grads(weight_grads, bias_grads)
        self._step_optimizers([model.critic.optimizer for model in self.models])  # step 12
        infos = []
        for i in range(len(self.models)):
            seed_info = {"critic_loss": info["critic_loss"][i], "target_q": info["target_q"][i]}
            for k in range(self.n_critics):
                seed_info[f"q{k + 1}"] = info["q"][i, k]
            infos.append(seed_info)
        return infos

    def _update_actors(self, obs: th.Tensor, update_actor: Sequence[bool]) -> list[dict[str, th.Tensor]]:
        """Step 13 of the seeds that update their actor (the gradients of all, computed together)."""
        parts = [
            seed_actor_gradients(
                obs[a:b], self.n_critics, _seeds(self.actor, a, b, 1), _seeds(self.critic, a, b, self.n_critics)
            )
            for a, b in self._chunks()
        ]
        weight_grads, bias_grads, loss = _joined(parts)
        infos: list[dict[str, th.Tensor]] = []
        for i, update in enumerate(update_actor):
            if update:
                for depth, lin in enumerate(self.actor.layers[i]):
                    lin.weight.grad = weight_grads[depth][i]
                    lin.bias.grad = bias_grads[depth][i]
            infos.append({"actor_loss": loss[i]} if update else {})
        self._step_optimizers([m.actor.optimizer for m, update in zip(self.models, update_actor) if update])
        return infos

    def _chunks(self) -> list[tuple[int, int]]:
        """The groups of seeds whose products run as one batched call (``seeds_per_product`` each)."""
        n, size = len(self.models), self.seeds_per_product
        return [(a, min(a + size, n)) for a in range(0, n, size)]


def _seeds(stack: MlpStack, a: int, b: int, per_seed: int) -> Weights:
    """The weights and biases of seeds ``a`` to ``b - 1`` (views), ``per_seed`` networks each."""
    return [w[a * per_seed : b * per_seed] for w in stack.weights], [x[a * per_seed : b * per_seed] for x in stack.biases]


def _joined(parts: list[tuple[Any, ...]]) -> tuple[Any, ...]:
    """The gradients (and statistics) of consecutive groups of seeds, as one group's: concatenated on the seed axis."""
    if len(parts) == 1:
        return parts[0]

    def join(values: list[Any]) -> Any:
        if isinstance(values[0], th.Tensor):
            return th.cat(values)
        if isinstance(values[0], dict):
            return {key: th.cat([v[key] for v in values]) for key in values[0]}
        return [th.cat([v[i] for v in values]) for i in range(len(values[0]))]

    return tuple(join([part[k] for part in parts]) for k in range(len(parts[0])))


__all__ = ["GlobalRandomState", "SeedRandomStreams", "SeedStackedMlpUpdate", "seed_actor_gradients", "seed_critic_gradients"]
