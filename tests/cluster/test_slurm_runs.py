"""``run.py`` on a real SLURM: a Hydra multirun as SLURM jobs, and a run whose job is requeued mid-run.

What docs/cluster.md tells a user to type, run against the one-node cluster of ``.ci/slurm.sh``.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch
from slurm_helpers import REPO, evaluations, job_fields, python, requeue_now, tensors, wait_for

SMOKE = ["debug=smoke", "progress_bar=false", "logger=none"]
SLURM_JOB = ["hydra/launcher=submitit_slurm", "hydra.launcher.cpus_per_task=1", "hydra.launcher.timeout_min=15"]
# The requeued runs: a checkpoint every 1000 steps, requeued after the first, 2000 steps left to train after it.
LENGTH = ["total_timesteps=3000", "checkpoint.freq=1000"]


@pytest.fixture(scope="module")
def uninterrupted(slurm, tmp_path_factory):
    """What every requeued run of this file must end as: ``run.py seeds=[0,1]`` never stopped, in two processes of
    one thread (as a job's two CPUs give; seed 0's folder is also the lone ``seed=0`` run's, bit for bit), on this
    machine, started at the first test that asks and trained beside its job. Yields a function that waits for it
    and returns seed ``s``'s folder."""
    folder = tmp_path_factory.mktemp("uninterrupted")
    process = subprocess.Popen(
        [python(), "run.py", *SMOKE, *LENGTH, "seeds=[0,1]", "torch_threads=2", f"run_dir={folder}"],
        cwd=REPO, env=slurm, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    ended = []

    def seed_folder(seed: int) -> Path:
        if not ended:
            ended.append(process.communicate(timeout=600)[1])
        assert process.returncode == 0, ended[0][-4000:]
        return folder / f"seed{seed}"

    yield seed_folder
    process.kill()


def _sessions(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "provenance.jsonl").read_text().splitlines()]


def test_multirun_of_two_seeds_runs_as_two_slurm_jobs(slurm, tmp_path):
    sweep_dir = tmp_path / "multirun"
    done = subprocess.run(
        [python(), "run.py", "-m", *SLURM_JOB, "seed=0,1", *SMOKE, "total_timesteps=1000", f"hydra.sweep.dir={sweep_dir}"],
        cwd=REPO, env=slurm, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-4000:]
    folders = sorted(p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name for p in folders] == ["0_pendulum_td3_seed0", "1_pendulum_td3_seed1"]
    jobs = set()
    for seed, folder in enumerate(folders):
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["seed"] == seed and summary["total_timesteps"] == 1000
        assert summary["provenance"]["machine"]["torch_threads"] == 1  # the job's cpus_per_task
        (session,) = _sessions(folder)
        assert session["start"] == "new" and session["job"]["scheduler"] == "slurm" and session["job"]["restarts"] == 0
        jobs.add(session["job"]["job_id"])
    assert len(jobs) == 2, "two SLURM jobs"
    # This cluster has no accounting: one line says so, not a warning at every poll
    assert "Bypassing sacct error" not in done.stdout + done.stderr
    assert (done.stdout + done.stderr).count("following the jobs with scontrol") == 1


@pytest.mark.parametrize("how", ["scontrol requeue", "time limit"])
def test_a_requeued_run_ends_in_its_folder_bit_identical_to_an_uninterrupted_run(slurm, tmp_path, how, uninterrupted):
    """A requeue after the run's first checkpoint (``scontrol requeue``: SIGTERM; or submitit's time-limit signal,
    SIGUSR2, after which submitit requeues the job): a checkpoint, then the job starts again in the same folder
    (found by its job id) and resumes; it ends with the weights and evaluations of a run never stopped."""
    sweep_dir = tmp_path / "multirun"
    launcher = subprocess.Popen(
        [python(), "run.py", "-m", *SLURM_JOB, "seed=0", *SMOKE, *LENGTH, f"hydra.sweep.dir={sweep_dir}"],
        cwd=REPO, env=slurm, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        run_dir = sweep_dir / "0_pendulum_td3_seed0"
        wait_for(lambda: (run_dir / "checkpoints" / "last" / "meta.json").is_file(), "the first checkpoint", 300, launcher)
        (job_id,) = [p.name for p in (sweep_dir / ".submitit").iterdir() if p.name.isdigit()]  # submitit's folder: the id
        requeue_now(job_id, how)
        out, err = launcher.communicate(timeout=600)
        assert launcher.returncode == 0, err[-4000:]
    finally:
        launcher.kill()
        subprocess.run(["scancel", "--name", "run"], capture_output=True)  # whatever failed, no job is left behind
    assert job_fields(job_id).get("Restarts") == "1"

    first, second = _sessions(run_dir)
    assert first["start"] == "new" and first["job"]["restarts"] == 0
    assert second["start"] == "requeue" and second["job"]["restarts"] == 1 and second["job"]["job_id"] == job_id
    assert second["resumed_from"] == "checkpoints/last" and 1000 <= second["at_step"] < 3000
    assert (run_dir / ".hydra" / "requeued_1" / "overrides.yaml").is_file()
    assert [p.name for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith(".")] == [run_dir.name]

    reference_dir = uninterrupted(0)
    assert evaluations(run_dir) == evaluations(reference_dir)  # every column but the wall time
    assert int(evaluations(run_dir)[-1]["timesteps"]) == 3000
    mine, theirs = tensors(run_dir), tensors(reference_dir)  # networks and optimizer states of the final checkpoint
    assert mine.keys() == theirs.keys() and len(mine) > 10
    for key in mine:
        assert torch.equal(mine[key], theirs[key]), key
    final = [json.loads((d / "summary.json").read_text())["final_mean_return"] for d in (run_dir, reference_dir)]
    assert final[0] == final[1]


def test_a_requeued_batch_job_finds_its_dated_folder_by_its_job_id(slurm, tmp_path):
    """``sbatch`` of a plain ``run.py`` whose run_dir names a new dated folder at each launch: started again after a
    requeue, the job finds the folder its first start trained in (a sibling of the one the clock names now)."""
    seed_dir = tmp_path / "runs" / "seed0"
    script = tmp_path / "job.sh"
    script.write_text(
        "#!/bin/bash\n"
        f"#SBATCH --cpus-per-task=1 --output={tmp_path}/job_%j.out --open-mode=append --job-name=run\n"
        f"cd {REPO}\n"
        f"exec {python()} run.py {' '.join(SMOKE)} {' '.join(LENGTH)} "
        f"'run_dir={seed_dir}/${{now:%H-%M-%S}}'\n"
    )
    done = subprocess.run(["sbatch", "--parsable", str(script)], env=slurm, capture_output=True, text=True, check=True)
    job_id = done.stdout.strip().split(";")[0]
    try:
        first = wait_for(lambda: [p for p in seed_dir.glob("*") if (p / "checkpoints" / "last" / "meta.json").is_file()],
                         "the first checkpoint", 300)  # fmt: skip
        requeue_now(job_id)
        wait_for(lambda: job_fields(job_id).get("JobState") in ("COMPLETED", "FAILED", "CANCELLED"), "the job's end", 300)
    finally:
        subprocess.run(["scancel", job_id], capture_output=True)
    log = (tmp_path / f"job_{job_id}.out").read_text()
    assert job_fields(job_id)["JobState"] == "COMPLETED", log[-3000:]
    assert [p.name for p in seed_dir.iterdir()] == [first[0].name], "one folder, continued"
    sessions = _sessions(first[0])
    assert [s["start"] for s in sessions] == ["new", "requeue"] and sessions[1]["job"]["restarts"] == 1
    assert json.loads((first[0] / "summary.json").read_text())["total_timesteps"] == 3000
    assert (first[0] / ".hydra" / "requeued_1").is_dir()


def test_a_requeued_job_of_seeds_in_processes_resumes_them_all_bit_identical(slurm, tmp_path, uninterrupted):
    """``sbatch --cpus-per-task=2`` of ``run.py seeds=[0,1]``: the job's two cores give two seed processes, which
    SLURM signals itself at the requeue (nothing is passed on: one SIGTERM each); each checkpoints, the job starts
    again, finds the seeds' folders by the first seed's (``seed<s>/<time>``, named anew by the clock at the restart:
    the job's earlier ones), resumes both in processes, and each seed ends with the weights and evaluations of a run
    never stopped. (A fixed ``run_dir`` is the simpler case of the same resume: nothing to find; the requeued runs
    above resume in theirs.)"""
    run = [*SMOKE, *LENGTH, "seeds=[0,1]"]
    runs = tmp_path / "runs"
    run_dir = f"{runs}/seed0/${{now:%H-%M-%S}}"

    def folders() -> list[Path | None]:
        return [next(iter((runs / f"seed{s}").iterdir()), None) for s in (0, 1)]

    script = tmp_path / "job.sh"
    script.write_text(
        "#!/bin/bash\n"
        f"#SBATCH --cpus-per-task=2 --output={tmp_path}/job_%j.out --open-mode=append --job-name=seeds\n"
        f"cd {REPO}\n"
        f"exec {python()} run.py {' '.join(run)} 'run_dir={run_dir}'\n"
    )
    done = subprocess.run(["sbatch", "--parsable", str(script)], env=slurm, capture_output=True, text=True, check=True)
    job_id = done.stdout.strip().split(";")[0]

    def both_checkpointed() -> bool:
        dirs = [d for d in folders() if d is not None] if all((runs / f"seed{s}").is_dir() for s in (0, 1)) else []
        return len(dirs) == 2 and all((d / "checkpoints" / "last" / "meta.json").is_file() for d in dirs)

    try:
        wait_for(both_checkpointed, "both seeds' first checkpoints", 300)
        requeue_now(job_id)
        wait_for(lambda: job_fields(job_id).get("JobState") in ("COMPLETED", "FAILED", "CANCELLED"), "the job's end", 300)
    finally:
        subprocess.run(["scancel", job_id], capture_output=True)
    log = (tmp_path / f"job_{job_id}.out").read_text()
    assert job_fields(job_id)["JobState"] == "COMPLETED", log[-3000:]
    assert log.count("in 2 processes") == 2, log[-3000:]  # at the first start and at the requeue
    assert [len(list((runs / f"seed{s}").iterdir())) for s in (0, 1)] == [1, 1], "one folder per seed, continued"
    for seed, run_dir_of_seed in zip((0, 1), folders()):
        reference_dir = uninterrupted(seed)
        sessions = _sessions(run_dir_of_seed)
        assert [s["start"] for s in sessions] == ["new", "requeue"] and sessions[1]["job"]["job_id"] == job_id
        assert 1000 <= sessions[1]["at_step"] < 3000
        assert evaluations(run_dir_of_seed) == evaluations(reference_dir)
        mine, theirs = tensors(run_dir_of_seed), tensors(reference_dir)
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine), seed
