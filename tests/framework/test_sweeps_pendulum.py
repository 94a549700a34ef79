"""Real sweeps on Pendulum-v1 with SQLite storage: every trial trains with ``run_experiment``.

The smoke search (``sweeps/pendulum_smoke.yaml``) runs 600-step trials with a Hyperband pruner, so a trial takes
a few seconds.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
import sqlalchemy.exc
import yaml
from optuna.storages import RetryHeartbeatStaleTrialCallback
from optuna.trial import TrialState

from sb3_td3x.sweeps.cli import main
from sb3_td3x.sweeps.objective import DEFAULT_CONFIG_DIR, TrialObjective, compose_config
from sb3_td3x.sweeps.spec import load_sweep
from sb3_td3x.sweeps.storage import open_storage
from sb3_td3x.sweeps.worker import open_study, run_worker

REPO = Path(__file__).resolve().parents[2]
SMOKE = REPO / "sweeps" / "pendulum_smoke.yaml"
STUDY = "td3x-pendulum-smoke"
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)

pytestmark = [
    pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning"),
    pytest.mark.filterwarnings("ignore:Fixed parameter .* is out of range:UserWarning"),
]


def sweep_command(*args: str, spec: Path = SMOKE) -> list[str]:
    return [sys.executable, "-m", "sb3_td3x.sweeps", str(spec), *args]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def load(storage: str, study_name: str = STUDY) -> list[optuna.trial.FrozenTrial]:
    return optuna.load_study(study_name=study_name, storage=storage).get_trials()


def sweep_in_process(capsys, *args: str, spec: Path = SMOKE) -> tuple[int, str]:
    """``python -m sb3_td3x.sweeps <smoke file> <args>`` without paying for a new interpreter each time."""
    code = main([str(spec), *args])
    return code, capsys.readouterr().err


def slower_smoke(tmp_path: Path) -> Path:
    """The smoke search with 1,000 steps between evaluations instead of 150: a test that interrupts a trial after its
    first evaluation needs the trial still running when the signal lands (150 steps of these tiny networks take well
    under the 0.2 s the test polls at on a fast CPU, so the trial could finish first)."""
    spec = yaml.safe_load(SMOKE.read_text())
    longer = {"total_timesteps": "4000", "eval.freq": "1000"}
    spec["overrides"] = [f"{key}={longer[key]}" if (key := o.split("=")[0]) in longer else o for o in spec["overrides"]]
    spec["pruner"].update(min_resource=1000, max_resource=4000)
    path = tmp_path / "pendulum_smoke_slower.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def test_sweep_prunes_persists_and_grows(tmp_path, capsys):
    out = tmp_path / "runs"
    storage = f"sqlite:///{out / STUDY / 'optuna.db'}"

    code, err = sweep_in_process(capsys, "--output-dir", str(out))
    assert code == 0, err
    trials = load(storage)
    assert [t.number for t in trials] == [0, 1, 2, 3]
    assert all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
    pruned = [t for t in trials if t.state == TrialState.PRUNED]
    assert pruned, "Hyperband stops at least one trial"
    assert all(max(t.intermediate_values) < 600 for t in pruned), "a pruned trial stops before its last step"
    assert all("HyperbandPruner" in t.user_attrs["prune_reason"] for t in pruned)
    assert any(t.state == TrialState.COMPLETE for t in trials)

    for t in trials:  # each trial keeps its config, seed and run folder
        run_dir = Path(t.user_attrs["run_dir"])
        assert run_dir == (out / STUDY / f"trial_{t.number:04d}").resolve()
        assert t.user_attrs["seed"] == t.number
        trained = yaml.safe_load((run_dir / "config.yaml").read_text())
        assert trained["seed"] == t.number
        assert trained["algo"]["learning_rate"] == pytest.approx(t.params["algo.learning_rate"])
        assert trained["algo"]["net_arch"] == yaml.safe_load(t.params["algo.net_arch"])
        assert trained["torch_threads"] == 1  # workers may share a machine
        assert f"run_dir={run_dir}" in t.user_attrs["overrides"]
        assert len(t.intermediate_values) >= 1

    study_dir = out / STUDY
    for name in ("summary.txt", "trials.csv", "best_overrides.txt", "tuned/best.yaml"):
        assert (study_dir / name).is_file(), name
    for plot in ("optimization_history", "intermediate_values"):
        assert (study_dir / "plots" / f"{plot}.png").stat().st_size > 1000
    best = optuna.load_study(study_name=STUDY, storage=storage).best_trial
    summary = (study_dir / "summary.txt").read_text()
    assert f"best: trial {best.number}" in summary and f"optuna-dashboard {storage}" in summary

    # the best-parameters files are accepted by run.py's config: as overrides, and as +tuned=best
    best_overrides = (study_dir / "best_overrides.txt").read_text().split()
    assert f"seed={best.number}" in best_overrides and not any(o.startswith("run_dir=") for o in best_overrides)
    for cfg in (
        compose_config(best_overrides, DEFAULT_CONFIG_DIR),
        compose_config([f"hydra.searchpath=[file://{study_dir}]", "+tuned=best"], DEFAULT_CONFIG_DIR),
    ):
        assert cfg.seed == best.number and cfg.total_timesteps == 600 and cfg.env.id == "Pendulum-v1"
        assert cfg.algo.learning_rate == pytest.approx(best.params["algo.learning_rate"])
        assert cfg.algo.net_arch == yaml.safe_load(best.params["algo.net_arch"])

    # the same command again: the study is complete, nothing is added or run twice
    code, err = sweep_in_process(capsys, "--output-dir", str(out))
    assert code == 0, err
    assert "already holds its 4 trials" in err
    assert [(t.number, t.state, t.params) for t in load(storage)] == [(t.number, t.state, t.params) for t in trials]

    # a larger budget: the study grows, earlier trials keep their parameters, values and folders
    code, err = sweep_in_process(capsys, "--output-dir", str(out), "--n-trials", "5")
    assert code == 0, err
    after = load(storage)
    assert [t.number for t in after] == [0, 1, 2, 3, 4]
    assert all(t.state in FINISHED for t in after)
    for old, new in zip(trials, after):
        assert (old.params, old.value, old.user_attrs) == (new.params, new.value, new.user_attrs)
    assert after[4].user_attrs["seed"] == 4 and after[4].params not in [t.params for t in trials]


def test_ctrl_c_leaves_the_study_consistent_and_the_same_command_continues(tmp_path, capsys):
    """The real command in its own process, stopped with SIGINT in the middle of its first trial."""
    out = tmp_path / "runs"
    storage = f"sqlite:///{out / STUDY / 'optuna.db'}"
    args = ("--output-dir", str(out), "--n-trials", "1")
    spec = slower_smoke(tmp_path)
    proc = subprocess.Popen(
        sweep_command(*args, spec=spec), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env()
    )
    try:
        _wait_until(lambda: _a_trial_has_evaluated(storage), proc, timeout=120)
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "Interrupted: trial 0 was marked FAIL (interrupted) and queued again" in stderr
    assert "Traceback" not in stderr

    interrupted, queued = load(storage)
    assert interrupted.state == TrialState.FAIL and interrupted.user_attrs["fail_reason"] == "interrupted by SIGINT"
    assert (Path(interrupted.user_attrs["run_dir"]) / "checkpoints" / "last").is_dir(), "the runner checkpointed"
    assert queued.state == TrialState.WAITING and queued.params == interrupted.params
    assert RetryHeartbeatStaleTrialCallback.retried_trial_number(queued) == 0

    code, err = sweep_in_process(capsys, *args, spec=spec)  # the same command again
    assert code == 0, err
    trials = load(storage)
    assert [t.number for t in trials] == [0, 1]  # 0 interrupted, 1 its copy: the budget of one trial is spent
    resumed = trials[1]
    assert resumed.state == TrialState.COMPLETE and resumed.params == interrupted.params
    # the copy resumed the run from its checkpoint: same folder and seed, evaluations from where it stopped
    assert resumed.user_attrs["run_dir"] == interrupted.user_attrs["run_dir"] and resumed.user_attrs["seed"] == 0
    assert f"resume={interrupted.user_attrs['run_dir']}" in resumed.user_attrs["overrides"]
    assert min(resumed.intermediate_values) > max(interrupted.intermediate_values)
    assert resumed.user_attrs["fail_reason"] is None, "the copy does not inherit its original's reason"
    evaluations = (Path(interrupted.user_attrs["run_dir"]) / "evaluations.csv").read_text().splitlines()[1:]
    assert [int(row.split(",")[0]) for row in evaluations] == [1000, 2000, 3000, 4000]
    summary = (out / STUDY / "summary.txt").read_text()
    assert "1 COMPLETE, 1 FAIL" in summary and "interrupted by SIGINT" in summary
    best_overrides = (out / STUDY / "best_overrides.txt").read_text()
    assert "resume=" not in best_overrides and "seed=0" in best_overrides


def test_a_diverged_or_crashing_trial_is_recorded_and_the_study_goes_on(tmp_path):
    """Real failures of the real runner: a learning rate of 1e30 makes the critic loss infinite, and tau=2 is a
    config error. Both trials end FAIL with their reason; the next trial still runs and completes."""
    spec = load_sweep(SMOKE)
    study_dir = tmp_path / STUDY
    study_storage = open_storage(f"sqlite:///{study_dir / 'optuna.db'}", STUDY)
    study = open_study(spec, study_storage, STUDY, spec.overrides)
    study.enqueue_trial({"algo.learning_rate": 1e30}, skip_if_exists=False)  # out of range on purpose
    study.enqueue_trial({"algo.tau": 2.0}, skip_if_exists=False)
    finished = []
    summary = run_worker(
        study,
        spec,
        study_storage,
        TrialObjective(spec, DEFAULT_CONFIG_DIR, ["total_timesteps=300"], study_dir),
        n_trials=3,
        on_finished=finished.append,
    )
    assert summary.ran == [0, 1, 2] and summary.study_finished and finished == [study]
    diverged, invalid, fine = study.get_trials()
    assert diverged.state == TrialState.FAIL
    assert diverged.user_attrs["fail_reason"].startswith("diverged: train/critic_loss became")
    assert invalid.state == TrialState.FAIL
    assert invalid.user_attrs["fail_reason"].startswith("ConfigError: Invalid configuration: algo.tau=2.0")
    assert "ConfigError" in (Path(invalid.user_attrs["run_dir"]) / "sweep_error.txt").read_text()
    assert fine.state in (TrialState.COMPLETE, TrialState.PRUNED)


def _a_trial_has_evaluated(storage: str) -> bool:
    try:
        trials = load(storage)
    except (KeyError, sqlalchemy.exc.SQLAlchemyError):  # the worker is still creating the study (or its tables)
        return False
    return any(t.state == TrialState.RUNNING and t.intermediate_values for t in trials)


def _wait_until(condition, proc: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(f"the sweep exited early with {proc.returncode}: {proc.communicate()[1]}")
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting for a trial to report an evaluation")
        time.sleep(0.2)


@pytest.mark.slow
def test_workers_launched_as_submitit_jobs_share_the_study(tmp_path, capsys):
    """The cluster path (``--launcher``) on this machine: submitit's local executor, configured like Hydra's
    submitit launcher, starts two worker jobs that together run exactly the budget of trials."""
    out = tmp_path / "runs"
    launcher = str(REPO / "sweeps" / "launcher" / "local.yaml")
    code = main([str(SMOKE), "--output-dir", str(out), "--n-trials", "2", "--launcher", launcher, "--workers", "2", "--wait"])
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    assert "submitted 2 local worker job(s)" in stdout and "workers exited with [0, 0]" in stdout
    trials = load(f"sqlite:///{out / STUDY / 'optuna.db'}")
    assert [t.number for t in trials] == [0, 1] and all(t.state in FINISHED for t in trials)
    assert (out / STUDY / "summary.txt").is_file()
    assert len(list((out / STUDY / "jobs").glob("*/*_log.err"))) == 2
