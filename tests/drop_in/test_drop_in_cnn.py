"""Drop-in: image observations with ``CnnPolicy`` (SB3's ``FakeImageEnv``), and the target networks' features extractors.

Mirrors SB3's ``tests/test_cnn.py`` (``test_cnn``, ``test_features_extractor_target_net``, ``test_channel_first_env``).
"""

from copy import deepcopy

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.envs import FakeImageEnv
from stable_baselines3.common.vec_env import VecTransposeImage, is_vecenv_wrapped

from sb3_td3x import TD3X

# Small images and features, small batches: the CNN dominates the run time.
CNN_KWARGS = dict(buffer_size=250, batch_size=32, policy_kwargs=dict(features_extractor_kwargs=dict(features_dim=32)))


def params_should_match(params, other_params) -> None:
    for param, other_param in zip(params, other_params, strict=True):
        assert th.allclose(param, other_param)


def params_should_differ(params, other_params) -> None:
    for param, other_param in zip(params, other_params, strict=True):
        assert not th.allclose(param, other_param)


def check_target_features_extractors(model: TD3X, shared: bool) -> None:
    """The actor target's and critic target's features extractors are equal when shared, different otherwise."""
    named_actor = model.actor_target.named_parameters()
    for (name, actor_param), critic_param in zip(named_actor, model.critic_target.parameters()):
        if "features_extractor" in name:
            assert th.allclose(actor_param, critic_param) == shared, name


# mirrors SB3 tests/test_cnn.py::test_cnn
def test_cnn(tmp_path):
    env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=1, discrete=False)
    model = TD3X("CnnPolicy", env, learning_starts=100, seed=1, **CNN_KWARGS).learn(120)
    # FakeImageEnv is channel-last: it is wrapped in VecTransposeImage.
    assert is_vecenv_wrapped(model.get_env(), VecTransposeImage)

    obs, _ = env.reset()
    # Channel-last input to predict.
    for _ in range(3):
        model.predict(obs, deterministic=False)
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == env.action_space.shape

    model.save(tmp_path / "cnn_model.zip")
    model = TD3X.load(tmp_path / "cnn_model.zip")
    np.testing.assert_allclose(action, model.predict(obs, deterministic=True)[0])


# mirrors SB3 tests/test_cnn.py::test_features_extractor_target_net
@pytest.mark.parametrize(
    "share_features_extractor",
    [
        True,
        False,
    ],
)
def test_features_extractor_target_net(share_features_extractor):
    env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=1, discrete=False)
    kwargs = deepcopy(CNN_KWARGS)
    kwargs["policy_kwargs"]["share_features_extractor"] = share_features_extractor
    # No delay: the actor and the Polyak updates happen at every gradient step.
    kwargs["policy_delay"] = 1
    model = TD3X("CnnPolicy", env, seed=0, learning_starts=100, **kwargs)

    if share_features_extractor:
        # The very same objects, not copies.
        assert model.policy.actor.features_extractor is model.policy.critic.features_extractor
        assert model.policy.actor_target.features_extractor is model.policy.critic_target.features_extractor
    else:
        assert model.policy.actor.features_extractor is not model.policy.critic.features_extractor
        assert model.policy.actor_target.features_extractor is not model.policy.critic_target.features_extractor

    # Targets start equal to their networks...
    params_should_match(model.critic.parameters(), model.critic_target.parameters())
    params_should_match(model.actor.parameters(), model.actor_target.parameters())
    model.learn(130)
    # ... and lag behind them once trained.
    params_should_differ(model.critic.parameters(), model.critic_target.parameters())
    params_should_differ(model.actor.parameters(), model.actor_target.parameters())
    check_target_features_extractors(model, share_features_extractor)

    # Fresh model, data collected without gradient steps (10 < learning_starts).
    model = TD3X("CnnPolicy", env, seed=0, learning_starts=100, **kwargs).learn(10)
    original_param = deepcopy(list(model.critic.parameters()))
    original_target_param = deepcopy(list(model.critic_target.parameters()))
    original_actor_target_param = deepcopy(list(model.actor_target.parameters()))

    # tau = 0: the targets do not move, the critic does.
    model.tau = 0.0
    model.train(gradient_steps=1)
    params_should_match(original_target_param, model.critic_target.parameters())
    params_should_match(original_actor_target_param, model.actor_target.parameters())
    check_target_features_extractors(model, share_features_extractor)
    params_should_differ(original_param, model.critic.parameters())

    # Learning rate 0: the networks do not move, the targets do (Polyak update).
    original_param = deepcopy(list(model.critic.parameters()))
    original_actor_param = deepcopy(list(model.actor.parameters()))
    model.lr_schedule = lambda _: 0.0
    model.tau = 0.01
    model.train(gradient_steps=1)
    params_should_differ(original_target_param, model.critic_target.parameters())
    params_should_match(original_param, model.critic.parameters())
    params_should_differ(original_actor_target_param, model.actor_target.parameters())
    params_should_match(original_actor_param, model.actor.parameters())
    check_target_features_extractors(model, share_features_extractor)


# mirrors SB3 tests/test_cnn.py::test_channel_first_env (SB3 runs it with A2C)
def test_channel_first_env(tmp_path):
    # Channel-first images are used as they are: a wrong layout would fail building the convolutions.
    env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=1, discrete=False, channel_first=True)
    model = TD3X("CnnPolicy", env, learning_starts=50, **CNN_KWARGS).learn(70)
    assert not is_vecenv_wrapped(model.get_env(), VecTransposeImage)

    obs, _ = env.reset()
    action, _ = model.predict(obs, deterministic=True)
    model.save(tmp_path / "cnn_model.zip")
    model = TD3X.load(tmp_path / "cnn_model.zip", env=env)
    np.testing.assert_allclose(action, model.predict(obs, deterministic=True)[0])


def test_a_cnn_moved_to_channels_last_mid_run_steps_as_torch_s_for_loop_adam():
    """A CnnPolicy moved to ``channels_last`` after training began (its Adam moments keep the old layout): one
    gradient step of TD3X's default optimizer (fused Adam) from the same weights, optimizer state and batch as one with
    torch's for-loop Adam. torch 2.13's fused CPU kernel alone leaves the convolutions about 1e-3 off (sb3_td3x's
    eager step lays the moments out as their parameters first: tests/unit/test_acceleration.py)."""
    # deepcopy: an optimizer's state_dict() holds its state tensors themselves, which load_state_dict would share
    models = [
        TD3X("CnnPolicy", FakeImageEnv(screen_height=40, screen_width=40, n_channels=3, discrete=False), learning_starts=100,
             seed=1, compile_update=False, **CNN_KWARGS).learn(110)
        for _ in range(2)
    ]  # fmt: skip
    state = deepcopy(models[0].get_parameters())
    batch = models[0].replay_buffer.sample(32)
    for model, fused in zip(models, (True, False)):
        model.set_parameters(deepcopy(state))
        model.policy.to(memory_format=th.channels_last)
        if not fused:
            for optimizer in (model.actor.optimizer, model.critic.optimizer):
                for group in optimizer.param_groups:
                    group.update(fused=False, foreach=False)
        model.sample_batch = lambda batch_size: batch
        th.manual_seed(0)
        model.train(gradient_steps=1, batch_size=32)
    assert models[0].critic.features_extractor.cnn[0].weight.is_contiguous(memory_format=th.channels_last)
    for (name, a), b in zip(models[0].policy.named_parameters(), models[1].policy.parameters()):
        th.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=lambda m, name=name: f"{name}: {m}")
