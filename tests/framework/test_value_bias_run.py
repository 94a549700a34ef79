"""The value measurement in a real run: the columns reach evaluations.csv, TensorBoard and the learning curve, for
TD3X and for SB3's TD3, and ``eval.value_bias=false`` switches them off."""

from __future__ import annotations

import csv
import math

import pytest
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.layout import VALUE_FIELDS
from sb3_td3x.experiment.runner import run_experiment

# 300 steps of Pendulum-v1 (64-64 networks), evaluated at 150 and 300 with 2 episodes of 200 steps. Pendulum's episodes
# are all cut by the time limit: tolerance 0.5 keeps the 132 states with gamma^k <= 0.5 (k >= 69) of each.
TINY = ["debug=smoke", "total_timesteps=300", "algo.learning_starts=100", "eval.freq=150", "progress_bar=false",
        "eval.value_horizon_tolerance=0.5"]


@pytest.mark.parametrize("algo, value_bias", [("td3", True), ("sb3_td3", True), ("td3", False)])
def test_the_columns_reach_the_csv_tensorboard_and_the_plot(tmp_path, algo, value_bias):
    cfg = compose_config(TINY + [f"algo={algo}", f"eval.value_bias={str(value_bias).lower()}", f"run_dir={tmp_path}"])
    run_experiment(cfg)
    with open(tmp_path / "evaluations.csv") as file:
        rows = list(csv.DictReader(file))
    assert [int(row["timesteps"]) for row in rows] == [150, 300]
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    height = Image.open(tmp_path / "learning_curve.png").size[1]
    if not value_bias:
        assert not set(VALUE_FIELDS) & set(rows[0]) and not {f"eval/{key}" for key in VALUE_FIELDS} & tags
        assert height == 400  # one panel
        return
    for row in rows:
        assert int(row["value_states"]) == 2 * 132
        values = {key: float(row[key]) for key in VALUE_FIELDS[:4]}
        assert all(math.isfinite(value) for value in values.values())
        assert values["overestimation"] == pytest.approx(values["value_estimate"] - values["true_value"])
        assert values["true_value"] < 0  # Pendulum's rewards are <= 0
    for key in VALUE_FIELDS:
        scalars = events.Scalars(f"eval/{key}")
        assert [event.step for event in scalars] == [150, 300]
        assert [event.value for event in scalars] == pytest.approx([float(row[key]) for row in rows], rel=1e-6)
    assert height > 600  # the second panel: estimate and true value
