"""``run.py algo=td3`` (TD3X) and ``run.py algo=sb3_td3`` (SB3's ``TD3``) from one seed make the same run.

The equivalence layer shows that TD3X's ``learn()`` is SB3's. This shows the same through everything ``run.py``
adds: the configs (``algo/td3.yaml`` and ``algo/sb3_td3.yaml``), the model built by Hydra from the seed, the
evaluations with the critic's value measurement, the checkpoints. So the Hopper comparison of the results page
compares two samples of one algorithm: its runs part only by float rounding, amplified over training.
"""

from __future__ import annotations

import csv

import pytest
import torch
from stable_baselines3 import TD3

from sb3_td3x import TD3X
from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.runner import run_experiment

# Hopper-v5 with 64-64 networks: 500 random steps, then 500 steps with a gradient step each; evaluations at 500, 1000
ARGS = ["debug=smoke", "env=hopper", "progress_bar=false", "logger=none", "total_timesteps=1000", "eval.freq=500",
        "algo.learning_starts=500", "torch_threads=1", "seed=4"]  # fmt: skip


def run(tmp_path, algo: str, *overrides: str) -> tuple[dict[str, torch.Tensor], list[dict[str, str]]]:
    run_dir = tmp_path / f"{algo}_{len(list(tmp_path.iterdir()))}"
    run_experiment(compose_config([*ARGS, f"algo={algo}", f"run_dir={run_dir}", *overrides]))
    with open(run_dir / "evaluations.csv", newline="") as file:
        evaluations = list(csv.DictReader(file))
    model = (TD3X if algo == "td3" else TD3).load(run_dir / "checkpoints" / "last" / "model.zip", device="cpu")
    return model.policy.state_dict(), evaluations


def test_run_py_trains_td3x_as_it_trains_sb3_td3(tmp_path):
    sb3_weights, sb3_evaluations = run(tmp_path, "sb3_td3")
    weights, evaluations = run(tmp_path, "td3")
    assert list(weights) == list(sb3_weights)
    # 500 gradient steps: fused (TD3X) against for-each (SB3) Adam rounding, about 3e-5 here
    for name, expected in sb3_weights.items():
        torch.testing.assert_close(weights[name], expected, rtol=0, atol=1e-3, msg=name)
    assert [row["timesteps"] for row in evaluations] == [row["timesteps"] for row in sb3_evaluations] == ["500", "1000"]
    for row, expected in zip(evaluations, sb3_evaluations):
        for column in ("mean_return", "mean_length", "value_estimate", "true_value", "value_states"):
            assert float(row[column]) == pytest.approx(float(expected[column]), rel=1e-3, abs=1e-3), column

    # The check can fail: another tau (0.006 for 0.005) moves the weights by far more than the tolerance
    other_weights, _ = run(tmp_path, "td3", "algo.tau=0.006")
    worst = max((other_weights[name] - expected).abs().max().item() for name, expected in sb3_weights.items())
    assert worst > 1e-2
