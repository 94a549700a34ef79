"""``sb3_td3x.common.redaction``: the one function that masks secrets in what is written or logged (issue 19)."""

from __future__ import annotations

import json
import logging
from urllib.parse import quote

import pytest
import yaml
from sqlalchemy.engine import URL

from sb3_td3x.common.redaction import MASK, find_secrets, is_secret_name, redact, redact_log_records
from sb3_td3x.common.redaction import main as check_files

PASSWORD = "p@ss:w/rd%"
ENCODED = quote(PASSWORD, safe="")  # p%40ss%3Aw%2Frd%25


@pytest.mark.parametrize(
    "url, shown",
    [
        ("postgresql://td3x:pw@db-host:5432/td3x", "postgresql://td3x:***@db-host:5432/td3x"),
        ("postgresql://td3x:pw@db-host/td3x", "postgresql://td3x:***@db-host/td3x"),
        ("postgresql+psycopg2://td3x:pw@127.0.0.1:55432/db", "postgresql+psycopg2://td3x:***@127.0.0.1:55432/db"),
        ("mysql+pymysql://root:pw@db-host/optuna?charset=utf8mb4", "mysql+pymysql://root:***@db-host/optuna?charset=utf8mb4"),
        ("mysql://root:pw@db-host:3306/optuna", "mysql://root:***@db-host:3306/optuna"),
        (f"postgresql://td3x:{ENCODED}@db-host:5432/td3x", "postgresql://td3x:***@db-host:5432/td3x"),  # as it must be
        (f"postgresql://td3x:{PASSWORD}@db-host:5432/td3x", "postgresql://td3x:***@db-host:5432/td3x"),  # as it may be typed
        ("mysql://u:a@b@db-host/optuna", "mysql://u:***@db-host/optuna"),  # a raw '@' SQLAlchemy would cut at
        ("https://user:ghp_token@github.com/o/r.git", "https://user:***@github.com/o/r.git"),
    ],
)
def test_the_password_of_a_url_is_masked(url, shown):
    assert redact(url) == shown
    assert redact(f"error: cannot open storage {url}: refused.") == f"error: cannot open storage {shown}: refused."
    assert redact(f"storage '{url}' is not valid") == f"storage '{shown}' is not valid"


def test_the_url_mask_is_sqlalchemys():
    url = URL.create("postgresql+psycopg2", "td3x", PASSWORD, "db-host", 5432, "td3x")
    assert redact(url.render_as_string(hide_password=False)) == url.render_as_string(hide_password=True)


@pytest.mark.parametrize(
    "text",
    [
        "sqlite:////tmp/runs/optuna.db",
        "sqlite:///runs/sweeps/td3x-pendulum/optuna.db",
        "postgresql://td3x@db-host:5432/td3x",  # no password: PGPASSWORD or ~/.pgpass gives it
        "postgresql://td3x:***@db-host:5432/td3x",  # masked already
        "journal:runs/study.log",
        "https://github.com/DLR-RM/stable-baselines3",
        "python run.py env=hopper algo=td3 seed=0 algo.tau=0.01 +tuned=best run_dir=runs/x",
        "run.py algo.net_arch=[64,64] max_tokens=5 norm_obs_keys=[a] key_fn=abs PWD=/work/main",
        "PGPASSWORD=<password> optuna-dashboard postgresql+psycopg2://td3x@db-host/td3x",  # a placeholder
        "",
    ],
)
def test_text_without_a_secret_is_left_as_it_is(text):
    assert redact(text) == text
    assert find_secrets(text) == []


@pytest.mark.parametrize(
    "text, shown",
    [
        ("run.py +env.kwargs.api_key=hunter2 seed=1", "run.py +env.kwargs.api_key=*** seed=1"),
        ("run.py +hydra.job.env_set.WANDB_API_KEY=abc123 seed=1", "run.py +hydra.job.env_set.WANDB_API_KEY=*** seed=1"),
        ("run.py key=abc env.kwargs.password='two words'", "run.py key=*** env.kwargs.password='***'"),
        ("run.py ++env.kwargs.token=t0k", "run.py ++env.kwargs.token=***"),
        ("WANDB_API_KEY=abc python run.py", "WANDB_API_KEY=*** python run.py"),
        ("export GITHUB_TOKEN=ghp_1 AWS_SECRET_ACCESS_KEY=x", "export GITHUB_TOKEN=*** AWS_SECRET_ACCESS_KEY=***"),
        ("PGPASSWORD=hunter2 optuna-dashboard postgresql://u@h/db", "PGPASSWORD=*** optuna-dashboard postgresql://u@h/db"),
        ("tool --password hunter2 --api-key=abc --storage x", "tool --password *** --api-key=*** --storage x"),
        ("postgresql://td3x@h/db?password=pw&sslmode=require", "postgresql://td3x@h/db?password=***&sslmode=require"),
    ],
)
def test_a_value_under_a_secret_name_is_masked(text, shown):
    assert redact(text) == shown
    assert redact(shown) == shown  # twice changes nothing
    assert find_secrets(text) == [(1, shown)] and find_secrets(shown) == []


def test_records_stay_json_and_yaml():
    record = json.dumps({"command": f"x --storage postgresql://u:{ENCODED}@h/db", "api_key": "a", "password": 12, "n": 1})
    shown = {"command": "x --storage postgresql://u:***@h/db", "api_key": MASK, "password": MASK, "n": 1}
    assert json.loads(redact(record)) == shown
    config = "env:\n  kwargs:\n    api_key: hunter2\n    secret: 'x y'\n  name: pendulum\ntoken: null\n"
    shown = {"env": {"kwargs": {"api_key": MASK, "secret": MASK}, "name": "pendulum"}, "token": None}
    assert yaml.safe_load(redact(config)) == shown
    assert redact("{'api_key': 'abc', 'seed': 0}") == "{'api_key': '***', 'seed': 0}"


def test_mappings_lists_and_environments():
    config = {"env": {"kwargs": {"api_key": "hunter2", "token": None, "credentials": {"user": "u"}}}, "seed": 0,
              "storage": "postgresql://u:pw@h/db", "tags": ["a", "b"]}  # fmt: skip
    assert redact(config) == {"env": {"kwargs": {"api_key": MASK, "token": None, "credentials": MASK}}, "seed": 0,
                              "storage": "postgresql://u:***@h/db", "tags": ["a", "b"]}  # fmt: skip
    assert config["env"]["kwargs"]["api_key"] == "hunter2"  # a copy: the caller's is left alone
    environment = {"WANDB_API_KEY": "k" * 40, "HF_TOKEN": "t", "PGPASSWORD": "p", "MY_SECRET": "s", "PATH": "/usr/bin",
                   "PWD": "/work", "OPTUNA_STORAGE": f"postgresql://u:{ENCODED}@h/db"}  # fmt: skip
    assert redact(environment) == {"WANDB_API_KEY": MASK, "HF_TOKEN": MASK, "PGPASSWORD": MASK, "MY_SECRET": MASK,
                                   "PATH": "/usr/bin", "PWD": "/work",
                                   "OPTUNA_STORAGE": "postgresql://u:***@h/db"}  # fmt: skip
    argv = ["sweeps", "--storage", "postgresql://u:pw@h/db", "--password", "hunter2", "env.kwargs.api_key=x", "--token=y"]
    assert redact(argv) == [
        "sweeps", "--storage", "postgresql://u:***@h/db", "--password", MASK, "env.kwargs.api_key=***", "--token=***"
    ]  # fmt: skip
    assert redact(("a", 1, None)) == ("a", 1, None) and redact(3.5) == 3.5


@pytest.mark.parametrize(
    "name, secret",
    [("WANDB_API_KEY", True), ("api_key", True), ("apiKey", True), ("key", True), ("env.kwargs.api_key", True),
     ("PGPASSWORD", True), ("DB_PASSWORD", True), ("GITHUB_TOKEN", True), ("MY_SECRET", True), ("passwd", True),
     ("AWS_SECRET_ACCESS_KEY", True), ("credentials", True), ("--api-key", True),
     ("PWD", False), ("OLDPWD", False), ("max_tokens", False), ("norm_obs_keys", False), ("keyboard", False),
     ("key_fn", False), ("seed", False), ("n_critics", False), ("total_timesteps", False), ("storage", False)],
)  # fmt: skip
def test_secret_names(name, secret):
    assert is_secret_name(name) == secret


def test_the_value_of_a_secret_environment_variable_is_masked_wherever_it_appears(monkeypatch):
    monkeypatch.setenv("WANDB_API_KEY", "0123456789abcdef-key")
    monkeypatch.setenv("SOME_TOKEN", "short")  # under 8 characters: too likely to be an ordinary word
    assert redact("wandb: using 0123456789abcdef-key, short") == "wandb: using ***, short"


@pytest.fixture
def log_record_factory():
    """Whatever a test installs as the log record factory is taken away after it."""
    factory = logging.getLogRecordFactory()
    yield
    logging.setLogRecordFactory(factory)


def test_log_lines_are_redacted(caplog, log_record_factory):
    redact_log_records()
    redact_log_records()  # once is enough: the second call does not wrap again
    log = logging.getLogger("sb3_td3x.test_secrets")
    with caplog.at_level(logging.INFO):
        log.info("study s in %s", f"postgresql://u:{ENCODED}@h/db")
        try:
            raise RuntimeError("password=hunter2")
        except RuntimeError:
            log.exception("failed")
    assert caplog.records[0].getMessage() == "study s in postgresql://u:***@h/db"
    assert "hunter2" not in caplog.text and ENCODED not in caplog.text and "password=***" in caplog.text


def test_the_check_names_the_file_and_line_and_never_shows_the_secret(tmp_path, capsys):
    clean, leaky = tmp_path / "config.yaml", tmp_path / "provenance.jsonl"
    clean.write_text("env:\n  kwargs:\n    api_key: '***'\n")
    leaky.write_text('{"at_step": 0}\n' + json.dumps({"command": f"sweeps --storage postgresql://u:{ENCODED}@h/db"}) + "\n")
    assert check_files([str(clean)]) == 0
    assert check_files([str(clean), str(leaky)]) == 3  # FOUND: not 1, which Python exits with on an error
    err = capsys.readouterr().err
    assert f"{leaky}:2: looks like a secret" in err and "postgresql://u:***@h/db" in err and ENCODED not in err
    assert check_files([str(tmp_path / "missing.json")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_tensorboard_text_and_hyperparameters_are_redacted(tmp_path):
    from stable_baselines3.common.logger import HParam

    from sb3_td3x.experiment.run.loggers import RedactedTensorBoardOutputFormat

    output = RedactedTensorBoardOutputFormat(str(tmp_path))
    values = {
        "cmd": f"sweeps --storage postgresql://u:{ENCODED}@h/db",
        "hp": HParam({"api_key": "abc123", "lr": 0.1}, {"m": 0}),
    }
    output.write(values, {key: None for key in values}, step=1)
    output.close()
    events = b"".join(path.read_bytes() for path in tmp_path.rglob("events.out.tfevents.*"))
    assert b"postgresql://u:***@h/db" in events and b"lr" in events
    assert ENCODED.encode() not in events and b"abc123" not in events
