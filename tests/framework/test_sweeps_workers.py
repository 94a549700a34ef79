"""Sweep workers as real processes on Pendulum-v1 with SQLite: what a cut-off worker, mixed heartbeat settings, a
double Ctrl-C at trial start and bad command-line values leave in the study and print.

Each scenario runs ``python -m sb3_td3x.sweeps sweeps/pendulum_smoke.yaml`` as a subprocess; a trial trains a few
seconds.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
from optuna.storages import fail_stale_trials
from optuna.trial import TrialState

from sb3_td3x.sweeps.cli import main
from sb3_td3x.sweeps.spec import load_sweep
from sb3_td3x.sweeps.storage import open_storage
from sb3_td3x.sweeps.worker import claim_trial, open_study

REPO = Path(__file__).resolve().parents[2]
SMOKE = REPO / "sweeps" / "pendulum_smoke.yaml"
STUDY = "td3x-pendulum-smoke"

pytestmark = [
    pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning"),
    pytest.mark.filterwarnings("ignore:Fixed parameter .* is out of range:UserWarning"),
]


def start_worker(*args: str, sweep_file: Path = SMOKE, prefix: tuple[str, ...] = ()) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    command = [*prefix, sys.executable, "-m", "sb3_td3x.sweeps", str(sweep_file), *args]
    return subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def finish(proc: subprocess.Popen, timeout: float = 120) -> str:
    try:
        return proc.communicate(timeout=timeout)[1]
    finally:
        proc.kill()


def trials(storage: str) -> list[optuna.trial.FrozenTrial]:
    return optuna.load_study(study_name=STUDY, storage=storage).get_trials()


def rows(out: Path, table: str) -> int:
    """Rows of one of Optuna's tables in the study's SQLite file: a cheap look while the worker runs."""
    try:
        with contextlib.closing(sqlite3.connect(out / STUDY / "optuna.db", timeout=5)) as db:
            return db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
    except sqlite3.OperationalError:  # no file or no tables yet: the worker is still creating the study
        return 0


def wait_until(condition, proc: subprocess.Popen, timeout: float = 60, poll: float = 0.1) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(f"the worker exited early with {proc.returncode}: {proc.communicate()[1]}")
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting for the worker")
        time.sleep(poll)


def test_a_worker_cut_off_past_the_grace_period_keeps_its_late_result(tmp_path):
    """SIGSTOP a worker in the middle of its trial for longer than the grace period; another worker marks the trial
    FAIL as stale; SIGCONT. The cut-off worker stops the trial at its next evaluation, keeps what it measured as a
    study attribute, writes the results and exits 0, without a traceback."""
    out = tmp_path / "runs"
    storage = f"sqlite:///{out / STUDY / 'optuna.db'}"
    heartbeat = ("--heartbeat-interval", "1", "--grace-period", "2")
    worker = start_worker("--output-dir", str(out), "--n-trials", "1", *heartbeat, "total_timesteps=3000")
    try:
        wait_until(lambda: rows(out, "trial_intermediate_values") > 0, worker)
        other = open_storage(storage, STUDY, heartbeat_interval=1, grace_period=2)
        for attempt in range(5):
            worker.send_signal(signal.SIGSTOP)
            time.sleep(3)  # past the grace period: its last heartbeat is more than 2 s old
            try:
                fail_stale_trials(optuna.load_study(study_name=STUDY, storage=other.storage))  # what any other worker does
                break
            except optuna.exceptions.StorageInternalError:
                # Stopped in the middle of a write, the worker holds SQLite's lock ("database is locked" after 5 s):
                # let it finish the write, and stop it again.
                worker.send_signal(signal.SIGCONT)
                time.sleep(0.3 * (attempt + 1))
        (stale,) = trials(storage)
        assert stale.state == TrialState.FAIL
        worker.send_signal(signal.SIGCONT)
        stderr = finish(worker)
    finally:
        worker.send_signal(signal.SIGCONT)
        worker.kill()
    assert worker.returncode == 0, stderr
    assert "Traceback" not in stderr and "UpdateFinishedTrialError" not in stderr
    assert "kept as the study's user attribute late_result_trial_0" in stderr

    study = optuna.load_study(study_name=STUDY, storage=storage)
    (trial,) = study.get_trials()
    assert trial.state == TrialState.FAIL and "fail_reason" not in trial.user_attrs, "the study's verdict stands"
    assert trial.intermediate_values == stale.intermediate_values, "nothing was reported on the finished trial"
    late = study.user_attrs["late_result_trial_0"]
    assert late["outcome"] == "stopped" and late["state_in_study"] == "FAIL"
    assert late["step"] > max(stale.intermediate_values) and isinstance(late["value"], float)
    assert late["worker"] == trial.user_attrs["worker"]
    summary = (out / STUDY / "summary.txt").read_text()
    assert "late results" in summary and f"{late['value']:.3f} at step {late['step']}" in summary


def test_a_worker_with_other_heartbeat_settings_is_refused(tmp_path):
    """A worker with the default heartbeat (every 60 s, grace period 120 s) has a trial running. A worker started
    with ``--heartbeat-interval 1 --grace-period 2`` would mark that healthy trial stale; it is refused instead
    (exit 2, one paragraph naming both settings and how to match them), and the trial stays RUNNING."""
    out = tmp_path / "runs"
    storage = f"sqlite:///{out / STUDY / 'optuna.db'}"
    spec = load_sweep(SMOKE)
    first = open_storage(storage, STUDY)  # the defaults, as the first worker's command line gives them
    study = open_study(spec, first, STUDY, spec.overrides)
    running = claim_trial(study, spec, first, n_trials=1)  # what the first worker does before it trains
    second = start_worker("--output-dir", str(out), "--n-trials", "1", "--heartbeat-interval", "1", "--grace-period", "2")
    stderr = finish(second)  # it starts in more than 2 s: the trial's heartbeat is older than its grace period

    assert second.returncode == 2, stderr
    assert "Traceback" not in stderr
    message = stderr.strip()
    assert message.startswith("error: ") and "\n" not in message, "one paragraph"
    assert "heartbeat interval of 60s and a grace period of 120s" in message
    assert "--heartbeat-interval 1 and a grace period of 2s" in message
    assert "--heartbeat-interval 60 --grace-period 120" in message, "says how to fix it"
    (trial,) = trials(storage)
    assert trial.number == running.number and trial.state == TrialState.RUNNING, "the healthy trial was left alone"
    assert study.user_attrs["heartbeat"] == {"heartbeat_interval": 60, "grace_period": 120}


@pytest.mark.parametrize(
    "sig, delay", [(signal.SIGINT, 0.0), (signal.SIGTERM, 0.5)], ids=["ctrl-c-at-trial-start", "sigterm-half-a-second-in"]
)
def test_two_signals_50ms_apart_leave_no_trial_running(tmp_path, sig, delay):
    """Two signals 50 ms apart as soon as the worker's first trial exists (a double Ctrl-C), or half a second later
    (two SIGTERMs): the worker exits 130 without a traceback, no trial is RUNNING, and what it says about the trial
    is what the study holds."""
    out = tmp_path / "runs"
    storage = f"sqlite:///{out / STUDY / 'optuna.db'}"
    worker = start_worker("--output-dir", str(out), "--n-trials", "2")
    try:
        wait_until(lambda: rows(out, "trials") > 0, worker, poll=0.02)
        time.sleep(delay)
        worker.send_signal(sig)
        time.sleep(0.05)
        worker.send_signal(sig)
        stderr = finish(worker)
    finally:
        worker.kill()
    assert worker.returncode == 130, stderr
    assert "Traceback" not in stderr
    now = trials(storage)
    assert not [t.number for t in now if t.state == TrialState.RUNNING], stderr
    first = now[0]
    if "trial 0 was marked FAIL (interrupted) and queued again" in stderr:
        assert first.state == TrialState.FAIL
        assert first.user_attrs["fail_reason"].startswith(f"interrupted by {sig.name}")
        queued = [t for t in now if t.state == TrialState.WAITING]
        assert len(queued) == 1 and queued[0].params == first.params, "a copy is queued to run it again"
    else:  # the trial ended before the signals: the worker says so
        assert "trial 0 ended" in stderr and first.state in (TrialState.COMPLETE, TrialState.PRUNED), stderr


def _bad_inputs(tmp_path: Path) -> dict[str, tuple[tuple[str, ...], Path, tuple[str, ...], str]]:
    """Bad inputs run as commands. Name: (arguments, sweep file, command prefix, expected phrase)."""
    out = ("--output-dir", str(tmp_path / "runs"))
    cases = {
        "heartbeat-interval 0": (("--heartbeat-interval", "0", *out), SMOKE, (), "--heartbeat-interval must be at least 1"),
    }
    if os.geteuid() != 0 or shutil.which("setpriv"):  # root reads any file: drop that power for this one command
        unreadable = tmp_path / "unreadable.yaml"
        shutil.copy(SMOKE, unreadable)
        unreadable.chmod(0)
        caps = "-dac_override,-dac_read_search"
        prefix = ("setpriv", f"--bounding-set={caps}", f"--inh-caps={caps}") if os.geteuid() == 0 else ()
        cases["unreadable sweep file"] = (out, unreadable, prefix, "cannot be read: permission denied")
    return cases


def test_bad_inputs_end_in_one_paragraph_and_exit_2(tmp_path):
    """A bad value ends before anything runs: exit 2, one ``error:`` paragraph, no traceback, no study folder. Two
    as commands, side by side (each one's cost is the interpreter's start); the others in this process below."""
    cases = _bad_inputs(tmp_path)
    procs = {name: start_worker(*args, sweep_file=file, prefix=prefix) for name, (args, file, prefix, _) in cases.items()}
    stderrs = {name: finish(proc) for name, proc in procs.items()}
    wrong = [_wrong(name, procs[name].returncode, stderrs[name], cases[name][3]) for name in cases]
    assert not any(wrong), "\n".join(filter(None, wrong))
    assert not (tmp_path / "runs").exists(), "nothing was created"


@pytest.mark.parametrize(
    "args, expected",
    [
        (("--heartbeat-interval", "-5"), "--heartbeat-interval must be at least 1"),
        (("--heartbeat-interval", "10", "--grace-period", "10"), "must be longer than --heartbeat-interval"),
        (("--heartbeat-interval", "5", "--grace-period", "3"), "must be longer than --heartbeat-interval"),
        (("--retry-stale", "-1"), "--retry-stale must be at least 0"),
        (("--max-consecutive-failures", "0"), "--max-consecutive-failures must be at least 1"),
        (("--n-trials", "0"), "--n-trials must be at least 1"),
        (("--workers", "0"), "--workers must be at least 1"),
        (("--study-name", "../elsewhere"), "--study-name '../elsewhere' may hold only"),
    ],
)
def test_more_bad_values_end_in_one_paragraph_and_exit_2(tmp_path, capsys, args, expected):
    """The same for the other numeric options and names, in this process (they are read before anything else)."""
    code = main([str(SMOKE), "--output-dir", str(tmp_path / "runs"), *args])
    assert not _wrong(" ".join(args), code, capsys.readouterr().err, expected)
    assert not (tmp_path / "runs").exists()


def test_a_folder_as_the_sweep_file_is_refused(tmp_path, capsys):
    code = main([str(REPO / "sweeps"), "--output-dir", str(tmp_path / "runs")])
    assert not _wrong("sweeps/ as the file", code, capsys.readouterr().err, "is a folder")


def test_an_output_dir_that_is_a_file_is_refused(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert not _wrong(
        "--output-dir a_file", main([str(SMOKE), "--output-dir", str(a_file)]), capsys.readouterr().err, "is a file"
    )


def _wrong(name: str, code: int, stderr: str, expected: str) -> str | None:
    """What is wrong with how a bad input ended, or ``None``."""
    stderr = stderr.strip()
    if code != 2 or "Traceback" in stderr or not stderr.startswith("error: ") or "\n" in stderr:
        return f"{name}: exit {code}, stderr {stderr[-600:]!r}"
    if expected not in stderr:
        return f"{name}: {stderr!r} does not say {expected!r}"
    return None
