"""benchmarks/bare_step.py: the floor it measures is TD3's update as TD3X runs it, not a cheaper computation."""

import sys
from pathlib import Path

import pytest
import torch as th

from sb3_td3x import TD3X

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
bare_step = pytest.importorskip("bare_step")
throughput = pytest.importorskip("throughput")


def _trained(step_variant: int | None) -> TD3X:
    """A model past the benchmark's learning_starts, then 5 gradient steps: its own update, or a bare step."""
    model = throughput.make_model(
        TD3X, "Pendulum-v1", 0, {"batch_size": 64, "buffer_size": 2_000, "policy_kwargs": {"net_arch": [32, 32]}},
        run_length=1_100,  # a short run's defaults: the eager MlpUpdate, the computation the bare step is
    )
    model.learn(1_100)
    if step_variant is not None:
        model._step_fn = bare_step.BareStep(model, step_variant)
    model.train(5, 64)
    return model


@pytest.mark.parametrize("variant", [3, 4])
def test_bare_step_with_the_models_streams_and_optimizers_trains_as_td3x(variant):
    """With SB3's sampling, the model's noise stream and its optimizers (v3, v4), the bare step gives the weights
    TD3X's update gives, actor steps and target updates included: its speed is that of the same computation."""
    expected = _trained(None)
    bare = _trained(variant)
    for (name, p), q in zip(bare.policy.named_parameters(), expected.policy.parameters()):
        th.testing.assert_close(p, q, msg=name)
