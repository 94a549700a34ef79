"""The aggregation command: statistics over seeds and the table/plots it writes from run folders."""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from sb3_td3x.experiment.analysis.aggregate import bootstrap_ci, iqm, main
from sb3_td3x.experiment.analysis.statistics import difference_ci, permutation_p_value


def test_iqm_drops_the_lowest_and_highest_quarter():
    assert iqm(np.array([0.0, 1.0, 2.0, 3.0, 100.0])) == pytest.approx(2.0)  # n=5: one value cut at each end
    assert iqm(np.array([[1.0, 2.0, 3.0, 4.0]]), axis=-1) == pytest.approx([2.5])
    assert iqm(np.array([5.0])) == 5.0


def test_bootstrap_interval_brackets_the_mean_and_narrows_with_more_seeds():
    rng = np.random.default_rng(1)
    few, many = rng.normal(10, 2, size=(1, 5)), rng.normal(10, 2, size=(1, 200))
    (low_few,), (high_few,) = bootstrap_ci(few, lambda v, axis: v.mean(axis=axis))
    (low_many,), (high_many,) = bootstrap_ci(many, lambda v, axis: v.mean(axis=axis))
    assert low_few <= few.mean() <= high_few and low_many <= many.mean() <= high_many
    assert high_many - low_many < high_few - low_few
    assert 9.0 < low_many < 10.0 < high_many < 11.0


def brute_force_p_value(a, b, statistic=np.mean):
    """The two-sided permutation p-value of the difference of ``statistic``, by a plain loop over every split."""
    pooled, observed, splits, as_large = list(a) + list(b), abs(statistic(a) - statistic(b)), 0, 0
    for first in itertools.combinations(range(len(pooled)), len(a)):
        second = [i for i in range(len(pooled)) if i not in first]
        splits += 1
        difference = statistic(np.array([pooled[i] for i in first])) - statistic(np.array([pooled[i] for i in second]))
        as_large += abs(difference) >= observed - 1e-9
    return as_large / splits


def test_permutation_test_counts_the_splits_at_least_as_far_apart():
    # 3 against 3 wholly apart: only the observed split and its mirror are as far apart, 2 of the 20
    assert permutation_p_value([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]) == pytest.approx(0.1)
    assert permutation_p_value([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 1.0  # no difference: every split is as far
    rng = np.random.default_rng(3)
    for n_a, n_b in ((5, 5), (4, 6), (2, 3)):
        a, b = rng.normal(0, 1, n_a), rng.normal(0.8, 1, n_b)
        assert permutation_p_value(a, b) == pytest.approx(brute_force_p_value(a, b))
    # Too many splits to list (C(40, 20)): a Monte Carlo estimate, never 0, small for groups far apart
    far = permutation_p_value(rng.normal(0, 1, 20), rng.normal(3, 1, 20), n_resamples=2000)
    assert 0 < far <= 1 / 2001 + 1e-12
    same = permutation_p_value(rng.normal(0, 1, 20), rng.normal(0, 1, 20), n_resamples=2000)
    assert same > 0.01
    # The statistic is the one given: one outlier seed decides every split's difference of means, not of IQMs
    outlier, ones = [0.0, 0.0, 0.0, 0.0, 1000.0], [1.0] * 5
    assert permutation_p_value(outlier, ones) == 1.0
    assert permutation_p_value(outlier, ones, statistic=iqm) == pytest.approx(brute_force_p_value(outlier, ones, iqm))
    assert permutation_p_value(outlier, ones, statistic=iqm) < 0.05


def test_difference_interval_brackets_the_difference_and_excludes_zero_only_when_apart():
    rng = np.random.default_rng(2)
    a, b = rng.normal(10, 1, 10), rng.normal(5, 1, 10)
    low, high = difference_ci(a, b)
    assert 0 < low < a.mean() - b.mean() < high
    low, high = difference_ci(b, a)
    assert low < b.mean() - a.mean() < high < 0
    low, high = difference_ci(rng.normal(0, 1, 10), rng.normal(0, 1, 10))
    assert low < 0 < high


def write_run(run_dir, env_id, algo, seed, returns):
    run_dir.mkdir(parents=True)
    OmegaConf.save(OmegaConf.create({"env": {"id": env_id}, "algo": {"name": algo}, "seed": seed}), run_dir / "config.yaml")
    steps = [1000 * (i + 1) for i in range(len(returns))]
    pd.DataFrame({"timesteps": steps, "mean_return": returns, "std_return": 0.0}).to_csv(
        run_dir / "evaluations.csv", index=False
    )


def test_the_command_writes_a_table_and_one_plot_per_env(tmp_path, capsys):
    for seed in range(3):
        write_run(tmp_path / "runs" / f"td3_{seed}", "Hopper-v5", "td3", seed, [10.0 * seed, 100.0 + seed, 200.0 + seed])
        write_run(tmp_path / "runs" / f"ddpg_{seed}", "Hopper-v5", "ddpg", seed, [1.0, 2.0, 3.0 + seed])
    write_run(tmp_path / "runs" / "short", "Ant-v5", "td3", 0, [5.0])
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    table = pd.read_csv(tmp_path / "out" / "aggregate.csv")
    hopper_td3 = table[(table.env_id == "Hopper-v5") & (table.algo == "td3")].iloc[0]
    assert hopper_td3.n_runs == 3 and hopper_td3.timesteps == 3000
    assert hopper_td3.final_mean == pytest.approx(201.0) and hopper_td3.ci_low <= 201.0 <= hopper_td3.ci_high
    assert hopper_td3.seeds == "0, 1, 2"  # each seed's final return, in seed order, for the results pages
    assert [float(x) for x in hopper_td3.per_seed_final.split(", ")] == [200.0, 201.0, 202.0]
    assert len(table) == 3
    assert (tmp_path / "out" / "aggregate_Hopper-v5.png").is_file() and (tmp_path / "out" / "aggregate_Ant-v5.png").is_file()
    assert "| Hopper-v5 | td3 | 3 | 3000 | 201.0 |" in capsys.readouterr().out


def test_the_command_compares_each_pair_of_algos_of_an_env(tmp_path, capsys):
    for seed in range(3):
        write_run(tmp_path / "runs" / f"td3_{seed}", "Hopper-v5", "td3", seed, [10.0 * seed, 100.0 + seed, 200.0 + seed])
        write_run(tmp_path / "runs" / f"ddpg_{seed}", "Hopper-v5", "ddpg", seed, [1.0, 2.0, 3.0 + seed, 4.0])
    write_run(tmp_path / "runs" / "ant", "Ant-v5", "td3", 0, [5.0])  # one algo on Ant: nothing to compare
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    compared = pd.read_csv(tmp_path / "out" / "compare.csv")
    assert len(compared) == 1
    row = compared.iloc[0]
    assert (row.env_id, row.algo_a, row.algo_b, row.n_a, row.n_b) == ("Hopper-v5", "ddpg", "td3", 3, 3)
    assert row.timesteps == 3000 and row.n_evaluations == 3  # ddpg's 4th evaluation has no td3 one beside it
    # final: ddpg 3, 4, 5 against td3 200, 201, 202; curve: each run's mean over the 3 shared evaluations
    assert row.final_difference == pytest.approx(4.0 - 201.0) and row.final_p_value == pytest.approx(0.1)
    assert row.final_ci_low <= -197.0 <= row.final_ci_high < 0
    ddpg_curves = [(1.0 + 2.0 + 3.0 + s) / 3 for s in range(3)]
    td3_curves = [(10.0 * s + 100.0 + s + 200.0 + s) / 3 for s in range(3)]
    assert row.curve_difference == pytest.approx(np.mean(ddpg_curves) - np.mean(td3_curves))
    assert row.curve_p_value == pytest.approx(brute_force_p_value(ddpg_curves, td3_curves))
    assert "| Hopper-v5 | ddpg | td3 | 3 | 3 | 3000 | -197.0 (" in capsys.readouterr().out
    # Aggregated again without a second algo, the folder keeps no comparison of the earlier runs
    assert main([str(tmp_path / "runs" / "ant"), "--out", str(tmp_path / "out")]) == 0
    assert not (tmp_path / "out" / "compare.csv").exists()


def test_two_folders_of_one_seed_are_refused_and_one_folder_given_twice_counts_once(tmp_path, capsys, monkeypatch):
    runs = tmp_path / "runs"
    for seed in range(2):
        write_run(runs / "td3" / f"seed{seed}", "Hopper-v5", "td3", seed, [100.0, 200.0 + seed])
    # A run started again, its first try kept beside it (as scripts/results.sh once did): not a third seed
    write_run(runs / "td3" / "seed0.unfinished", "Hopper-v5", "td3", 0, [5.0])
    write_run(runs / "ddpg" / "seed0", "Hopper-v5", "ddpg", 0, [1.0, 2.0])  # the same seed of another algo: fine
    assert main([str(runs), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert "2 run folders of Hopper-v5, algo td3, seed 0" in error and "seed0.unfinished" in error, error
    assert "name the run folders to aggregate" in error and not (tmp_path / "out" / "aggregate.csv").exists()
    # The run folders named, one of them through two paths spelled otherwise (absolute, relative): each counted once
    monkeypatch.chdir(tmp_path)
    named = [str(runs / "td3" / "seed0"), str(runs / "td3" / "seed1"), "runs/td3", "runs/ddpg"]
    (runs / "td3" / "seed0.unfinished" / "config.yaml").unlink()  # no longer a run folder
    assert main([*named, "--out", str(tmp_path / "out")]) == 0
    table = pd.read_csv(tmp_path / "out" / "aggregate.csv").set_index("algo")
    assert table.loc["td3", "n_runs"] == 2 and table.loc["td3", "final_mean"] == pytest.approx(200.5)
    assert table.loc["ddpg", "n_runs"] == 1


def test_the_command_says_when_there_is_nothing_to_aggregate(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "No run folder" in capsys.readouterr().err


def write_value_run(run_dir, algo, seed, estimates, true_values):
    """A run whose evaluations measured the critic's value (the columns of eval.value_bias)."""
    write_run(run_dir, "Hopper-v5", algo, seed, [1.0] * len(estimates))
    evaluations = pd.read_csv(run_dir / "evaluations.csv")
    estimates, true_values = np.array(estimates), np.array(true_values)
    evaluations = evaluations.assign(value_estimate=estimates, true_value=true_values, overestimation=estimates - true_values,
                                     normalized_bias=(estimates - true_values) / np.abs(true_values), value_states=100)
    evaluations.to_csv(run_dir / "evaluations.csv", index=False)


def test_the_value_columns_are_aggregated_over_seeds_and_runs_without_them_still_aggregate(tmp_path, capsys):
    runs = tmp_path / "runs"
    for seed in range(3):
        write_value_run(runs / f"ddpg_{seed}", "ddpg", seed, [20.0, 30.0 + seed, 40.0 + 2 * seed], [10.0, 10.0, 20.0])
    write_value_run(runs / "td3_0", "td3", 0, [5.0, float("nan"), 8.0], [10.0, 10.0, 10.0])  # NaN: no state that time
    write_run(runs / "td3_old", "Hopper-v5", "td3", 1, [1.0, 2.0, 3.0])  # made before the value columns
    assert main([str(runs), "--out", str(tmp_path / "out")]) == 0
    table = pd.read_csv(tmp_path / "out" / "aggregate.csv")  # returns: every run, the old one included
    assert table.set_index("algo").loc["td3", "n_runs"] == 2
    values = pd.read_csv(tmp_path / "out" / "value_bias.csv").set_index("algo")
    ddpg, td3 = values.loc["ddpg"], values.loc["td3"]
    assert ddpg.n_runs == 3 and ddpg.timesteps == 3000 and ddpg.seeds == "0, 1, 2"
    assert ddpg.value_estimate == pytest.approx(42.0) and ddpg.true_value == pytest.approx(20.0)
    assert ddpg.overestimation == pytest.approx(22.0) and ddpg.normalized_bias == pytest.approx(1.1)
    assert ddpg.overestimation_ci_low <= 22.0 <= ddpg.overestimation_ci_high and ddpg.overestimation_ci_low == 20.0
    assert ddpg.per_seed_overestimation == "20.0, 22.0, 24.0"
    assert td3.n_runs == 1 and td3.timesteps == 3000 and td3.overestimation == pytest.approx(-2.0)
    assert td3.normalized_bias == pytest.approx(-0.2)
    assert (tmp_path / "out" / "value_bias_Hopper-v5.png").is_file()
    assert "| Hopper-v5 | ddpg | 3 | 3000 | 42.0 | 20.0 | 22.0 | 1.100 | 20.0, 22.0, 24.0 |" in capsys.readouterr().out
    # DDPG's overestimation against TD3's: at the last step (22 against -2), and over the steps both measured (td3's
    # NaN at 2000 leaves 1000 and 3000: ddpg 10 then 20, 22, 24; td3 -5 then -2); 3 seeds against 1: 4 splits
    compared = pd.read_csv(tmp_path / "out" / "value_bias_compare.csv").iloc[0]
    assert (compared.algo_a, compared.algo_b, compared.n_a, compared.n_b) == ("ddpg", "td3", 3, 1)
    assert compared.n_evaluations == 2 and compared.final_difference == pytest.approx(24.0)
    assert compared.curve_difference == pytest.approx(np.mean([15.0, 16.0, 17.0]) - (-3.5))
    assert compared.final_p_value == pytest.approx(0.25)  # td3's lone seed is the farthest of the 4
    assert np.isnan(compared.final_ci_low) and np.isnan(compared.curve_ci_high)  # one td3 seed: no spread to resample


def test_runs_without_the_value_columns_write_no_value_table(tmp_path):
    write_run(tmp_path / "runs" / "old", "Hopper-v5", "td3", 0, [1.0, 2.0])
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "aggregate.csv").is_file() and not (tmp_path / "out" / "value_bias.csv").exists()
    assert not (tmp_path / "out" / "value_bias_compare.csv").exists()
