"""n-step returns on TD3X's tensor buffer are SB3's: the same batches as SB3's NStepReplayBuffer from the same
transitions, and a seeded ``TD3X(n_steps=3)`` learns what SB3's ``TD3(n_steps=3)`` learns."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.buffers import NStepReplayBuffer
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise

from sb3_td3x import TD3X
from sb3_td3x.common.buffers import TensorReplayBuffer
from sb3_td3x.variants import TD3NStep

OBS = gym.spaces.Box(-5, 5, (4,), dtype=np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), dtype=np.float32)
FIELDS = ("observations", "actions", "next_observations", "dones", "rewards", "discounts")


def fill(buffers, steps: int, n_envs: int, seed: int = 0) -> None:
    """Episodes of a few steps that end by termination or by truncation (TimeLimit.truncated), per env."""
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        done = rng.uniform(size=n_envs) < 0.25
        truncated = done & (rng.uniform(size=n_envs) < 0.5)  # SB3 stores truncations as done, with the flag
        infos = [{"TimeLimit.truncated": bool(t)} for t in truncated]
        transition = (rng.normal(size=(n_envs, 4)), rng.normal(size=(n_envs, 4)),
                      rng.uniform(-1, 1, size=(n_envs, 2)), rng.normal(size=n_envs), done, infos)  # fmt: skip
        for buffer in buffers:
            buffer.add(*transition)


@pytest.mark.parametrize("handle_timeout_termination", [True, False])
@pytest.mark.parametrize("n_envs", [1, 3])
@pytest.mark.parametrize("steps", [23, 71])  # partly filled, and wrapped around (the newest overwrote the oldest)
@pytest.mark.parametrize("n_steps", [3, 5, 9])
def test_the_same_n_step_batches_as_sb3_for_every_start(n_steps, steps, n_envs, handle_timeout_termination):
    """The same bits, but for the returns of 8 terms or more, which numpy sums pairwise (to float rounding)."""
    kwargs = dict(n_envs=n_envs, handle_timeout_termination=handle_timeout_termination, n_steps=n_steps, gamma=0.9)
    reference = NStepReplayBuffer(90, OBS, ACT, device="cpu", **kwargs)
    buffer = TensorReplayBuffer(90, OBS, ACT, device="cpu", **kwargs)
    fill([reference, buffer], steps, n_envs)
    assert (reference.pos, reference.full) == (buffer.pos, buffer.full)
    starts = np.arange(reference.size())  # every stored position, the newest included
    cut_short = 0
    for env_seed in range(3):  # which env each start reads: drawn by both from numpy's generator
        np.random.seed(env_seed)
        expected = reference._get_samples(starts)
        np.random.seed(env_seed)
        got = buffer._get_samples(starts)
        for name in FIELDS:
            exact = name != "rewards" or n_steps < 8
            tolerance = {"rtol": 0, "atol": 0} if exact else {}
            th.testing.assert_close(getattr(got, name), getattr(expected, name), **tolerance, msg=name)
        cut_short += int((expected.discounts > 0.9**n_steps + 1e-6).sum())  # fewer steps summed
    assert cut_short > 10, "no sequence ended early: the test would not see how endings are handled"


@pytest.mark.parametrize("n_envs", [1, 2])
def test_a_seeded_sample_is_sb3s(n_envs):
    kwargs = dict(n_envs=n_envs, n_steps=3, gamma=0.99)
    reference = NStepReplayBuffer(40, OBS, ACT, device="cpu", **kwargs)
    buffer = TensorReplayBuffer(40, OBS, ACT, device="cpu", **kwargs)
    fill([reference, buffer], 57, n_envs)
    np.random.seed(5)
    expected = reference.sample(32)
    np.random.seed(5)
    got = buffer.sample(32)
    for name in FIELDS:
        th.testing.assert_close(getattr(got, name), getattr(expected, name), rtol=0, atol=0, msg=name)


class ScalingNormalizer:
    """What the buffers ask of a VecNormalize: its observation and reward normalisation (here affine maps)."""

    def normalize_obs(self, obs):
        return (obs - 0.5) * 2.0

    def normalize_reward(self, reward):
        return reward * 0.1


def test_n_step_batches_with_vec_normalize_are_sb3s():
    """Each reward of the sequence normalised before it is discounted, the observations normalised: as SB3 does."""
    kwargs = dict(n_envs=2, n_steps=3, gamma=0.99)
    reference = NStepReplayBuffer(60, OBS, ACT, device="cpu", **kwargs)
    buffer = TensorReplayBuffer(60, OBS, ACT, device="cpu", **kwargs)
    fill([reference, buffer], 45, 2)
    starts = np.arange(reference.size())
    np.random.seed(0)
    expected = reference._get_samples(starts, env=ScalingNormalizer())
    np.random.seed(0)
    got = buffer._get_samples(starts, env=ScalingNormalizer())
    for name in FIELDS:
        th.testing.assert_close(getattr(got, name), getattr(expected, name).float(), msg=name)


def test_the_n_step_target_is_the_hand_written_return():
    """One sequence by hand: r0 + g r1 + g^2 r2, bootstrapped with g^3 at s3; cut at a termination (no bootstrap) and
    at a truncation (bootstrapped with g^2 at the truncation's next observation)."""
    buffer = TensorReplayBuffer(20, OBS, ACT, device="cpu", n_steps=3, gamma=0.5)
    rewards, ends = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0], [None, None, None, None, "terminated", None, "truncated"]
    for t, (reward, end) in enumerate(zip(rewards, ends)):
        done, infos = np.array([end is not None]), [{"TimeLimit.truncated": end == "truncated"}]
        buffer.add(np.full((1, 4), t), np.full((1, 4), t + 1), np.zeros((1, 2)), np.array([reward]), done, infos)
    batch = buffer._get_samples(th.tensor([0, 2, 3, 5]))
    th.testing.assert_close(batch.rewards.squeeze(1), th.tensor([1 + 1 + 1.0, 4 + 4 + 4.0, 8 + 8.0, 32 + 32.0]))
    th.testing.assert_close(batch.discounts.squeeze(1), th.tensor([0.125, 0.125, 0.25, 0.25]))
    th.testing.assert_close(batch.next_observations[:, 0], th.tensor([3.0, 5.0, 5.0, 7.0]))
    th.testing.assert_close(batch.dones.squeeze(1), th.tensor([0.0, 1.0, 1.0, 0.0]))  # a truncation bootstraps


def test_seeded_td3x_n_step_learns_what_sb3_td3_n_step_learns():
    """Both from the seed alone (as tests/equivalence/test_same_learning.py): SB3's TD3 on its NStepReplayBuffer,
    TD3X on its tensor buffer, the hooks run eagerly (the compiled update is held to them in test_user_changes.py's
    stock-n-step case)."""
    kwargs = dict(learning_starts=100, batch_size=32, n_steps=3, seed=3,
                  action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
                  policy_kwargs=dict(net_arch=[32, 32], optimizer_kwargs=dict(foreach=False)))  # fmt: skip
    sb3 = TD3("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=3), **kwargs)
    assert type(sb3.replay_buffer) is NStepReplayBuffer
    sb3.learn(400)
    td3x = TD3NStep("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=3), **kwargs)
    assert type(td3x.replay_buffer) is TensorReplayBuffer and td3x.replay_buffer.n_steps == 3
    td3x.learn(400)
    assert td3x.update_path == "eager"
    assert sb3._n_updates == td3x._n_updates > 100
    for (name, expected), got in zip(sb3.policy.state_dict().items(), td3x.policy.state_dict().values()):
        th.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5, msg=name)
    one_step = TD3X("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=3), **{**kwargs, "n_steps": 1})
    one_step.learn(400)
    moved = max(float((a - b).detach().abs().max()) for a, b in zip(one_step.policy.parameters(), td3x.policy.parameters()))
    assert moved > 1e-2, "one-step and 3-step returns train alike here: the test would not see n ignored"


def test_td3_nstep_defaults_to_3_and_saves_and_loads(tmp_path):
    model = TD3NStep("MlpPolicy", "Pendulum-v1", learning_starts=20, policy_kwargs=dict(net_arch=[8]), seed=0)
    assert model.n_steps == 3 and model.replay_buffer.n_steps == 3 and model.replay_buffer.gamma == model.gamma
    model.learn(40)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = TD3NStep.load(tmp_path / "model", env=model.get_env())
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert loaded.n_steps == 3 and loaded.replay_buffer.n_steps == 3
    assert loaded.replay_buffer.sample(4).discounts is not None
