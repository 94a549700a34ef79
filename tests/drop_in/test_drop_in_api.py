"""Drop-in: ``TD3X`` and ``DDPG`` take the arguments of SB3's ``TD3`` and ``DDPG``, with the same names, order and defaults.

No SB3 test file does this for TD3 (SB3 is the reference); it is the precondition of every other ``test_drop_in_*``
file: code written for ``stable_baselines3.TD3`` runs unchanged with ``TD3X``.
"""

import inspect

from stable_baselines3 import DDPG as SB3DDPG
from stable_baselines3 import TD3
from stable_baselines3.td3.policies import TD3Policy

from sb3_td3x import DDPG, TD3X

# The additions that make DDPG and the paper's ablations presets, switched to SB3's TD3 by default.
TD3X_SWITCHES = {"critic_learning_rate": None, "target_policy_smoothing": True, "clipped_double_q": True}


def parameters(function) -> dict[str, inspect.Parameter]:
    return dict(inspect.signature(function).parameters)


def test_constructor_matches_td3():
    sb3, ours = parameters(TD3.__init__), parameters(TD3X.__init__)
    # Every TD3 argument with TD3's default, in TD3's order; the additions come after TD3's positional arguments
    # (all but the private _init_setup_model), so positional calls mean the same.
    assert [name for name in ours if name in sb3] == list(sb3)
    n_positional = len(sb3) - 1
    assert list(ours)[:n_positional] == list(sb3)[:n_positional]
    for name, parameter in sb3.items():
        assert ours[name].default == parameter.default, name
    extras = {name: ours[name].default for name in ours if name not in sb3}
    assert TD3X_SWITCHES.items() <= extras.items()


def test_positional_arguments_mean_the_same():
    args = ("MlpPolicy", "Pendulum-v1", 3e-4, 1_000, 50, 32, 0.01, 0.9)
    sb3, ours = TD3(*args), TD3X(*args)
    for name in ("learning_rate", "buffer_size", "learning_starts", "batch_size", "tau", "gamma"):
        assert getattr(ours, name) == getattr(sb3, name), name


def test_learn_matches_td3():
    sb3, ours = parameters(TD3.learn), parameters(TD3X.learn)
    assert list(ours) == list(sb3)
    for name, parameter in sb3.items():
        if name != "tb_log_name":  # each algorithm logs under its own name
            assert ours[name].default == parameter.default, name


def test_policy_aliases_match_td3():
    assert TD3X.policy_aliases.keys() == TD3.policy_aliases.keys()
    # Code that checks isinstance(model.policy, TD3Policy) keeps working.
    for policy_class in TD3X.policy_aliases.values():
        assert issubclass(policy_class, TD3Policy)


def test_ddpg_accepts_sb3_ddpg_arguments():
    sb3 = parameters(SB3DDPG.__init__)
    kwargs = {
        name: parameter.default
        for name, parameter in sb3.items()
        if name not in ("self", "policy", "env", "_init_setup_model")
    }
    kwargs["buffer_size"] = 1_000
    model = DDPG("MlpPolicy", "Pendulum-v1", **kwargs)
    reference = SB3DDPG("MlpPolicy", "Pendulum-v1", **kwargs)
    # SB3's DDPG is TD3 with one critic, no delay and no target smoothing (noise clipped to 0).
    assert len(model.critic.q_networks) == len(reference.critic.q_networks) == 1
    assert model.policy_delay == reference.policy_delay == 1
    assert reference.target_noise_clip == 0.0 and model.target_policy_smoothing is False
    assert model.clipped_double_q is False


def test_ddpg_positional_arguments():
    model = DDPG("MlpPolicy", "Pendulum-v1", 3e-4, 1_000)
    assert model.learning_rate == 3e-4 and model.buffer_size == 1_000
