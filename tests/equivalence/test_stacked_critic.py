"""A critic whose twin weights live stacked (``benchmarks/user_changes.py``'s ``StackedCritic``: one ``[2, out, in]``
parameter a layer, one ``baddbmm`` a hidden layer for both critics, the one-unit output per critic) learns bit for bit
what TD3X's stock critics (SB3's two separate networks) learn, from the same seed, eager, with Adam's loop (as
test_same_learning.py runs it against SB3's ``TD3``): what a stacked default critic would need to keep SB3's equality
(docs/performance.md, "Where TD3X falls short"). On x86 ATen runs each of a batched product's matrices through the
same BLAS call as a single product; measured on an Intel Xeon, 2026-11-29. The same critic with its output
layer stacked too does not (ATen's batched product rounds a one-unit output otherwise), which shows that the test sees
a difference of rounding."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.noise import NormalActionNoise

from sb3_td3x import TD3X


@pytest.fixture
def stacked(monkeypatch):
    monkeypatch.syspath_prepend("benchmarks")
    import user_changes

    return user_changes


def seeded_learn(policy, steps: int = 700) -> TD3X:
    model = TD3X(
        policy,
        gym.make("Pendulum-v1"),
        learning_starts=200,
        batch_size=100,
        seed=0,
        action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
        policy_kwargs={"net_arch": [32, 32], "optimizer_kwargs": {"foreach": False}},
        compile_update=False,
    )
    model.learn(steps)  # each model built right before its learn(): the constructor reseeds the global generators
    return model


def stacked_weights(critic) -> list[th.Tensor]:
    return [th.stack([critic.qf0[i].weight, critic.qf1[i].weight]) for i in (0, 2, 4)]


def test_stacked_twin_critics_learn_the_separate_ones_bit_for_bit(stacked):
    plain = seeded_learn("MlpPolicy")
    batched = seeded_learn(stacked.StackedPolicy)
    for separate, together in zip(stacked_weights(plain.critic), batched.critic.weights, strict=True):
        assert th.equal(separate, together)
    for separate, together in zip(stacked_weights(plain.critic_target), batched.critic_target.weights, strict=True):
        assert th.equal(separate, together)
    for a, b in zip(plain.actor.parameters(), batched.actor.parameters(), strict=True):
        assert th.equal(a, b)


def test_the_check_sees_a_stacked_output_layer(stacked, monkeypatch):
    def all_stacked(self, obs, actions):
        x = self._input(obs, actions, not self.share_features_extractor)
        h = x.expand(len(self.weights[0]), *x.shape)
        for i in range(len(self.weights)):
            h = th.baddbmm(self.biases[i], h, self.weights[i].mT)
            h = h.relu() if i < len(self.weights) - 1 else h
        return h

    plain = seeded_learn("MlpPolicy", steps=300)
    monkeypatch.setattr(stacked.StackedCritic, "q_values", all_stacked)
    batched = seeded_learn(stacked.StackedPolicy, steps=300)
    differences = [(a - b).abs().max().item() for a, b in zip(stacked_weights(plain.critic), batched.critic.weights)]
    assert 0 < max(differences) < 1e-3, differences
