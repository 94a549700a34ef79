"""The statistics over seeds: the mean, and the interquartile mean (IQM, the mean of the middle 50%, as recommended
by Agarwal et al. 2021, "Deep RL at the Edge of the Statistical Precipice"). One table, ``STATISTICS``, serves the
aggregation of finished runs, a batch of seeds (``run.py seeds=[...]``) and the sweeps' ``seeds_aggregate``."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def iqm(values: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean along ``axis``: drop the lowest and highest 25% (``floor(n / 4)`` values each) and average."""
    values = np.sort(values, axis=axis)
    n = values.shape[axis]
    cut = n // 4
    return np.take(values, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def mean(values: np.ndarray, axis: int = -1) -> np.ndarray:
    return values.mean(axis=axis)


STATISTICS: dict[str, Callable[..., np.ndarray]] = {"mean": mean, "iqm": iqm}


def seed_statistic(name: str, values: list[float]) -> float:
    """Statistic ``name`` of one value per seed."""
    return float(STATISTICS[name](np.asarray(values, dtype=float)))
