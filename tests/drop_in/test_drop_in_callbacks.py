"""Drop-in: SB3's callbacks drive ``TD3X`` and ``DDPG`` training as they drive ``TD3``.

Mirrors SB3's ``tests/test_callbacks.py`` (``test_callbacks``, ``test_eval_callback_vec_env``,
``test_eval_success_logging``, ``test_checkpoint_additional_info``, and the ``StopTrainingOnMaxEpisodes`` check with
several envs that SB3 runs for A2C/PPO).
"""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.callbacks import (
    CallbackList,
    CheckpointCallback,
    EvalCallback,
    EveryNTimesteps,
    LogEveryNTimesteps,
    StopTrainingOnMaxEpisodes,
    StopTrainingOnNoModelImprovement,
    StopTrainingOnRewardThreshold,
)
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import BitFlippingEnv, IdentityEnvBox
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_td3x import DDPG, TD3X

TINY = dict(policy_kwargs=dict(net_arch=[32]), learning_starts=100, batch_size=64, buffer_size=1_000)


# mirrors SB3 tests/test_callbacks.py::test_callbacks
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_callbacks(tmp_path, model_class):
    log_folder = tmp_path / "logs/callbacks/"
    model = model_class("MlpPolicy", "Pendulum-v1", **TINY)

    checkpoint_callback = CheckpointCallback(save_freq=200, save_path=log_folder)
    # Stop training when the performance is good enough, or when it stops improving. SB3's threshold, -1200, may stop
    # this short run at random: here it is unreachable, and test_stop_training_callbacks checks that stopping works.
    callback_on_best = StopTrainingOnRewardThreshold(reward_threshold=0.0, verbose=1)
    # At most 3 evaluations in 300 steps: too few for 2 without improvement after the first.
    callback_no_model_improvement = StopTrainingOnNoModelImprovement(max_no_improvement_evals=2, min_evals=1, verbose=1)
    eval_callback = EvalCallback(
        gym.make("Pendulum-v1"),
        callback_on_new_best=callback_on_best,
        callback_after_eval=callback_no_model_improvement,
        best_model_save_path=log_folder,
        log_path=log_folder,
        eval_freq=100,
        n_eval_episodes=1,
        warn=False,
    )
    # The checkpoint callback again, event-driven.
    checkpoint_on_event = CheckpointCallback(save_freq=1, save_path=log_folder, name_prefix="event")
    event_callback = EveryNTimesteps(n_steps=250, callback=checkpoint_on_event)
    callback_max_episodes = StopTrainingOnMaxEpisodes(max_episodes=100, verbose=1)
    log_callback = LogEveryNTimesteps(n_steps=100)
    callback = CallbackList([checkpoint_callback, eval_callback, event_callback, callback_max_episodes, log_callback])
    model.learn(300, callback=callback)

    # The callbacks see the rollout's local variables...
    assert model.env.observation_space.contains(callback.locals["new_obs"][0])
    assert checkpoint_callback.locals["new_obs"] is callback.locals["new_obs"]
    assert event_callback.locals["new_obs"] is callback.locals["new_obs"]
    assert checkpoint_on_event.locals["new_obs"] is callback.locals["new_obs"]
    # ... and count as the model does.
    assert event_callback.num_timesteps == model.num_timesteps
    assert event_callback.n_calls == model.num_timesteps
    # They did their work: checkpoints, evaluations, the best model.
    assert eval_callback.n_calls > 0 and len(eval_callback.evaluations_timesteps) > 0
    assert (log_folder / "evaluations.npz").exists()
    assert (log_folder / "best_model.zip").exists()
    assert (log_folder / "rl_model_200_steps.zip").exists()
    assert (log_folder / "event_250_steps.zip").exists()
    # A checkpoint is a model TD3X loads.
    checkpoint = model_class.load(log_folder / "rl_model_200_steps.zip", env=model.get_env())
    assert checkpoint.num_timesteps == 200

    model.learn(100, callback=None)
    # A list becomes a CallbackList.
    model.learn(100, callback=[checkpoint_callback, eval_callback])
    # A function of (locals, globals), the old way.
    model.learn(100, callback=lambda _locals, _globals: True)


@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_stop_training_callbacks(model_class):
    """The callbacks of test_callbacks that stop training, each made to trigger at a known step."""
    # No gradient steps: this is about when training stops.
    kwargs = dict(policy_kwargs=dict(net_arch=[32]), learning_starts=1_000, buffer_size=1_000)
    model = model_class("MlpPolicy", "Pendulum-v1", **kwargs)
    on_best = StopTrainingOnRewardThreshold(reward_threshold=-1e6)
    eval_callback = EvalCallback(
        gym.make("Pendulum-v1"), callback_on_new_best=on_best, eval_freq=100, n_eval_episodes=1, warn=False
    )
    model.learn(1_000, callback=eval_callback)
    assert model.num_timesteps == 100

    # Always the same return: the first evaluation sets the best, the second does not improve on it.
    eval_env = gym.wrappers.TransformReward(gym.make("Pendulum-v1"), lambda _: 0.0)
    no_improvement = StopTrainingOnNoModelImprovement(max_no_improvement_evals=0, min_evals=0)
    eval_callback = EvalCallback(
        eval_env, callback_after_eval=no_improvement, eval_freq=100, n_eval_episodes=1, warn=False
    )
    model.learn(1_000, callback=eval_callback)
    assert model.num_timesteps == 200


@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_stop_on_max_episodes_multi_env(model_class):
    """The StopTrainingOnMaxEpisodes check that SB3 runs with several envs, for A2C/PPO."""
    n_envs, max_episodes, max_episode_length = 2, 1, 200  # Pendulum-v1 episodes last 200 steps
    envs = make_vec_env("Pendulum-v1", n_envs=n_envs, seed=0)
    # No gradient steps: this is about counting episodes.
    model = model_class("MlpPolicy", envs, policy_kwargs=dict(net_arch=[32]), learning_starts=1_000, buffer_size=1_000)
    callback_max_episodes = StopTrainingOnMaxEpisodes(max_episodes=max_episodes, verbose=1)
    model.learn(1_000, callback=CallbackList([callback_max_episodes]))
    assert callback_max_episodes.n_episodes // n_envs == max_episodes
    assert model.num_timesteps // n_envs == max_episode_length


# mirrors SB3 tests/test_callbacks.py::test_eval_callback_vec_env (SB3 runs it with A2C on IdentityEnv)
def test_eval_callback_vec_env():
    n_eval_envs = 3
    eval_env = DummyVecEnv([lambda: IdentityEnvBox(ep_length=20)] * n_eval_envs)
    model = TD3X("MlpPolicy", IdentityEnvBox(ep_length=20), seed=0, **TINY)
    eval_callback = EvalCallback(eval_env, eval_freq=100, n_eval_episodes=3, warn=False)
    model.learn(200, callback=eval_callback)
    assert eval_callback.n_calls == model.num_timesteps
    assert np.isfinite(eval_callback.last_mean_reward)
    # IdentityEnvBox pays at most 1 per step: 20 steps per episode.
    assert -20.0 <= eval_callback.last_mean_reward <= 20.0


# mirrors SB3 tests/test_callbacks.py::test_eval_success_logging (SB3 runs it with DQN)
def test_eval_success_logging(tmp_path):
    n_bits, n_envs = 2, 2
    eval_env = DummyVecEnv([lambda: BitFlippingEnv(n_bits=n_bits, continuous=True)] * n_envs)
    eval_callback = EvalCallback(eval_env, eval_freq=100, log_path=tmp_path, warn=False)
    model = TD3X(
        "MultiInputPolicy",
        BitFlippingEnv(n_bits=n_bits, continuous=True),
        replay_buffer_class=HerReplayBuffer,
        seed=0,
        **TINY,
    )
    model.learn(300, callback=eval_callback)
    # The env's is_success info is collected and saved (SB3 also checks > 50% success: a learning check for DQN).
    assert len(eval_callback._is_success_buffer) > 0
    assert "successes" in np.load(tmp_path / "evaluations.npz")


# mirrors SB3 tests/test_callbacks.py::test_checkpoint_additional_info (SB3 runs it with DQN)
def test_checkpoint_additional_info(tmp_path):
    log_folder = tmp_path / "logs"
    env = VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")]))
    model = TD3X("MlpPolicy", env, **TINY)
    checkpoint_callback = CheckpointCallback(
        save_freq=200, save_path=log_folder, verbose=2, save_replay_buffer=True, save_vecnormalize=True
    )
    model.learn(200, callback=checkpoint_callback)

    assert (log_folder / "rl_model_200_steps.zip").exists()
    assert (log_folder / "rl_model_replay_buffer_200_steps.pkl").exists()
    assert (log_folder / "rl_model_vecnormalize_200_steps.pkl").exists()
    # Everything loads back, and training resumes from it.
    env = VecNormalize.load(log_folder / "rl_model_vecnormalize_200_steps.pkl", DummyVecEnv([lambda: gym.make("Pendulum-v1")]))
    model = TD3X.load(log_folder / "rl_model_200_steps.zip", env=env)
    model.load_replay_buffer(log_folder / "rl_model_replay_buffer_200_steps.pkl")
    # Callbacks run before the step's transition is stored (SB3's order): 199 transitions at step 200.
    assert model.replay_buffer.size() == 199
    model.learn(100, reset_num_timesteps=False)
    assert model.num_timesteps == 300
