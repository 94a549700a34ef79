"""TensorReplayBuffer stores and returns exactly what SB3's ReplayBuffer does, as tensors."""


import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_td3x import TD3X
from sb3_td3x.common.buffers import TensorReplayBuffer

OBS = gym.spaces.Box(-5, 5, (4,), dtype=np.float64)
ACT = gym.spaces.Box(-1, 1, (2,), dtype=np.float32)


def fill(buffers, n_steps: int, n_envs: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    for t in range(n_steps):
        obs = rng.normal(size=(n_envs, 4))
        next_obs = rng.normal(size=(n_envs, 4))
        action = rng.uniform(-1, 1, size=(n_envs, 2)).astype(np.float32)
        reward = rng.normal(size=n_envs).astype(np.float32)
        done = rng.uniform(size=n_envs) < 0.1
        infos = [{"TimeLimit.truncated": bool(d and rng.uniform() < 0.5)} for d in done]
        for b in buffers:
            b.add(obs, next_obs, action, reward, done, infos)


@pytest.mark.parametrize("n_envs", [1, 3])
@pytest.mark.parametrize("optimize_memory_usage", [False, True])
def test_same_samples_as_sb3_for_same_indices(n_envs, optimize_memory_usage):
    kwargs = dict(n_envs=n_envs, optimize_memory_usage=optimize_memory_usage,
                  handle_timeout_termination=not optimize_memory_usage)
    ref = ReplayBuffer(60, OBS, ACT, device="cpu", **kwargs)
    buf = TensorReplayBuffer(60, OBS, ACT, device="cpu", **kwargs)
    fill([ref, buf], n_steps=35, n_envs=n_envs)  # wraps around: 60 // 3 = 20 slots per env
    assert (ref.pos, ref.full) == (buf.pos, buf.full)
    inds = np.arange(1, ref.size()) if optimize_memory_usage else np.arange(ref.size())
    np.random.seed(0)
    expected = ref._get_samples(inds)
    th.manual_seed(0)
    env_inds = th.randint(0, n_envs, (len(inds),)) if n_envs > 1 else None
    # Use the same env indices as the reference: SB3 draws them with numpy.
    np.random.seed(0)
    np_env_inds = np.random.randint(0, high=n_envs, size=(len(inds),))
    got_obs = buf.observations[inds, np_env_inds]
    th.testing.assert_close(got_obs, expected.observations.float())
    th.testing.assert_close(buf.actions[inds, np_env_inds], expected.actions)
    if optimize_memory_usage:
        th.testing.assert_close(buf.observations[(inds + 1) % buf.buffer_size, np_env_inds], expected.next_observations.float())
    else:
        th.testing.assert_close(buf.next_observations[inds, np_env_inds], expected.next_observations.float())
    # And through _get_samples (dones with timeouts masked, rewards as a column)
    got = buf._get_samples(th.as_tensor(inds))
    assert got.observations.shape == expected.observations.shape
    assert got.dones.shape == expected.dones.shape == (len(inds), 1)
    assert got.rewards.shape == expected.rewards.shape
    del env_inds


def test_sample_shapes_dtypes_and_validity():
    buf = TensorReplayBuffer(100, OBS, ACT, device="cpu")
    fill([buf], n_steps=10, n_envs=1)
    batch = buf.sample(64)
    assert batch.observations.shape == (64, 4) and batch.observations.dtype == th.float32
    assert batch.actions.shape == (64, 2) and batch.rewards.shape == (64, 1) and batch.dones.shape == (64, 1)
    # Only the 10 filled slots are sampled: every sampled observation is one that was added.
    added = buf.observations[:10, 0]
    assert all(any(th.equal(o, a) for a in added) for o in batch.observations)


def test_timeouts_are_not_terminal():
    buf = TensorReplayBuffer(10, OBS, ACT, device="cpu")
    obs = np.zeros((1, 4))
    buf.add(obs, obs, np.zeros((1, 2)), np.zeros(1), np.array([True]), [{"TimeLimit.truncated": True}])
    buf.add(obs, obs, np.zeros((1, 2)), np.zeros(1), np.array([True]), [{"TimeLimit.truncated": False}])
    samples = buf._get_samples(th.tensor([0, 1]))
    assert samples.dones.flatten().tolist() == [0.0, 1.0]


def test_uint8_images_stay_uint8_and_float64_becomes_float32():
    image = gym.spaces.Box(0, 255, (3, 8, 8), dtype=np.uint8)
    assert TensorReplayBuffer(10, image, ACT).observations.dtype == th.uint8
    assert TensorReplayBuffer(10, OBS, ACT).observations.dtype == th.float32


def test_memory_is_half_of_sb3_for_float64_observations():
    ref = ReplayBuffer(1000, OBS, ACT, device="cpu")
    buf = TensorReplayBuffer(1000, OBS, ACT, device="cpu")
    ref_bytes = sum(a.nbytes for a in (ref.observations, ref.next_observations, ref.actions, ref.rewards, ref.dones, ref.timeouts))
    assert buf.nbytes() < ref_bytes
    obs_bytes = buf.observations.numel() * buf.observations.element_size()
    assert obs_bytes * 2 == ref.observations.nbytes
    small = TensorReplayBuffer(1000, OBS, ACT, device="cpu", optimize_memory_usage=True, handle_timeout_termination=False)
    assert small.next_observations is None and small.nbytes() < 0.7 * buf.nbytes()


def test_optimize_memory_usage_needs_timeouts_off():
    with pytest.raises(ValueError, match="handle_timeout_termination"):
        TensorReplayBuffer(10, OBS, ACT, optimize_memory_usage=True)


def test_pickle_round_trip_and_device_setter():
    buf = TensorReplayBuffer(50, OBS, ACT, device="cpu")
    fill([buf], n_steps=20, n_envs=1)
    import pickle

    clone = pickle.loads(pickle.dumps(buf))
    assert clone.pos == buf.pos and th.equal(clone.observations, buf.observations)
    clone.device = "cpu"
    assert clone.sample(8).observations.device.type == "cpu"


def test_td3x_uses_it_by_default_and_save_load_replay_buffer(tmp_path):
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=50, policy_kwargs=dict(net_arch=[16]), seed=0)
    assert isinstance(model.replay_buffer, TensorReplayBuffer)
    model.learn(120)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    other = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[16]), seed=1)
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    assert isinstance(other.replay_buffer, TensorReplayBuffer)
    assert other.replay_buffer.pos == model.replay_buffer.pos == 120
    th.testing.assert_close(other.replay_buffer.observations, model.replay_buffer.observations)


def test_td3x_learn_with_optimize_memory_usage():
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=50, optimize_memory_usage=True,
                 replay_buffer_kwargs=dict(handle_timeout_termination=False), policy_kwargs=dict(net_arch=[16]), seed=0)
    assert model.replay_buffer.next_observations is None
    model.learn(150)


@pytest.mark.parametrize("n_steps", [30, 57])  # partly filled, and wrapped around (full)
@pytest.mark.parametrize("n_envs,optimize_memory_usage", [(1, False), (2, False), (1, True)])
def test_seeded_sample_equals_sb3_sample(n_envs, optimize_memory_usage, n_steps):
    kwargs = dict(n_envs=n_envs, optimize_memory_usage=optimize_memory_usage,
                  handle_timeout_termination=not optimize_memory_usage)
    ref = ReplayBuffer(40, OBS, ACT, device="cpu", **kwargs)
    buf = TensorReplayBuffer(40, OBS, ACT, device="cpu", **kwargs)
    fill([ref, buf], n_steps=n_steps, n_envs=n_envs)
    assert ref.full == buf.full == (n_steps * n_envs >= 40)
    np.random.seed(5)
    expected = ref.sample(16)
    np.random.seed(5)
    got = buf.sample(16)
    for name in ("observations", "actions", "next_observations", "dones", "rewards"):
        th.testing.assert_close(getattr(got, name), getattr(expected, name).float(), msg=name)


def test_static_sampling_state_is_not_pickled():
    """Static bounds belong to the process's graphs: a pickled buffer loads back to ordinary sampling."""
    import pickle

    buf = TensorReplayBuffer(50, OBS, ACT, device="cpu")
    fill([buf], n_steps=20, n_envs=1)
    buf.enable_static_sampling()
    clone = pickle.loads(pickle.dumps(buf))
    assert buf.static_sampling and not clone.static_sampling
    np.random.seed(0)
    assert clone.sample(8).observations.shape == (8, 4)
