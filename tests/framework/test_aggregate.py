"""The aggregation command: statistics over seeds and the table/plots it writes from run folders."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from sb3_td3x.experiment.aggregate import bootstrap_ci, iqm, main


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


def test_runs_without_the_value_columns_write_no_value_table(tmp_path):
    write_run(tmp_path / "runs" / "old", "Hopper-v5", "td3", 0, [1.0, 2.0])
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "aggregate.csv").is_file() and not (tmp_path / "out" / "value_bias.csv").exists()
