"""``python run.py seeds=[...]``: the seeds trained together (in one process, or in one per core) write the folders
their lone ``seed=`` runs write, with the same evaluations, weights and replay buffers (to the bit on a CPU); a batch
stopped by SIGTERM resumes, whole, from any seed's folder."""

from __future__ import annotations

import csv
import io
import json
import os
import pickle
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
import torch as th
from omegaconf import OmegaConf

from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.run.checkpoints import META_FILE
from sb3_td3x.experiment.run.folder import seed_folders

REPO = Path(__file__).resolve().parents[2]
# Pendulum-v1, 600 steps, training from step 150, evaluated every 150 steps on 2 episodes. Short on purpose: the
# batched update equals the lone one to float rounding, and TD3 on Pendulum magnifies rounding as training goes on
# (measured: relative differences of 1e-8 in the mean return after 300 updates, 1e-5 after 600, 1e-2 after 900).
RUN = [
    "torch_threads=1",  # runs side by side beside the other test worker's: no more threads than cores
    "debug=smoke",
    "env=pendulum",
    "total_timesteps=600",
    "algo.learning_starts=150",
    "eval.freq=150",
    "algo.net_arch=[32,32]",
    "logger=none",
    "progress_bar=false",
]


def run_py(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "run.py", *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def finish(process: subprocess.Popen, timeout: float = 300) -> tuple[str, str]:
    stdout, stderr = process.communicate(timeout=timeout)
    assert process.returncode == 0, stderr[-3000:]
    return stdout, stderr


def evaluations(run_dir: Path) -> list[dict[str, float]]:
    with open(run_dir / "evaluations.csv") as file:
        return [{key: float(value) for key, value in row.items() if key != "time"} for row in csv.DictReader(file)]


def assert_same_evaluations(ours: Path, theirs: Path) -> None:
    a, b = evaluations(ours), evaluations(theirs)
    assert [row["timesteps"] for row in a] == [row["timesteps"] for row in b] == [150, 300, 450, 600]
    for row, lone in zip(a, b):
        for key in ("mean_return", "std_return", "value_estimate", "true_value"):
            assert row[key] == pytest.approx(lone[key], rel=1e-4, abs=1e-4, nan_ok=True), (ours, row["timesteps"], key)


# Hopper-v5 with TD3's 400-300 networks (at 64-64 the old seed-stacked update happened to round as the lone one; at
# 400-300 it differed after 150 updates), 1000 steps: 500 gradient steps after 500 random ones.
HOPPER_STEPS = 1000
HOPPER = [
    "env=hopper",
    f"total_timesteps={HOPPER_STEPS}",
    "algo.learning_starts=500",
    "eval.freq=500",
    "eval.n_episodes=2",
    "logger=none",
    "progress_bar=false",
    "algo.batch_size=100",  # the paper's
    "torch_threads=1",  # four processes side by side: more threads than cores would wait on each other
]


def summary_of(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def final_state(run_dir: Path) -> tuple[list[dict[str, str]], dict[str, th.Tensor], dict[str, th.Tensor]]:
    """The evaluations (as written), the final weights and the replay buffer's contents of a finished run."""
    with open(run_dir / "evaluations.csv") as file:
        rows = [{key: value for key, value in row.items() if key != "wall_time"} for row in csv.DictReader(file)]
    last = run_dir / "checkpoints" / "last"
    assert json.loads((last / META_FILE).read_text())["num_timesteps"] == HOPPER_STEPS
    with zipfile.ZipFile(last / "model.zip") as archive:
        weights = th.load(io.BytesIO(archive.read("policy.pth")), weights_only=True)
    with open(last / "replay_buffer.pkl", "rb") as file:
        buffer = pickle.load(file)
    stored = {name: th.as_tensor(getattr(buffer, name)) for name in ("observations", "next_observations", "actions", "rewards", "dones")}
    return rows, weights, stored


def largest_difference(ours: dict[str, th.Tensor], theirs: dict[str, th.Tensor]) -> str:
    gaps = {name: (ours[name].double() - theirs[name].double()).abs().max().item() for name in theirs}
    name = max(gaps, key=gaps.get)
    return f"largest difference {gaps[name]:.3g} in {name}"


def test_each_batched_seed_is_its_lone_run_to_the_bit_on_hopper(tmp_path):
    """``seeds=[0,1,2]`` in two processes against three lone ``seed=i`` runs: every seed's evaluations, final weights
    and replay buffer bit-identical to its lone run's, after 500 gradient steps."""
    seeds = (0, 1, 2)
    # Two processes (seed_processes, as on two cores by default): seeds 0 and 2 batched in one, seed 1 in the other.
    processes = [run_py(*HOPPER, "seeds=[0,1,2]", "seed_processes=2", f"run_dir={tmp_path / 'batch'}")]
    processes += [run_py(*HOPPER, f"seed={seed}", f"run_dir={tmp_path / f'lone{seed}'}") for seed in seeds]
    for process in processes:
        finish(process, timeout=1500)
    for seed, together in zip(seeds, ([0, 2], [1], [0, 2])):
        summary = json.loads((tmp_path / "batch" / f"seed{seed}" / "summary.json").read_text())
        assert summary["trained_with_seeds"] == [0, 1, 2] and summary["trained_together"] == together
        assert summary["update_path"] == "eager"  # each seed's own update (a short run's: eager)
    for seed in seeds:
        (rows, weights, buffer), (lone_rows, lone_weights, lone_buffer) = (
            final_state(tmp_path / "batch" / f"seed{seed}"),
            final_state(tmp_path / f"lone{seed}"),
        )
        assert [row["timesteps"] for row in lone_rows] == ["500", "1000"]
        assert rows == lone_rows, f"seed {seed}: evaluations {rows} != {lone_rows}"
        assert weights.keys() == lone_weights.keys()
        assert all(th.equal(weights[k], lone_weights[k]) for k in weights), (
            f"seed {seed} weights: {largest_difference(weights, lone_weights)}"
        )
        assert all(th.equal(buffer[k], lone_buffer[k]) for k in buffer), (
            f"seed {seed} replay buffer: {largest_difference(buffer, lone_buffer)}"
        )


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> tuple[Path, Path, str]:
    """``seeds=[0,1]`` trained together in one process, and seed 1's lone run beside it (2 cores), never stopped: the
    folders, evaluations and report of a batch, and what every stopped and resumed ``seeds=[0,1]`` of this file must
    end as (each seed computes its lone run, in whichever process it trains). Returns the batch's folder, the lone
    run's folder and the batch's stdout."""
    root = tmp_path_factory.mktemp("uninterrupted")
    lone = run_py(*RUN, "seed=1", f"run_dir={root / 'lone'}")
    stdout, _ = finish(run_py(*RUN, "seeds=[0,1]", "seed_processes=1", f"run_dir={root / 'batch'}"))
    finish(lone)
    return root / "batch", root / "lone", stdout


def test_a_batch_writes_the_folders_and_evaluations_of_its_lone_runs(uninterrupted):
    batch_dir, lone_dir, stdout = uninterrupted
    folders = [batch_dir / "seed0", batch_dir / "seed1"]
    for folder in folders:
        for name in ("config.yaml", "evaluations.csv", "summary.json", "learning_curve.png", "provenance.jsonl"):
            assert (folder / name).is_file(), folder / name
        assert (folder / "checkpoints" / "last" / META_FILE).is_file()
        config = OmegaConf.load(folder / "config.yaml")
        assert list(config.seeds) == [0, 1] and config.seed_run_dirs == [str(f) for f in folders]
        assert summary_of(folder)["update_path"] == "eager" and summary_of(folder)["trained_together"] == [0, 1]
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["trained_with_seeds"] == [0, 1]
    assert OmegaConf.load(folders[1] / "config.yaml").seed == 1
    assert_same_evaluations(folders[1], lone_dir)
    # The aggregate across seeds, mean and IQM, is printed at the end.
    assert "Across seeds (mean" in stdout and "Across seeds (iqm" in stdout and "| Pendulum-v1 | td3 | 2 | 600 |" in stdout


def test_a_batch_stopped_by_sigterm_resumes_from_any_seed_folder(tmp_path, uninterrupted):
    batch_dir, reference_dir = tmp_path / "stopped", uninterrupted[0]
    args = [*RUN, "seeds=[0,1]", "seed_processes=2", "checkpoint.freq=100000"]  # a process per seed, as on 2 cores
    process = run_py(*args, f"run_dir={batch_dir}")
    deadline = time.time() + 300
    while not (batch_dir / "seed1" / "evaluations.csv").is_file() or len(evaluations(batch_dir / "seed1")) < 2:
        assert process.poll() is None and time.time() < deadline, "the batch ended before it could be stopped"
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    assert "Traceback" not in stderr and f"python run.py resume={batch_dir / 'seed0'}" in stderr
    stopped_at = [
        json.loads((batch_dir / f"seed{s}" / "checkpoints" / "last" / META_FILE).read_text())["num_timesteps"] for s in (0, 1)
    ]
    # Stopped mid-run: seed 1 after its second evaluation; seed 0, in its own process, wherever it was by then.
    assert stopped_at[1] >= 300 and all(0 < step < 600 for step in stopped_at), stopped_at

    stdout, _ = finish(run_py(f"resume={batch_dir / 'seed1'}", "progress_bar=false"))  # any seed's folder
    assert "Resuming" in stdout and "Training seeds [0, 1] in 2 processes" in stdout
    for seed in (0, 1):
        assert_same_evaluations(batch_dir / f"seed{seed}", reference_dir / f"seed{seed}")
        sessions = (batch_dir / f"seed{seed}" / "provenance.jsonl").read_text().splitlines()
        assert len(sessions) == 2


def test_seed_folders_are_named_as_lone_runs():
    assert seed_folders("runs/hopper/td3/seed0/2026-01-01_00-00-00", [0, 2], seed=0) == [
        Path("runs/hopper/td3/seed0/2026-01-01_00-00-00"),
        Path("runs/hopper/td3/seed2/2026-01-01_00-00-00"),
    ]
    assert seed_folders("/tmp/mine", [0, 1], seed=0) == [Path("/tmp/mine/seed0"), Path("/tmp/mine/seed1")]
    assert seed_folders("/tmp/seed0/x", [0, 1]) == [Path("/tmp/seed0/x/seed0"), Path("/tmp/seed0/x/seed1")]
    # seed is the first of seeds unless given, so Hydra makes the first seed's folder and the others are named alike
    assert compose_config(["seeds=[3,4]"]).seed == 3 and compose_config(["seeds=[3,4]", "seed=4"]).seed == 4
    assert compose_config([]).seed == 0 and "seed3" in compose_config(["seeds=[3,4]"]).run_dir


def test_bad_seeds_and_seed_processes_are_refused_with_a_message():
    """Each bad value ends run.py before anything trains: exit 2, what was wrong, no traceback. The three commands
    side by side (each one's cost is the interpreter's start)."""
    cases = {
        "seeds=[1,1]": "seeds=[1, 1] must list distinct seeds",
        "seeds=[1,2] seed=5": "seed=5 is not one of seeds=[1, 2]",
        "seeds=[0,1] seed_processes=0": "seed_processes=0 must be >= 1 or null",
    }
    processes = {case: run_py(*RUN, *case.split()) for case in cases}
    for case, process in processes.items():
        _, stderr = process.communicate(timeout=120)
        assert process.returncode == 2 and cases[case] in stderr and "Traceback" not in stderr, (case, stderr[-3000:])


def test_a_killed_seed_process_is_one_paragraph_the_others_finish_and_resume_continues_it(tmp_path, uninterrupted):
    """seeds=[0,1] in two processes; the one training seed 1 is killed (SIGKILL, as the OOM killer does): seed 0
    finishes, run.py says which seeds were lost and how to continue (exit 5), and resume= continues seed 1 from its
    last checkpoint to the same evaluations as an uninterrupted run."""
    args = [*RUN, "seeds=[0,1]", "seed_processes=2", "checkpoint.freq=150"]
    process = run_py(*args, f"run_dir={tmp_path / 'killed'}")
    killed = tmp_path / "killed" / "seed1"
    deadline = time.time() + 300
    while not (killed / "evaluations.csv").is_file() or len(evaluations(killed)) < 2:
        assert process.poll() is None and time.time() < deadline, "the run ended before it could be killed"
        time.sleep(0.05)
    owner = json.loads((killed / ".lock").read_text())["pid"]  # the process that owns seed 1's folder
    assert owner != process.pid
    os.kill(owner, signal.SIGKILL)
    _, stderr = process.communicate(timeout=300)
    assert process.returncode == 5, stderr[-3000:]
    assert "Traceback" not in stderr and "The process training seeds [1] ended with exit code -9" in stderr
    assert f"python run.py resume={tmp_path / 'killed' / 'seed0'}" in stderr
    assert (tmp_path / "killed" / "seed0" / "summary.json").is_file()  # the other seed finished
    assert not (killed / "summary.json").is_file()
    finish(run_py(f"resume={killed}", "progress_bar=false"))
    for seed in (0, 1):
        assert_same_evaluations(tmp_path / "killed" / f"seed{seed}", uninterrupted[0] / f"seed{seed}")


def test_seed_processes_one_per_core_on_a_cpu_at_most_one_per_seed(monkeypatch):
    from sb3_td3x.experiment import jobs
    from sb3_td3x.experiment.launch.seed_processes import groups_of, processes_for

    monkeypatch.setattr(jobs, "available_cores", lambda: 2)
    assert processes_for(compose_config(["seeds=[0,1,2,3]", "device=cpu"])) == 2
    assert processes_for(compose_config(["seeds=[0,1,2,3]", "device=cpu", "torch_threads=1"])) == 1
    assert processes_for(compose_config(["seeds=[0,1,2,3]", "device=cpu", "seed_processes=3"])) == 3
    assert processes_for(compose_config(["seeds=[0,1]", "device=cpu", "seed_processes=8"])) == 2
    monkeypatch.setattr(jobs, "available_cores", lambda: 16)
    assert processes_for(compose_config(["seeds=[0,1,2]", "device=cpu"])) == 3
    assert processes_for(compose_config(["seeds=[0,1,2]", "device=cuda"])) == 3  # the same rule on a GPU (under MPS)
    assert groups_of(5, 2) == [[0, 2, 4], [1, 3]] and groups_of(2, 2) == [[0], [1]]


def test_a_seed_process_error_crosses_to_run_py_whole():
    from sb3_td3x.experiment.errors import ConfigError, TrainingDiverged, TrainingInterrupted
    from sb3_td3x.experiment.launch.seed_processes import _portable, _rebuilt

    diverged = _rebuilt(_portable(TrainingDiverged("train/critic_loss", float("nan"), 812)))
    assert isinstance(diverged, TrainingDiverged) and "became nan at step 812" in str(diverged)
    stopped = _rebuilt(_portable(TrainingInterrupted("SIGTERM", 143, 300, "/runs/x/seed1")))
    assert isinstance(stopped, TrainingInterrupted) and (stopped.exit_code, stopped.num_timesteps) == (143, 300)
    assert isinstance(_rebuilt(_portable(ConfigError("bad"))), ConfigError)
    other = _rebuilt(_portable(ZeroDivisionError("x")))
    assert "ZeroDivisionError: x" in str(other)


def test_seed_processes_whose_run_py_is_killed_checkpoint_stop_and_resume(tmp_path, uninterrupted):
    """run.py killed with SIGKILL (nothing of it runs again): its seed processes notice, checkpoint and stop rather
    than train on unwatched, and resume= continues both seeds to the evaluations of an uninterrupted run."""
    args = [*RUN, "seeds=[0,1]", "seed_processes=2", "checkpoint.freq=100000"]
    process = run_py(*args, f"run_dir={tmp_path / 'orphaned'}")
    folders = [tmp_path / "orphaned" / f"seed{seed}" for seed in (0, 1)]
    deadline = time.time() + 300
    while not all((f / "evaluations.csv").is_file() and len(evaluations(f)) >= 2 for f in folders):
        assert process.poll() is None and time.time() < deadline, "the run ended before it could be killed"
        time.sleep(0.05)
    owners = [json.loads((f / ".lock").read_text())["pid"] for f in folders]
    process.kill()
    process.communicate(timeout=60)
    while any(Path(f"/proc/{pid}").exists() for pid in owners):  # they stop on their own
        assert time.time() < deadline + 60, "the seed processes went on after run.py was killed"
        time.sleep(0.1)
    stopped_at = [json.loads((f / "checkpoints" / "last" / META_FILE).read_text())["num_timesteps"] for f in folders]
    # A seed stops at its next step once its watch (every 0.5 s) sees run.py gone; one that reached its last step
    # within that time ends its run complete (600, summary written) instead: a true record, which resume= leaves be.
    # At least one seed must have stopped mid-run, or nothing here was tested.
    ended = [step == 600 and (f / "summary.json").is_file() for step, f in zip(stopped_at, folders)]
    assert all(300 <= step < 600 or done for step, done in zip(stopped_at, ended)), stopped_at
    assert any(step < 600 for step in stopped_at), f"both seeds finished before run.py's death was seen: {stopped_at}"
    finish(run_py(f"resume={folders[0]}", "progress_bar=false"))
    for seed, folder in zip((0, 1), folders):
        assert_same_evaluations(folder, uninterrupted[0] / f"seed{seed}")
