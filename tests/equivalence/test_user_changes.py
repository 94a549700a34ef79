"""A user's change always reaches training, and keeps the speed: the compiled update compiles it as written.

For a catalogue of changes a researcher makes (a network's ``forward``, an activation, a hook on a subclass or on the
instance, a module or gradient hook, a frozen layer, a custom autograd function, a value annealed during training...),
the update compiled with ``compile_update=True`` is trained against the same model's eager hooks
(``compile_update=False``) from one seed, and must end with the same weights to float rounding. Where Dynamo cannot
make one graph of the change, the update must say so and run eagerly (:data:`STEPS_ASIDE`). Each case is also
trained without the change: the change must move the weights far beyond the tolerance, so a path that dropped it would
fail the test. Collection must pick the actions SB3's own ``_sample_action`` picks (``predict``, ``actor.forward``).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from conftest import DummyEnv
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import FlattenExtractor, create_mlp
from stable_baselines3.td3.policies import Actor
from torch import nn

from sb3_td3x.td3x import TD3X, TD3XCritic, TD3XPolicy
from sb3_td3x.td3x.hooks import HOOK_NAMES

STEPS, LEARNING_STARTS = 260, 60  # 200 gradient steps on Pendulum-v1
NET = [32, 32]


# --- the changes a user makes -----------------------------------------------------------------------------------------
class ScaledCritic(TD3XCritic):
    def forward(self, obs, actions):
        return tuple(2.0 * q for q in super().forward(obs, actions))


class CriticQ1Changed(TD3XCritic):
    def q1_forward(self, obs, actions):
        return super().q1_forward(obs, actions) - actions.pow(2).sum(dim=1, keepdim=True)


class HalfActor(Actor):
    def forward(self, obs):
        return 0.5 * super().forward(obs)


class ScaledFlatten(FlattenExtractor):
    def forward(self, observations):
        return 0.5 * super().forward(observations)


class ScaledCriticPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return ScaledCritic(**critic_kwargs).to(self.device)


class Q1ChangedPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return CriticQ1Changed(**critic_kwargs).to(self.device)


class HalfActorPolicy(TD3XPolicy):
    def make_actor(self, features_extractor=None):
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return HalfActor(**actor_kwargs).to(self.device)


class OffsetPredictPolicy(TD3XPolicy):
    def _predict(self, observation, deterministic=False):
        return (self.actor(observation) * 0.8 + 0.1).clamp(-1, 1)


def _subclass_overriding(hook: str) -> type[TD3X]:
    """A TD3X subclass that overrides ``hook`` with a different step (each changes what is learned)."""

    def actor_network(self, features_dim, action_dim, net_arch, activation_fn):
        layers = create_mlp(features_dim, action_dim, net_arch, activation_fn, squash_output=True,
                            post_linear_modules=[nn.LayerNorm])  # fmt: skip
        return nn.Sequential(*layers)

    def q_network(self, input_dim, net_arch, activation_fn):
        return nn.Sequential(*create_mlp(input_dim, 1, net_arch, nn.ELU))

    def update_priorities(self, batch, current_q, target_q):  # the first critic's squared TD error
        self.replay_buffer.update_priorities(batch.indices, (current_q[0].detach() - target_q).pow(2).squeeze(1))

    def sample_batch(self, batch_size):
        batch = TD3X.sample_batch(self, batch_size)
        return batch._replace(rewards=batch.rewards * 0.5 + 1.0)

    def target_actions(self, next_observations):
        return TD3X.target_actions(self, next_observations) * 0.5

    def target_policy_smoothing_noise(self, actions):
        return TD3X.target_policy_smoothing_noise(self, actions) * 3.0

    def next_q_values(self, next_observations, next_actions):
        return TD3X.next_q_values(self, next_observations, next_actions) * 0.8

    def clipped_double_q_value(self, next_q):
        return next_q.mean(dim=0)

    def td_target(self, rewards, dones, discounts, next_q):
        return TD3X.td_target(self, rewards + 1.0, dones, discounts, next_q)

    def current_q_values(self, batch):
        return TD3X.current_q_values(self, batch) * 1.2

    def critic_loss(self, current_q, target_q):
        loss = sum(F.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}

    def optimize_critic(self, loss):
        self.critic.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        th.nn.utils.clip_grad_norm_(self.critic.parameters(), 0.05)
        self.critic.optimizer.step()
        with th.no_grad():  # and a decay of the weights after the step
            th._foreach_mul_(list(self.critic.parameters()), 0.99)

    def should_update_actor(self, n_updates):
        return n_updates % 3 == 0

    def actor_loss(self, observations):
        loss, info = TD3X.actor_loss(self, observations)
        loss = loss + self.actor(observations).pow(2).mean()
        return loss, {"actor_loss": loss.detach()}

    def optimize_actor(self, loss):
        self.actor.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        th.nn.utils.clip_grad_norm_(self.actor.parameters(), 0.01)
        self.actor.optimizer.step()

    def update_actor_target(self):
        self._polyak(self._actor_params, self._actor_target_params, 0.5)

    def update_critic_target(self):
        self._polyak(self._critic_params, self._critic_target_params, 0.5)

    def compute_target_q(self, batch):
        return TD3X.compute_target_q(self, batch) * 0.9

    def update_from_batch(self, batch, update_actor):
        return TD3X.update_from_batch(self, batch._replace(rewards=-batch.rewards), update_actor)

    def gradient_step(self, batch_size, update_actor):
        batch = self.sample_batch(batch_size)
        return self.update_from_batch(batch._replace(rewards=batch.rewards * 2.0), update_actor)

    return type(f"Custom_{hook}", (TD3X,), {hook: locals()[hook]})


def _set_on_instance(model: TD3X) -> None:
    model.td_target = lambda rewards, dones, discounts, next_q: rewards + 0.5 * (1.0 - dones) * discounts * next_q


def _critic_forward_on_instance(model: TD3X) -> None:
    critic = model.critic
    original = critic.forward
    critic.forward = lambda obs, actions: tuple(q * 0.5 for q in original(obs, actions))


def _forward_hook_on_critic_layer(model: TD3X) -> None:
    model.critic.qf0[0].register_forward_hook(lambda module, args, out: out * 1.5)


def _gradient_hook_on_critic(model: TD3X) -> None:
    model.critic.qf1[2].weight.register_hook(lambda grad: grad * 0.0)


def _frozen_actor_layer(model: TD3X) -> None:
    model.actor.mu[0].requires_grad_(False)


def _weight_norm_on_critic(model: TD3X) -> None:
    from torch.nn.utils.parametrizations import weight_norm

    for critic in (model.critic, model.critic_target):
        weight_norm(critic.qf0[2])
    model._create_aliases()
    model.critic.optimizer = th.optim.Adam(model.critic.parameters(), lr=1e-3)


class ScaleGradient(th.autograd.Function):
    """The identity forward, the gradient clipped elementwise backward: a custom autograd function inside a network."""

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        return grad.clamp(-0.002, 0.002)


class GradientScaledCritic(TD3XCritic):
    def forward(self, obs, actions):
        return tuple(ScaleGradient.apply(q) for q in super().forward(obs, actions))


class GradientScaledCriticPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return GradientScaledCritic(**critic_kwargs).to(self.device)


class DroQCriticsTD3X(TD3X):
    """Critics with dropout and LayerNorm (DroQ's), through the network hook: random masks drawn inside the update."""

    def q_network(self, input_dim, net_arch, activation_fn):
        layers: list[nn.Module] = []
        for width in net_arch:
            layers += [nn.Linear(input_dim, width), nn.Dropout(0.1), nn.LayerNorm(width), activation_fn()]
            input_dim = width
        return nn.Sequential(*layers, nn.Linear(input_dim, 1))


class BatchNormCriticsTD3X(TD3X):
    """Critics with batch normalisation after each hidden layer (no bias before it, which the normalisation would
    cancel: docs/extending.md), through the network hook: running statistics updated inside the update by each critic
    pass in train mode, and copied to the target critics by update_critic_target."""

    def q_network(self, input_dim, net_arch, activation_fn):
        layers: list[nn.Module] = []
        for width in net_arch:
            layers += [nn.Linear(input_dim, width, bias=False), nn.BatchNorm1d(width), activation_fn()]
            input_dim = width
        return nn.Sequential(*layers, nn.Linear(input_dim, 1))


class AnnealedNoiseTD3X(TD3X):
    """Target policy smoothing noise annealed with the updates done: a Python value that changes at every step."""

    def target_policy_smoothing_noise(self, actions):
        return TD3X.target_policy_smoothing_noise(self, actions) * (1.0 + self._n_updates)


def _backward_hook_on_critic_layer(model: TD3X) -> None:
    model.critic.qf0[2].register_full_backward_hook(lambda module, grad_in, grad_out: (grad_in[0] + 0.01,))


def _post_accumulate_hook_on_actor(model: TD3X) -> None:
    def shift(p):
        p.grad.add_(0.1)

    model.actor.mu[2].weight.register_post_accumulate_grad_hook(shift)


@dataclass
class Case:
    cls: type[TD3X] = TD3X
    kwargs: dict[str, Any] = field(default_factory=dict)
    after: Callable[[TD3X], None] | None = None  # a change made on the built model
    teardown: Callable[[], None] | None = None


_global_hooks: list[Any] = []


def _global_forward_hook(model: TD3X) -> None:
    def scale_linears(module, args, out):
        return out * 1.1 if isinstance(module, nn.Linear) and module.out_features == 1 else out

    _global_hooks.append(nn.modules.module.register_module_forward_hook(scale_linears))


def _remove_global_hooks() -> None:
    while _global_hooks:
        _global_hooks.pop().remove()


# What an override needs to do something: update_priorities writes into a prioritised buffer only.
HOOK_CASE_KWARGS: dict[str, dict[str, Any]] = {"update_priorities": {"replay_buffer_kwargs": {"alpha": 0.6}}}

CASES: dict[str, Case] = {
    "critic-forward-subclass": Case(kwargs={"policy": ScaledCriticPolicy}),
    "critic-q1_forward-subclass": Case(kwargs={"policy": Q1ChangedPolicy}),
    "actor-forward-subclass": Case(kwargs={"policy": HalfActorPolicy}),
    "features-extractor-subclass": Case(kwargs={"policy_kwargs": {"features_extractor_class": ScaledFlatten}}),
    "tanh-activation": Case(kwargs={"policy_kwargs": {"activation_fn": nn.Tanh}}),
    "leaky-relu-activation": Case(kwargs={"policy_kwargs": {"activation_fn": nn.LeakyReLU}}),
    "hook-set-on-instance": Case(after=_set_on_instance),
    "critic-forward-set-on-instance": Case(after=_critic_forward_on_instance),
    "forward-hook-on-a-layer": Case(after=_forward_hook_on_critic_layer),
    "global-module-forward-hook": Case(after=_global_forward_hook, teardown=_remove_global_hooks),
    "gradient-hook-on-a-parameter": Case(after=_gradient_hook_on_critic),
    "post-accumulate-grad-hook-on-a-parameter": Case(after=_post_accumulate_hook_on_actor),
    "backward-hook-on-a-layer": Case(after=_backward_hook_on_critic_layer),
    "custom-autograd-function-in-the-critic": Case(kwargs={"policy": GradientScaledCriticPolicy}),
    "noise-annealed-with-the-updates": Case(cls=AnnealedNoiseTD3X),
    "dropout-and-layernorm-critics": Case(cls=DroQCriticsTD3X),  # the masks drawn in the graph as eagerly
    "batchnorm-critics": Case(cls=BatchNormCriticsTD3X),  # buffers written by the graph: compared too (weights())
    # AMSGrad's running maximum of the second moments, a state tensor of its own; betas of (0.9, 0.9) let the second
    # moments fall within the 20 updates, so that the maximum changes the steps (3e-3 apart from Adam's)
    "adam-amsgrad": Case(kwargs={"policy_kwargs": {"optimizer_kwargs": {"amsgrad": True, "betas": (0.9, 0.9)}}}),
    "frozen-actor-layer": Case(after=_frozen_actor_layer),
    "weight-norm-parametrization": Case(after=_weight_norm_on_critic),
    "policy-_predict-overridden": Case(kwargs={"policy": OffsetPredictPolicy}),
    # Prioritised replay with the stock hooks: update_from_batch's update_priorities writes the priorities.
    "prioritized-replay-buffer": Case(kwargs={"replay_buffer_kwargs": {"alpha": 0.6}}),
    "prioritized-with-importance-weights": Case(kwargs={"replay_buffer_kwargs": {"alpha": 0.6, "beta": 0.4}}),
    **{
        f"{hook}-overridden": Case(cls=_subclass_overriding(hook), kwargs=HOOK_CASE_KWARGS.get(hook, {}))
        for hook in HOOK_NAMES
    },
}

# Stock set-ups the fast paths must keep computing as the hooks do (no change: compared, not required to differ).
STOCK: dict[str, Case] = {
    "stock-defaults": Case(),
    "stock-shared-features-extractor-3-critics": Case(
        kwargs={"policy_kwargs": {"share_features_extractor": True, "n_critics": 3}}
    ),
    "stock-n-step-returns": Case(kwargs={"n_steps": 3}),  # the tensor buffer's batches carry gamma ** m
}


# --- training -----------------------------------------------------------------------------------------------------------
def build(case: Case, **overrides: Any) -> TD3X:
    kwargs = {"policy": "MlpPolicy", **case.kwargs, **overrides}
    policy = kwargs.pop("policy")
    policy_kwargs = {"net_arch": NET, **kwargs.pop("policy_kwargs", {})}
    kwargs = {"learning_starts": LEARNING_STARTS, "batch_size": 64, **kwargs}
    model = case.cls(
        policy,
        "Pendulum-v1",
        policy_kwargs=policy_kwargs,
        action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
        seed=0,
        **kwargs,
    )
    if case.after is not None:
        case.after(model)
    return model


def train(case: Case, **overrides: Any) -> TD3X:
    model = build(case, **overrides)
    try:
        model.learn(STEPS)
    finally:
        if case.teardown is not None:
            case.teardown()
    return model


def updates_after_collection(model: TD3X, steps: int, updates: int) -> TD3X:
    """``learn(steps)`` with ``learning_starts >= steps`` (collection only: random actions), then ``updates`` gradient
    steps from a fixed seed: the update alone, without the environment loop that turns float rounding into another
    trajectory (for paths that do not round as eager autograd does)."""
    model.learn(steps)
    np.random.seed(0)
    th.manual_seed(0)
    model.train(gradient_steps=updates, batch_size=model.batch_size)
    return model


def train_updates(case: Case, updates: int = 100, **overrides: Any) -> TD3X:
    """``updates`` gradient steps on a buffer filled with random actions (:func:`updates_after_collection`)."""
    model = build(case, learning_starts=STEPS, **overrides)
    try:
        updates_after_collection(model, STEPS, updates)
    finally:
        if case.teardown is not None:
            case.teardown()
    return model


def weights(model: TD3X) -> list[th.Tensor]:
    """The parameters, then the buffers (a batch normalisation's running statistics)."""
    return [t.detach().clone() for t in (*model.policy.parameters(), *model.policy.buffers())]


def assert_same_weights(model: TD3X, reference: TD3X, rtol: float = 1e-4, atol: float = 1e-5) -> None:
    for i, (a, b) in enumerate(zip(weights(model), weights(reference))):
        th.testing.assert_close(
            a, b, rtol=rtol, atol=atol, msg=lambda m, i=i: f"tensor {i} (the parameters, then the buffers): {m}"
        )


def max_difference(model: TD3X, reference: TD3X) -> float:
    return max(float((a - b).abs().max()) for a, b in zip(weights(model), weights(reference)))


_PROBE = th.Generator().manual_seed(1)
PROBE_OBS, PROBE_ACTIONS = th.randn(64, 3, generator=_PROBE), th.rand(64, 1, generator=_PROBE) * 2 - 1


@th.no_grad()
def outputs(model: TD3X) -> th.Tensor:
    """What the trained networks compute on fixed inputs (comparable whatever the parametrisation), in evaluation
    mode (no dropout)."""
    training = model.policy.training
    model.policy.set_training_mode(False)
    try:
        q = th.cat(TD3XCritic.forward(model.critic, PROBE_OBS, PROBE_ACTIONS), dim=1)
        return th.cat([Actor.forward(model.actor, PROBE_OBS), q], dim=1)
    finally:
        model.policy.set_training_mode(training)


@functools.cache
def unchanged_outputs() -> th.Tensor:
    """The networks trained with no change at all: what a fast path that dropped the user's change would give."""
    return outputs(train(Case(), compile_update=False))


def assert_collection_is_sb3s(model: TD3X) -> None:
    """Collection's actions are SB3's ``_sample_action``'s (through ``predict`` and ``actor.forward``)."""
    obs = model.replay_buffer.observations[:16, 0].cpu().numpy()
    for row in obs:
        model._last_obs = row[None]
        ours = model._sample_action(0, None, 1)
        sb3s = OffPolicyAlgorithm._sample_action(model, 0, None, 1)
        np.testing.assert_allclose(ours[1], sb3s[1], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(ours[0], sb3s[0], rtol=1e-5, atol=1e-6)


# --- the tests ------------------------------------------------------------------------------------------------------------
#: Changes Dynamo cannot put in one graph with the rest of the update: the compiled update must step aside to the eager
#: one, and say why (a fragment of update_reason).
STEPS_ASIDE = {
    "gradient-hook-on-a-parameter": "a gradient hook on a parameter",
    "post-accumulate-grad-hook-on-a-parameter": "a gradient hook on a parameter",
    "optimize_critic-overridden": "torch.compile cannot make one graph of it",  # optimizer.zero_grad(): a graph break
    "optimize_actor-overridden": "torch.compile cannot make one graph of it",
    "backward-hook-on-a-layer": "backwards hooks",  # torch 2.13: "Module-level backwards hooks require compiled autograd"
    "gradient_step-overridden": "randint",  # a gradient_step of its own, compiled whole: numpy's sampling in it
    # Polyak updates written without torch.no_grad(): autograd records them, and AOTAutograd refuses the graph.
    "update_actor_target-overridden": "modified by an inplace operation",
    "update_critic_target-overridden": "modified by an inplace operation",
}
#: Changes to collection alone: the update does not see them (checked by test_a_users_change_reaches_collection).
COLLECTION_ONLY = {"policy-_predict-overridden"}


@functools.cache
def unchanged_updates() -> TD3X:
    """The update with no change at all: what a path that dropped the user's change would give."""
    return train_updates(Case(), updates=20, compile_update=False)


def assert_far_beyond_rounding(compiled: TD3X, eager: TD3X, name: str) -> None:
    """The compiled and the eager update agree far more closely than the eager one agrees with the update without the
    change: compared weight by weight, or through what the networks compute where the change reparametrises them."""
    unchanged = unchanged_updates()
    if [p.shape for p in eager.policy.parameters()] == [p.shape for p in unchanged.policy.parameters()]:
        rounding, dropped = max_difference(compiled, eager), max_difference(eager, unchanged)
    else:
        rounding = float((outputs(compiled) - outputs(eager)).abs().max())
        dropped = float((outputs(eager) - outputs(unchanged)).abs().max())
    assert rounding < 0.05 * dropped, f"{name}: the change moves the outputs by {dropped:.2e}, the paths differ by {rounding:.2e}"


@pytest.mark.parametrize("name", list(CASES))
def test_a_users_change_is_compiled_as_written(name, dynamo_graphs_only):
    """Dynamo captures each change with the rest of the update (run here by AOTAutograd's eager kernels, the
    ``aot_eager`` backend, so that the catalogue stays fast; Inductor compiles these graphs in the tests below), or
    the update says why not and runs eagerly."""
    case = CASES[name]
    compiled = train_updates(case, updates=20, compile_update=True)
    eager = train_updates(case, updates=20, compile_update=False)
    assert eager.update_path == "eager"
    if name in STEPS_ASIDE:
        assert compiled.update_path == "eager" and STEPS_ASIDE[name] in compiled.update_reason, compiled.update_reason
    else:
        assert compiled.update_path == "compiled", compiled.update_reason
        # all but those before each optimizer's first step (Adam's state): the actor's comes at update 2, or 3 where
        # should_update_actor is overridden
        assert compiled._updates_compiled >= 17, f"{compiled._updates_compiled} of 20 updates ran compiled"
    assert_same_weights(compiled, eager)
    if name not in COLLECTION_ONLY:  # the change matters: a path that dropped it would end far from the reference
        assert_far_beyond_rounding(compiled, eager, name)


#: The cases Inductor compiles (the other tests run Dynamo's graphs with ``aot_eager``): each distinct graph costs about
#: 34 s of Inductor's compile on a cold cache (CI starts cold), 4 s warm, so they are few. The stock update (the default
#: of every long CPU run: its graph is shared with test_auto_compiles_a_long_run, which the cache then finds), and one
#: hook override whose graph has a lowering the stock graph lacks (smooth_l1_loss and its backward). Changes that only
#: add pointwise operations (a scaled forward, an activation, a noise scale) give Inductor nothing new: the catalogue
#: above checks that Dynamo captures them.
INDUCTOR_CASES = ["stock-defaults", "critic_loss-overridden"]


@pytest.mark.parametrize("name", INDUCTOR_CASES)
def test_inductor_compiles_a_users_change_as_written(name):
    """The real compiled update (Inductor's kernels) on the stock update and on a change."""
    case = {**CASES, **STOCK}[name]
    compiled = train_updates(case, updates=20, compile_update=True)
    eager = train_updates(case, updates=20, compile_update=False)
    assert compiled.update_path == "compiled", compiled.update_reason
    # Inductor's fused kernels and the compiled Adam round differently from eager's (3e-8 after one step, 3e-7 after 20).
    assert_same_weights(compiled, eager)
    if name != "stock-defaults":
        assert_far_beyond_rounding(compiled, eager, name)


@pytest.mark.parametrize("name", list(CASES))
def test_a_users_change_reaches_collection_and_changes_learning(name):
    """learn() with the change (the default of a short run: the eager hooks) collects with SB3's ``_sample_action``
    actions, and the change moves what is learned."""
    case = CASES[name]
    model = train(case)
    assert model.update_path == "eager"
    dropped = float((outputs(model) - unchanged_outputs()).abs().max())
    assert dropped > 1e-3, f"the case {name} does not change training ({dropped:.2e}): it proves nothing"
    assert_collection_is_sb3s(model)


@pytest.mark.parametrize("name", list(STOCK))
def test_the_stock_setups_compile_and_match_the_hooks(name, dynamo_graphs_only):
    """Dynamo's graphs of the stock set-ups (``aot_eager``, as the catalogue; Inductor compiles stock-defaults in
    test_inductor_compiles_a_users_change_as_written) compute what the hooks compute, and collection is SB3's."""
    compiled = train_updates(STOCK[name], updates=20, compile_update=True)
    eager = train_updates(STOCK[name], updates=20, compile_update=False)
    assert compiled.update_path == "compiled" and eager.update_path == "eager"
    assert compiled._step_fn.recompiled == []  # no class changed: compiled once
    assert_same_weights(compiled, eager)
    model = train(STOCK[name])
    assert model.exploration_path == "actor"
    assert_collection_is_sb3s(model)


# --- changes made between two trainings (a callback, a notebook): the update made before must not outlive them ----------
def _critic_optimizer_over_qf0_only(model: TD3X) -> None:
    model.critic.optimizer = th.optim.Adam(model.critic.qf0.parameters(), lr=1e-3)


def _add_qf1_param_group(model: TD3X) -> None:
    model.critic.optimizer.add_param_group({"params": list(model.critic.qf1.parameters())})


def _replace_last_critic_layer(model: TD3X) -> None:
    """A layer reset as a new module (as plasticity research does), its parameters given to the optimizer as a new
    group; the old layer's stay in the optimizer without a gradient, which Adam's ``step()`` skips."""
    layer = nn.Linear(NET[-1], 1)
    with th.no_grad():
        layer.weight.copy_(th.randn(1, NET[-1], generator=th.Generator().manual_seed(3)))
        layer.bias.zero_()
    model.critic.qf0[-1] = layer
    model.critic.optimizer.add_param_group({"params": list(layer.parameters())})


def _set(**values: Any) -> Callable[[TD3X], None]:
    return lambda model: model.__dict__.update(values)


def _adam_betas_and_weight_decay(model: TD3X) -> None:
    for group in model.critic.optimizer.param_groups:
        group.update(betas=(0.5, 0.9), weight_decay=0.5)


def _targets_loaded(model: TD3X) -> None:
    model.actor_target.load_state_dict(model.actor.state_dict())
    with th.no_grad():
        for p in model.critic_target.parameters():
            p.mul_(0.5)


def _second_moments_replaced(model: TD3X) -> None:
    """Adam's second moments of the critics given as new tensors (rescaled), the first moments and step counts kept."""
    for state in model.critic.optimizer.state.values():
        state["exp_avg_sq"] = state["exp_avg_sq"] * 100.0


def _new_critic_optimizer(model: TD3X) -> None:
    model.critic.optimizer = th.optim.Adam(model.critic.parameters(), lr=5e-3)


#: name: (a change made on the built model, a change made after its first 10 updates)
BETWEEN_TRAININGS: dict[str, tuple[Callable[[TD3X], None] | None, Callable[[TD3X], None]]] = {
    "param-group-added": (_critic_optimizer_over_qf0_only, _add_qf1_param_group),
    "layer-replaced-as-a-new-module": (None, _replace_last_critic_layer),
    "gamma-tau-and-policy_delay-set": (None, _set(gamma=0.5, tau=0.3, policy_delay=3)),
    "adam-betas-and-weight-decay-set": (None, _adam_betas_and_weight_decay),
    "targets-loaded": (None, _targets_loaded),
    "adam-second-moments-replaced": (None, _second_moments_replaced),
    "critic-optimizer-replaced": (None, _new_critic_optimizer),
}


def around_a_change(
    change: Callable[[TD3X], Callable[[], None] | None] | None,
    compile_update: bool,
    before: Callable[[TD3X], None] | None = None,
) -> TD3X:
    """10 updates (:func:`updates_after_collection`), ``change`` (``None``: none), 10 more; what ``change`` returns, if
    anything, undoes it after them (a class patched for this model only)."""
    model = build(Case(after=before), learning_starts=STEPS, compile_update=compile_update)
    model = updates_after_collection(model, STEPS, 10)
    undo = change(model) if change is not None else None
    try:
        model.train(gradient_steps=10, batch_size=model.batch_size)
    finally:
        if undo is not None:
            undo()
    return model


@pytest.mark.parametrize("name", list(BETWEEN_TRAININGS))
def test_a_change_between_two_trainings_is_compiled_as_written(name, dynamo_graphs_only):
    """A change made between two ``train()`` calls reaches the compiled update (recompiled where it must be) as it
    reaches the eager one: 10 updates, the change, 10 more, compiled and eagerly from one seed."""
    before, between = BETWEEN_TRAININGS[name]
    compiled, eager = around_a_change(between, True, before), around_a_change(between, False, before)
    assert compiled.update_path == "compiled", compiled.update_reason
    # Eager: each optimizer's first step (it makes Adam's state), and the first after the change where it brings
    # parameters without state (a group added, a new layer, a new optimizer)
    new_state = name in ("param-group-added", "layer-replaced-as-a-new-module", "critic-optimizer-replaced")
    assert compiled._updates_compiled == 18 - new_state, f"{compiled._updates_compiled} of 20 updates ran compiled"
    assert compiled._step_fn.recompiled == []  # Dynamo's guards see these changes; no class changed
    assert_same_weights(compiled, eager)
    rounding, moved = max_difference(compiled, eager), max_difference(eager, around_a_change(None, False, before))
    assert rounding < 0.05 * moved, f"{name}: the change moves the weights by {moved:.2e}, the paths differ by {rounding:.2e}"


def _patch(owner: Any, name: str, wrap: Callable[[Any], Any]) -> Callable[[], None]:
    """``owner.name = wrap(owner.name)``; returns what puts it back."""
    original = owner.__dict__[name]
    setattr(owner, name, wrap(original))
    return lambda: setattr(owner, name, original)


class _HalfLinear(nn.Linear):
    def forward(self, x: th.Tensor) -> th.Tensor:
        return super().forward(x) * 0.5


def _swap_first_critic_layer_class(model: TD3X) -> Callable[[], None]:
    model.critic.qf0[0].__class__ = _HalfLinear  # Dynamo's guard on the module's class sees this one itself
    return lambda: None


#: name: a change made on a class (or an object's class) after the first 10 updates; returns what undoes it
CLASS_CHANGES: dict[str, Callable[[TD3X], Callable[[], None]]] = {
    "td3x-hook-replaced-on-the-class": lambda model: _patch(
        TD3X, "td_target", lambda f: lambda self, *args: f(self, *args) * 0.5
    ),
    "sb3-critic-forward-patched": lambda model: _patch(
        ContinuousCritic, "forward", lambda f: lambda self, obs, act: tuple(q * 0.5 for q in f(self, obs, act))
    ),
    "torch-linear-forward-patched": lambda model: _patch(nn.Linear, "forward", lambda f: lambda self, x: f(self, x) * 0.5),
    "a-layer-class-swapped": _swap_first_critic_layer_class,
}


@pytest.mark.parametrize("name", list(CLASS_CHANGES))
def test_a_class_changed_between_two_trainings_is_compiled_as_written(name, dynamo_graphs_only):
    """A method replaced on a class after the update was compiled (a hook of TD3X's, SB3's critic ``forward``,
    torch's ``nn.Linear.forward``): Dynamo does not guard on methods found on classes, so the old graph ran on,
    silently. The update is compiled again and trains what the eager one trains; so it does after a module's class
    is swapped (there Dynamo's own guard recompiles)."""
    compiled, eager = around_a_change(CLASS_CHANGES[name], True), around_a_change(CLASS_CHANGES[name], False)
    assert compiled.update_path == "compiled" and compiled._updates_compiled == 18, compiled.update_reason
    assert len(compiled._step_fn.recompiled) == (name != "a-layer-class-swapped"), compiled._step_fn.recompiled
    assert_same_weights(compiled, eager)
    rounding, moved = max_difference(compiled, eager), max_difference(eager, around_a_change(None, False))
    assert rounding < 0.05 * moved, f"{name}: the change moves the weights by {moved:.2e}, the paths differ by {rounding:.2e}"


def test_a_replaced_optimizer_step_steps_the_update_aside(dynamo_graphs_only):
    """``Adam.step`` replaced on the class: the compiled update, which runs torch's functional Adam, would not run it;
    the update steps aside, saying so, and trains as the eager one."""

    def twice(step: Callable[..., Any]) -> Callable[..., Any]:
        return lambda self, closure=None: (step(self, closure), step(self, closure))[1]

    def step_twice(model: TD3X) -> Callable[[], None]:
        return _patch(th.optim.Adam, "step", twice)

    compiled, eager = around_a_change(step_twice, True), around_a_change(step_twice, False)
    assert compiled.update_path == "eager" and "Adam.step was replaced" in compiled.update_reason, compiled.update_reason
    assert "from update 11 on" in compiled.update_reason
    assert_same_weights(compiled, eager)
    assert max_difference(eager, around_a_change(None, False)) > 1e-3


def test_a_parameter_that_never_has_a_gradient_leaves_the_update_compiled(dynamo_graphs_only):
    """A parameter in the critic's optimizer that the loss never reaches (a head kept for later) gets no Adam state,
    eagerly or compiled; the update still compiles (it once waited for that state, and so ran eagerly at every step
    while update_path said compiled) and trains what the eager one trains."""

    def unused_head(model: TD3X) -> None:
        model.critic.extra = nn.Linear(4, 1)
        model.critic.optimizer = th.optim.Adam(model.critic.parameters(), lr=1e-3)

    compiled = train_updates(Case(after=unused_head), updates=20, compile_update=True)
    eager = train_updates(Case(after=unused_head), updates=20, compile_update=False)
    assert compiled.update_path == "compiled" and compiled._updates_compiled == 18, compiled._updates_compiled
    assert_same_weights(compiled, eager)
    for model in (compiled, eager):
        assert all(p not in model.critic.optimizer.state for p in model.critic.extra.parameters())


def _observation_space_updates(kind: str, updates: int = 20, **overrides: Any) -> TD3X:
    """``updates`` gradient steps on a buffer filled with random actions (:func:`updates_after_collection`), for
    observations other than a flat Box: a dict (SB3's ``BitFlippingEnv``, continuous, through ``MultiInputPolicy``),
    the same with SB3's ``HerReplayBuffer``, or images (SB3's ``FakeImageEnv``, uint8, through ``CnnPolicy``)."""
    from stable_baselines3 import HerReplayBuffer
    from stable_baselines3.common.envs import BitFlippingEnv, FakeImageEnv

    kwargs: dict[str, Any] = {"learning_starts": 200, "batch_size": 32, "policy_kwargs": {"net_arch": NET}, "seed": 3}
    if kind == "images":
        env, policy = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1, discrete=False), "CnnPolicy"
        env.observation_space.seed(3)  # its images are draws of the space, which SB3's seed does not reach
        kwargs["buffer_size"] = 1_000
    else:
        env, policy = BitFlippingEnv(n_bits=4, continuous=True, max_steps=8), "MultiInputPolicy"
    if kind == "her":
        kwargs |= {"replay_buffer_class": HerReplayBuffer, "replay_buffer_kwargs": {"n_sampled_goal": 4}}
    return updates_after_collection(TD3X(policy, env, **(kwargs | overrides)), 200, updates)


@pytest.mark.parametrize("kind", ["dict", "her", "images"])
def test_other_observation_spaces_compile_and_match_the_hooks(kind, dynamo_graphs_only):
    """Dict observations, hindsight relabelling (HER's rewards relabelled in numpy, before the graph) and uint8 images
    (scaled inside the graph, as SB3's ``preprocess_obs`` does) train the same weights compiled as eagerly; a
    different update (another tau) does not."""
    compiled = _observation_space_updates(kind, compile_update=True)
    eager = _observation_space_updates(kind, compile_update=False)
    assert compiled.update_path == "compiled" and eager.update_path == "eager"
    assert_same_weights(compiled, eager)
    with pytest.raises(AssertionError):
        assert_same_weights(compiled, _observation_space_updates(kind, compile_update=False, tau=0.01))


def test_discrete_observations_step_aside_and_say_why(dynamo_graphs_only):
    """SB3's one-hot encoding of a Discrete observation reads the space's size as a numpy integer, which Dynamo cannot
    make a Python int of: the compiled update steps aside, names the place, and trains what the eager one trains."""
    def run(compile_update: bool) -> TD3X:
        # A Discrete(5) space seeded anew per model: both draw the same observations.
        env = gym.wrappers.TimeLimit(DummyEnv(gym.spaces.Discrete(5, seed=3), gym.spaces.Box(-1, 1, (1,))), 10)
        model = TD3X("MlpPolicy", env, learning_starts=100, batch_size=32, seed=3, policy_kwargs={"net_arch": NET},
                     compile_update=compile_update)  # fmt: skip
        return updates_after_collection(model, 100, 4)

    compiled, eager = run(True), run(False)
    assert compiled.update_path == "eager" and "preprocessing.py" in compiled.update_reason
    assert_same_weights(compiled, eager, rtol=0, atol=0)


def test_auto_compiles_a_long_run_and_it_trains_what_the_hooks_train(monkeypatch):
    """compile_update=None (auto) on a run long enough (here: every run) compiles the update, the default of a long
    run on a CPU (Inductor: the graph of test_inductor_compiles_a_users_change_as_written[stock-defaults]); the
    comparison sees a different update (another tau, eagerly: no other graph to compile). Its products run without
    their biases (``graph_passes``), which the pointwise kernels after them add."""
    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    auto = train_updates(STOCK["stock-defaults"], updates=20)
    reference = train_updates(STOCK["stock-defaults"], updates=20, compile_update=False)
    assert auto.update_path == "compiled" and auto.update_compiled
    assert_same_weights(auto, reference)
    with th.profiler.profile(activities=[th.profiler.ProfilerActivity.CPU]) as profile:
        auto.train(gradient_steps=2, batch_size=auto.batch_size)
    operators = {event.key for event in profile.key_averages()}
    assert "aten::mm" in operators and "aten::addmm" not in operators  # graph_passes: each bias after its product
    other_tau = train_updates(STOCK["stock-defaults"], updates=20, compile_update=False, tau=0.02)
    with pytest.raises(AssertionError):
        assert_same_weights(auto, other_tau)


def test_the_compiled_bf16_update_follows_the_eager_bf16_update():
    """bf16 products compiled by Inductor (the stock update: a change's bf16 graph adds nothing the fp32 cases above do
    not show) follow the eager bf16 update far more closely than fp32 does, so a compiled update that dropped autocast
    would fail: after 20 updates, compiled to eager bf16 3.9e-5, eager fp32 and compiled fp32 to eager bf16 5.3e-3
    (AMD EPYC Zen 4, 2026-11-27). test_denormals.py's 64-64 networks and batches of 256: the same graph, which
    Inductor's cache then finds (a graph costs about 25 s of CPU to compile cold)."""
    case, size = STOCK["stock-defaults"], {"policy_kwargs": {"net_arch": [64, 64]}, "batch_size": 256}
    with pytest.warns(UserWarning) if _bf16_warns() else contextlib.nullcontext():
        compiled = train_updates(case, updates=20, bf16=True, compile_update=True, **size)
        eager = train_updates(case, updates=20, bf16=True, compile_update=False, **size)
    assert compiled.update_path == "compiled" and eager.update_path == "eager"
    fp32 = train_updates(case, updates=20, compile_update=False, **size)
    # bf16 products (8 bits of mantissa): Inductor and eager autocast round differently, far less than fp32 does.
    rounding, fp32_apart = max_difference(compiled, eager), max_difference(eager, fp32)
    assert rounding < 0.05 * fp32_apart, f"compiled bf16 is {rounding:.2e} from eager bf16, fp32 {fp32_apart:.2e}"


def _bf16_warns() -> bool:
    from sb3_td3x.td3x.update_paths.precision import bf16_on_cpu_warning

    return bf16_on_cpu_warning(th.device("cpu")) is not None
