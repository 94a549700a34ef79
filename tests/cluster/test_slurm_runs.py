"""``run.py`` on a real SLURM: a Hydra multirun as SLURM jobs, and a run whose job is requeued mid-run.

What docs/cluster.md tells a user to type, run against the one-node cluster of ``.ci/slurm.sh``.
"""

from __future__ import annotations

import io
import json
import subprocess
import zipfile
from pathlib import Path

import pandas as pd
import pytest
import torch

from conftest import REPO, job_fields, python, requeue_now, wait_for  # tests/cluster/conftest.py

SMOKE = ["debug=smoke", "progress_bar=false", "logger=none"]
SLURM_JOB = ["hydra/launcher=submitit_slurm", "hydra.launcher.cpus_per_task=1", "hydra.launcher.timeout_min=15"]


def _sessions(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "provenance.jsonl").read_text().splitlines()]


def test_multirun_of_two_seeds_runs_as_two_slurm_jobs(slurm, tmp_path):
    sweep_dir = tmp_path / "multirun"
    done = subprocess.run(
        [python(), "run.py", "-m", *SLURM_JOB, "seed=0,1", *SMOKE, f"hydra.sweep.dir={sweep_dir}"],
        cwd=REPO, env=slurm, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-4000:]
    folders = sorted(p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name for p in folders] == ["0_pendulum_td3_seed0", "1_pendulum_td3_seed1"]
    jobs = set()
    for seed, folder in enumerate(folders):
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["seed"] == seed and summary["total_timesteps"] == 2000
        assert summary["provenance"]["machine"]["torch_threads"] == 1  # the job's cpus_per_task
        (session,) = _sessions(folder)
        assert session["start"] == "new" and session["job"]["scheduler"] == "slurm" and session["job"]["restarts"] == 0
        jobs.add(session["job"]["job_id"])
    assert len(jobs) == 2, "two SLURM jobs"
    # This cluster has no accounting: one line says so, not a warning at every poll
    assert "Bypassing sacct error" not in done.stdout + done.stderr
    assert (done.stdout + done.stderr).count("following the jobs with scontrol") == 1


def _model_tensors(checkpoint: Path) -> dict[str, torch.Tensor]:
    tensors = {}
    with zipfile.ZipFile(checkpoint / "model.zip") as archive:
        for name in archive.namelist():
            if name.endswith(".pth"):
                state = torch.load(io.BytesIO(archive.read(name)), map_location="cpu", weights_only=False)
                flat = state if isinstance(state, dict) else {}
                for key, value in _flatten(flat, name):
                    tensors[key] = value
    return tensors


def _flatten(tree, prefix):
    if isinstance(tree, torch.Tensor):
        yield prefix, tree
    elif isinstance(tree, dict):
        for key, value in tree.items():
            yield from _flatten(value, f"{prefix}/{key}")
    elif isinstance(tree, (list, tuple)):
        for index, value in enumerate(tree):
            yield from _flatten(value, f"{prefix}/{index}")


@pytest.mark.parametrize("how", ["scontrol requeue", "time limit"])
def test_a_requeued_run_ends_in_its_folder_bit_identical_to_an_uninterrupted_run(slurm, tmp_path, how):
    """A requeue after the run's first checkpoint (``scontrol requeue``: SIGTERM; or submitit's time-limit signal,
    SIGUSR2, after which submitit requeues the job): a checkpoint, then the job starts again in the same folder
    (found by its job id) and resumes; it ends with the weights and evaluations of a run never stopped."""
    length = ["total_timesteps=4000", "checkpoint.freq=1000"]
    sweep_dir = tmp_path / "multirun"
    launcher = subprocess.Popen(
        [python(), "run.py", "-m", *SLURM_JOB, "seed=0", *SMOKE, *length, f"hydra.sweep.dir={sweep_dir}"],
        cwd=REPO, env=slurm, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    reference = subprocess.Popen(  # the same run, never stopped, on this machine (one thread, as the job's one CPU)
        [python(), "run.py", "seed=0", *SMOKE, *length, "torch_threads=1", f"run_dir={tmp_path / 'reference'}"],
        cwd=REPO, env=slurm, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        run_dir = sweep_dir / "0_pendulum_td3_seed0"
        wait_for(lambda: (run_dir / "checkpoints" / "last" / "meta.json").is_file(), "the first checkpoint", 300, launcher)
        job_id = _sessions(run_dir)[0]["job"]["job_id"]
        requeue_now(job_id, how)
        out, err = launcher.communicate(timeout=600)
        assert launcher.returncode == 0, err[-4000:]
        assert reference.wait(timeout=600) == 0, reference.communicate()[1][-4000:]
    finally:
        launcher.kill()
        reference.kill()
    assert job_fields(job_id).get("Restarts") == "1"

    first, second = _sessions(run_dir)
    assert first["start"] == "new" and first["job"]["restarts"] == 0
    assert second["start"] == "requeue" and second["job"]["restarts"] == 1 and second["job"]["job_id"] == job_id
    assert second["resumed_from"] == "checkpoints/last" and 1000 <= second["at_step"] < 4000
    assert (run_dir / ".hydra" / "requeued_1" / "overrides.yaml").is_file()
    assert [p.name for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith(".")] == [run_dir.name]

    columns = ["timesteps", "mean_return", "std_return", "mean_length"]
    requeued = pd.read_csv(run_dir / "evaluations.csv")
    never_stopped = pd.read_csv(tmp_path / "reference" / "evaluations.csv")
    pd.testing.assert_frame_equal(requeued[columns], never_stopped[columns])
    assert requeued["timesteps"].iloc[-1] == 4000
    mine, theirs = _model_tensors(run_dir / "checkpoints" / "last"), _model_tensors(tmp_path / "reference" / "checkpoints" / "last")
    assert mine.keys() == theirs.keys() and len(mine) > 10
    for key in mine:
        assert torch.equal(mine[key], theirs[key]), key
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["final_mean_return"] == json.loads((tmp_path / "reference" / "summary.json").read_text())["final_mean_return"]
