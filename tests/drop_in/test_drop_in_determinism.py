"""Drop-in: two runs with the same seed give the same actions, rewards and parameters.

Mirrors SB3's ``tests/test_deterministic.py::test_deterministic_training_common`` (SB3 runs it with ``TD3``), with
``TD3X`` and ``DDPG``, and also compares every parameter and optimizer state after training.
"""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise

from sb3_td3x import DDPG, TD3X

SEED = 0
N_STEPS_TRAINING = 300


def train_and_roll_out(model_class, seed: int, n_envs: int = 1):
    kwargs = dict(
        policy_kwargs=dict(net_arch=[64]),
        action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
        learning_starts=100,
        train_freq=4,
        batch_size=64,
    )
    env = "Pendulum-v1" if n_envs == 1 else make_vec_env("Pendulum-v1", n_envs=n_envs)
    model = model_class("MlpPolicy", env, seed=seed, **kwargs)
    model.learn(N_STEPS_TRAINING)
    env = model.get_env()
    obs = env.reset()
    actions, rewards = [], []
    for _ in range(50):
        action, _ = model.predict(obs, deterministic=False)
        obs, reward, _, _ = env.step(action)
        actions.append(action)
        rewards.append(reward)
    return model, np.array(actions), np.array(rewards)


def assert_same_state(model_a, model_b) -> None:
    params_a, params_b = model_a.get_parameters(), model_b.get_parameters()
    assert params_a.keys() == params_b.keys()
    for key, value in params_a["policy"].items():
        assert th.equal(value, params_b["policy"][key]), key
    for name in ("actor.optimizer", "critic.optimizer"):
        state_a, state_b = params_a[name]["state"], params_b[name]["state"]
        for index in state_a:
            assert th.equal(state_a[index]["exp_avg"], state_b[index]["exp_avg"]), f"{name}/{index}"


# mirrors SB3 tests/test_deterministic.py::test_deterministic_training_common
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize("n_envs", [1, 2])
def test_deterministic_training_common(model_class, n_envs):
    model_a, actions_a, rewards_a = train_and_roll_out(model_class, SEED, n_envs)
    model_b, actions_b, rewards_b = train_and_roll_out(model_class, SEED, n_envs)
    # SB3 compares sums; identical arrays is the stronger statement.
    np.testing.assert_array_equal(actions_a, actions_b)
    np.testing.assert_array_equal(rewards_a, rewards_b)
    assert_same_state(model_a, model_b)
    assert model_a._n_updates == model_b._n_updates > 0


def test_different_seeds_differ():
    """The counter-check: the equalities above are not vacuous."""
    _, actions_a, _ = train_and_roll_out(TD3X, SEED)
    _, actions_b, _ = train_and_roll_out(TD3X, SEED + 1)
    assert not np.array_equal(actions_a, actions_b)
