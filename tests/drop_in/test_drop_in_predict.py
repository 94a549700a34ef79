"""Drop-in: ``predict`` (shapes, vectorized envs, devices, deterministic flag) and train/eval mode switching.

Mirrors SB3's ``tests/test_predict.py`` (``test_auto_wrap``, ``test_predict``, ``test_subclassed_space_env``) and
``tests/test_train_eval_mode.py`` (``test_td3_train_with_batch_norm``, ``test_offpolicy_collect_rollout_batch_norm``,
``test_predict_with_dropout_batch_norm``), with ``TD3X``.
"""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_td3x import DDPG, TD3X

# A bare minimum of exploration before learning, small networks: these tests are about the interfaces.
TINY = dict(policy_kwargs=dict(net_arch=[64, 64]), learning_starts=100, batch_size=64, buffer_size=1_000)


class SubClassedBox(spaces.Box):
    pass


class CustomSubClassedSpaceEnv(gym.Env):
    def __init__(self):
        super().__init__()
        self.observation_space = SubClassedBox(-1, 1, shape=(2,), dtype=np.float32)
        self.action_space = SubClassedBox(-1, 1, shape=(2,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, np.random.rand() > 0.5, False, {}


class FlattenBatchNormDropoutExtractor(BaseFeaturesExtractor):
    """Flatten, then batch norm and dropout: layers whose output depends on train/eval mode."""

    def __init__(self, observation_space: spaces.Space):
        super().__init__(observation_space, get_flattened_obs_dim(observation_space))
        self.flatten = th.nn.Flatten()
        self.batch_norm = th.nn.BatchNorm1d(self._features_dim)
        self.dropout = th.nn.Dropout(0.5)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.dropout(self.batch_norm(self.flatten(observations)))


def batch_norm_stats(model: TD3X) -> dict[str, tuple[th.Tensor, th.Tensor]]:
    """(bias, running mean) of the batch norm layer of the actor, the critic and their targets."""
    return {
        name: (module.features_extractor.batch_norm.bias.clone(), module.features_extractor.batch_norm.running_mean.clone())
        for name, module in [
            ("actor", model.actor),
            ("critic", model.critic),
            ("actor_target", model.actor_target),
            ("critic_target", model.critic_target),
        ]
    }


BATCH_NORM_POLICY = dict(net_arch=[16, 16], features_extractor_class=FlattenBatchNormDropoutExtractor)


# mirrors SB3 tests/test_predict.py::test_auto_wrap
def test_auto_wrap():
    model = TD3X("MlpPolicy", gym.make("Pendulum-v1"), **TINY)
    assert model.get_env().num_envs == 1
    model.learn(150)


# mirrors SB3 tests/test_predict.py::test_predict
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize(
    "device", ["cpu", "auto", pytest.param("cuda", marks=pytest.mark.skipif(not th.cuda.is_available(), reason="no GPU"))]
)
def test_predict(model_class, device):
    model = model_class("MlpPolicy", "Pendulum-v1", device=device, **TINY)
    assert model.policy.device.type == get_device(device).type

    env = gym.make("Pendulum-v1")
    vec_env = DummyVecEnv([lambda: gym.make("Pendulum-v1")] * 2)

    obs, _ = env.reset(seed=0)
    action, state = model.predict(obs)
    assert isinstance(action, np.ndarray)
    assert action.shape == env.action_space.shape
    assert env.action_space.contains(action)
    assert state is None

    vec_env_obs = vec_env.reset()
    action, _ = model.predict(vec_env_obs)
    assert isinstance(action, np.ndarray)
    assert action.shape == (vec_env_obs.shape[0], *env.action_space.shape)
    assert all(env.action_space.contains(a) for a in action)

    # As in SB3's TD3, predict() is deterministic either way: exploration noise only enters during collection.
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=False)[0])
    # A batch of one observation gives the same action as the observation alone.
    np.testing.assert_allclose(model.predict(obs[None])[0][0], model.predict(obs)[0], rtol=1e-6)


# mirrors SB3 tests/test_predict.py::test_subclassed_space_env
def test_subclassed_space_env():
    env = CustomSubClassedSpaceEnv()
    model = TD3X("MlpPolicy", env, policy_kwargs=dict(net_arch=[32]), learning_starts=100, batch_size=64)
    model.learn(200)
    obs, _ = env.reset()
    action, _ = model.predict(obs)
    assert env.action_space.contains(action)
    env.step(action)


# mirrors SB3 tests/test_train_eval_mode.py::test_td3_train_with_batch_norm
def test_td3x_train_with_batch_norm():
    model = TD3X(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=BATCH_NORM_POLICY,
        learning_starts=0,
        batch_size=64,
        tau=0,  # the targets' weights do not move...
        seed=1,
    )
    before = batch_norm_stats(model)
    model.learn(total_timesteps=200)
    after = batch_norm_stats(model)

    for name in ("actor", "critic"):
        assert not th.isclose(before[name][0], after[name][0]).all(), f"{name} bias"
        assert not th.isclose(before[name][1], after[name][1]).all(), f"{name} running mean"
        bias_before_target = before[f"{name}_target"][0]
        assert th.isclose(bias_before_target, after[f"{name}_target"][0]).all(), f"{name}_target bias"
        # ... but the running statistics are copied to the targets even when tau=0.
        assert th.isclose(after[name][1], after[f"{name}_target"][1]).all(), f"{name}_target running mean"


# mirrors SB3 tests/test_train_eval_mode.py::test_offpolicy_collect_rollout_batch_norm
def test_offpolicy_collect_rollout_batch_norm():
    model = TD3X(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=BATCH_NORM_POLICY,
        learning_starts=10,
        seed=1,
        gradient_steps=0,
        train_freq=1,
    )
    before = batch_norm_stats(model)
    model.learn(total_timesteps=100)
    after = batch_norm_stats(model)
    # Collecting rollouts runs the actor in eval mode: no batch norm statistics change.
    for name in before:
        for value_before, value_after in zip(before[name], after[name]):
            assert th.equal(value_before, value_after), name


# mirrors SB3 tests/test_train_eval_mode.py::test_predict_with_dropout_batch_norm
def test_predict_with_dropout_batch_norm():
    model = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs=BATCH_NORM_POLICY, learning_starts=0, seed=1)
    before = batch_norm_stats(model)
    observation = model.get_env().reset()
    first_prediction, _ = model.predict(observation, deterministic=True)
    for _ in range(5):
        prediction, _ = model.predict(observation, deterministic=True)
        # Dropout is off and batch norm uses its running statistics: the same action every time.
        np.testing.assert_allclose(first_prediction, prediction)
    after = batch_norm_stats(model)
    for name in before:
        for value_before, value_after in zip(before[name], after[name]):
            assert th.equal(value_before, value_after), name


def test_train_switches_modes():
    """train() puts the networks in train mode, predict() and collection in eval mode (SB3's contract)."""
    model = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs=BATCH_NORM_POLICY, learning_starts=0, batch_size=16)
    model.learn(20)
    model.train(gradient_steps=1, batch_size=16)
    assert model.actor.training and model.critic.training
    model.predict(model.get_env().reset())
    assert not model.actor.training
