"""Unit tests of TD3X's hooks on hand-made tensors: one test per step of the algorithm, and gradient isolation."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from conftest import feed, random_batches
from stable_baselines3.common.logger import configure
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_td3x import DDPG, PRESETS, TD3X

BATCH, OBS_DIM, ACT_DIM = 64, 3, 1


def make_model(**kwargs) -> TD3X:
    kwargs.setdefault("policy_kwargs", dict(net_arch=[32, 32]))
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=0, seed=0, **kwargs)
    model.set_logger(configure(None, []))
    return model


def make_batch(seed: int = 0, batch_size: int = BATCH) -> ReplayBufferSamples:
    return random_batches(1, batch_size, OBS_DIM, ACT_DIM, seed=seed, done_probability=0.3)[0]


# Step 6 --------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sigma,clip", [(0.2, 0.5), (5.0, 0.3), (0.0, 0.5), (1.0, 0.0)])
def test_smoothing_noise_within_clip_and_batch_shaped(sigma, clip):
    model = make_model(target_policy_noise=sigma, target_noise_clip=clip)
    actions = th.zeros(10_000, 6)
    noise = model.target_policy_smoothing_noise(actions)
    assert noise.shape == actions.shape
    assert noise.abs().max() <= clip
    if sigma > 0 and clip > 0:
        # Drawn per element of the batch, not once per action dimension: rows differ.
        assert not th.allclose(noise[0], noise[1])
        # Gaussian with std sigma before clipping: the unclipped part has the right spread.
        assert noise.std() > 0.5 * min(sigma, clip)


def test_target_actions_within_bounds_and_noisy():
    model = make_model(target_policy_noise=2.0, target_noise_clip=0.5)
    next_obs = th.randn(2_000, OBS_DIM) * 10
    next_actions = model.target_actions(next_obs)
    assert next_actions.shape == (2_000, ACT_DIM)
    assert next_actions.min() >= -1.0 and next_actions.max() <= 1.0
    deterministic = model.actor_target(next_obs)
    assert not th.allclose(next_actions, deterministic)
    assert (next_actions - deterministic).abs().max() <= 0.5 + 1e-6


def test_target_actions_without_smoothing_are_the_target_policy():
    model = make_model(target_policy_smoothing=False)
    next_obs = th.randn(BATCH, OBS_DIM)
    th.testing.assert_close(model.target_actions(next_obs), model.actor_target(next_obs).clamp(-1, 1), rtol=0, atol=0)


# Steps 7-9 -----------------------------------------------------------------------------------------------------------
def test_clipped_double_q_is_min_over_critics():
    model = make_model()
    next_q = th.tensor([[[1.0], [5.0], [-2.0]], [[3.0], [4.0], [-7.0]]])  # (n_critics=2, batch=3, 1)
    th.testing.assert_close(model.clipped_double_q_value(next_q), th.tensor([[1.0], [4.0], [-7.0]]))
    model.clipped_double_q = False
    th.testing.assert_close(model.clipped_double_q_value(next_q), th.tensor([[1.0], [5.0], [-2.0]]))


def test_clipped_double_q_general_in_n_critics():
    model = make_model(policy_kwargs=dict(net_arch=[16], n_critics=5))
    next_q = model.next_q_values(th.randn(BATCH, OBS_DIM), th.rand(BATCH, ACT_DIM))
    assert next_q.shape == (5, BATCH, 1)
    th.testing.assert_close(model.clipped_double_q_value(next_q), next_q.min(dim=0).values)


def test_td_target_equation():
    model = make_model(gamma=0.9)
    rewards = th.tensor([[1.0], [2.0], [-1.0]])
    dones = th.tensor([[0.0], [1.0], [0.0]])
    next_q = th.tensor([[10.0], [10.0], [-5.0]])
    y = model.td_target(rewards, dones, model.gamma, next_q)
    th.testing.assert_close(y, th.tensor([[1.0 + 0.9 * 10.0], [2.0], [-1.0 + 0.9 * -5.0]]))


def test_compute_target_q_matches_equation_on_a_batch():
    model = make_model(gamma=0.97)
    batch = make_batch()
    th.manual_seed(3)
    y = model.compute_target_q(batch)
    assert y.shape == (BATCH, 1) and not y.requires_grad
    # Recompute by hand with the same noise.
    th.manual_seed(3)
    noise = (th.randn(BATCH, ACT_DIM) * model.target_policy_noise).clamp(-model.target_noise_clip, model.target_noise_clip)
    with th.no_grad():
        next_a = (model.actor_target(batch.next_observations) + noise).clamp(-1, 1)
        q1, q2 = model.critic_target(batch.next_observations, next_a)
        expected = batch.rewards + model.gamma * (1 - batch.dones) * th.min(q1, q2)
    th.testing.assert_close(y, expected)


# Steps 10-11 ---------------------------------------------------------------------------------------------------------
def test_critic_loss_is_sum_of_mse():
    model = make_model()
    current_q = th.randn(2, BATCH, 1)
    target_q = th.randn(BATCH, 1)
    loss, info = model.critic_loss(current_q, target_q)
    expected = F.mse_loss(current_q[0], target_q) + F.mse_loss(current_q[1], target_q)
    th.testing.assert_close(loss, expected)
    th.testing.assert_close(info["q1"], current_q[0].mean())
    th.testing.assert_close(info["q2"], current_q[1].mean())
    th.testing.assert_close(info["target_q"], target_q.mean())


# DDPG: with the switches off, target and losses reduce to DDPG's ------------------------------------------------------
@pytest.mark.parametrize("make", [lambda: make_model(**PRESETS["ddpg"] | {"policy_kwargs": dict(net_arch=[32, 32], n_critics=1)}),
                                  lambda: DDPG("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[32, 32]), seed=0)])
def test_switches_off_reduce_to_ddpg(make):
    model = make()
    assert model.critic.n_critics == 1 and model.policy_delay == 1
    assert not model.target_policy_smoothing and not model.clipped_double_q
    batch = make_batch()
    y = model.compute_target_q(batch)
    with th.no_grad():
        q_next = model.critic_target.q1_forward(batch.next_observations, model.actor_target(batch.next_observations))
    # DDPG's target: y = r + gamma * (1 - d) * Q'(s', mu'(s')), no noise, no min
    th.testing.assert_close(y, batch.rewards + model.gamma * (1 - batch.dones) * q_next)
    loss, _ = model.critic_loss(model.current_q_values(batch), y)
    th.testing.assert_close(loss, F.mse_loss(model.critic.q1_forward(batch.observations, batch.actions), y))
    actor_loss, _ = model.actor_loss(batch.observations)
    th.testing.assert_close(actor_loss, -model.critic.q1_forward(batch.observations, model.actor(batch.observations)).mean())


def test_no_cdq_with_two_critics_uses_first_target_critic():
    model = make_model(clipped_double_q=False, target_policy_smoothing=False)
    batch = make_batch()
    y = model.compute_target_q(batch)
    with th.no_grad():
        q1_next = model.critic_target.q1_forward(batch.next_observations, model.actor_target(batch.next_observations))
    th.testing.assert_close(y, batch.rewards + model.gamma * (1 - batch.dones) * q1_next)


# Gradient isolation --------------------------------------------------------------------------------------------------
def grads(module: th.nn.Module) -> list:
    return [p.grad for p in module.parameters()]


def test_the_actor_step_leaves_critic_without_gradient():
    """Step 13 differentiates the actor loss with respect to the actor's parameters only (optimize_actor): the
    critic, whose Q_1 the loss goes through, gets no gradient and is not stepped."""
    model = make_model()
    critic_before = [p.detach().clone() for p in model.critic.parameters()]
    loss, _ = model.actor_loss(make_batch().observations)
    model.optimize_actor(loss)
    assert all(g is None for g in grads(model.critic))
    assert all(g is not None and g.abs().sum() > 0 for g in grads(model.actor))
    assert all(g is None for g in grads(model.actor_target) + grads(model.critic_target))
    assert all(th.equal(a, b) for a, b in zip(critic_before, model.critic.parameters()))
    assert all(p.requires_grad for p in model.critic.parameters())


def test_critic_loss_leaves_actor_untouched():
    model = make_model()
    batch = make_batch()
    loss, _ = model.critic_loss(model.current_q_values(batch), model.compute_target_q(batch))
    loss.backward()
    assert all(g is None for g in grads(model.actor))
    assert all(g is not None for g in grads(model.critic))
    assert all(g is None for g in grads(model.actor_target) + grads(model.critic_target))


def test_target_networks_never_get_gradients():
    model = make_model(policy_delay=1)
    feed(model, [make_batch(i) for i in range(3)])
    model.train(gradient_steps=3, batch_size=BATCH)
    for target in (model.actor_target, model.critic_target):
        assert all(not p.requires_grad and p.grad is None for p in target.parameters())


def test_losses_do_not_step_optimizers_or_touch_targets():
    model = make_model()
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    batch = make_batch()
    model.critic_loss(model.current_q_values(batch), model.compute_target_q(batch))
    model.actor_loss(batch.observations)
    for k, v in model.policy.state_dict().items():
        th.testing.assert_close(v, before[k], rtol=0, atol=0)


# Steps 14-15 ---------------------------------------------------------------------------------------------------------
def perturb(module: th.nn.Module) -> None:
    with th.no_grad():
        for p in module.parameters():
            p.add_(th.randn_like(p))


@pytest.mark.parametrize("tau", [0.0, 1.0, 0.25])
def test_polyak_update(tau):
    model = make_model(tau=tau)
    perturb(model.actor)
    perturb(model.critic)
    online = [p.clone() for p in [*model.actor.parameters(), *model.critic.parameters()]]
    old_target = [p.clone() for p in [*model.actor_target.parameters(), *model.critic_target.parameters()]]
    model.update_actor_target()
    model.update_critic_target()
    new_target = [*model.actor_target.parameters(), *model.critic_target.parameters()]
    for p, old, new in zip(online, old_target, new_target):
        th.testing.assert_close(new, tau * p + (1 - tau) * old)
        if tau == 0.0:
            th.testing.assert_close(new, old, rtol=0, atol=0)
        if tau == 1.0:
            th.testing.assert_close(new, p, rtol=0, atol=0)


def test_polyak_copies_batch_norm_statistics():
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class BNExtractor(BaseFeaturesExtractor):
        def __init__(self, observation_space):
            super().__init__(observation_space, features_dim=8)
            self.net = th.nn.Sequential(th.nn.Linear(observation_space.shape[0], 8), th.nn.BatchNorm1d(8))

        def forward(self, obs):
            return self.net(obs)

    model = make_model(policy_kwargs=dict(net_arch=[16], features_extractor_class=BNExtractor))
    model.policy.set_training_mode(True)
    model.actor(th.randn(32, OBS_DIM) * 5 + 3)
    model.critic(th.randn(32, OBS_DIM) * 5 + 3, th.rand(32, ACT_DIM))
    model.update_actor_target()
    model.update_critic_target()
    for online, target in ((model.actor, model.actor_target), (model.critic, model.critic_target)):
        bn, bn_t = online.features_extractor.net[1], target.features_extractor.net[1]
        th.testing.assert_close(bn_t.running_mean, bn.running_mean, rtol=0, atol=0)
        th.testing.assert_close(bn_t.running_var, bn.running_var, rtol=0, atol=0)


# Step 13: delayed policy updates -------------------------------------------------------------------------------------
@pytest.mark.parametrize("policy_delay,steps", [(1, 5), (2, 7), (3, 10)])
def test_actor_updated_once_every_policy_delay_steps(policy_delay, steps):
    class Counting(TD3X):
        def optimize_actor(self, loss):
            self.actor_steps_at.append(self._n_updates)
            super().optimize_actor(loss)

        def update_actor_target(self):
            self.target_steps_at.append(self._n_updates)
            super().update_actor_target()

    model = Counting("MlpPolicy", "Pendulum-v1", policy_delay=policy_delay, policy_kwargs=dict(net_arch=[16]), seed=0)
    model.set_logger(configure(None, []))
    model.actor_steps_at, model.target_steps_at = [], []
    feed(model, [make_batch(i) for i in range(steps)])
    actor_before = [p.clone() for p in model.actor.parameters()]
    model.train(gradient_steps=steps, batch_size=BATCH)
    expected = [n for n in range(1, steps + 1) if n % policy_delay == 0]
    assert model.actor_steps_at == expected
    assert model.target_steps_at == expected
    assert model._n_actor_updates == len(expected)
    assert model.logger.name_to_value["train/actor_updates"] == len(expected)
    assert any(not th.equal(a, b) for a, b in zip(actor_before, model.actor.parameters()))


def test_actor_not_updated_before_policy_delay():
    model = make_model(policy_delay=2)
    feed(model, [make_batch()])
    actor_before = [p.clone() for p in model.actor.parameters()]
    critic_before = [p.clone() for p in model.critic.parameters()]
    model.train(gradient_steps=1, batch_size=BATCH)
    assert all(th.equal(a, b) for a, b in zip(actor_before, model.actor.parameters()))
    assert any(not th.equal(a, b) for a, b in zip(critic_before, model.critic.parameters()))


def test_train_logs_q_statistics():
    model = make_model(policy_delay=2)
    feed(model, [make_batch(i) for i in range(4)])
    model.train(gradient_steps=4, batch_size=BATCH)
    logged = model.logger.name_to_value
    for key in ("train/critic_loss", "train/actor_loss", "train/q1_mean", "train/q2_mean", "train/target_q_mean"):
        assert key in logged and np.isfinite(logged[key]), key
    assert logged["train/actor_updates"] == 2


def test_separate_critic_learning_rate():
    model = make_model(learning_rate=1e-3, critic_learning_rate=3e-4)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    assert model.critic.optimizer.param_groups[0]["lr"] == pytest.approx(3e-4)
    feed(model, [make_batch()])
    model._current_progress_remaining = 0.5
    model.critic_lr_schedule = lambda progress: 1e-4 * progress
    model.train(gradient_steps=1, batch_size=BATCH)
    assert model.critic.optimizer.param_groups[0]["lr"] == pytest.approx(5e-5)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)


def test_a_hook_can_be_overridden():
    """The point of the hooks: changing one step (here a Huber critic loss) needs one method, not a copy of train().
    The override must run at every gradient step and change what is learned (it would not, if it were dropped)."""

    class HuberTD3X(TD3X):
        calls = 0

        def critic_loss(self, current_q, target_q):
            HuberTD3X.calls += 1
            loss = sum(F.smooth_l1_loss(q, target_q) for q in current_q)
            return loss, {"critic_loss": loss.detach()}

    def trained(cls):
        model = cls("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=50, policy_kwargs=dict(net_arch=[16]), seed=0)
        model.learn(120)
        return model

    huber, plain = trained(HuberTD3X), trained(TD3X)
    assert huber._n_updates == 70 and HuberTD3X.calls == 70
    assert huber.update_path == "eager"  # a short run: the hooks as written, eagerly
    difference = max(float((a - b).abs().max()) for a, b in zip(huber.critic.parameters(), plain.critic.parameters()))
    assert difference > 1e-3
