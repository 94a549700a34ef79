"""A run stopped by SIGTERM resumes where it stopped and makes the same curve as a run never stopped."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import stopped_and_resumed

from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.experiment.run.checkpoints import META_FILE, find_checkpoint, save_checkpoint, verify_checkpoint
from sb3_td3x.experiment.run.folder import config_for_resume

REPO = Path(__file__).resolve().parents[2]
# 2000 steps of InvertedPendulum-v5 with small networks, evaluated every 500 steps; the only checkpoint before
# the end is the one SIGTERM writes. One torch thread: two runs side by side, beside the other test worker's (more
# threads than cores made this test take 69 to 186 s in the suite, 19 s alone).
RUN = ["debug=smoke", "env=inverted_pendulum", "checkpoint.freq=100000", "progress_bar=false", "torch_threads=1"]


def run_py(*args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "run.py", *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs
    )


def curve(run_dir: Path) -> list[tuple[int, float, float, float, float]]:
    """Each evaluation's step, return, its std, and the critic's value estimate against the true value."""
    with open(run_dir / "evaluations.csv") as file:
        return [
            (int(row["timesteps"]), float(row["mean_return"]), float(row["std_return"]), float(row["value_estimate"]),
             float(row["true_value"]))
            for row in csv.DictReader(file)
        ]


def policy_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    with zipfile.ZipFile(run_dir / "checkpoints" / "last" / "model.zip") as archive, archive.open("policy.pth") as file:
        return torch.load(file, map_location="cpu")


def test_sigterm_then_resume_finishes_the_same_run(tmp_path):
    reference, stopped = tmp_path / "reference", tmp_path / "stopped"
    reference_process = run_py(*RUN, f"run_dir={reference}")  # in parallel: 2 cores
    process = run_py(*RUN, f"run_dir={stopped}")
    deadline = time.time() + 300
    while not (stopped / "evaluations.csv").is_file() or len(curve(stopped)) < 2:  # past step 1000
        assert process.poll() is None and time.time() < deadline, "the run ended before it could be stopped"
        time.sleep(0.05)
    time.sleep(0.5)  # most likely within an episode
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM
    assert "Traceback" not in stderr and f"python run.py resume={stopped}" in stderr
    stopped_at = json.loads((stopped / "checkpoints" / "last" / META_FILE).read_text())["num_timesteps"]
    assert 1000 <= stopped_at < 2000
    assert reference_process.wait(timeout=300) == 0, reference_process.stderr.read()[-3000:]

    process = run_py(f"resume={stopped}", "progress_bar=false")
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr[-3000:]
    assert f"Resuming {stopped} at step {stopped_at}" in stdout

    assert json.loads((stopped / "checkpoints" / "last" / META_FILE).read_text())["num_timesteps"] == 2000
    assert curve(stopped) == curve(reference)
    assert [row[0] for row in curve(stopped)] == [500, 1000, 1500, 2000]
    reference_weights, resumed_weights = policy_weights(reference), policy_weights(stopped)
    for name, tensor in reference_weights.items():
        torch.testing.assert_close(resumed_weights[name], tensor, rtol=0, atol=0, msg=name)
    assert (stopped / ".hydra" / "config.yaml").is_file() and list((stopped / ".hydra").glob("resumed_*"))
    sessions = [json.loads(line) for line in (stopped / "provenance.jsonl").read_text().splitlines()]
    assert [session["at_step"] for session in sessions] == [0, stopped_at]  # one line per session, for the results pages
    updates = json.loads((stopped / "summary.json").read_text())["update_sessions"]  # each session's update
    assert [(u["from_step"], u["update_path"]) for u in updates] == [(0, "eager"), (stopped_at, "eager")]
    never_stopped = json.loads((reference / "summary.json").read_text())["update_sessions"]
    assert [(u["from_step"], u["update_path"]) for u in never_stopped] == [(0, "eager")]


def test_resume_takes_the_saved_config_and_the_overrides_a_resume_may_make(tmp_path):
    cfg = compose_config(["env=inverted_pendulum", "algo=ddpg", f"run_dir={tmp_path}"])
    from omegaconf import OmegaConf

    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    (tmp_path / "checkpoints" / "last").mkdir(parents=True)
    for name in (META_FILE, "replay_buffer.pkl"):
        (tmp_path / "checkpoints" / "last" / name).write_text("{}")
    default = compose_config([f"resume={tmp_path}", "total_timesteps=5000"])  # composed with the default env and algo
    resumed = config_for_resume(default, [f"resume={tmp_path}", "total_timesteps=5000", "eval.freq=100", "logger=none"])
    assert (resumed.env.id, resumed.algo.name, resumed.total_timesteps, resumed.eval.freq, resumed.logger.name) == (
        "InvertedPendulum-v5",
        "ddpg",
        5000,
        100,
        "none",
    )
    assert resumed.run_dir == str(tmp_path)
    with pytest.raises(ConfigError, match="config group 'env'"):
        config_for_resume(default, [f"resume={tmp_path}", "env=ant"])
    with pytest.raises(ConfigError, match=r"cannot change algo.tau: 0.005 in the checkpoint, 0.01 asked"):
        config_for_resume(default, [f"resume={tmp_path}", "algo.tau=0.01"])


def test_a_checkpoint_cut_between_its_renames_is_still_found(tmp_path):
    last = tmp_path / "last"
    assert find_checkpoint(last) is None
    (tmp_path / "last.prev").mkdir()
    (tmp_path / "last.prev" / META_FILE).write_text('{"num_timesteps": 100}')
    assert find_checkpoint(last) == tmp_path / "last.prev"  # the old one moved aside, the new one not yet in place
    (tmp_path / "last.tmp").mkdir()  # a save that died while writing (no meta.json yet): never used
    assert find_checkpoint(last) == tmp_path / "last.prev"
    (tmp_path / "last.tmp" / META_FILE).write_text('{"num_timesteps": 200}')  # written whole, not yet renamed
    assert find_checkpoint(last) == tmp_path / "last.tmp"


def test_save_checkpoint_keeps_the_one_before(tmp_path):
    from sb3_td3x import TD3X
    from sb3_td3x.experiment.run.envs import make_train_env

    cfg = compose_config(["env=pendulum"])
    model = TD3X(
        "MlpPolicy", make_train_env(cfg.env, 1, 0), buffer_size=500, learning_starts=10, policy_kwargs={"net_arch": [8]}
    )
    model.learn(20)
    save_checkpoint(tmp_path / "last", model, {"n": 1})
    model.learn(20, reset_num_timesteps=False)
    save_checkpoint(tmp_path / "last", model, {"n": 2})
    model.learn(20, reset_num_timesteps=False)
    save_checkpoint(tmp_path / "last", model, {"n": 3})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last", "last.prev"]
    assert json.loads((tmp_path / "last" / META_FILE).read_text())["num_timesteps"] == 60
    assert json.loads((tmp_path / "last.prev" / META_FILE).read_text())["num_timesteps"] == 40
    assert os.path.getsize(tmp_path / "last" / "replay_buffer.pkl") > 0
    assert verify_checkpoint(tmp_path / "last") is None and verify_checkpoint(tmp_path / "last.prev") is None


@pytest.mark.parametrize("optimize_memory_usage", [False, True])
def test_the_replay_buffer_is_saved_as_its_filled_rows_and_loaded_whole(tmp_path, optimize_memory_usage):
    from sb3_td3x import TD3X
    from sb3_td3x.experiment.run.checkpoints import load_checkpoint
    from sb3_td3x.experiment.run.envs import make_train_env

    cfg = compose_config(["env=pendulum"])
    kwargs = dict(buffer_size=100_000, learning_starts=10, policy_kwargs={"net_arch": [8]}, seed=0, device="cpu")
    if optimize_memory_usage:
        kwargs.update(optimize_memory_usage=True, replay_buffer_kwargs={"handle_timeout_termination": False})
    model = TD3X("MlpPolicy", make_train_env(cfg.env, 1, 0), **kwargs)
    model.learn(50)
    save_checkpoint(tmp_path / "last", model, {})
    assert os.path.getsize(tmp_path / "last" / "replay_buffer.pkl") < 100_000  # 100k preallocated rows: about 3 MB
    loaded, _ = load_checkpoint(tmp_path / "last", TD3X, make_train_env(cfg.env, 1, 0), device="cpu")
    before, after = model.replay_buffer, loaded.replay_buffer
    assert (after.pos, after.full, after.buffer_size) == (before.pos, before.full, before.buffer_size)
    for name in ("observations", "actions", "rewards", "dones"):
        assert getattr(after, name).shape == getattr(before, name).shape
        assert (getattr(after, name) == getattr(before, name)).all(), name
    if not optimize_memory_usage:
        assert (after.next_observations == before.next_observations).all()
        assert (after.timeouts == before.timeouts).all()


def test_a_compiled_run_stopped_and_resumed_is_the_run_never_stopped(tmp_path):
    """The compiled update (what compile_update=None picks for a long run on a CPU; asked for here, the run being
    short) is deterministic through a stop and a resume: the same evaluations and weights, to the bit, as a run
    never stopped (the stop is a report that raises, which checkpoints as a signal does). 1000 steps: 300 compiled
    updates before the stop at step 500, 500 after it. On Pendulum-v1 with 32-32 networks and batches of 64: the
    graph of test_user_changes.py's stock case and test_seed_batch.py's compiled one, which Inductor's cache then
    finds (a graph costs about 25 s of CPU to compile cold)."""
    overrides = [*RUN, "env=pendulum", "algo.net_arch=[32,32]", "logger=none", "algo.compile_update=true"]
    overrides += ["total_timesteps=1000", "algo.learning_starts=200", "eval.freq=250"]
    reference, stopped = stopped_and_resumed(overrides, tmp_path, stop_at=500)
    summary = json.loads((stopped / "summary.json").read_text())
    assert summary["update_path"] == "compiled"
    # Each session's update, kept through the checkpoint: the record of the stopped run names both sessions'.
    assert [(s["from_step"], s["update_path"]) for s in summary["update_sessions"]] == [(0, "compiled"), (500, "compiled")]
    assert summary["update_sessions"][1]["update_reason"] == summary["update_reason"]
    assert [row[0] for row in curve(stopped)] == [250, 500, 750, 1000]
    np.testing.assert_array_equal(curve(stopped), curve(reference))  # to the bit; Pendulum measures no value: NaN
    for name, tensor in policy_weights(reference).items():
        torch.testing.assert_close(policy_weights(stopped)[name], tensor, rtol=0, atol=0, msg=name)
