"""Sweeps with ``seeds_per_trial: K``: each trial trains K seeds in one process and is scored by their aggregate.

The field checks and the trial plumbing (which seeds, which overrides, resuming) use a stand-in for training; the
last test is a real sweep on Pendulum-v1 whose trials train two seeds each with ``run_experiment``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import optuna
import pytest
import yaml
from optuna.trial import TrialState

from sb3_td3x.experiment.errors import TrainingInterrupted
from sb3_td3x.experiment.layout import LAST
from sb3_td3x.experiment.run.checkpoints import META_FILE, REPLAY_BUFFER_FILE, checkpoint_dir
from sb3_td3x.sweeps.cli import main
from sb3_td3x.sweeps.objective import DEFAULT_CONFIG_DIR, TrialObjective, compose_config
from sb3_td3x.sweeps.results import write_results
from sb3_td3x.sweeps.spec import load_sweep
from sb3_td3x.sweeps.storage import open_storage
from sb3_td3x.sweeps.worker import SweepInterrupted, open_study, run_worker

REPO = Path(__file__).resolve().parents[2]
SMOKE = REPO / "sweeps" / "pendulum_smoke.yaml"

pytestmark = [
    pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning"),
    pytest.mark.filterwarnings("ignore:Fixed parameter .* is out of range:UserWarning"),
]

VALID = """\
study_name: s
metric: eval/mean_return
direction: maximize
n_trials: 2
seed: 10
overrides: [env=pendulum]
sampler: {_target_: optuna.samplers.TPESampler, seed: 0, multivariate: true}
pruner: {_target_: optuna.pruners.MedianPruner}
search_space:
  algo.tau: {low: 0.001, high: 0.02, log: true}
"""


def sweep_file(tmp_path: Path, extra: str = "", text: str = VALID) -> Path:
    path = tmp_path / "sweep.yaml"
    path.write_text(text + extra)
    return path


def test_one_seed_per_trial_is_the_default():
    spec = load_sweep(SMOKE)
    assert (spec.seeds_per_trial, spec.seeds_aggregate) == (1, "mean")
    assert [spec.trial_seeds(n) for n in range(3)] == [[0], [1], [2]]  # seed + n, as before the field existed


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ("seeds_per_trial: 0\n", "seeds_per_trial must be an integer of at least 1"),
        ("seeds_per_trial: -2\n", "seeds_per_trial must be an integer of at least 1"),
        ("seeds_per_trial: two\n", "not 'two'"),
        ("seeds_per_trial: 1.5\n", "not 1.5"),
        ("seeds_per_trial: true\n", "not True"),
        ("seeds_per_trial: [1, 2]\n", "seeds_per_trial must be an integer"),
        ("seeds_aggregate: median\n", "seeds_aggregate must be one of mean, iqm (how a trial's seeds make its value), not"),
        ("seeds_aggregate: 3\n", "seeds_aggregate must be one of mean, iqm"),
        ("seeds_aggregate: null\n", "seeds_aggregate must be one of mean, iqm"),
    ],
)
def test_bad_seeds_fields_give_one_clear_error(extra, expected, tmp_path, capsys):
    code = main([str(sweep_file(tmp_path, extra)), "--output-dir", str(tmp_path / "runs"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"error: {tmp_path / 'sweep.yaml'}: ") and expected in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "runs").exists()


def test_seeds_is_set_by_the_sweep(tmp_path, capsys):
    path = sweep_file(tmp_path, text=VALID.replace("[env=pendulum]", "[env=pendulum, 'seeds=[1,2]']"))
    assert main([str(path), "--output-dir", str(tmp_path / "runs"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "seeds is set by the sweep" in err and "set seeds_per_trial" in err, err


def _run(spec, tmp_path: Path, objective: TrialObjective, n_trials: int) -> optuna.Study:
    study_storage = open_storage(f"sqlite:///{tmp_path / 'optuna.db'}", spec.study_name)
    study = open_study(spec, study_storage, spec.study_name, spec.overrides)
    run_worker(study, spec, study_storage, objective, n_trials=n_trials)
    return study


def test_trials_train_disjoint_seeds_and_pass_the_aggregate_to_the_runner(tmp_path):
    spec = load_sweep(sweep_file(tmp_path, "seeds_per_trial: 3\nseeds_aggregate: iqm\n"))
    calls = []

    def stand_in(cfg, report, seeds_aggregate, report_seeds):
        calls.append((cfg.seed, list(cfg.seeds), cfg.run_dir, seeds_aggregate))
        returns = {seed: -10.0 * seed for seed in cfg.seeds}
        report_seeds(150, returns)
        report(150, -123.0)
        return -123.0

    study = _run(spec, tmp_path, TrialObjective(spec, DEFAULT_CONFIG_DIR, [], tmp_path / "s", train_fn=stand_in), 2)
    first, second = study.get_trials()
    assert [c[:2] for c in calls] == [(10, [10, 11, 12]), (13, [13, 14, 15])]  # seed + n*K + j: no seed twice
    assert {c[3] for c in calls} == {"iqm"}
    assert calls[0][2] == str((tmp_path / "s" / "trial_0000").resolve())  # each seed's folder is <run_dir>/seed<s>
    assert first.state == second.state == TrialState.COMPLETE and first.value == -123.0
    assert first.user_attrs["seed"] == 10 and first.user_attrs["seeds"] == [10, 11, 12]
    assert first.user_attrs["seeds_aggregate"] == "iqm"
    assert first.user_attrs["seed_values"] == {"10": -100.0, "11": -110.0, "12": -120.0}
    assert first.user_attrs["seed_values_step"] == 150
    assert {"seed=10", "seeds=[10,11,12]"} <= set(first.user_attrs["overrides"])
    assert first.intermediate_values == {150: -123.0}


def test_one_seed_per_trial_calls_the_runner_as_before(tmp_path):
    spec = load_sweep(sweep_file(tmp_path))
    seeds = []

    def stand_in(cfg, report):  # no seed options: a trial of one seed is today's trial
        seeds.append((cfg.seed, cfg.get("seeds")))
        report(150, -1.0)
        return -1.0

    study = _run(spec, tmp_path, TrialObjective(spec, DEFAULT_CONFIG_DIR, [], tmp_path / "s", train_fn=stand_in), 2)
    assert seeds == [(10, None), (11, None)]
    assert all("seeds" not in t.user_attrs and "seed_values" not in t.user_attrs for t in study.get_trials())
    assert not any(o.startswith("seeds=") for o in study.get_trials()[0].user_attrs["overrides"])


def test_an_interrupted_trial_of_several_seeds_resumes_from_its_first_seeds_folder(tmp_path):
    spec = load_sweep(sweep_file(tmp_path, "seeds_per_trial: 2\n"))
    calls = []

    def stand_in(cfg, report, seeds_aggregate, report_seeds):
        calls.append((list(cfg.seeds), cfg.run_dir, cfg.resume))
        if len(calls) == 1:  # the runner checkpointed each seed on SIGINT; resuming needs the first one's
            report_seeds(150, {10: -5.0, 11: -7.0})
            report(150, -6.0)
            last = checkpoint_dir(Path(cfg.run_dir) / "seed10", LAST)
            last.mkdir(parents=True)
            (last / META_FILE).write_text("{}")
            (last / REPLAY_BUFFER_FILE).write_bytes(b"")
            raise TrainingInterrupted("SIGINT", 130, 150, cfg.run_dir)
        report_seeds(300, {10: -3.0, 11: -1.0})
        report(300, -2.0)
        return -2.0

    objective = TrialObjective(spec, DEFAULT_CONFIG_DIR, [], tmp_path / "s", train_fn=stand_in)
    with pytest.raises(SweepInterrupted):
        _run(spec, tmp_path, objective, 1)
    study = _run(spec, tmp_path, objective, 1)
    interrupted, resumed = study.get_trials()
    run_dir = str((tmp_path / "s" / "trial_0000").resolve())
    assert calls == [([10, 11], run_dir, None), ([10, 11], run_dir, f"{run_dir}/seed10")]
    assert interrupted.state == TrialState.FAIL and resumed.state == TrialState.COMPLETE and resumed.value == -2.0
    assert resumed.user_attrs["seeds"] == [10, 11] and f"resume={run_dir}/seed10" in resumed.user_attrs["overrides"]
    assert resumed.user_attrs["seed_values"] == {"10": -3.0, "11": -1.0} and resumed.user_attrs["seed_values_step"] == 300


def _evaluations(seed_dir: Path) -> dict[int, float]:
    with open(seed_dir / "evaluations.csv") as file:
        return {int(row["timesteps"]): float(row["mean_return"]) for row in csv.DictReader(file)}


def test_a_sweep_of_two_seeds_per_trial_is_scored_by_their_mean(tmp_path):
    """Real training: trial 0 completes, trial 1 is pruned at its first evaluation (a threshold above any Pendulum
    return, so that which trial stops does not hang on the returns). The value and every reported step are the mean
    of the two seeds' own evaluations, which differ, so one seed's value would fail."""
    text = SMOKE.read_text().replace("\nseed: 0\n", "\nseed: 10\n") + "seeds_per_trial: 2\n"
    spec = load_sweep(sweep_file(tmp_path, text=text))
    assert spec.seeds_per_trial == 2 and spec.seeds_aggregate == "mean"
    study_dir = tmp_path / spec.study_name
    study_storage = open_storage(f"sqlite:///{study_dir / 'optuna.db'}", spec.study_name)
    study = open_study(spec, study_storage, spec.study_name, spec.overrides)
    objective = TrialObjective(spec, DEFAULT_CONFIG_DIR, ["total_timesteps=300"], study_dir)  # evaluations at 150, 300
    study.pruner = optuna.pruners.NopPruner()
    run_worker(study, spec, study_storage, objective, n_trials=1)
    study.pruner = optuna.pruners.ThresholdPruner(lower=0.0)  # Pendulum's returns are negative
    run_worker(study, spec, study_storage, objective, n_trials=2)
    complete, pruned = study.get_trials()

    assert complete.state == TrialState.COMPLETE and complete.user_attrs["seeds"] == [10, 11]
    run_dir = Path(complete.user_attrs["run_dir"])
    summaries = {seed: json.loads((run_dir / f"seed{seed}" / "summary.json").read_text()) for seed in (10, 11)}
    assert [summaries[seed]["seed"] for seed in (10, 11)] == [10, 11]
    finals = {seed: summaries[seed]["final_mean_return"] for seed in (10, 11)}
    assert abs(finals[10] - finals[11]) > 1.0, "the seeds must differ for the mean to tell them apart"
    assert complete.value == pytest.approx((finals[10] + finals[11]) / 2, rel=1e-9, abs=1e-9)
    assert complete.user_attrs["seed_values"] == pytest.approx({"10": finals[10], "11": finals[11]})
    assert complete.user_attrs["seed_values_step"] == 300
    evaluations = {seed: _evaluations(run_dir / f"seed{seed}") for seed in (10, 11)}
    assert set(complete.intermediate_values) == {150, 300}
    for step, value in complete.intermediate_values.items():  # the pruner saw the mean at every evaluation
        assert value == pytest.approx((evaluations[10][step] + evaluations[11][step]) / 2, rel=1e-9, abs=1e-9)
    assert {"seed=10", "seeds=[10,11]"} <= set(complete.user_attrs["overrides"])

    assert pruned.state == TrialState.PRUNED and pruned.user_attrs["seeds"] == [12, 13]
    assert list(pruned.intermediate_values) == [150]
    assert "ThresholdPruner at step 150 (evaluation mean return of seeds [12, 13]" in pruned.user_attrs["prune_reason"]
    assert pruned.user_attrs["seed_values_step"] == 150 and set(pruned.user_attrs["seed_values"]) == {"12", "13"}
    assert pruned.intermediate_values[150] == pytest.approx(sum(pruned.user_attrs["seed_values"].values()) / 2)
    for seed in (12, 13):  # every seed was checkpointed when the pruner stopped the trial
        assert (checkpoint_dir(Path(pruned.user_attrs["run_dir"]) / f"seed{seed}", LAST) / META_FILE).is_file()

    files = write_results(study, study_dir, DEFAULT_CONFIG_DIR, "sqlite", "optuna-dashboard")
    assert f"mean of 2 seeds: 10 {finals[10]:.2f}, 11 {finals[11]:.2f}" in files.summary
    best_overrides = files.best_overrides.read_text().split()
    assert "seeds=[10,11]" in best_overrides and "seed=10" in best_overrides
    assert list(compose_config(best_overrides, DEFAULT_CONFIG_DIR).seeds) == [10, 11]
    assert yaml.safe_load((study_dir / "tuned" / "best.yaml").read_text())["seeds"] == [10, 11]


def test_an_interrupted_trial_of_two_seeds_resumes_both_where_they_stopped(tmp_path):
    """Real training: Ctrl-C after the first evaluation (raised from the report, where the runner checkpoints every
    seed), then the queued copy resumes with ``resume=<trial>/seed10``: both seeds go on from step 150 in their own
    folders instead of starting again."""
    from sb3_td3x.experiment.runner import run_experiment

    text = SMOKE.read_text().replace("\nseed: 0\n", "\nseed: 10\n") + "seeds_per_trial: 2\n"
    spec = load_sweep(sweep_file(tmp_path, text=text))
    study_dir = tmp_path / spec.study_name

    def ctrl_c_at_the_first_evaluation(cfg, report, **seed_options):
        def interrupting(num_timesteps, value):
            report(num_timesteps, value)
            if cfg.resume is None:
                raise KeyboardInterrupt

        return run_experiment(cfg, report=interrupting, **seed_options)

    objective = TrialObjective(spec, DEFAULT_CONFIG_DIR, ["total_timesteps=300"], study_dir, ctrl_c_at_the_first_evaluation)
    with pytest.raises(SweepInterrupted):
        _run(spec, tmp_path, objective, 1)
    study = _run(spec, tmp_path, objective, 1)
    interrupted, resumed = study.get_trials()
    run_dir = Path(interrupted.user_attrs["run_dir"])
    assert interrupted.state == TrialState.FAIL and interrupted.user_attrs["fail_reason"] == "interrupted by SIGINT"
    assert resumed.state == TrialState.COMPLETE and resumed.user_attrs["seeds"] == [10, 11]
    assert f"resume={run_dir / 'seed10'}" in resumed.user_attrs["overrides"]
    assert sorted(path.name for path in run_dir.iterdir() if path.name.startswith("seed")) == ["seed10", "seed11"]
    nested = sorted(str(path.relative_to(run_dir)) for path in (run_dir / "seed10").glob("seed*"))
    assert not nested, f"the resumed seeds must go on in trial_0000/seed<s>, not start again in trial_0000/{nested}"
    assert list(interrupted.intermediate_values) == [150] and list(resumed.intermediate_values) == [300]
    finals = {}
    for seed in (10, 11):  # each seed evaluated once at 150 (before Ctrl-C) and once at 300 (after resuming)
        assert list(_evaluations(run_dir / f"seed{seed}")) == [150, 300]
        finals[seed] = json.loads((run_dir / f"seed{seed}" / "summary.json").read_text())["final_mean_return"]
    assert resumed.value == pytest.approx((finals[10] + finals[11]) / 2, rel=1e-9, abs=1e-9)
