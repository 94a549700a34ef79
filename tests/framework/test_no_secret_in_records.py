"""No secret in any record: a database password given to a sweep appears in no file of its output folders, no study
attribute, no log line and no console output. A W&B key given to ``run.py``: in the test of a whole run folder,
``tests/framework/test_run_e2e.py::test_run_py_writes_a_complete_run_folder`` (one run checks both).

The sweep runs on the PostgreSQL server of ``.ci/postgres.sh`` (``SB3_TD3X_TEST_PG_URL``), as its second user
``td3x_secret``, whose password holds the characters a URL must encode. Without a server the sweep test is skipped
(it fails in CI, where the server must be there). Issue 19.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import uuid
from pathlib import Path
from urllib.parse import quote, quote_plus

import optuna
import pytest
from omegaconf import OmegaConf

from sb3_td3x.common.redaction import MASK, find_secrets, redact

REPO = Path(__file__).resolve().parents[2]
SMOKE = REPO / "sweeps" / "pendulum_smoke.yaml"
PASSWORD_ENV = "SB3_TD3X_STORAGE_PASSWORD"  # sb3_td3x.sweeps.storage.PASSWORD_ENV
# Created by .ci/postgres.sh beside the tests' own user.
SECRET_USER = "td3x_secret"
PASSWORD = "p@ss:w/rd%"
TINY = ["total_timesteps=300", "algo.learning_starts=100", "algo.buffer_size=1000", "eval.freq=300", "eval.n_episodes=1"]


def forms(secret: str) -> list[str]:
    """The secret as written and as a URL encodes it."""
    return sorted({secret, quote(secret, safe=""), quote_plus(secret)})


def assert_nowhere(secrets: list[str], folders: list[Path], outputs: dict[str, str]) -> int:
    """No form of any secret in any file under ``folders`` nor in ``outputs`` (name: text); returns the number of
    files read. A failure lists every place that holds one."""
    needles = [form for secret in secrets for form in forms(secret)]
    leaks = [f"{name} holds {needle!r}" for name, text in outputs.items() for needle in needles if needle in text]
    files = sorted({path for folder in folders for path in folder.rglob("*") if path.is_file()})
    for path in files:
        data = path.read_bytes()
        leaks += [f"{path} holds {needle!r}" for needle in needles if needle.encode() in data]
    assert not leaks, f"{len(leaks)} leaks:\n" + "\n".join(leaks)
    return len(files)


def run(command: list[str], env: dict[str, str], timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    return done


def secret_user_url(pg_url: str) -> str:
    """The server of ``pg_url`` as its user ``td3x_secret``, the password URL-encoded; skipped (failed in CI) when
    the server has no such user, i.e. it was not started by this checkout's ``.ci/postgres.sh``."""
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    base = make_url(pg_url)
    url = base.set(drivername="postgresql+psycopg2", username=SECRET_USER, password=PASSWORD, database=SECRET_USER)
    try:
        engine = create_engine(url, connect_args={"connect_timeout": 10})
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        engine.dispose()
    except Exception as err:  # noqa: BLE001
        first_line = (str(getattr(err, "orig", None) or err).strip().splitlines() or [""])[0]
        reason = (
            f"cannot connect to {base.host}:{base.port} as {SECRET_USER} ({redact(first_line)}); if the server is up, "
            "run .ci/postgres.sh again: it creates that user"
        )
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    encoded = url.render_as_string(hide_password=False)
    assert quote(PASSWORD, safe="") in encoded  # p%40ss%3Aw%2Frd%25: the URL a user writes
    return encoded


def test_a_sweep_on_postgresql_writes_its_password_nowhere(pg_url, tmp_path):
    """A sweep with the password in ``--storage`` (two trials, TensorBoard on), then ``--report`` on the same study
    with the URL written without its password and the password in ``SB3_TD3X_STORAGE_PASSWORD``: no trial folder, study file,
    study or trial attribute, log line or console output holds the password; the dashboard line shows it masked
    and says how to give it."""
    url = secret_user_url(pg_url)
    study_name = f"test-secrets-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "sweeps"
    sweep = OmegaConf.load(SMOKE)
    sweep.pruner = {"_target_": "optuna.pruners.NopPruner"}  # both trials run to their end and write every record
    sweep_file = tmp_path / "sweep.yaml"
    OmegaConf.save(sweep, sweep_file)
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("PGPASSWORD", None)
    env.pop(PASSWORD_ENV, None)
    common = ["--study-name", study_name, "--output-dir", str(out)]
    overrides = [*TINY, "logger=tensorboard"]
    sweep_run = run([sys.executable, "-m", "sb3_td3x.sweeps", str(sweep_file), *overrides, "--storage", url,
                     *common, "--n-trials", "2"], env)  # fmt: skip
    first_summary = (out / study_name / "summary.txt").read_text()
    storage = optuna.storages.RDBStorage(url)
    try:
        study = optuna.load_study(study_name=study_name, storage=storage)
        trials = study.get_trials()
        assert [t.state for t in trials] == [optuna.trial.TrialState.COMPLETE] * 2
        attributes = json.dumps([study.user_attrs] + [t.user_attrs for t in trials] + [t.system_attrs for t in trials])
        outputs = {"sweep's stdout": sweep_run.stdout, "sweep's stderr": sweep_run.stderr,
                   "summary.txt of the sweep": first_summary, "study and trial attributes": attributes}  # fmt: skip
        assert assert_nowhere([PASSWORD], [tmp_path], outputs) > 20

        # The same study again, the password from the environment: a worker connects from its command line and
        # environment alone, never from the records.
        without_password = url.replace(":" + quote(PASSWORD, safe=""), "")
        assert "@" in without_password and PASSWORD not in without_password
        report = run([sys.executable, "-m", "sb3_td3x.sweeps", str(sweep_file), *overrides,
                      "--storage", without_password, *common, "--report"], {**env, PASSWORD_ENV: PASSWORD})  # fmt: skip
        assert_nowhere([PASSWORD], [tmp_path], {"--report's stdout": report.stdout, "--report's stderr": report.stderr})

        # The summary the sweep wrote (and printed): the dashboard command with the password masked, and how to give it
        assert f"dashboard: optuna-dashboard postgresql+psycopg2://{SECRET_USER}:{MASK}@" in first_summary
        assert f"PGPASSWORD=<password> optuna-dashboard postgresql+psycopg2://{SECRET_USER}@" in first_summary
        assert first_summary in sweep_run.stdout
        assert (out / study_name / "summary.txt").read_text() == first_summary  # rewritten by --report, the same
        for trial in trials:  # every trial's records: the command is kept, its password masked
            run_dir = Path(trial.user_attrs["run_dir"])
            assert (run_dir / "tb").is_dir()
            for name in ("provenance.jsonl", "summary.json"):
                text = (run_dir / name).read_text()
                assert f"--storage postgresql+psycopg2://{SECRET_USER}:{MASK}@" in text, name
                assert find_secrets(text) == [], name
        assert (out / study_name / "trials.csv").is_file() and (out / study_name / "best_overrides.txt").is_file()
    finally:
        optuna.delete_study(study_name=study_name, storage=storage)
        storage.engine.dispose()


def test_postgresqls_own_pgpassword_works_with_a_url_without_password(pg_url, monkeypatch):
    """What docs/sweeps.md advises: the URL without its password, the password in PGPASSWORD (read by libpq)."""
    from sb3_td3x.sweeps.storage import open_storage

    url = secret_user_url(pg_url).replace(":" + quote(PASSWORD, safe=""), "")
    monkeypatch.delenv(PASSWORD_ENV, raising=False)
    monkeypatch.setenv("PGPASSWORD", PASSWORD)
    study_storage = open_storage(url, "test-pgpassword")
    assert optuna.get_all_study_names(study_storage.storage) is not None
    assert study_storage.password_hint() is None and study_storage.dashboard_command() == f"optuna-dashboard {url}"
    study_storage.storage.engine.dispose()


def test_launcher_jobs_get_the_password_through_their_environment(monkeypatch):
    """``--launcher`` pickles the workers' command line into its job folder: the password leaves the URL for
    ``SB3_TD3X_STORAGE_PASSWORD``, which the jobs inherit."""
    from sb3_td3x.sweeps.cli import _password_to_environment
    from sb3_td3x.sweeps.storage import PASSWORD_ENV as NAME

    assert NAME == PASSWORD_ENV
    monkeypatch.setenv(PASSWORD_ENV, "placeholder")  # restored after the test
    url = f"postgresql+psycopg2://td3x:{quote(PASSWORD, safe='')}@db-host:5432/td3x"
    assert _password_to_environment(url) == "postgresql+psycopg2://td3x@db-host:5432/td3x"
    assert os.environ[PASSWORD_ENV] == PASSWORD
    for unchanged in ("sqlite:///runs/x/optuna.db", "journal:runs/x.log", "postgresql://td3x@db-host/td3x"):
        assert _password_to_environment(unchanged) == unchanged


@pytest.mark.parametrize("url", ["postgresql://u:p@ss@127.0.0.1:9/db", "postgresql://u:hunter2@127.0.0.1:port/db"])
def test_a_storage_url_that_cannot_be_read_is_one_clear_line_without_its_password(url, tmp_path, capsys):
    """A raw '@' in the password (SQLAlchemy would take the rest of it for the host, and the driver's error would
    show it), a port that is not a number: one line saying how to write the URL, no traceback, no password."""
    from sb3_td3x.sweeps.cli import main

    factory = logging.getLogRecordFactory()
    try:
        code = main([str(SMOKE), "--storage", url, "--output-dir", str(tmp_path)])
    finally:
        logging.setLogRecordFactory(factory)  # main() wraps it for the rest of its process
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: storage 'postgresql://u:***@127.0.0.1:") and err.count("\n") == 1, err
    assert "percent-encode" in err and "SB3_TD3X_STORAGE_PASSWORD" in err
    assert "p@ss" not in err and "ss@" not in err and "hunter2" not in err and "Traceback" not in err


def test_publish_refuses_a_record_that_holds_a_secret(tmp_path):
    """``scripts/publish_results.sh`` copies nothing while a record looks like it holds a secret, and says which."""
    seed = tmp_path / "runs" / "pendulum" / "td3" / "seed0"
    seed.mkdir(parents=True)
    (seed / "evaluations.csv").write_text("timesteps,mean_return\n300,-1200.0\n")
    (seed / "provenance.jsonl").write_text(json.dumps({"command": "run.py +hydra.job.env_set.WANDB_API_KEY=abc123"}) + "\n")
    docs = tmp_path / "docs"
    out = subprocess.run(
        ["bash", str(REPO / "scripts" / "publish_results.sh"), str(tmp_path / "runs")],
        env={"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "PYTHON": sys.executable,
             "PYTHONPATH": os.environ.get("PYTHONPATH", ""),  # where packages come from a path (a GPU machine's)
             "RESULTS_DOCS_DIR": str(docs), "RESULTS_PAGE": ""},  # fmt: skip
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip
    assert out.returncode == 2, out.stdout + out.stderr
    assert f"{seed / 'provenance.jsonl'}:1: looks like a secret" in out.stderr and "not publishing" in out.stderr
    assert "abc123" not in out.stderr + out.stdout and "Traceback" not in out.stderr
    assert not docs.exists()


def test_publish_says_when_the_secret_check_itself_fails(tmp_path):
    """A checker that crashes (here a PYTHON without this package) is not reported as a secret: the script says the
    check failed and how to fix it, and copies nothing."""
    seed = tmp_path / "runs" / "pendulum" / "td3" / "seed0"
    seed.mkdir(parents=True)
    (seed / "evaluations.csv").write_text("timesteps,mean_return\n300,-1200.0\n")
    broken_python = tmp_path / "python"
    broken_python.write_text("#!/bin/sh\necho 'ModuleNotFoundError: No module named sb3_td3x' >&2\nexit 1\n")
    broken_python.chmod(0o755)
    # The fake exits 1, as Python does on an uncaught error (the module reports a finding with status 3).
    docs = tmp_path / "docs"
    out = subprocess.run(
        ["bash", str(REPO / "scripts" / "publish_results.sh"), str(tmp_path / "runs")],
        env={"PATH": "/usr/bin:/bin", "PYTHON": str(broken_python), "RESULTS_DOCS_DIR": str(docs), "RESULTS_PAGE": ""},
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )  # fmt: skip
    assert out.returncode == 2, out.stdout + out.stderr
    assert "the secret check" in out.stderr and "set PYTHON" in out.stderr, out.stderr
    assert "look like they hold a secret" not in out.stderr
    assert not docs.exists()
