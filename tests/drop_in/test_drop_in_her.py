"""Drop-in: Hindsight Experience Replay (``HerReplayBuffer``) with ``MultiInputPolicy`` on SB3's ``BitFlippingEnv``.

Mirrors SB3's ``tests/test_her.py`` (``test_her``, ``test_multiprocessing``, ``test_goal_selection_strategy``,
``test_save_load``, ``test_save_load_replay_buffer``, ``test_full_replay_buffer``) with ``TD3X`` and ``DDPG``, on the
continuous-action version of the env. ``test_performance_her`` is SB3's DQN-only learning check: not mirrored.
"""

import pathlib
import warnings
from copy import deepcopy

import numpy as np
import pytest
import torch as th
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import BitFlippingEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.vec_env import SubprocVecEnv
from stable_baselines3.her.goal_selection_strategy import KEY_TO_GOAL_STRATEGY, GoalSelectionStrategy

from sb3_td3x import DDPG, TD3X

N_BITS = 4
HER_KWARGS = dict(n_sampled_goal=2, goal_selection_strategy="future")


def her_model(model_class, env, **kwargs):
    defaults = dict(
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs=HER_KWARGS,
        train_freq=4,
        gradient_steps=1,
        policy_kwargs=dict(net_arch=[64]),
        learning_starts=100,
        batch_size=64,
        buffer_size=int(2e4),
    )
    return model_class("MultiInputPolicy", env, **{**defaults, **kwargs})


# mirrors SB3 tests/test_her.py::test_her
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize("image_obs_space", [False, True])
@pytest.mark.parametrize("n_envs", [1, 2])
def test_her(model_class, image_obs_space, n_envs):
    def make_env():
        return BitFlippingEnv(n_bits=N_BITS, continuous=True, image_obs_space=image_obs_space)

    env = make_vec_env(make_env, n_envs=n_envs)
    kwargs = dict(gradient_steps=n_envs, replay_buffer_kwargs=dict(HER_KWARGS, copy_info_dict=True), seed=0)
    if image_obs_space:
        kwargs.update(batch_size=32, buffer_size=500)
    model = her_model(model_class, env, **kwargs)
    assert isinstance(model.replay_buffer, HerReplayBuffer)
    model.learn(total_timesteps=150)
    assert model._n_updates > 0
    # Real and relabelled transitions alike: the reward is the env's for the next achieved goal and the desired goal.
    batch = model.replay_buffer.sample(64)
    assert set(batch.observations) == {"observation", "achieved_goal", "desired_goal"}
    reward_env = make_env()
    reward_env.reset(seed=0)  # the image version needs a state to decode images
    expected_rewards = reward_env.compute_reward(
        batch.next_observations["achieved_goal"].cpu().numpy(), batch.observations["desired_goal"].cpu().numpy(), None
    )
    np.testing.assert_array_equal(batch.rewards.cpu().numpy().ravel(), expected_rewards)
    # With relabelled goals, some sampled transitions are successes.
    assert (expected_rewards == 0).any()
    evaluate_policy(model, Monitor(make_env()), n_eval_episodes=2)


# mirrors SB3 tests/test_her.py::test_multiprocessing
def test_multiprocessing():
    env = make_vec_env(
        lambda: BitFlippingEnv(n_bits=N_BITS, continuous=True),
        n_envs=2,
        vec_env_cls=SubprocVecEnv,
        vec_env_kwargs=dict(start_method="fork"),  # the quickest start; the workers only step the env
    )
    try:
        model = her_model(TD3X, env, learning_starts=50)
        model.learn(total_timesteps=100)
        assert model.num_timesteps >= 100
    finally:
        env.close()


# mirrors SB3 tests/test_her.py::test_goal_selection_strategy (SB3 runs it with SAC)
@pytest.mark.parametrize(
    "goal_selection_strategy",
    ["final", "episode", "future", GoalSelectionStrategy.FINAL, GoalSelectionStrategy.EPISODE, GoalSelectionStrategy.FUTURE],
)
def test_goal_selection_strategy(goal_selection_strategy):
    env = BitFlippingEnv(continuous=True)
    action_noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
    model = her_model(
        TD3X,
        env,
        replay_buffer_kwargs=dict(goal_selection_strategy=goal_selection_strategy, n_sampled_goal=2),
        buffer_size=int(1e5),
        action_noise=action_noise,
    )
    assert model.action_noise is not None
    expected = KEY_TO_GOAL_STRATEGY.get(goal_selection_strategy, goal_selection_strategy)
    assert model.replay_buffer.goal_selection_strategy == expected
    model.learn(total_timesteps=150)


# mirrors SB3 tests/test_her.py::test_save_load
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_save_load(tmp_path, model_class):
    env = BitFlippingEnv(n_bits=N_BITS, continuous=True)
    model = her_model(model_class, env, tau=0.05, batch_size=128, learning_rate=0.001, buffer_size=int(1e5), gamma=0.98)
    model.learn(total_timesteps=150)

    obs, _ = env.reset()
    observations = {key: [] for key in obs}
    for _ in range(10):
        obs = env.step(env.action_space.sample())[0]
        for key in obs:
            observations[key].append(obs[key])
    observations = {key: np.array(values) for key, values in observations.items()}

    params = deepcopy(model.policy.state_dict())
    model.policy.load_state_dict({name: th.rand_like(param) for name, param in params.items()})
    new_params = model.policy.state_dict()
    for key in params:
        assert not th.allclose(params[key], new_params[key]), key
    params = deepcopy(new_params)
    selected_actions, _ = model.predict(observations, deterministic=True)
    model.save(tmp_path / "test_save.zip")
    del model

    # custom_objects replace only attributes the model has.
    custom_objects = dict(learning_rate=2e-5, dummy=1.0)
    model_ = model_class.load(str(tmp_path / "test_save.zip"), env=env, custom_objects=custom_objects, verbose=2)
    assert model_.verbose == 2
    assert model_.learning_rate == custom_objects["learning_rate"]
    assert not hasattr(model_, "dummy")

    model = model_class.load(str(tmp_path / "test_save.zip"), env=env)
    for key, value in model.policy.state_dict().items():
        assert th.equal(params[key], value), key
    new_selected_actions, _ = model.predict(observations, deterministic=True)
    np.testing.assert_allclose(selected_actions, new_selected_actions, atol=1e-4)
    # Training goes on after a load (the replay buffer is not saved with the model: a fresh one fills up).
    assert isinstance(model.replay_buffer, HerReplayBuffer)
    model.learn(total_timesteps=150)

    # Keyword arguments to load() override the saved values.
    model = model_class.load(str(tmp_path / "test_save.zip"), env=env, verbose=3, learning_rate=2.0)
    assert model.learning_rate == 2.0
    assert model.verbose == 3


# mirrors SB3 tests/test_her.py::test_save_load_replay_buffer (SB3 runs it with SAC)
@pytest.mark.parametrize("truncate_last_trajectory", [False, True])
def test_save_load_replay_buffer(tmp_path, recwarn, truncate_last_trajectory):
    warnings.filterwarnings(action="ignore", category=DeprecationWarning)
    path = pathlib.Path(tmp_path / "replay_buffer.pkl")
    env = BitFlippingEnv(n_bits=N_BITS, continuous=True)
    model = her_model(TD3X, env, train_freq=2, seed=1)
    # 202 steps: the last episode (4 steps each) is unfinished when the buffer is saved.
    model.learn(202)
    old_replay_buffer = deepcopy(model.replay_buffer)
    model.save_replay_buffer(path)
    del model.replay_buffer
    with pytest.raises(AttributeError):
        model.replay_buffer
    assert len(recwarn) == 0

    model.load_replay_buffer(path, truncate_last_traj=truncate_last_trajectory)
    if truncate_last_trajectory:
        assert len(recwarn) == 1
        warning = recwarn.pop(UserWarning)
        assert "The last trajectory in the replay buffer will be truncated" in str(warning.message)
    else:
        assert len(recwarn) == 0

    replay_buffer = model.replay_buffer
    pos = replay_buffer.pos
    assert pos == old_replay_buffer.pos == 202
    for key in ("observation", "achieved_goal", "desired_goal"):
        np.testing.assert_array_equal(old_replay_buffer.observations[key][:pos], replay_buffer.observations[key][:pos])
        np.testing.assert_array_equal(
            old_replay_buffer.next_observations[key][:pos], replay_buffer.next_observations[key][:pos]
        )
    np.testing.assert_array_equal(old_replay_buffer.actions[:pos], replay_buffer.actions[:pos])
    np.testing.assert_array_equal(old_replay_buffer.rewards[:pos], replay_buffer.rewards[:pos])
    # Truncation may mark the last transition done: compare the others.
    np.testing.assert_array_equal(old_replay_buffer.dones[: pos - 1], replay_buffer.dones[: pos - 1])

    model.learn(200, reset_num_timesteps=truncate_last_trajectory)


# mirrors SB3 tests/test_her.py::test_full_replay_buffer
def test_full_replay_buffer():
    """HER with a full buffer must not sample the unfinished current episode."""
    env = BitFlippingEnv(n_bits=N_BITS, continuous=True)
    model = her_model(TD3X, env, learning_starts=1, buffer_size=20, batch_size=16, seed=757)
    model.learn(total_timesteps=100)
    assert model.replay_buffer.full
