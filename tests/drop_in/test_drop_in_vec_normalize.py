"""Drop-in: off-policy training and evaluation under ``VecNormalize``, with plain and HER replay buffers.

Mirrors SB3's ``tests/test_vec_normalize.py`` (``test_offpolicy_normalization``, ``test_her_normalization``, and the
save/load of the statistics in ``test_vec_env``) with ``TD3X`` and ``DDPG``. Also checks what SB3's off-policy
algorithms promise with ``VecNormalize``: the replay buffer keeps the raw observations and rewards, and the sampled
batches are normalized with the current statistics.
"""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_td3x import DDPG, TD3X

TINY = dict(policy_kwargs=dict(net_arch=[64]), learning_starts=100, batch_size=64, buffer_size=1_000)


class DummyGoalEnv(gym.Env):
    """A goal-conditioned env with random observations; the reward says whether the achieved goal is the desired one."""

    def __init__(self):
        super().__init__()
        box = spaces.Box(low=-20.0, high=20.0, shape=(4,), dtype=np.float32)
        self.observation_space = spaces.Dict({"observation": box, "achieved_goal": box, "desired_goal": box})
        self.action_space = spaces.Box(low=-1, high=1, shape=(3,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        obs = self.observation_space.sample()
        reward = self.compute_reward(obs["achieved_goal"], obs["desired_goal"], {})
        return obs, reward, np.random.rand() > 0.8, False, {}

    def compute_reward(self, achieved_goal, desired_goal, _info):
        return -(np.linalg.norm(achieved_goal - desired_goal, axis=-1) > 0).astype(np.float32)


def make_env():
    return Monitor(gym.make("Pendulum-v1"))


def normalized_pair(training: bool = True, norm_reward: bool = True) -> VecNormalize:
    return VecNormalize(
        DummyVecEnv([make_env]), training=training, norm_obs=True, norm_reward=norm_reward, clip_obs=10.0, clip_reward=10.0
    )


def to_numpy(x) -> np.ndarray:
    """Replay buffers may store numpy arrays (SB3) or tensors: compare them as numpy arrays."""
    return x.cpu().numpy() if isinstance(x, th.Tensor) else np.asarray(x)


# mirrors SB3 tests/test_vec_normalize.py::test_offpolicy_normalization
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_offpolicy_normalization(model_class):
    env = normalized_pair()
    eval_env = normalized_pair(training=False, norm_reward=False)
    model = model_class("MlpPolicy", env, **TINY)

    # The VecNormalize wrapper follows set_env.
    assert model.get_vec_normalize_env() is env
    model.set_env(eval_env)
    assert model.get_vec_normalize_env() is eval_env
    model.learn(total_timesteps=10)
    model.set_env(env)
    model.learn(total_timesteps=150)
    assert isinstance(model.get_vec_normalize_env(), VecNormalize)
    assert model._n_updates > 0


# mirrors SB3 tests/test_vec_normalize.py::test_her_normalization
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_her_normalization(model_class):
    env = VecNormalize(DummyVecEnv([lambda: Monitor(DummyGoalEnv())]), clip_obs=10.0, clip_reward=10.0)
    eval_env = VecNormalize(
        DummyVecEnv([lambda: Monitor(DummyGoalEnv())]), training=False, norm_reward=False, clip_obs=10.0, clip_reward=10.0
    )
    model = model_class(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs=dict(n_sampled_goal=2),
        seed=2,
        **TINY,
    )
    assert model.get_vec_normalize_env() is env
    model.set_env(eval_env)
    assert model.get_vec_normalize_env() is eval_env
    model.learn(total_timesteps=10)
    model.set_env(env)
    model.learn(total_timesteps=150)
    assert isinstance(model.get_vec_normalize_env(), VecNormalize)
    assert model._n_updates > 0


def test_replay_buffer_keeps_raw_data_and_samples_normalized():
    """SB3's contract: raw transitions in the buffer, normalized with the latest statistics when sampled."""
    env = normalized_pair()
    model = TD3X("MlpPolicy", env, **TINY)
    model.learn(total_timesteps=150)
    buffer = model.replay_buffer
    size = buffer.size()
    raw_obs = to_numpy(buffer.observations)[:size, 0]  # (size, obs_dim)
    raw_rewards = to_numpy(buffer.rewards)[:size, 0]  # (size,)
    # Pendulum's raw observation (cos, sin, angular velocity): the first two entries on the unit circle.
    np.testing.assert_allclose(raw_obs[:, 0] ** 2 + raw_obs[:, 1] ** 2, 1.0, rtol=1e-5)

    batch = model.sample_batch(16)
    expected_obs = env.normalize_obs(raw_obs)  # (size, obs_dim)
    expected_rewards = env.normalize_reward(raw_rewards)  # (size,)
    observations = to_numpy(batch.observations)  # (16, obs_dim)
    rewards = to_numpy(batch.rewards)  # (16, 1)
    for obs, reward in zip(observations, rewards):
        # Every sampled row is the normalization of one stored transition.
        matches = np.where(np.isclose(expected_obs, obs, atol=1e-5).all(axis=1))[0]
        assert len(matches) > 0, obs
        assert np.isclose(expected_rewards[matches], reward[0], atol=1e-5).any()


# mirrors the save/load part of SB3 tests/test_vec_normalize.py::test_vec_env, with a model trained under it
def test_save_load_with_vec_normalize(tmp_path):
    env = normalized_pair()
    model = DDPG("MlpPolicy", env, **TINY)
    model.learn(total_timesteps=150)
    model.save(tmp_path / "model.zip")
    env.save(tmp_path / "vec_normalize.pkl")

    eval_env = VecNormalize.load(tmp_path / "vec_normalize.pkl", DummyVecEnv([make_env]))
    eval_env.training, eval_env.norm_reward = False, False
    assert np.array_equal(eval_env.obs_rms.mean, env.obs_rms.mean)
    assert np.array_equal(eval_env.obs_rms.var, env.obs_rms.var)

    loaded = DDPG.load(tmp_path / "model.zip", env=eval_env)
    assert loaded.get_vec_normalize_env() is eval_env
    obs = eval_env.reset()
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
