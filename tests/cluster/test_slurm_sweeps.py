"""Sweep workers as jobs of a real SLURM on a PostgreSQL study: the documented launch, and a worker requeued in the
middle of a trial, which resumes the trial from its checkpoint while ``--wait`` follows the job to its real end."""

from __future__ import annotations

import json
import subprocess
import uuid

import optuna
from omegaconf import OmegaConf
from optuna.trial import TrialState
from slurm_helpers import REPO, job_fields, python, requeue_now, wait_for

from sb3_td3x.sweeps.storage import open_storage

SMOKE = REPO / "sweeps" / "pendulum_smoke.yaml"
SLURM_LAUNCHER = REPO / "sweeps" / "launcher" / "slurm.yaml"  # as documented: 2 CPUs and 8 GB a worker


def _sweep(slurm, pg_url, tmp_path, sweep_file, study, *extra, workers=2):
    command = [
        python(), "-m", "sb3_td3x.sweeps", str(sweep_file), *extra, "--storage", pg_url, "--study-name", study,
        "--output-dir", str(tmp_path / "runs"), "--launcher", str(SLURM_LAUNCHER), "--workers", str(workers), "--wait",
    ]  # fmt: skip
    return subprocess.Popen(command, cwd=REPO, env=slurm, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_sweep_workers_as_slurm_jobs_complete_the_study(slurm, pg_url, tmp_path):
    study = f"slurm-{uuid.uuid4().hex[:8]}"
    proc = _sweep(slurm, pg_url, tmp_path, SMOKE, study, "--n-trials", "4")
    try:
        out, err = proc.communicate(timeout=600)
    finally:
        proc.kill()
        subprocess.run(["scancel", "--name", f"sweep-{study}"], capture_output=True)
    assert proc.returncode == 0, err[-4000:]
    assert "submitted 2 slurm worker job(s)" in out and "workers exited with [0, 0]" in out
    trials = optuna.load_study(study_name=study, storage=open_storage(pg_url, study).storage).get_trials()
    assert len(trials) == 4 and all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
    assert {t.user_attrs["job"]["scheduler"] for t in trials} == {"slurm"}
    # each trial ran in one of the two jobs (how they share the four depends on when each started)
    assert len({t.user_attrs["job"]["job_id"] for t in trials}) in (1, 2)
    assert out.count(": COMPLETED, exit 0") == 2, out
    assert (tmp_path / "runs" / study / "summary.txt").is_file()
    assert "Bypassing sacct error" not in out + err
    assert err.count("following the jobs with scontrol") == 1, err  # this cluster has no accounting: said once


def test_a_requeued_worker_resumes_its_trial_and_wait_reports_the_real_end(slurm, pg_url, tmp_path):
    study = f"slurm-requeue-{uuid.uuid4().hex[:8]}"
    sweep = OmegaConf.load(SMOKE)
    sweep.pruner = {"_target_": "optuna.pruners.NopPruner"}  # no trial may end before the requeue
    sweep.overrides = [o for o in sweep.overrides if not o.startswith(("total_timesteps", "checkpoint.freq"))]
    sweep.overrides += ["total_timesteps=2000", "checkpoint.freq=500"]
    sweep_file = tmp_path / "sweep.yaml"
    OmegaConf.save(sweep, sweep_file)
    proc = _sweep(slurm, pg_url, tmp_path, sweep_file, study, "--n-trials", "2", workers=1)
    try:
        first_trial = (tmp_path / "runs" / study / "trial_0000").resolve()
        wait_for(lambda: (first_trial / "checkpoints" / "last" / "meta.json").is_file(), "trial 0's checkpoint", 300, proc)
        queue = ["squeue", "-h", "-n", f"sweep-{study}", "-o", "%i"]
        job_id = wait_for(lambda: subprocess.run(queue, capture_output=True, text=True).stdout.strip(), "the worker job", 30)
        requeue_now(job_id)
        out, err = proc.communicate(timeout=600)
    finally:
        proc.kill()
        subprocess.run(["scancel", "--name", f"sweep-{study}"], capture_output=True)  # no job is left behind
    assert proc.returncode == 0, err[-4000:]
    assert job_fields(job_id).get("Restarts") == "1"
    # --wait followed the job through its requeue to its real end
    assert f"worker job {job_id}: COMPLETED, requeued 1 time(s), exit 0" in out, out
    assert "workers exited with [0]" in out

    trials = optuna.load_study(study_name=study, storage=open_storage(pg_url, study).storage).get_trials()
    states = {t.number: t.state for t in trials}
    assert states == {0: TrialState.FAIL, 1: TrialState.COMPLETE, 2: TrialState.COMPLETE}, states
    assert trials[0].user_attrs["fail_reason"] == "interrupted by SIGTERM"
    # trial 1 repeats trial 0 and trained in trial 0's folder, from its checkpoint; every record says so
    assert trials[1].user_attrs["run_dir"] == str(first_trial)
    assert f"resume={first_trial}" in trials[1].user_attrs["overrides"]
    sessions = [json.loads(line) for line in (first_trial / "provenance.jsonl").read_text().splitlines()]
    assert [s["start"] for s in sessions] == ["new", "resume"]
    assert [s["job"]["restarts"] for s in sessions] == [0, 1]
    assert sessions[1]["resumed_from"] == "checkpoints/last" and sessions[1]["at_step"] >= 500
    assert json.loads((first_trial / "summary.json").read_text())["total_timesteps"] == 2000
    assert not (tmp_path / "runs" / study / "trial_0001").exists()
    logs = "".join(p.read_text() for p in (tmp_path / "runs" / study / "jobs").glob("*/*_log.err"))
    assert f"trial 1 resumes the run of the trial it repeats, in {first_trial}" in logs
    assert "trial 1 started in" not in logs
