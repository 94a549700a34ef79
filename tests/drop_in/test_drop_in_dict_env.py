"""Drop-in: Dict observations with ``MultiInputPolicy`` (vectors, images, discrete entries, frame stacking, VecNormalize).

Mirrors SB3's ``tests/test_dict_env.py`` (``test_consistency``, ``test_dict_spaces``, ``test_dict_vec_framestack``,
``test_vec_normalize``, ``test_dict_nested``) with ``TD3X`` and ``DDPG``, on SB3's ``SimpleMultiObsEnv`` and on a
dummy env with an image, a vector and a discrete entry.
"""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.envs import SimpleMultiObsEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack, VecNormalize

from sb3_td3x import DDPG, TD3X

# Small replay buffer, small networks and CNN features, a gradient step every 8 env steps.
OFF_POLICY_KWARGS = dict(
    buffer_size=250,
    batch_size=32,
    policy_kwargs=dict(net_arch=[32], features_extractor_kwargs=dict(cnn_output_dim=32)),
    train_freq=8,
    gradient_steps=1,
)


class DummyDictEnv(gym.Env):
    """Random observations in a Dict space: an image, a vector and a discrete entry (or the vector only)."""

    def __init__(self, channel_last: bool = False, nested_dict_obs: bool = False, vec_only: bool = False):
        super().__init__()
        self.action_space = spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32)
        image_shape = (64, 64, 1) if channel_last else (1, 64, 64)
        self.observation_space = spaces.Dict(
            {
                "img": spaces.Box(low=0, high=255, shape=image_shape, dtype=np.uint8),
                "vec": spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32),
                "discrete": spaces.Discrete(4),
            }
        )
        if vec_only:
            self.observation_space = spaces.Dict({"vec": spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32)})
        if nested_dict_obs:
            self.observation_space.spaces["nested-dict"] = spaces.Dict({"nested-dict-discrete": spaces.Discrete(4)})

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.observation_space.seed(seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


# mirrors SB3 tests/test_dict_env.py::test_consistency
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_consistency(model_class):
    """A Dict with one vector entry and the flattened vector give the same networks, so the same actions."""
    dict_env = gym.wrappers.TimeLimit(DummyDictEnv(vec_only=True), 100)
    env = gym.wrappers.FlattenObservation(dict_env)
    obs, _ = dict_env.reset(seed=10)
    kwargs = dict(buffer_size=250, batch_size=64, train_freq=8, gradient_steps=1)

    dict_model = model_class("MultiInputPolicy", dict_env, gamma=0.5, seed=1, **kwargs)
    action_before_learning_1, _ = dict_model.predict(obs, deterministic=True)
    dict_model.learn(total_timesteps=200)

    normal_model = model_class("MlpPolicy", env, gamma=0.5, seed=1, **kwargs)
    action_before_learning_2, _ = normal_model.predict(obs["vec"], deterministic=True)
    normal_model.learn(total_timesteps=200)

    action_1, _ = dict_model.predict(obs, deterministic=True)
    action_2, _ = normal_model.predict(obs["vec"], deterministic=True)
    np.testing.assert_allclose(action_before_learning_1, action_before_learning_2)
    # The same update on the same numbers; SB3's Dict buffer stores float64 observations where the tensor buffer
    # stores float32, so equal to float rounding rather than bit for bit.
    np.testing.assert_allclose(action_1, action_2, rtol=1e-4, atol=1e-5)
    # Learning did change the policy: the comparison after learning is not a comparison of initial weights.
    assert not np.allclose(action_before_learning_1, action_1)


# mirrors SB3 tests/test_dict_env.py::test_dict_spaces
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize("channel_last", [False, True])
def test_dict_spaces(model_class, channel_last):
    env = gym.wrappers.TimeLimit(DummyDictEnv(channel_last=channel_last), 100)
    model = model_class("MultiInputPolicy", env, gamma=0.5, seed=1, **OFF_POLICY_KWARGS)
    model.learn(total_timesteps=200)
    assert model._n_updates > 0
    obs, _ = env.reset()
    action, _ = model.predict(obs)
    assert env.action_space.contains(action)
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


# mirrors SB3 tests/test_dict_env.py::test_dict_vec_framestack
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize("channel_last", [False, True])
def test_dict_vec_framestack(model_class, channel_last):
    channels_order = {"vec": None, "img": "last" if channel_last else "first"}
    env = DummyVecEnv([lambda: SimpleMultiObsEnv(random_start=True, discrete_actions=False, channel_last=channel_last)])
    env = VecFrameStack(env, n_stack=3, channels_order=channels_order)
    model = model_class("MultiInputPolicy", env, gamma=0.5, seed=1, **OFF_POLICY_KWARGS)
    model.learn(total_timesteps=200)
    assert model._n_updates > 0
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


# mirrors SB3 tests/test_dict_env.py::test_vec_normalize
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_vec_normalize(model_class):
    env = DummyVecEnv([lambda: gym.wrappers.TimeLimit(DummyDictEnv(), 100)])
    # VecNormalize normalizes Box entries only: the vector here.
    env = VecNormalize(env, norm_obs_keys=["vec"])
    model = model_class("MultiInputPolicy", env, gamma=0.5, seed=1, **OFF_POLICY_KWARGS)
    assert model.get_vec_normalize_env() is env
    model.learn(total_timesteps=200)
    assert model._n_updates > 0
    assert env.obs_rms["vec"].count > 200
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


# mirrors SB3 tests/test_dict_env.py::test_dict_nested
def test_dict_nested():
    with pytest.raises(NotImplementedError):
        TD3X("MultiInputPolicy", DummyDictEnv(nested_dict_obs=True), seed=1)
