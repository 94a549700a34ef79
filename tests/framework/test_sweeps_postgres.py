"""Two worker processes on one study in a real PostgreSQL server; one of them is killed in the middle of a trial.

The server comes from ``.ci/postgres.sh`` (Debian's ``postgresql`` package), which prints the URL to put in
``SB3_TD3X_TEST_PG_URL``. Without it the test is skipped on a developer's machine and fails in CI.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import optuna
from omegaconf import OmegaConf
from optuna.trial import TrialState

from sb3_td3x.sweeps.storage import open_storage

REPO = Path(__file__).resolve().parents[2]
SMOKE = REPO / "sweeps" / "pendulum_smoke.yaml"
N_TRIALS = 4


def test_two_workers_share_one_study_and_a_killed_workers_trial_is_marked(pg_url, tmp_path):
    study_name = f"test-two-workers-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "runs"
    # The smoke search without its pruner: a trial that could be pruned at its first evaluation might end between
    # the moment the test sees it running and the kill.
    sweep = OmegaConf.load(SMOKE)
    sweep.pruner = {"_target_": "optuna.pruners.NopPruner"}
    sweep_file = tmp_path / "sweep.yaml"
    OmegaConf.save(sweep, sweep_file)
    command = [
        sys.executable, "-m", "sb3_td3x.sweeps", str(sweep_file),
        "--storage", pg_url, "--study-name", study_name, "--n-trials", str(N_TRIALS), "--output-dir", str(out),
        "--heartbeat-interval", "1", "--grace-period", "4",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    victim, survivor = workers = [
        subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        for _ in range(2)
    ]
    storage = open_storage(pg_url, study_name).storage  # psycopg2 for postgresql://, as the workers use
    try:
        killed_number = _wait_for_running_trial_of(victim, storage, study_name, timeout=180)
        victim.send_signal(signal.SIGKILL)  # no chance to clean up: only the heartbeat can tell
        victim.wait(timeout=30)
        still_running = optuna.load_study(study_name=study_name, storage=storage).get_trials(states=(TrialState.RUNNING,))
        assert killed_number in [t.number for t in still_running], "the victim was killed in the middle of its trial"
        _, survivor_err = survivor.communicate(timeout=240)
    finally:
        for worker in workers:
            worker.kill()
    assert survivor.returncode == 0, survivor_err
    assert victim.returncode == -signal.SIGKILL

    trials = optuna.load_study(study_name=study_name, storage=storage).get_trials()
    assert [t.number for t in trials] == list(range(N_TRIALS)), "exactly n_trials, none duplicated"
    killed = trials[killed_number]
    assert killed.state == TrialState.FAIL and "fail_reason" not in killed.user_attrs  # failed by the heartbeat
    assert killed.user_attrs["worker"].endswith(f":{victim.pid}")
    others = [t for t in trials if t.number != killed_number]
    assert all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in others), [t.state for t in others]
    assert {t.user_attrs["worker"].rsplit(":", 1)[1] for t in trials} <= {str(victim.pid), str(survivor.pid)}
    assert any(t.user_attrs["worker"].endswith(f":{survivor.pid}") for t in others)
    assert len({t.user_attrs["run_dir"] for t in trials}) == N_TRIALS
    assert len({t.user_attrs["seed"] for t in trials}) == N_TRIALS

    summary = (out / study_name / "summary.txt").read_text()  # written by the survivor, the last worker
    assert f"{N_TRIALS} trials:" in summary and "stopped sending heartbeats" in summary
    assert "td3x:***@" in summary
    optuna.delete_study(study_name=study_name, storage=storage)  # kept when the test fails, for a look


def _wait_for_running_trial_of(worker: subprocess.Popen, storage, study_name: str, timeout: float) -> int:
    """The number of a trial that ``worker`` is running and that has reported at least one evaluation."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if worker.poll() is not None:
            raise AssertionError(f"the worker exited early with {worker.returncode}: {worker.communicate()[1]}")
        try:
            trials = optuna.load_study(study_name=study_name, storage=storage).get_trials()
        except KeyError:  # the study does not exist yet
            trials = []
        for t in trials:
            if (
                t.state == TrialState.RUNNING
                and t.intermediate_values
                and t.user_attrs.get("worker", "").endswith(f":{worker.pid}")
            ):
                return t.number
        time.sleep(0.2)
    raise AssertionError("timed out waiting for the worker to run a trial")
