"""What a run folder guarantees under faults: one owner, resumes checked against the checkpoint, damaged files
survived, bad input refused in one paragraph. Each scenario runs ``run.py`` in subprocesses on real Pendulum runs.

Every run here computes the same 1000 steps (``debug=smoke`` shortened: training from step 200, an evaluation every
250 steps; seed 0, one thread), so each faulty history is compared with one uninterrupted run, to the last bit of the
weights and every evaluation: the reference, or ``half`` (its first 500 steps, checkpointed at 250 and 500).
"""

from __future__ import annotations

import csv
import json
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
import torch
import yaml

from sb3_td3x.experiment.cli import EXIT_CONFIG_ERROR, EXIT_NOT_WRITTEN
from sb3_td3x.experiment.run.lock import RunFolderBusy, RunFolderLock

REPO = Path(__file__).resolve().parents[2]
RUN = ["debug=smoke", "torch_threads=1", "logger=none", "progress_bar=false", "checkpoint.save_best=false"]
RUN += ["total_timesteps=1000", "algo.learning_starts=200", "eval.freq=250"]  # 800 training steps, 4 evaluations


def run_py(*args: str, wait: bool = True, timeout: float = 300) -> subprocess.CompletedProcess | subprocess.Popen:
    command = [sys.executable, "run.py", *args]
    if not wait:
        return subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=timeout, check=False)


def assert_one_paragraph(result: subprocess.CompletedProcess, *needles: str) -> None:
    assert result.returncode == EXIT_CONFIG_ERROR, (result.returncode, result.stderr[-3000:])
    assert "Traceback" not in result.stdout + result.stderr, result.stderr[-3000:]
    message = result.stderr.strip()
    assert message.startswith("Error:") and "\n" not in message, message
    for needle in needles:
        assert needle in message, message


def weights(run_dir: Path) -> dict[str, torch.Tensor]:
    with zipfile.ZipFile(run_dir / "checkpoints" / "last" / "model.zip") as archive, archive.open("policy.pth") as file:
        return torch.load(file, map_location="cpu")


def evaluations(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "evaluations.csv") as file:
        return [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader(file)]


def assert_same_run(run_dir: Path, reference: Path) -> None:
    assert evaluations(run_dir) == evaluations(reference)
    expected, got = weights(reference), weights(run_dir)
    for name, tensor in expected.items():
        assert torch.equal(got[name], tensor), name


def sessions(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "provenance.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """1000 steps never interrupted."""
    run_dir = tmp_path_factory.mktemp("reference") / "run"
    result = run_py(*RUN, f"run_dir={run_dir}")
    assert result.returncode == 0, result.stderr[-3000:]
    return run_dir


@pytest.fixture(scope="module")
def half(tmp_path_factory) -> Path:
    """The same run stopped at step 500, with checkpoints at 250 (``last.prev``, 50 steps into training) and 500
    (``last``)."""
    run_dir = tmp_path_factory.mktemp("half") / "run"
    result = run_py(*RUN, "total_timesteps=500", "checkpoint.freq=250", f"run_dir={run_dir}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["last", "last.prev"]
    return run_dir


def copy_of(half: Path, tmp_path: Path) -> Path:
    run_dir = tmp_path / "run"
    shutil.copytree(half, run_dir)
    return run_dir


def wait_until_locked(run_dir: Path, process: subprocess.Popen) -> None:
    deadline = time.time() + 120
    while True:
        assert process.poll() is None, process.communicate()[1][-3000:]
        assert time.time() < deadline
        try:
            RunFolderLock.check_free(run_dir)
        except RunFolderBusy:
            return
        time.sleep(0.05)


# One owner per run folder ------------------------------------------------------------------------------------------
def test_a_second_process_is_refused_and_the_first_finishes_as_if_alone(tmp_path, half, reference):
    """While a process holds the folder (a resume here; a new run takes the same lock, ``RunFolder.claim``), a second
    resume and a new run in that folder are both refused, write nothing, and the first ends as if it had been alone."""
    run_dir = copy_of(half, tmp_path)
    hydra_record = (run_dir / ".hydra" / "config.yaml").read_text()
    first = run_py(f"resume={run_dir}", "total_timesteps=1000", "checkpoint.freq=25", wait=False)  # often in a save
    wait_until_locked(run_dir, first)
    first.send_signal(signal.SIGSTOP)  # paused while it holds the folder (a requeued job beside a stalled one)
    try:
        resumed = run_py(f"resume={run_dir}", "total_timesteps=1000")
        again = run_py(*RUN, f"run_dir={run_dir}")
    finally:
        first.send_signal(signal.SIGCONT)
    assert_one_paragraph(resumed, f"{run_dir} is in use by process {first.pid}")
    assert_one_paragraph(again, f"{run_dir} is in use by process {first.pid}")
    _, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr[-3000:]
    assert_same_run(run_dir, reference)
    # The refused ones wrote nothing, Hydra's records included: only the first's own resumed_<date>, the new run's
    # .hydra/config.yaml not written over, one provenance line per session that trained.
    assert len(list((run_dir / ".hydra").glob("resumed_*"))) == 1
    assert (run_dir / ".hydra" / "config.yaml").read_text() == hydra_record
    assert [s["at_step"] for s in sessions(run_dir)] == [0, 500]


# Resume checked against the checkpoint -----------------------------------------------------------------------------
def test_resume_refuses_what_would_change_the_computation_and_records_what_it_applies(tmp_path, half, reference):
    """A resume is checked against the checkpoint, never against ``config.yaml``: here that file is damaged, which
    neither changes what is refused nor stops the resume that follows, and it is written whole again."""
    run_dir = copy_of(half, tmp_path)
    text = (run_dir / "config.yaml").read_text()
    (run_dir / "config.yaml").write_text(text[: len(text) // 3])  # cut inside a mapping: not YAML any more
    config_before = (run_dir / "config.yaml").read_text()
    refused = run_py(
        f"resume={run_dir}", "algo.learning_rate=0.002", "algo.batch_size=32", "algo.net_arch=[32]", "seed=5", "n_envs=2"
    )
    assert_one_paragraph(
        refused,
        "algo.learning_rate: 0.001 in the checkpoint, 0.002 asked",
        "algo.batch_size: 64 in the checkpoint, 32 asked",
        "algo.net_arch: [64, 64] in the checkpoint, [32] asked",
        "seed: 0 in the checkpoint, 5 asked",
        "n_envs: 1 in the checkpoint, 2 asked",
    )
    assert (run_dir / "config.yaml").read_text() == config_before  # a refused resume leaves the folder as it was
    assert not list((run_dir / ".hydra").glob("resumed_*"))

    applied = run_py(f"resume={run_dir}", "total_timesteps=1000", "checkpoint.freq=100")
    assert applied.returncode == 0, applied.stderr[-3000:]
    assert_same_run(run_dir, reference)
    last = sessions(run_dir)[-1]
    assert last["at_step"] == 500 and last["resumed_from"] == "checkpoints/last"
    assert last["changes"] == {
        "total_timesteps": {"from": 500, "to": 1000},
        "checkpoint.freq": {"from": 250, "to": 100},
    }
    rewritten = yaml.safe_load((run_dir / "config.yaml").read_text())  # whole again, and what trained
    expected = yaml.safe_load((half / "config.yaml").read_text())
    expected.update(total_timesteps=1000, resume=str(run_dir), run_dir=str(run_dir))
    expected["checkpoint"]["freq"] = 100
    assert rewritten == expected


def test_a_new_run_in_a_folder_that_holds_a_run_is_refused(tmp_path, half):
    run_dir = copy_of(half, tmp_path)
    hydra_record = (run_dir / ".hydra" / "config.yaml").read_text()
    result = run_py(*RUN, "seed=3", f"run_dir={run_dir}")
    assert_one_paragraph(result, f"run_dir={run_dir} already holds a run", "a checkpoint at step 500", f"resume={run_dir}")
    assert (run_dir / ".hydra" / "config.yaml").read_text() == hydra_record


# A damaged checkpoint falls back to the one before ----------------------------------------------------------------
@pytest.mark.parametrize("damage", ["truncate replay_buffer.pkl", "truncate model.zip", "truncate state.pkl", "delete model.zip"])
def test_a_damaged_checkpoint_falls_back_to_the_one_before(tmp_path, half, damage):
    """Resumed to ``half``'s own end (step 500) from its checkpoint at 250: the same run as ``half``."""
    run_dir = copy_of(half, tmp_path)
    action, name = damage.split()
    path = run_dir / "checkpoints" / "last" / name
    if action == "delete":
        path.unlink()
    else:
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    result = run_py(f"resume={run_dir}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    problem = f"{name} is missing" if action == "delete" else f"{name} has"
    assert f"Checkpoint {run_dir}/checkpoints/last is not usable: {problem}" in result.stdout
    assert f"Resuming from the older checkpoint {run_dir}/checkpoints/last.prev (step 250) instead" in result.stdout
    assert_same_run(run_dir, half)
    assert sessions(run_dir)[-1]["resumed_from"] == "checkpoints/last.prev"
    assert (run_dir / "checkpoints" / "last.damaged").is_dir()  # kept for inspection, never deleted


def test_a_save_cut_between_its_renames_resumes_from_the_new_checkpoint(tmp_path, half, reference):
    run_dir = copy_of(half, tmp_path)
    checkpoints = run_dir / "checkpoints"
    # The state a kill leaves right after the new checkpoint was written whole and the old one moved aside.
    shutil.rmtree(checkpoints / "last.prev")
    (checkpoints / "last").rename(checkpoints / "last.tmp")
    shutil.copytree(half / "checkpoints" / "last.prev", checkpoints / "last.prev")
    result = run_py(f"resume={run_dir}", "total_timesteps=1000")
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"Resuming {run_dir} at step 500" in result.stdout
    assert_same_run(run_dir, reference)


def test_no_whole_checkpoint_is_one_paragraph_and_deletes_nothing(tmp_path, half):
    run_dir = copy_of(half, tmp_path)
    for name in ("last", "last.prev"):
        (run_dir / "checkpoints" / name / "state.pkl").write_bytes(b"\0" * 10)
    result = run_py(f"resume={run_dir}")
    assert_one_paragraph(result, "no checkpoint of this run could be loaded", "last: state.pkl has 10 bytes")
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["last", "last.prev"]


# A full disk ------------------------------------------------------------------------------------------------------
@pytest.fixture
def small_disk(tmp_path):
    """A 700 kB tmpfs: room for the first checkpoints of the smoke run, not for all of them (needs root)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=700k", "tmpfs", str(mount)], capture_output=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small file system here: {done.stderr.decode().strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_stops_with_one_paragraph_and_the_run_resumes(small_disk, reference):
    run_dir = small_disk / "run"
    result = run_py(*RUN, "checkpoint.freq=250", f"run_dir={run_dir}")
    assert result.returncode == EXIT_NOT_WRITTEN, result.stderr[-3000:]
    message = result.stderr.strip()
    assert "Traceback" not in result.stdout + message and "\n" not in message, message
    assert "No space left on device" in message and f"python run.py resume={run_dir}" in message
    assert not (run_dir / "checkpoints" / "last.tmp").exists()
    curve = run_dir / "learning_curve.png"
    assert not curve.exists() or curve.stat().st_size > 0
    subprocess.run(["mount", "-o", "remount,size=20m", str(small_disk)], check=True)  # space freed
    resumed = run_py(f"resume={run_dir}")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(run_dir, reference)


# Bad input: one paragraph, exit status 2 --------------------------------------------------------------------------
BAD_INPUTS = {
    "algo.buffer_size=1000000000000": "needs about",
    "logger.log_interval=0": "logger.log_interval=0 must be >= 1",
    "algo.policy=CnnPolicy": "algo.policy=CnnPolicy needs image observations",
    "+env.kwargs.foo=1": "unexpected keyword argument 'foo'",
    "seeds=[]": "seeds=[] must list distinct seeds",
    "algo.taau=0.1": "takes no argument 'taau'. Did you mean algo.tau?",
    "run_dir=<a file>": "is a file, not a folder",
    "algo._target_=nosuchmodule.MyTD3": "cannot be imported",  # and Hydra's own log line of it not printed too
}


def test_bad_input_is_one_paragraph(tmp_path):
    (tmp_path / "a_file").write_text("")
    processes = {}
    for arg in BAD_INPUTS:  # side by side: each fails within seconds
        arg_line = arg.replace("<a file>", str(tmp_path / "a_file"))
        args = [*RUN, arg_line] + ([] if arg.startswith("run_dir") else [f"run_dir={tmp_path / arg.split('=')[0]}"])
        processes[arg] = (args, run_py(*args, wait=False))
    for arg, (args, process) in processes.items():
        stdout, stderr = process.communicate(timeout=300)
        result = subprocess.CompletedProcess(args, process.returncode, stdout, stderr)
        assert_one_paragraph(result, BAD_INPUTS[arg])
    assert not (tmp_path / "algo.buffer_size" / "checkpoints").exists()
