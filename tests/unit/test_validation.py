"""Bad input fails at construction with a ValueError naming the parameter and the allowed range."""

import gymnasium as gym
import numpy as np
import pytest

from sb3_td3x import DDPG, TD3X


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(policy_delay=0), "policy_delay"),
        (dict(policy_delay=1.5), "policy_delay"),
        (dict(target_policy_noise=-0.1), "target_policy_noise"),
        (dict(target_noise_clip=-1.0), "target_noise_clip"),
        (dict(target_noise_clip=float("nan")), "target_noise_clip"),
        (dict(tau=1.5), "tau"),
        (dict(tau=-0.01), "tau"),
        (dict(gamma=1.01), "gamma"),
        (dict(gamma=-0.5), "gamma"),
        (dict(batch_size=0), "batch_size"),
        (dict(batch_size=32.0), "batch_size"),
        (dict(learning_rate=-1e-3), "learning_rate"),
        (dict(critic_learning_rate=0.0), "critic_learning_rate"),
        (dict(buffer_size=0), "buffer_size"),
        (dict(learning_starts=-5), "learning_starts"),
        (dict(gradient_steps=-2), "gradient_steps"),
        # A switch given as a string is refused: "False" is a true value, so clipped_double_q="False" would keep it on.
        (dict(clipped_double_q="False"), "clipped_double_q"),
        (dict(target_policy_smoothing="no"), "target_policy_smoothing"),
        (dict(bf16="no"), "bf16"),
        (dict(flush_denormals=None), "flush_denormals"),
        (dict(optimize_memory_usage="False"), "optimize_memory_usage"),
        (dict(policy_kwargs=dict(n_critics=0)), "n_critics"),
        (dict(policy_kwargs=dict(n_critics=2.0)), "n_critics"),
        (dict(train_freq=0), "train_freq"),
        (dict(train_freq=(1, "steps")), "train_freq"),
        # A layer of width 0 trains a network that outputs its last bias, whatever the input; SB3 accepts it.
        (dict(policy_kwargs=dict(net_arch=[64, 0])), "net_arch"),
        (dict(policy_kwargs=dict(net_arch=[-1])), "net_arch"),
        (dict(policy_kwargs=dict(net_arch={"pi": [8]})), "net_arch"),  # SB3: an assertion error
        (dict(policy_kwargs=dict(net_arch=(64, 64))), "net_arch"),  # SB3: a bare assertion
        # SB3 takes any object and fails at learn()'s first noisy action, with an AttributeError.
        (dict(action_noise="normal"), "action_noise"),
        (dict(action_noise=0.1), "action_noise"),
    ],
)
def test_bad_hyperparameters_raise_value_error(kwargs, message):
    with pytest.raises(ValueError, match=message) as info:
        TD3X("MlpPolicy", "Pendulum-v1", **kwargs)
    # The message gives the allowed range, not only the name.
    assert "must be" in str(info.value)


def test_discrete_action_space_is_rejected():
    with pytest.raises(ValueError, match="continuous action space"):
        TD3X("MlpPolicy", "CartPole-v1")


def test_unbounded_action_space_is_rejected():
    class Unbounded(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (2,))
        action_space = gym.spaces.Box(-np.inf, np.inf, (1,))

    with pytest.raises(ValueError, match="bounded action space"):
        TD3X("MlpPolicy", Unbounded())


def test_ddpg_validates_too():
    with pytest.raises(ValueError, match="tau"):
        DDPG("MlpPolicy", "Pendulum-v1", tau=3)


@pytest.mark.parametrize("kwargs", [dict(tau=0.0), dict(tau=1.0), dict(gamma=0.0), dict(gamma=1.0), dict(policy_delay=1),
                                    dict(target_policy_noise=0.0, target_noise_clip=0.0), dict(gradient_steps=-1),
                                    dict(train_freq=(2, "episode")), dict(train_freq=(3, "step")),
                                    dict(policy_kwargs=dict(net_arch=[])),
                                    dict(policy_kwargs=dict(net_arch={"pi": [8], "qf": [16, 16]})),
                                    dict(policy_kwargs=dict(net_arch={"pi": [8], "qf": (16,), "users_key": 3}))])
def test_edge_values_are_accepted(kwargs):
    TD3X("MlpPolicy", "Pendulum-v1", **{"policy_kwargs": dict(net_arch=[8]), **kwargs})


def test_a_noise_of_the_users_own_class_is_accepted_as_sb3_accepts_it():
    """SB3 calls the noise and its ``reset()``; an object with both is a noise, whatever its class."""

    class Constant:
        def __call__(self):
            return np.full(1, 0.3)

        def reset(self):
            pass

    TD3X("MlpPolicy", "Pendulum-v1", action_noise=Constant(), learning_starts=0, policy_kwargs=dict(net_arch=[8])).learn(20)
