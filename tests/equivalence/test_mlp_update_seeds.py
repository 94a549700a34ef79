"""MlpUpdate over N models (a SeedBatch's update) against each model's lone MlpUpdate: bit for bit on a CPU.

Each model is built and filled with 300 random transitions by its own ``learn()``; the lone ones then train with
``model.train()``, the others through one ``MlpUpdate`` of all of them, each drawing from its own detached streams.
"""

import numpy as np
import pytest
import torch as th

from sb3_td3x import TD3X
from sb3_td3x.td3x.update_paths.mlp import MlpUpdate

SEEDS = (0, 1, 2)
FILL, STEPS = 300, 120


def filled(seed: int, env: str = "Pendulum-v1", detach: bool = False, **kwargs) -> TD3X:
    options = {"learning_starts": FILL, "batch_size": 32, "policy_kwargs": {"net_arch": [32, 32]}, **kwargs}
    model = TD3X("MlpPolicy", env, seed=seed, **options)
    model.learn(FILL)  # random actions only: no gradient step yet
    if detach:  # as a SeedBatch does, right after the model is built
        model.random_streams.detach()
    return model


def train_together(update: MlpUpdate, steps: int) -> None:
    """What each model's ``train(steps)`` does, the updates through ``update``."""
    for _ in range(steps):
        batches, update_actor = [], []
        for model in update.models:
            model._n_updates += 1
            update_actor.append(model.should_update_actor(model._n_updates))
            batches.append(model.sample_batch(model.batch_size))
        update.step(batches, update_actor)
        for model, updated in zip(update.models, update_actor):
            model._n_actor_updates += updated


def lone_and_together(per_seed, env="Pendulum-v1", seeds_per_product=None):
    lone = []
    for i, seed in enumerate(SEEDS):
        model = filled(seed, env, **per_seed(i))
        model.train(STEPS, model.batch_size)
        assert model.update_path == "mlp"
        model.random_streams.detach()  # keeps where the lone run left the global generators
        lone.append(model)
    models = [filled(seed, env, detach=True, **per_seed(i)) for i, seed in enumerate(SEEDS)]
    assert MlpUpdate.why_not_together(models) is None
    train_together(MlpUpdate(models, seeds_per_product=seeds_per_product), STEPS)
    return lone, models


def assert_same(models, lone, exact=True):
    tolerance = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-4, "atol": 1e-5}
    for i, (model, alone) in enumerate(zip(models, lone)):
        assert (model._n_updates, model._n_actor_updates) == (alone._n_updates, alone._n_actor_updates)
        for (name, a), b in zip(alone.policy.state_dict().items(), model.policy.state_dict().values()):
            th.testing.assert_close(b, a, **tolerance, msg=lambda m, name=name, i=i: f"seed {i} {name}: {m}")
        for role in ("actor", "critic"):
            ours, theirs = (getattr(m, role).optimizer.state_dict()["state"] for m in (model, alone))
            for key in theirs:
                for field in theirs[key]:
                    th.testing.assert_close(ours[key][field], theirs[key][field], **tolerance)
        # Each seed drew as many numbers as its lone run: its streams end where the lone run's globals end.
        ours, theirs = model.random_streams.state(), alone.random_streams.state()
        assert np.array_equal(ours["numpy"][1], theirs["numpy"][1]) and th.equal(ours["torch"], theirs["torch"])


@pytest.mark.parametrize(
    "per_seed",
    [
        lambda i: {},
        lambda i: {"learning_rate": 1e-3 * (i + 1), "tau": 0.005 * (i + 1), "policy_delay": i + 1},
        lambda i: {"policy_kwargs": {"net_arch": [16, 8], "n_critics": 3}, "target_policy_smoothing": False},
    ],
    ids=["defaults", "own-lr-tau-delay", "3-critics-no-smoothing"],
)
def test_n_models_through_one_update_are_their_lone_runs_to_the_bit(per_seed):
    lone, models = lone_and_together(per_seed)
    assert_same(models, lone)


def test_a_mujoco_task_to_the_bit():
    lone, models = lone_and_together(lambda i: {"policy_kwargs": {"net_arch": [64, 64]}}, env="Hopper-v5")
    assert_same(models, lone)


def test_all_seeds_in_one_product_as_on_a_gpu_to_float_rounding():
    lone, models = lone_and_together(lambda i: {}, seeds_per_product=len(SEEDS))
    assert_same(models, lone, exact=False)


def test_the_test_sees_a_different_update():
    lone, models = lone_and_together(lambda i: {})
    with pytest.raises(AssertionError):
        assert_same(models, [filled(seed) for seed in SEEDS])  # untrained
    assert_same(models, lone)


class HuberTD3X(TD3X):
    def critic_loss(self, current_q, target_q):
        loss = sum(th.nn.functional.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}


def test_what_cannot_share_the_update_is_refused_with_every_reason():
    def build(cls=TD3X, **kwargs):
        return cls("MlpPolicy", "Pendulum-v1", **{"policy_kwargs": {"net_arch": [8]}, **kwargs})

    assert "critic_loss overridden by HuberTD3X" in MlpUpdate.why_not_together([build(), build(HuberTD3X)])
    assert "networks or device differ" in MlpUpdate.why_not_together([build(), build(policy_kwargs={"net_arch": [4]})])
    assert "gamma is 0.9" in MlpUpdate.why_not_together([build(), build(gamma=0.9)])
    assert "bf16" in MlpUpdate.why_not_together([build(), build(bf16=True)])
    model = build()
    assert "given twice" in MlpUpdate.why_not_together([model, model])
    assert "mlp_update=False" in MlpUpdate.why_not_together([build(), build(mlp_update=False)])
