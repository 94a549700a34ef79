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
