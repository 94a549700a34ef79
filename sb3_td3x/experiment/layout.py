"""Where things are in a run folder: the names of its files, written once for every module
that writes them (:mod:`~sb3_td3x.experiment.run`) or reads them (:mod:`~sb3_td3x.experiment.analysis`, the sweeps).

A run folder holds ``config.yaml`` (what trains), ``provenance.jsonl`` (one line per session), ``evaluations.csv`` and
``.json`` (one row per evaluation), ``checkpoints/{last,best}``, ``learning_curve.png``, ``summary.json`` (at the end),
``run.log`` and ``tb/`` (docs/experiments.md lists them all).
"""

from __future__ import annotations

CONFIG_FILE = "config.yaml"
SUMMARY_FILE = "summary.json"
PROVENANCE_FILE = "provenance.jsonl"
RUN_LOG = "run.log"  # Hydra's job log (run.py), per seed in a batch
LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"  # Hydra's, as run.py's own lines
LEARNING_CURVE_PNG = "learning_curve.png"

EVALUATIONS_CSV = "evaluations.csv"
EVALUATIONS_JSON = "evaluations.json"
#: The columns of every evaluation row.
EVALUATION_FIELDS = ("timesteps", "mean_return", "std_return", "mean_length", "wall_time")
#: The columns of the critic's value measurement (:mod:`~sb3_td3x.experiment.run.value_bias`), with ``eval.value_bias``.
VALUE_FIELDS = ("value_estimate", "true_value", "overestimation", "normalized_bias", "value_states")

#: The checkpoints a run keeps: the newest (resumes from it) and the best evaluated.
LAST, BEST = "last", "best"
