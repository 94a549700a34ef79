"""Drop-in: saving and loading ``TD3X`` and ``DDPG`` models, policies, actors and replay buffers.

Mirrors SB3's ``tests/test_save_load.py`` (``test_save_load``, ``test_set_env``, ``test_exclude_include_saved_params``,
``test_save_load_env_cnn``, ``test_save_load_replay_buffer``, ``test_warn_buffer``, ``test_save_load_policy``,
``test_no_resource_warning``, ``test_cast_lr_schedule``), plus a TD3X round trip: the TD3X switches survive
``save``/``load`` and the loaded model evaluates exactly as the saved one.
"""

import pathlib
import tempfile
from collections import OrderedDict
from copy import deepcopy

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.envs import FakeImageEnv, IdentityEnvBox
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_td3x import DDPG, TD3X

def identity_env() -> IdentityEnvBox:
    return IdentityEnvBox(-10, 10)


def to_numpy(x) -> np.ndarray:
    return x.cpu().numpy() if isinstance(x, th.Tensor) else np.asarray(x)


def sample_observations(env: DummyVecEnv, n: int = 10) -> np.ndarray:
    env.reset()
    return np.concatenate([env.step([env.action_space.sample()])[0] for _ in range(n)], axis=0)


# mirrors SB3 tests/test_save_load.py::test_save_load
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_save_load(tmp_path, model_class):
    env = DummyVecEnv([identity_env])
    model = model_class("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), learning_starts=100, batch_size=64)
    model.learn(total_timesteps=200)
    observations = sample_observations(env)
    original_params = deepcopy(model.get_parameters())
    assert set(original_params) == {"policy", "actor.optimizer", "critic.optimizer"}

    # set_parameters rejects unknown objects, with or without exact_match.
    invalid = deepcopy(original_params)
    invalid["I_should_not_be_a_valid_object"] = "and_I_am_an_invalid_tensor"
    with pytest.raises(ValueError):
        model.set_parameters(invalid, exact_match=True)
    with pytest.raises(ValueError):
        model.set_parameters(invalid, exact_match=False)
    # exact_match catches a missing object...
    with pytest.raises(ValueError):
        model.set_parameters(dict(list(original_params.items())[:-1]), exact_match=True)
    # ... and a missing tensor inside a state dict (torch's strict load_state_dict).
    truncated = {name: OrderedDict(list(params.items())[:-1]) for name, params in original_params.items()}
    with pytest.raises(RuntimeError):
        model.set_parameters(truncated, exact_match=True)

    # Random values for every tensor but the last of each state dict (optimizers left as they are).
    random_params = {
        name: params if "optim" in name else OrderedDict((k, th.rand_like(v)) for k, v in list(params.items())[:-1])
        for name, params in original_params.items()
    }
    model.set_parameters(random_params, exact_match=False)
    params = model.get_parameters()
    for name in original_params:
        if "optim" in name:
            continue
        last_key = list(original_params[name])[-1]
        for key in original_params[name]:
            changed = not th.allclose(original_params[name][key], params[name][key])
            assert changed == (key != last_key), f"{name}/{key}"

    selected_actions, _ = model.predict(observations, deterministic=True)
    model.save(tmp_path / "test_save.zip")
    del model

    for device in ["auto", "cpu", "cuda"] if th.cuda.is_available() else ["auto", "cpu"]:
        model = model_class.load(str(tmp_path / "test_save.zip"), env=env, device=device)
        assert model.device.type == get_device(device).type
        assert model.policy.device.type == get_device(device).type
        new_params = model.get_parameters()
        for name in new_params:
            if "optim" in name:
                continue
            for key in params[name]:
                assert new_params[name][key].device.type == get_device(device).type
                assert th.equal(params[name][key].cpu(), new_params[name][key].cpu()), f"{name}/{key} changed on load"
        new_selected_actions, _ = model.predict(observations, deterministic=True)
        np.testing.assert_allclose(selected_actions, new_selected_actions, atol=1e-4)
        # Learning goes on after a load.
        model.learn(total_timesteps=120)


# mirrors SB3 tests/test_save_load.py::test_set_env
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_set_env(tmp_path, model_class):
    env = DummyVecEnv([identity_env])
    env2 = DummyVecEnv([identity_env])
    env3 = identity_env()
    env4 = DummyVecEnv([identity_env for _ in range(2)])

    model = model_class("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), learning_starts=50, train_freq=4, batch_size=32)
    model.learn(total_timesteps=64)

    model.set_env(env2, force_reset=True)
    assert model._last_obs is None
    model.learn(total_timesteps=64, reset_num_timesteps=True)
    assert model.num_timesteps == 64

    # A plain gym env is wrapped.
    model.set_env(env3)
    model.learn(total_timesteps=64)

    # The number of envs must match.
    with pytest.raises(AssertionError):
        model.set_env(env4)

    model.set_env(model.get_env(), force_reset=False)
    assert model._last_obs is not None
    model.learn(total_timesteps=64, reset_num_timesteps=False)
    assert model.num_timesteps == 2 * 64

    current_env = model.get_env()
    model.save(tmp_path / "test_save.zip")
    del model
    # Same env, not reset: the timestep count goes on.
    model = model_class.load(tmp_path / "test_save.zip", env=current_env, force_reset=False)
    assert model._last_obs is not None
    model.learn(total_timesteps=64, reset_num_timesteps=False)
    assert model.num_timesteps == 3 * 64

    # Another env: reset, but the timestep count is kept.
    model = model_class.load(tmp_path / "test_save.zip", env=env3, force_reset=True)
    assert model._last_obs is None
    model.learn(total_timesteps=64, reset_num_timesteps=False)
    assert model.num_timesteps == 3 * 64

    # Loading with a different number of envs is allowed.
    model = model_class.load(tmp_path / "test_save.zip", env=env4)
    model.learn(total_timesteps=64)
    assert model.n_envs == 2


# mirrors SB3 tests/test_save_load.py::test_exclude_include_saved_params
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
def test_exclude_include_saved_params(tmp_path, model_class):
    env = DummyVecEnv([identity_env])
    model = model_class("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), verbose=2)

    model.save(tmp_path / "test_save", exclude=["verbose"])
    model = model_class.load(str(tmp_path / "test_save.zip"))
    assert model.verbose != 2

    model.verbose = 2
    # include wins over exclude.
    model.save(tmp_path / "test_save", exclude=["verbose"], include=["verbose"])
    custom_objects = dict(learning_rate=2e-5, dummy=1.0)
    model = model_class.load(str(tmp_path / "test_save.zip"), custom_objects=custom_objects, print_system_info=True)
    assert model.verbose == 2
    assert model.learning_rate == custom_objects["learning_rate"]
    # Only attributes the model already has are replaced.
    assert not hasattr(model, "dummy")
    # The schedules are rebuilt from the custom learning rate (critic_learning_rate is None: the critics follow it).
    assert model.lr_schedule(1.0) == pytest.approx(2e-5)
    assert model.critic_lr_schedule(1.0) == pytest.approx(2e-5)


# mirrors SB3 tests/test_save_load.py::test_save_load_env_cnn
def test_save_load_env_cnn(tmp_path):
    env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=False)
    kwargs = dict(
        policy_kwargs=dict(net_arch=[32], features_extractor_kwargs=dict(features_dim=32)),
        buffer_size=100,
        learning_starts=50,
        train_freq=4,
        batch_size=32,
    )
    model = TD3X("CnnPolicy", env, **kwargs).learn(100)
    model.save(tmp_path / "test_save")
    # Loading with an image env (wrapped in VecTransposeImage again) and training on.
    model = TD3X.load(str(tmp_path / "test_save.zip"), env=env, **kwargs).learn(100)
    assert model.num_timesteps == 100


# mirrors SB3 tests/test_save_load.py::test_save_load_replay_buffer
def test_save_load_replay_buffer(tmp_path):
    path = pathlib.Path(tmp_path / "logs/replay_buffer.pkl")
    path.parent.mkdir(exist_ok=True, parents=True)
    model = TD3X("MlpPolicy", identity_env(), buffer_size=1000, policy_kwargs=dict(net_arch=[64]), learning_starts=200)
    model.learn(300)
    old_replay_buffer = deepcopy(model.replay_buffer)
    model.save_replay_buffer(path)
    model.replay_buffer = None
    for device in ["cpu", "cuda"] if th.cuda.is_available() else ["cpu"]:
        # Force the device, to check that the loaded buffer follows it.
        model.device = th.device(device)
        model.load_replay_buffer(path)
        assert model.replay_buffer.device.type == model.device.type

    # The buffer may keep its data as numpy arrays (SB3) or as tensors: compare, and feed back, numpy arrays.
    names = ("observations", "actions", "rewards", "dones", "timeouts")
    old = {name: to_numpy(getattr(old_replay_buffer, name)) for name in names}
    for name, value in old.items():
        np.testing.assert_array_equal(value, to_numpy(getattr(model.replay_buffer, name)), err_msg=name)
    assert model.replay_buffer.size() == old_replay_buffer.size() == 300

    # extend() takes SB3's add() arguments, one row per env step.
    infos = [[{"TimeLimit.truncated": truncated}] for truncated in old["timeouts"]]
    model.replay_buffer.extend(old["observations"], old["observations"], old["actions"], old["rewards"], old["dones"], infos)
    # And the loaded buffer trains the model.
    model.train(gradient_steps=2, batch_size=32)


# mirrors SB3 tests/test_save_load.py::test_warn_buffer
@pytest.mark.parametrize("optimize_memory_usage", [False, True])
def test_warn_buffer(recwarn, optimize_memory_usage):
    model = TD3X(
        "MlpPolicy",
        identity_env(),
        buffer_size=100,
        optimize_memory_usage=optimize_memory_usage,
        # The memory-efficient buffer cannot handle timeouts.
        replay_buffer_kwargs={"handle_timeout_termination": not optimize_memory_usage},
        policy_kwargs=dict(net_arch=[64]),
        # The warning is about the buffer: gradient steps would only cost time.
        learning_starts=1_000,
    )
    assert model.replay_buffer.optimize_memory_usage == optimize_memory_usage
    model.learn(150)
    model.learn(150, reset_num_timesteps=False)
    assert len(recwarn) == 0

    model.learn(150)
    if optimize_memory_usage:
        assert len(recwarn) == 1
        warning = recwarn.pop(UserWarning)
        assert "The last trajectory in the replay buffer will be truncated" in str(warning.message)
    else:
        assert len(recwarn) == 0


# mirrors SB3 tests/test_save_load.py::test_save_load_policy
@pytest.mark.parametrize("model_class", [TD3X, DDPG])
@pytest.mark.parametrize("policy_str", ["MlpPolicy", "CnnPolicy"])
def test_save_load_policy(tmp_path, model_class, policy_str):
    if policy_str == "MlpPolicy":
        env = identity_env()
        kwargs = dict(policy_kwargs=dict(net_arch=[16]), learning_starts=100, batch_size=64)
    else:
        env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=False)
        kwargs = dict(
            buffer_size=250,
            learning_starts=100,
            batch_size=32,
            policy_kwargs=dict(features_extractor_kwargs=dict(features_dim=32)),
        )
    env = DummyVecEnv([lambda: env])
    model = model_class(policy_str, env, **kwargs)
    model.learn(total_timesteps=120)
    observations = sample_observations(env)

    policy, actor = model.policy, model.policy.actor
    policy_class, actor_class = type(policy), type(actor)
    params = deepcopy(policy.state_dict())
    policy.load_state_dict({name: th.rand_like(param) for name, param in params.items()})
    new_params = policy.state_dict()
    for key in params:
        assert not th.allclose(params[key], new_params[key]), key
    params = deepcopy(new_params)

    selected_actions, _ = policy.predict(observations, deterministic=True)
    selected_actions_actor, _ = actor.predict(observations, deterministic=True)
    policy.save(tmp_path / "policy.pkl")
    actor.save(tmp_path / "actor.pkl")
    del policy, actor

    policy = policy_class.load(tmp_path / "policy.pkl")
    actor = actor_class.load(tmp_path / "actor.pkl")
    assert type(policy) is policy_class
    for key, value in policy.state_dict().items():
        assert th.equal(params[key], value), key
    new_selected_actions, _ = policy.predict(observations, deterministic=True)
    new_selected_actions_actor, _ = actor.predict(observations, deterministic=True)
    np.testing.assert_allclose(selected_actions, new_selected_actions, atol=1e-4)
    np.testing.assert_allclose(selected_actions_actor, new_selected_actions_actor, atol=1e-4)
    np.testing.assert_allclose(selected_actions_actor, new_selected_actions, atol=1e-4)


# mirrors SB3 tests/test_save_load.py::test_no_resource_warning (the replay buffer part; SB3 uses SAC)
@pytest.mark.filterwarnings("error")
def test_no_resource_warning(tmp_path):
    TD3X("MlpPolicy", "Pendulum-v1", buffer_size=200).save(tmp_path / "td3x_pendulum")
    TD3X.load(tmp_path / "td3x_pendulum")
    with tempfile.TemporaryFile() as fp:
        TD3X("MlpPolicy", "Pendulum-v1", buffer_size=200).save(fp)
        fp.seek(0)
        TD3X.load(fp)
        assert not fp.closed

    model = TD3X("MlpPolicy", "Pendulum-v1", buffer_size=200)
    model.save_replay_buffer(tmp_path / "replay")
    model.load_replay_buffer(tmp_path / "replay")
    model.save_replay_buffer(str(tmp_path / "replay"))
    model.load_replay_buffer(str(tmp_path / "replay"))
    with tempfile.TemporaryFile() as fp:
        model.save_replay_buffer(fp)
        fp.seek(0)
        model.load_replay_buffer(fp)
        assert not fp.closed


# mirrors SB3 tests/test_save_load.py::test_cast_lr_schedule, for both of TD3X's schedules
def test_cast_lr_schedule(tmp_path):
    model = TD3X(
        "MlpPolicy",
        "Pendulum-v1",
        buffer_size=200,
        learning_rate=lambda progress: progress * np.sin(1.0),
        critic_learning_rate=lambda progress: progress * np.cos(1.0),
    )
    for _ in range(2):
        assert type(model.lr_schedule(1.0)) is float
        assert np.allclose(model.lr_schedule(0.5), 0.5 * np.sin(1.0))
        assert type(model.critic_lr_schedule(1.0)) is float
        assert np.allclose(model.critic_lr_schedule(0.5), 0.5 * np.cos(1.0))
        model.save(tmp_path / "td3x.zip")
        model = TD3X.load(tmp_path / "td3x.zip")


# Cross-check: TD3X's own arguments survive save/load, and the loaded model evaluates as the saved one did.
def test_td3x_switches_survive_save_load(tmp_path):
    env = gym.make("Pendulum-v1")
    model = TD3X(
        "MlpPolicy",
        env,
        policy_kwargs=dict(net_arch=[64, 64]),
        learning_starts=100,
        batch_size=64,
        critic_learning_rate=3e-4,
        target_policy_smoothing=False,
        clipped_double_q=False,
        policy_delay=3,
        target_policy_noise=0.3,
        target_noise_clip=0.4,
        seed=0,
    )
    model.learn(200)
    model.save(tmp_path / "td3x.zip")
    eval_env = Monitor(gym.make("Pendulum-v1"))
    eval_env.reset(seed=123)
    expected = evaluate_policy(model, eval_env, n_eval_episodes=1, deterministic=True, return_episode_rewards=True)

    loaded = TD3X.load(tmp_path / "td3x.zip", env=env)
    for name in (
        "critic_learning_rate",
        "target_policy_smoothing",
        "clipped_double_q",
        "policy_delay",
        "target_policy_noise",
        "target_noise_clip",
        "_n_actor_updates",
        "_n_updates",
        "num_timesteps",
    ):
        assert getattr(loaded, name) == getattr(model, name), name
    assert loaded.critic.optimizer.param_groups[0]["lr"] == pytest.approx(3e-4)
    assert loaded.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    # The optimizers' state (Adam moments) is restored too.
    saved_state = model.critic.optimizer.state_dict()["state"]
    loaded_state = loaded.critic.optimizer.state_dict()["state"]
    assert saved_state.keys() == loaded_state.keys()
    for key in saved_state:
        assert th.equal(saved_state[key]["exp_avg"], loaded_state[key]["exp_avg"])

    eval_env.reset(seed=123)
    assert evaluate_policy(loaded, eval_env, n_eval_episodes=1, deterministic=True, return_episode_rewards=True) == expected
    loaded.learn(120)
