"""Drop-in: short training runs, the scenarios SB3 runs for ``TD3`` and ``DDPG``, with ``TD3X`` and our ``DDPG``.

Mirrors SB3's ``tests/test_run.py`` (action noise, ``train_freq``, multiple envs, ``gradient_steps=-1``,
``n_critics``), ``tests/test_n_step_replay.py::test_run`` (``n_steps > 1``), ``tests/test_custom_policy.py``
(``net_arch`` variants, custom optimizer) and ``tests/test_spaces.py`` (observation and action spaces, float64).
"""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise, VectorizedActionNoise

from conftest import DummyEnv
from sb3_td3x import DDPG, TD3X
from sb3_td3x.common.buffers import TensorReplayBuffer

TINY = dict(policy_kwargs=dict(net_arch=[64, 64]), learning_starts=100, batch_size=64)
BOX_FLOAT32 = spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float32)
BOX_FLOAT64 = spaces.Box(low=-1, high=1, shape=(2,), dtype=np.float64)


# mirrors SB3 tests/test_run.py::test_deterministic_pg
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize("noise_class", [NormalActionNoise, OrnsteinUhlenbeckActionNoise])
def test_deterministic_pg(model_class, noise_class):
    action_noise = noise_class(np.zeros(1), 0.1 * np.ones(1))
    model = model_class(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[64, 64]),
        learning_starts=100,
        buffer_size=250,
        batch_size=64,
        action_noise=action_noise,
    )
    model.learn(total_timesteps=200)

    assert model.num_timesteps == 200
    assert model.action_noise is action_noise
    # One gradient step per env step once num_timesteps > learning_starts; the actor every policy_delay steps.
    assert model._n_updates == 100
    assert model._n_actor_updates == 100 // model.policy_delay


# mirrors SB3 tests/test_run.py::test_n_critics ("for TD3, n_critics=1 corresponds to DDPG")
@pytest.mark.parametrize("n_critics", [1, 3])
def test_n_critics(n_critics):
    model = TD3X(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[64, 64], n_critics=n_critics),
        learning_starts=100,
        buffer_size=10_000,
        batch_size=64,
    )
    model.learn(total_timesteps=150)
    assert len(model.critic.q_networks) == n_critics
    assert len(model.critic_target.q_networks) == n_critics


# mirrors SB3 tests/test_run.py::test_train_freq (SB3 runs it with SAC; the code path is OffPolicyAlgorithm's)
@pytest.mark.parametrize("train_freq", [4, (4, "step"), (1, "episode")])
def test_train_freq(tmp_path, train_freq):
    kwargs = dict(policy_kwargs=dict(net_arch=[64, 64]), learning_starts=100, buffer_size=10_000, batch_size=64)
    model = TD3X("MlpPolicy", "Pendulum-v1", train_freq=train_freq, **kwargs)
    model.learn(total_timesteps=150)
    model.save(tmp_path / "test_save.zip")
    env = model.get_env()

    model = TD3X.load(tmp_path / "test_save.zip", env=env)
    model.learn(total_timesteps=150)
    model = TD3X.load(tmp_path / "test_save.zip", train_freq=train_freq, env=env)
    model.learn(total_timesteps=150)
    # Rollouts are whole multiples of train_freq, so learn() may overshoot by less than one rollout.
    assert model.num_timesteps >= 150
    assert model._n_updates > 0


# mirrors SB3 tests/test_run.py::test_train_freq_fail
@pytest.mark.parametrize("train_freq", ["4", ("1", "episode"), "non_sense", (1, "close")])
def test_train_freq_fail(train_freq):
    with pytest.raises(ValueError):
        TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[64, 64]), train_freq=train_freq).learn(250)


# mirrors SB3 tests/test_run.py::test_offpolicy_multi_env
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_offpolicy_multi_env(model_class):
    def make_env():
        # The short time limit makes the timeout-handling code run.
        return gym.wrappers.TimeLimit(gym.make("Pendulum-v1"), 50)

    env = make_vec_env(make_env, n_envs=2)
    kwargs = dict(
        policy_kwargs=dict(net_arch=[64], n_critics=1),
        buffer_size=10_000,
        batch_size=64,
        action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
    )
    model = model_class("MlpPolicy", env, learning_starts=100, train_freq=5, **kwargs)
    model.learn(total_timesteps=150)
    # learn() vectorizes a single-env action noise.
    assert isinstance(model.action_noise, VectorizedActionNoise)
    assert model.num_timesteps >= 150

    # gradient_steps=-1: as many gradient steps as transitions collected.
    train_freq = 3
    model = model_class("MlpPolicy", env, learning_starts=0, train_freq=train_freq, gradient_steps=-1, **kwargs)
    model.learn(total_timesteps=train_freq)
    assert model.logger.name_to_value["train/n_updates"] == train_freq * env.num_envs


# mirrors SB3 tests/test_n_step_replay.py::test_run
def test_n_step_returns():
    gamma = 0.989
    model = TD3X(
        "MlpPolicy",
        make_vec_env("Pendulum-v1", n_envs=2),
        train_freq=4,
        n_steps=3,
        policy_kwargs=dict(net_arch=[64]),
        learning_starts=100,
        buffer_size=20_000,
        batch_size=64,
        gamma=gamma,
    )
    # TD3X's tensor buffer computes NStepReplayBuffer's returns (tests/equivalence/test_n_step_returns.py), with its
    # n_steps and gamma attributes.
    assert isinstance(model.replay_buffer, TensorReplayBuffer)
    assert model.replay_buffer.n_steps == 3
    assert model.replay_buffer.gamma == gamma
    model.learn(total_timesteps=150)
    batch = model.replay_buffer.sample(16)
    # The n-step buffer gives each transition its own discount, gamma ** k with k <= n_steps.
    assert batch.discounts is not None
    assert th.all(batch.discounts <= gamma + 1e-6) and th.all(batch.discounts >= gamma**3 - 1e-6)


# mirrors SB3 tests/test_save_load.py::test_warn_buffer and tests/test_buffer_optimization.py (memory mode), training
def test_optimize_memory_usage():
    model = TD3X(
        "MlpPolicy",
        "Pendulum-v1",
        optimize_memory_usage=True,
        # The memory-efficient buffer cannot handle timeouts.
        replay_buffer_kwargs=dict(handle_timeout_termination=False),
        buffer_size=150,
        **TINY,
    )
    model.learn(total_timesteps=200)
    buffer = model.replay_buffer
    assert buffer.optimize_memory_usage
    # Next observations are read from the following row: no array of their own.
    assert getattr(buffer, "next_observations", None) is None
    assert buffer.full and model._n_updates == 100


# mirrors SB3 tests/test_custom_policy.py::test_custom_offpolicy
@pytest.mark.parametrize("net_arch", [[], [4], [4, 4], dict(qf=[8], pi=[8, 4])])
def test_custom_offpolicy(net_arch):
    model = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=net_arch), learning_starts=100, batch_size=64)
    model.learn(150)
    pi_arch = net_arch["pi"] if isinstance(net_arch, dict) else net_arch
    qf_arch = net_arch["qf"] if isinstance(net_arch, dict) else net_arch
    actor_linears = [m for m in model.actor.mu if isinstance(m, th.nn.Linear)]
    critic_linears = [m for m in model.critic.q_networks[0] if isinstance(m, th.nn.Linear)]
    assert [m.out_features for m in actor_linears] == [*pi_arch, 1]
    assert [m.out_features for m in critic_linears] == [*qf_arch, 1]


# mirrors SB3 tests/test_custom_policy.py::test_custom_optimizer
@pytest.mark.parametrize("optimizer_kwargs", [None, dict(weight_decay=0.0)])
def test_custom_optimizer(optimizer_kwargs):
    policy_kwargs = dict(optimizer_class=th.optim.AdamW, optimizer_kwargs=optimizer_kwargs, net_arch=[32])
    model = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs, learning_starts=100, batch_size=64)
    model.learn(150)
    assert isinstance(model.actor.optimizer, th.optim.AdamW)
    assert isinstance(model.critic.optimizer, th.optim.AdamW)


# mirrors SB3 tests/test_spaces.py::test_identity_spaces
@pytest.mark.parametrize(
    "observation_space", [spaces.MultiDiscrete([4, 3]), spaces.MultiBinary(8), spaces.MultiBinary((3, 2))]
)
def test_identity_spaces(observation_space):
    env = gym.wrappers.TimeLimit(DummyEnv(observation_space, BOX_FLOAT32), max_episode_steps=100)
    model = TD3X("MlpPolicy", env, gamma=0.5, seed=1, policy_kwargs=dict(net_arch=[64]), batch_size=64)
    model.learn(total_timesteps=200)
    evaluate_policy(model, env, n_eval_episodes=2, warn=False)


# mirrors SB3 tests/test_spaces.py::test_action_spaces
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_action_spaces(model_class):
    model_class("MlpPolicy", "Pendulum-v1", learning_starts=2, train_freq=32)
    # Multi-dimensional Box actions.
    env = gym.wrappers.TimeLimit(DummyEnv(BOX_FLOAT32, spaces.Box(-1, 1, shape=(2, 2), dtype=np.float32)), 100)
    model = model_class("MlpPolicy", env, learning_starts=2, train_freq=32, batch_size=16)
    model.learn(64)
    action, _ = model.predict(env.reset()[0])
    assert action.shape == (2, 2)
    # Departure from SB3, on purpose: unsupported action spaces raise ValueError where SB3 raises AssertionError.
    with pytest.raises(ValueError, match="continuous action space"):
        model_class("MlpPolicy", "CartPole-v1")


# mirrors SB3 tests/test_spaces.py::test_float64_action_space
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize(
    "observation_space",
    [
        BOX_FLOAT32,
        BOX_FLOAT64,
        spaces.Dict({"a": BOX_FLOAT32, "b": BOX_FLOAT32}),
        spaces.Dict({"a": BOX_FLOAT32, "b": BOX_FLOAT64}),
    ],
)
@pytest.mark.parametrize("action_space", [BOX_FLOAT32, BOX_FLOAT64])
def test_float64_action_space(model_class, observation_space, action_space):
    env = gym.wrappers.TimeLimit(DummyEnv(observation_space, action_space), max_episode_steps=200)
    policy = "MultiInputPolicy" if isinstance(observation_space, spaces.Dict) else "MlpPolicy"
    model = model_class(policy, env, learning_starts=60, batch_size=16, policy_kwargs=dict(net_arch=[12]))
    model.learn(64)
    initial_obs, _ = env.reset()
    action, _ = model.predict(initial_obs, deterministic=False)
    assert action.dtype == env.action_space.dtype
