"""Sweep files, storages and the trial budget, without training: every ready search composes with conf/, bad
input gives one clear message (never a traceback), and trials are counted exactly."""

from __future__ import annotations

import time
from pathlib import Path

import optuna
import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser
from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution
from optuna.storages import RetryHeartbeatStaleTrialCallback
from optuna.trial import TrialState

from sb3_td3x.experiment.configs.compose import check_config
from sb3_td3x.sweeps.cli import main
from sb3_td3x.sweeps.errors import SweepSpecError
from sb3_td3x.sweeps.launch import load_launcher
from sb3_td3x.sweeps.objective import DEFAULT_CONFIG_DIR, TrialObjective, check_composes, compose_config
from sb3_td3x.sweeps.spec import load_sweep, override_value, parse_param
from sb3_td3x.sweeps.storage import StudyStorage, open_storage
from sb3_td3x.sweeps.worker import budget_used, claim_trial, open_study, run_worker

REPO = Path(__file__).resolve().parents[2]
SWEEP_FILES = sorted((REPO / "sweeps").glob("*.yaml"))
LAUNCHER_FILES = sorted((REPO / "sweeps" / "launcher").glob("*.yaml"))

VALID = """\
study_name: t
metric: eval/mean_return
direction: maximize
n_trials: 2
overrides: [env=pendulum]
sampler: {_target_: optuna.samplers.TPESampler, seed: 0, multivariate: true}
pruner: {_target_: optuna.pruners.MedianPruner}
search_space:
  algo.tau: {low: 0.001, high: 0.02, log: true}
"""


def test_the_ready_searches_exist():
    names = {path.stem for path in SWEEP_FILES}
    assert {"pendulum", "pendulum_smoke", "hopper", "halfcheetah", "walker2d", "ant"} <= names


@pytest.mark.parametrize("path", SWEEP_FILES, ids=lambda p: p.name)
def test_every_sweep_file_loads_and_composes_with_conf(path):
    spec = load_sweep(path)
    assert spec.direction == "maximize"
    sampler = spec.make_sampler()
    assert isinstance(sampler, optuna.samplers.TPESampler) and sampler._multivariate
    assert spec.sampler.get("seed") is not None, "ready searches use a seeded sampler"
    check_composes(spec, DEFAULT_CONFIG_DIR, [])
    # every choice and both ends of every range compose too, not only the first: config k takes value k of each
    values = {
        p.path: p.distribution.choices
        if isinstance(p.distribution, CategoricalDistribution)
        else (p.distribution.low, p.distribution.high)
        for p in spec.params
    }
    for k in range(max(len(v) for v in values.values())):
        overrides = [p.override(values[p.path][k % len(values[p.path])]) for p in spec.params]
        cfg = compose_config(spec.overrides + overrides + ["run_dir=/tmp/x"], DEFAULT_CONFIG_DIR)
        check_config(cfg)


@pytest.mark.parametrize("path", LAUNCHER_FILES, ids=lambda p: p.name)
def test_launcher_files_follow_the_submitit_launcher_schema(path, tmp_path):
    cluster, params = load_launcher(path, tmp_path / "jobs", "sweep-x")
    assert cluster in ("slurm", "local")
    assert params["folder"] == str(tmp_path / "jobs" / "%j")
    assert params["parameters"]["name"] == "sweep-x"
    if cluster == "slurm":
        assert "slurm_partition" in params["parameters"] and "timeout_min" in params["parameters"]


@pytest.mark.parametrize(
    "value",
    [0.0003, 1e-05, 3, True, None, "relu", "two words", [64, 64], [400, 300], {"a": 1, "b": [1, 2]}],
)
def test_override_values_read_back_as_the_same_value(value):
    parsed = OverridesParser.create().parse_override(f"algo.x={override_value(value)}").value()
    assert parsed == value


def test_list_choices_are_stored_as_their_override_text():
    param = parse_param("algo.net_arch", {"choices": [[64, 64], [256, 256]]}, Path("f.yaml"))
    assert param.distribution.choices == ("[64,64]", "[256,256]")
    assert param.override("[64,64]") == "algo.net_arch=[64,64]"
    assert parse_param("algo.policy_delay", {"low": 1, "high": 4}, Path("f")).distribution == IntDistribution(1, 4)
    assert parse_param("algo.tau", {"low": 1, "high": 2, "type": "float"}, Path("f")).distribution == FloatDistribution(
        1.0, 2.0
    )


MALFORMED = {
    "not_yaml": ("study_name: [unclosed\n", "is not valid YAML"),
    "missing_fields": ("study_name: t\n", "lacks the field(s)"),
    "unknown_field": (VALID + "n_trial: 3\n", "n_trial"),
    "wrong_type": (VALID.replace("n_trials: 2", "n_trials: many"), "n_trials"),
    "entry_not_mapping": (VALID.replace("{low: 0.001, high: 0.02, log: true}", "0.01"), "must be a mapping"),
    "empty_range": (VALID.replace("low: 0.001, high: 0.02", "low: 0.02, high: 0.001"), "must be smaller than high"),
    "log_of_zero": (VALID.replace("low: 0.001", "low: 0.0"), "log range needs low > 0"),
    "unknown_key": (VALID.replace("log: true", "logarithmic: true"), "logarithmic"),
    "empty_choices": (VALID.replace("{low: 0.001, high: 0.02, log: true}", "{choices: []}"), "non-empty list"),
    "minimize_a_return": (VALID.replace("maximize", "minimize"), "direction must be 'maximize'"),
    "unknown_metric": (VALID.replace("eval/mean_return", "reward"), "metric must be one of"),
    "sampler_without_target": (VALID.replace("_target_: optuna.samplers.TPESampler, ", ""), "needs a '_target_'"),
    "sampler_not_found": (VALID.replace("TPESampler", "TPESamplr"), "cannot build the sampler"),
    "pruner_is_not_a_pruner": (
        VALID.replace("optuna.pruners.MedianPruner", "optuna.samplers.RandomSampler"),
        "not an Optuna BasePruner",
    ),
    "unknown_config_path": (VALID.replace("algo.tau", "algo.tua"), "do not compose"),
    "choice_of_wrong_type": (
        VALID.replace("{low: 0.001, high: 0.02, log: true}", "{choices: [fast, slow]}"),
        "do not compose",
    ),
    "searched_and_fixed": (VALID.replace("[env=pendulum]", "[env=pendulum, algo.tau=0.01]"), "both searched"),
    "seed_searched": (VALID + "  seed: {low: 0, high: 9}\n", "seed is set by the sweep"),
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_a_malformed_sweep_file_gives_one_clear_error(name, tmp_path, capsys):
    text, expected = MALFORMED[name]
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    code = main([str(path), "--output-dir", str(tmp_path / "runs"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: ") and expected in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "runs").exists(), "nothing is created before the sweep file is known to be good"


def test_a_missing_sweep_file_is_a_clear_error(tmp_path, capsys):
    assert main([str(tmp_path / "nope.yaml")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("storage", "expected"),
    [
        ("postgres://td3x:s3cret@127.0.0.1:9/td3x", "write postgresql://"),
        ("not-a-storage", "neither a database URL nor a journal file"),
        ("sqlite:////proc/no/such/dir/optuna.db", "cannot create the folder"),
    ],
)
def test_a_bad_storage_gives_one_clear_error(storage, expected, tmp_path, capsys):
    path = tmp_path / "ok.yaml"
    path.write_text(VALID)
    assert main([str(path), "--storage", storage, "--output-dir", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err and "s3cret" not in err, err


def test_an_unreachable_database_gives_one_clear_error(tmp_path, capsys):
    path = tmp_path / "ok.yaml"
    path.write_text(VALID)
    storage = "postgresql://td3x:s3cret@127.0.0.1:9/td3x"  # nothing listens on port 9
    assert main([str(path), "--storage", storage, "--output-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot open storage postgresql"), err
    assert "td3x:***@127.0.0.1:9/td3x" in err and "Connection refused" in err
    assert "Traceback" not in err and "s3cret" not in err


def test_passwords_are_masked_in_what_is_shown():
    assert StudyStorage("postgresql://u:pw@h:5432/db", None, None, 60).display_url == "postgresql://u:***@h:5432/db"
    assert StudyStorage("sqlite:///a.db", None, None, 60).display_url == "sqlite:///a.db"


def _objective(trial: optuna.Trial) -> float:
    return trial.suggest_float("x", 0.0, 1.0)


@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
def test_the_budget_counts_every_trial_except_failed_ones_queued_again(tmp_path):
    """n_trials is the study's total: a failed-and-retried trial is replaced by its retry, not counted twice."""
    spec = load_sweep(REPO / "sweeps" / "pendulum_smoke.yaml")
    storage = optuna.storages.InMemoryStorage()
    study_storage = StudyStorage("memory", storage, lambda: __import__("contextlib").nullcontext(), None)
    study = optuna.create_study(storage=storage, direction="maximize")
    claimed = []
    while (trial := claim_trial(study, spec, study_storage, n_trials=3)) is not None:
        claimed.append(trial.number)
        study.tell(trial, state=TrialState.FAIL) if trial.number == 1 else study.tell(trial, 1.0)
        if trial.number == 1:
            failed = study.get_trials(deepcopy=True)[1]
            RetryHeartbeatStaleTrialCallback(max_retry=1)(study, failed)  # what --retry-stale does for a dead worker
    trials = study.get_trials(deepcopy=False)
    assert claimed == [0, 1, 2, 3]  # trial 2 is the retry of 1 (taken from the queue), trial 3 the last new one
    assert RetryHeartbeatStaleTrialCallback.retried_trial_number(trials[2]) == 1
    assert budget_used(trials) == 3
    assert claim_trial(study, spec, study_storage, n_trials=3) is None


def test_workers_draw_different_startup_points():
    """The sampler is reseeded per trial, so two workers sharing the file's seed do not repeat each other."""
    spec = load_sweep(REPO / "sweeps" / "pendulum_smoke.yaml")
    draws = []
    for offset in (0, 1):
        study = optuna.create_study(direction="maximize", sampler=spec.make_sampler(seed_offset=offset))
        trial = study.ask()
        draws.append(spec.params[0].suggest(trial))
    assert draws[0] != draws[1]
    with pytest.raises(SweepSpecError):
        parse_param("algo.x", {"low": 1, "high": 2, "step": 0.3, "type": "int"}, Path("f"))


def test_report_on_a_study_that_does_not_exist_is_a_clear_error(tmp_path, capsys):
    path = tmp_path / "ok.yaml"
    path.write_text(VALID)
    assert main([str(path), "--report", "--output-dir", str(tmp_path), "--quiet"]) == 2
    assert "there is no study 't' in sqlite:///" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
def test_a_journal_file_holds_a_study_to_its_budget(tmp_path):
    """The journal storage (no database, no heartbeat) through the whole worker loop. Training is replaced by a
    stand-in here: this test is about the storage; the real runner is in test_sweeps_pendulum.py."""
    spec = load_sweep(REPO / "sweeps" / "pendulum_smoke.yaml")
    journal = tmp_path / "study.log"
    study_storage = open_storage(f"journal:{journal}", "j")
    assert study_storage.heartbeat_interval is None
    assert study_storage.dashboard_command() == f"optuna-dashboard {journal}"
    study = open_study(spec, study_storage, "j", spec.overrides)

    def stand_in(cfg, report):
        report(150, -1000.0 * cfg.algo.tau)
        return -1000.0 * cfg.algo.tau

    objective = TrialObjective(spec, DEFAULT_CONFIG_DIR, [], tmp_path / "j", train_fn=stand_in)
    assert run_worker(study, spec, study_storage, objective, n_trials=3).ran == [0, 1, 2]
    assert (tmp_path / "study.log.sweep-lock").exists()
    reopened = optuna.load_study(study_name="j", storage=open_storage(str(journal), "j").storage)
    assert [t.state for t in reopened.trials] == [TrialState.COMPLETE] * 3
    assert reopened.trials[0].user_attrs["overrides"][-1] == f"run_dir={(tmp_path / 'j' / 'trial_0000').resolve()}"


@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
def test_a_dead_workers_trial_goes_stale_and_is_run_again_with_retry_stale(tmp_path):
    """A trial whose worker stopped sending heartbeats is marked FAIL by the next worker and, with
    ``--retry-stale 1``, queued again with the same parameters and run. Training is a stand-in here; the real
    kill is in test_sweeps_postgres.py."""
    spec = load_sweep(REPO / "sweeps" / "pendulum_smoke.yaml")
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    study_storage = open_storage(url, "s", heartbeat_interval=1, grace_period=2, retry_stale=1)
    study = open_study(spec, study_storage, "s", spec.overrides)
    dead = claim_trial(study, spec, study_storage, n_trials=2)  # claimed by a "worker" that then dies silently
    dead_params = {p.path: p.suggest(dead) for p in spec.params}
    time.sleep(3)

    def stand_in(cfg, report):
        report(150, -1000.0 * cfg.algo.tau)
        return -1000.0 * cfg.algo.tau

    objective = TrialObjective(spec, DEFAULT_CONFIG_DIR, [], tmp_path / "s", train_fn=stand_in)
    summary = run_worker(study, spec, study_storage, objective, n_trials=2)
    trials = study.get_trials()
    assert trials[0].state == TrialState.FAIL and trials[0].params == dead_params
    assert summary.ran == [1, 2] and summary.study_finished
    assert RetryHeartbeatStaleTrialCallback.retried_trial_number(trials[1]) == 0 and trials[1].params == dead_params
    assert trials[1].state == trials[2].state == TrialState.COMPLETE
    assert budget_used(trials) == 2
