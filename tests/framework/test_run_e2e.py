"""``python run.py`` end to end on a small MuJoCo env, and ``run_experiment`` as the sweeps call it."""

from __future__ import annotations

import csv
import glob
import json
import math
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_td3x.common.redaction import MASK, find_secrets
from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.errors import TrainingDiverged
from sb3_td3x.experiment.launch.hydra_jobs import threads_per_job
from sb3_td3x.experiment.run.checkpoints import META_FILE, MODEL_FILE, REPLAY_BUFFER_FILE, STATE_FILE
from sb3_td3x.experiment.runner import run_experiment

REPO = Path(__file__).resolve().parents[2]
FAKE_KEY = "0123456789abcdef-not-a-real-wandb-key"
# A tiny run: 2000 steps of InvertedPendulum-v5, 64-64 networks, evaluations every 500 steps.
SMOKE = ["debug=smoke", "env=inverted_pendulum", "progress_bar=false"]


def default_threads_and_rendering(env: dict[str, str]) -> tuple[int, bool]:
    """The number of threads torch uses by default in a new process, and whether it can render a MuJoCo frame."""
    code = (
        "import torch; print(torch.get_num_threads(), flush=True); import gymnasium as gym; "
        "e = gym.make('InvertedPendulum-v5', render_mode='rgb_array'); e.reset(); e.render(); print('rendered')"
    )
    done = subprocess.run([sys.executable, "-c", code], check=False, env=env, capture_output=True, text=True, timeout=120)
    lines = done.stdout.split()
    assert lines and lines[0].isdigit(), done.stdout + done.stderr[-3000:]
    return int(lines[0]), done.returncode == 0 and lines[-1] == "rendered"


def read_wandb_records(path: Path) -> list:
    """The protobuf records of an offline ``run-<id>.wandb`` file (a LevelDB-style log of 32 KiB blocks)."""
    from wandb.proto import wandb_internal_pb2

    raw, block, header = path.read_bytes(), 32768, 7
    assert raw[:4] == b":W&B"
    records, pending, pos = [], b"", header
    while pos + header <= len(raw):
        left = block - pos % block
        if left < header:
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", raw[pos : pos + header])
        if length == 0 and kind == 0:  # zero padding at the end of a block
            pos += left
            continue
        data, pos = raw[pos + header : pos + header + length], pos + header + length
        pending = data if kind in (1, 2) else pending + data
        if kind in (1, 4):  # full record, or the last piece of one
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            records.append(record)
    return records


def test_run_py_writes_a_complete_run_folder(tmp_path):
    """Every record of a run, and no W&B key in any of them (issue 19): ``WANDB_API_KEY`` in the environment and on the
    command line (``+hydra.job.env_set``, a usual way to hand a job its key), ``logger=wandb`` offline: the key is in no
    file of the run folder, of Hydra's records, of W&B's offline run or of W&B's cache in $HOME, and not in the console
    output; the records say a key was there, masked."""
    run_dir = tmp_path / "run"
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    # A key in the environment must not end up in any file; mode=offline keeps the test off the network.
    env.update(HOME=str(home), WANDB_API_KEY=FAKE_KEY, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    default_threads, video = default_threads_and_rendering(env)
    # 1000 steps, evaluated every 250: it trains on all the cores (torch_threads=null), beside the other test process
    args = SMOKE + ["total_timesteps=1000", "eval.freq=250", "checkpoint.freq=500"]
    args += ["logger=wandb", "logger.wandb.mode=offline", f"+hydra.job.env_set.WANDB_API_KEY={FAKE_KEY}"]
    args += [f"run_dir={run_dir}"] + (["video=final", "video.width=64", "video.height=64"] if video else [])
    result = subprocess.run(
        [sys.executable, "run.py", *args], check=False, cwd=REPO, env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    assert "Done: final evaluation" in result.stdout + result.stderr

    # evaluation log: one row per 250 steps, JSON and CSV agree
    with open(run_dir / "evaluations.csv") as file:
        rows = list(csv.DictReader(file))
    assert [int(row["timesteps"]) for row in rows] == [250, 500, 750, 1000]
    assert all(math.isfinite(float(row["mean_return"])) for row in rows)
    history = json.loads((run_dir / "evaluations.json").read_text())
    assert [entry["mean_return"] for entry in history] == [float(row["mean_return"]) for row in rows]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["final_mean_return"] == float(rows[-1]["mean_return"]) and summary["total_timesteps"] == 1000
    provenance = summary["provenance"]  # what the results pages cite: command, commit, machine, versions
    assert provenance["machine"]["cores"] >= 1 and provenance["versions"]["torch"] == torch.__version__
    # A single run trains on all the cores torch would use by default (torch_threads=null).
    assert provenance["machine"]["torch_threads"] == default_threads
    assert provenance["commit"] is None or len(provenance["commit"].removesuffix("-dirty")) == 40
    sessions = [json.loads(line) for line in (run_dir / "provenance.jsonl").read_text().splitlines()]
    assert len(sessions) == 1 and sessions[0]["at_step"] == 0 and sessions[0]["commit"] == provenance["commit"]

    # checkpoints: last has everything needed to resume, best the policy to deploy
    last, best = run_dir / "checkpoints" / "last", run_dir / "checkpoints" / "best"
    assert {MODEL_FILE, REPLAY_BUFFER_FILE, STATE_FILE, META_FILE} <= {p.name for p in last.iterdir()}
    assert json.loads((last / META_FILE).read_text())["num_timesteps"] == 1000
    assert {MODEL_FILE, STATE_FILE, META_FILE} <= {p.name for p in best.iterdir()}
    assert not list((run_dir / "checkpoints").glob("*.tmp"))
    previous = json.loads((run_dir / "checkpoints" / "last.prev" / META_FILE).read_text())  # the one before, kept whole
    assert previous["num_timesteps"] < 1000 and REPLAY_BUFFER_FILE in previous["files"]

    # learning curve
    image = Image.open(run_dir / "learning_curve.png")
    assert image.format == "PNG" and image.size[0] >= 300

    # TensorBoard: evaluations and training losses
    events = EventAccumulator(str(run_dir / "tb"))
    events.Reload()
    tags = events.Tags()["scalars"]
    assert {"eval/mean_reward", "train/critic_loss", "train/actor_loss", "rollout/ep_rew_mean"} <= set(tags)
    assert [event.step for event in events.Scalars("eval/mean_reward")] == [250, 500, 750, 1000]
    # the critic's value estimate against the true value (eval.value_bias, on by default)
    assert [event.step for event in events.Scalars("eval/overestimation")] == [250, 500, 750, 1000]

    # W&B offline run: config and metrics, including every evaluation
    (wandb_file,) = glob.glob(str(run_dir / "wandb" / "offline-run-*" / "run-*.wandb"))
    records = read_wandb_records(Path(wandb_file))
    run_record = next(r.run for r in records if r.WhichOneof("record_type") == "run")
    config_keys = {item.key for item in run_record.config.update}
    assert {"algo", "env", "seed", "total_timesteps"} <= config_keys
    history_rows = [
        {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in r.history.item}
        for r in records
        if r.WhichOneof("record_type") == "history"
    ]
    eval_rows = [row for row in history_rows if "eval/mean_reward" in row]
    assert [row["global_step"] for row in eval_rows] == [250, 500, 750, 1000]
    assert [row["eval/mean_reward"] for row in eval_rows] == pytest.approx([float(row["mean_return"]) for row in rows])
    for key in ("value_estimate", "true_value", "overestimation", "normalized_bias", "value_states"):
        assert [row[f"eval/{key}"] for row in eval_rows] == pytest.approx([float(row[key]) for row in rows]), key
    assert any("train/critic_loss" in row for row in history_rows)

    # the composed config is saved, and no credential landed anywhere: no file, no console output
    assert "inverted_pendulum" in (run_dir / "config.yaml").read_text()
    files = [path for path in tmp_path.rglob("*") if path.is_file()]  # the run folder and $HOME
    assert [path for path in files if FAKE_KEY.encode() in path.read_bytes()] == [] and len(files) > 10
    assert FAKE_KEY not in result.stdout + result.stderr
    # The records say a key was there, masked, and still read as what they were.
    assert f"+hydra.job.env_set.WANDB_API_KEY={MASK}" in sessions[0]["command"] and "logger=wandb" in sessions[0]["command"]
    assert provenance["command"] == sessions[0]["command"]
    assert yaml.safe_load((run_dir / ".hydra" / "hydra.yaml").read_text())["hydra"]["job"]["env_set"] == {
        "WANDB_API_KEY": MASK
    }
    # The publishing check finds nothing left to mask in the records it publishes.
    for name in ("config.yaml", "summary.json", "provenance.jsonl", "evaluations.csv"):
        assert find_secrets((run_dir / name).read_text()) == [], name

    if video:
        gif = Image.open(run_dir / "video.gif")
        assert gif.n_frames > 2


def test_run_experiment_reports_every_evaluation_and_returns_the_final_one(tmp_path):
    cfg = compose_config(SMOKE + ["logger=none", f"run_dir={tmp_path}"])
    reports: list[tuple[int, float]] = []
    final = run_experiment(cfg, report=lambda step, value: reports.append((step, value)))
    assert isinstance(final, float)
    assert [step for step, _ in reports] == [500, 1000, 1500, 2000]
    assert reports[-1][1] == final
    assert not (tmp_path / "tb").exists()  # logger=none


def test_summary_json_names_the_code_the_session_started_with(tmp_path, monkeypatch):
    """A commit made while a run trains (a long results run, the repository worked on beside it) must not be credited
    with the run: summary.json repeats the provenance taken when the session started, as provenance.jsonl has it."""
    from sb3_td3x.experiment.run import train

    real, calls = train.provenance, []

    def provenance_then_a_commit():
        calls.append(1)
        return {**real(), "commit": ("a" if len(calls) == 1 else "b") * 40}

    monkeypatch.setattr(train, "provenance", provenance_then_a_commit)
    run_experiment(compose_config(SMOKE + ["logger=none", f"run_dir={tmp_path}"]))
    summary = json.loads((tmp_path / "summary.json").read_text())
    started = json.loads((tmp_path / "provenance.jsonl").read_text().splitlines()[-1])
    assert summary["provenance"]["commit"] == started["commit"] == "a" * 40


class Pruned(Exception):
    pass


def test_a_report_that_raises_stops_the_run_with_a_checkpoint(tmp_path):
    cfg = compose_config(SMOKE + ["logger=tensorboard", f"run_dir={tmp_path}"])

    def report(step: int, value: float) -> None:
        if step >= 1000:
            raise Pruned(step)

    with pytest.raises(Pruned):
        run_experiment(cfg, report=report)
    meta = json.loads((tmp_path / "checkpoints" / "last" / META_FILE).read_text())
    assert meta["num_timesteps"] == 1000
    assert (tmp_path / "learning_curve.png").is_file()


def test_a_nan_loss_raises_training_diverged(tmp_path):
    import gymnasium as gym

    if "NaNPendulum-v0" not in gym.registry:
        gym.register("NaNPendulum-v0", entry_point=make_nan_pendulum, max_episode_steps=200)
    cfg = compose_config(["debug=smoke", "progress_bar=false", "logger=none", "env.id=NaNPendulum-v0", f"run_dir={tmp_path}"])
    with pytest.raises(TrainingDiverged, match=r"train/critic_loss became nan at step"):
        run_experiment(cfg)


def make_nan_pendulum():
    """Pendulum whose reward turns NaN after 600 steps (past learning_starts=500 of debug=smoke)."""
    import gymnasium as gym

    class NaNReward(gym.Wrapper):
        steps = 0

        def step(self, action):
            obs, reward, terminated, truncated, info = self.env.step(action)
            NaNReward.steps += 1
            return obs, (np.nan if NaNReward.steps > 600 else reward), terminated, truncated, info

    return NaNReward(gym.make("Pendulum-v1").unwrapped)


@pytest.mark.parametrize(
    "n_jobs, cores, threads",
    [(-1, 2, 1), (-1, 16, 1), (1, 8, 8), (2, 8, 4), (3, 8, 2), (-2, 8, 1), (-5, 8, 2), (16, 2, 1), (None, 8, None)],
)
def test_multirun_jobs_share_the_cores(n_jobs, cores, threads):
    """torch_threads=null in a multirun: the cores divided among the jobs joblib runs at once (None: one job at a
    time, all cores)."""
    assert threads_per_job(n_jobs, cores) == threads
