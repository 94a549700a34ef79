"""Where things are in a run folder: the names of its files and of the seeds' folders, written once for every module
that writes them (:mod:`~sb3_td3x.experiment.run`) or reads them (:mod:`~sb3_td3x.experiment.analysis`, the sweeps).

A run folder holds ``config.yaml`` (what trains), ``provenance.jsonl`` (one line per session), ``evaluations.csv`` and
``.json`` (one row per evaluation), ``checkpoints/{last,best}``, ``learning_curve.png``, ``summary.json`` (at the end),
``run.log`` and ``tb/`` (docs/experiments.md lists them all).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

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


def checkpoint_dir(run_dir: Path, name: str) -> Path:
    return run_dir / "checkpoints" / name


def seed_folders(run_dir: Path | str, seeds: Sequence[int], seed: int | None = None) -> list[Path]:
    """The run folder of each of ``seeds`` trained together from ``run_dir``; the one function that names them.

    Where ``run_dir`` has a part ``seed<seed>`` (the folder Hydra made for ``run.py seeds=[...]``, from its first
    seed), that part names each seed instead: ``runs/hopper/td3/seed3/<date>`` for seed 3, as ``seed=3`` names it.
    Otherwise (a ``run_dir=`` of the user's, a multirun job, a sweep trial) ``<run_dir>/seed<s>``.
    """
    parts = list(Path(run_dir).parts)
    if seed is None or f"seed{seed}" not in parts:
        return [Path(run_dir) / f"seed{s}" for s in seeds]
    at = len(parts) - 1 - parts[::-1].index(f"seed{seed}")
    return [Path(*parts[:at], f"seed{s}", *parts[at + 1 :]) for s in seeds]
