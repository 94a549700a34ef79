"""The variants (sb3_td3x.variants) from run.py: a short ``python run.py algo=<variant> env=hopper debug=smoke`` runs to
its end with a run folder and a summary; a LAP run stopped and resumed is the run never stopped, priorities included."""

from __future__ import annotations

import csv
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import stopped_and_resumed
import yaml

from sb3_td3x.experiment.run.checkpoints import META_FILE, REPLAY_BUFFER_FILE

REPO = Path(__file__).resolve().parents[2]
VARIANTS = {
    "td3_lap": ("sb3_td3x.variants.TD3LAP", "eager"),  # a smoke run is short: the hooks eagerly
    "td3_nstep": ("sb3_td3x.variants.TD3NStep", "eager"),
    "td3_layernorm": ("sb3_td3x.variants.TD3LayerNorm", "eager"),
    "td3_c51": ("sb3_td3x.variants.TD3C51", "eager"),
}


@pytest.mark.parametrize("algo", list(VARIANTS))
def test_run_py_trains_the_variant_to_a_summary(tmp_path, algo):
    """debug=smoke on Hopper-v5, cut to 1000 steps (500 of them training) with one torch thread."""
    run_dir = tmp_path / "run"
    args = [f"algo={algo}", "env=hopper", "debug=smoke", "total_timesteps=1000", "progress_bar=false", "logger=none",
            "torch_threads=1", f"run_dir={run_dir}"]  # fmt: skip
    result = subprocess.run(
        [sys.executable, "run.py", *args], check=False, cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    target, update_path = VARIANTS[algo]
    assert summary["total_timesteps"] == 1000 and np.isfinite(summary["final_mean_return"])
    assert summary["update_path"] == update_path
    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert config["algo"]["_target_"] == target and config["algo"]["name"] == algo
    assert (run_dir / "evaluations.csv").is_file() and (run_dir / "checkpoints" / "last" / META_FILE).is_file()


def test_a_lap_run_stopped_and_resumed_is_the_run_never_stopped(tmp_path):
    """The priorities are part of the replay buffer's checkpoint: a TD3LAP run stopped at step 800 and resumed ends
    with the evaluations (one of them after the resume), the weights and the priorities (every level of the sum tree,
    the priority of new transitions, the update count) of the run never stopped, to the bit."""
    overrides = ["algo=td3_lap", "debug=smoke", "env=inverted_pendulum", "total_timesteps=1200", "eval.freq=400",
                 "checkpoint.freq=100000", "progress_bar=false", "torch_threads=1", "logger=none"]  # fmt: skip
    reference, stopped = stopped_and_resumed(overrides, tmp_path, stop_at=800)
    assert _curve(stopped) == _curve(reference)
    ends = [_last_checkpoint(run) for run in (reference, stopped)]
    for name, tensor in ends[0]["policy"].items():
        torch.testing.assert_close(ends[1]["policy"][name], tensor, rtol=0, atol=0, msg=name)
    buffers = [end["buffer"] for end in ends]
    assert buffers[0].prioritized and int(buffers[0].priority_updates) == 700  # 1200 steps, learning from 500
    levels = [b.priorities.sums + b.priorities.maxima[1:] for b in buffers]
    for k, (a, b) in enumerate(zip(*levels)):
        assert torch.equal(a, b), f"priority tree level {k}"
    assert torch.equal(buffers[0].max_priority, buffers[1].max_priority)
    assert torch.equal(buffers[0].priority_updates, buffers[1].priority_updates)
    assert (buffers[0].priorities.leaves[:1200] > 1.0).any()  # priorities were written, not only the initial 1


def _curve(run_dir: Path) -> list[tuple[str, ...]]:
    """Each evaluation's step, return, its std, and the critic's value estimate against the true value."""
    with open(run_dir / "evaluations.csv") as file:
        fields = ("timesteps", "mean_return", "std_return", "value_estimate", "true_value")
        return [tuple(row[name] for name in fields) for row in csv.DictReader(file)]


def _last_checkpoint(run_dir: Path) -> dict:
    import zipfile

    last = run_dir / "checkpoints" / "last"
    with zipfile.ZipFile(last / "model.zip") as archive, archive.open("policy.pth") as file:
        policy = torch.load(file, map_location="cpu")
    with open(last / REPLAY_BUFFER_FILE, "rb") as file:
        buffer = pickle.load(file)
    return {"policy": policy, "buffer": buffer}


def test_the_value_bias_of_a_c51_critic_is_its_expected_value():
    from sb3_td3x.experiment.run.value_bias import critic_estimates
    from sb3_td3x.variants import TD3C51

    model = TD3C51("MlpPolicy", "Pendulum-v1", v_min=-10.0, v_max=10.0, policy_kwargs={"net_arch": [16]}, seed=0)
    rng = np.random.default_rng(0)
    observations = [rng.normal(size=3).astype(np.float32) for _ in range(8)]
    actions = rng.uniform(-2, 2, size=(8, 1)).astype(np.float32)
    estimates = critic_estimates(model, observations, observations, actions, np.zeros(8), np.zeros(8))
    from sb3_td3x.common.buffers import TensorReplayBufferSamples

    obs = torch.as_tensor(np.stack(observations))
    batch = TensorReplayBufferSamples(obs, torch.as_tensor(actions) / 2, obs, torch.zeros(8, 1), torch.zeros(8, 1))
    with torch.no_grad():
        expected = model.q_value_estimates(batch)[0, :, 0].double().numpy()
    assert estimates.shape == expected.shape
    np.testing.assert_allclose(estimates, expected, rtol=1e-5)
