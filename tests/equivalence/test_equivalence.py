"""From the same weights, batches and noise, TD3X's gradient steps give the parameters SB3's TD3 gives."""

import pytest
import torch as th
from conftest import random_batches
from stable_baselines3 import DDPG as SB3DDPG
from stable_baselines3 import TD3
from stable_baselines3.common.logger import configure
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_td3x import DDPG, TD3X
from sb3_td3x.td3x.policies import copy_sb3_policy_weights

OBS_DIM, ACT_DIM, BATCH = 3, 1, 32


def batches(n: int) -> list[ReplayBufferSamples]:
    return random_batches(n, BATCH, OBS_DIM, ACT_DIM, seed=42)


def run_steps(model, data: list[ReplayBufferSamples], seed: int) -> None:
    model.set_logger(configure(None, []))
    it = iter(data)
    model.replay_buffer.sample = lambda batch_size, env=None: next(it)
    th.manual_seed(seed)  # the target policy smoothing noise
    model.train(gradient_steps=len(data), batch_size=BATCH)


def assert_same_parameters(reference: th.nn.Module, candidate) -> None:
    expected = reference.state_dict()
    got = candidate.sb3_state_dict() if hasattr(candidate, "sb3_state_dict") else candidate.state_dict()
    assert expected.keys() == got.keys()
    for key in expected:
        th.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-6, msg=key)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(policy_delay=2, tau=0.005),
        dict(policy_delay=1, tau=0.1, gamma=0.9),
        dict(policy_delay=3, target_policy_noise=0.5, target_noise_clip=0.2),
        dict(policy_delay=2, policy_kwargs=dict(net_arch=[32, 32], n_critics=3)),
    ],
)
def test_td3x_gradient_steps_equal_sb3_td3(kwargs):
    kwargs = dict(policy_kwargs=dict(net_arch=[32, 32]), learning_starts=0, seed=0) | kwargs
    sb3 = TD3("MlpPolicy", "Pendulum-v1", **kwargs)
    td3x = TD3X("MlpPolicy", "Pendulum-v1", **kwargs)
    copy_sb3_policy_weights(sb3.policy, td3x.policy)
    assert_same_parameters(sb3.policy, td3x.policy)

    data = batches(6)
    run_steps(sb3, data, seed=7)
    run_steps(td3x, data, seed=7)
    assert_same_parameters(sb3.policy, td3x.policy)
    # The optimizers moved the same way too (Adam's moments).
    for opt_name in ("actor", "critic"):
        ref = getattr(sb3, opt_name).optimizer.state_dict()["state"]
        got = getattr(td3x, opt_name).optimizer.state_dict()["state"]
        assert len(ref) == len(got)


def test_ddpg_preset_equals_sb3_ddpg():
    """SB3's DDPG is TD3 with target_policy_noise=0.1, target_noise_clip=0.0 (zero noise); ours switches it off."""
    kwargs = dict(policy_kwargs=dict(net_arch=[32, 32]), learning_starts=0, seed=0)
    sb3 = SB3DDPG("MlpPolicy", "Pendulum-v1", **kwargs)
    ddpg = DDPG("MlpPolicy", "Pendulum-v1", **kwargs)
    copy_sb3_policy_weights(sb3.policy, ddpg.policy)
    data = batches(4)
    run_steps(sb3, data, seed=1)
    run_steps(ddpg, data, seed=1)
    assert_same_parameters(sb3.policy, ddpg.policy)


def test_equivalence_test_can_fail():
    """Guard against a vacuous comparison: a different hyperparameter must give different parameters."""
    kwargs = dict(policy_kwargs=dict(net_arch=[32, 32]), learning_starts=0, seed=0, policy_delay=1)
    sb3 = TD3("MlpPolicy", "Pendulum-v1", **kwargs)
    td3x = TD3X("MlpPolicy", "Pendulum-v1", **(kwargs | dict(gamma=0.5)))
    copy_sb3_policy_weights(sb3.policy, td3x.policy)
    data = batches(2)
    run_steps(sb3, data, seed=7)
    run_steps(td3x, data, seed=7)
    with pytest.raises(AssertionError):
        assert_same_parameters(sb3.policy, td3x.policy)
