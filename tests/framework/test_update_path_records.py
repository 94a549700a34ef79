"""The update a run used, and why, in its records: summary.json and the log line of the first train()."""

import json

from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.runner import run_experiment

SMOKE = ["debug=smoke", "env=inverted_pendulum", "progress_bar=false", "logger=none", "total_timesteps=700"]


def test_summary_and_log_name_the_update_path_and_its_reason(tmp_path, caplog):
    caplog.set_level("INFO", logger="sb3_td3x")
    run_experiment(compose_config(SMOKE + [f"run_dir={tmp_path}"]))
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["update_path"] == "eager" and "not compiled: a run of" in summary["update_reason"]
    assert summary["update_sessions"] == [{"from_step": 0, "update_path": "eager", "update_reason": summary["update_reason"]}]
    assert summary["exploration_path"] == "actor"
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("update: ")]
    assert len(lines) == 1, lines  # once, at the first train()
    assert lines[0].startswith(f"update: eager ({summary['update_reason']}); exploration: actor (")


def test_sb3s_td3_records_no_update_path(tmp_path):
    run_experiment(compose_config(SMOKE + [f"run_dir={tmp_path}", "algo=sb3_td3"]))
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["update_path"] is None and summary["update_reason"] is None
    assert summary["update_sessions"] == [{"from_step": 0, "update_path": None, "update_reason": None}]
