"""The statistics over seeds: the mean, and the interquartile mean (IQM, the mean of the middle 50%, as recommended
by Agarwal et al. 2021, "Deep RL at the Edge of the Statistical Precipice"). One table, ``STATISTICS``, serves the
aggregation of finished runs, a batch of seeds (``run.py seeds=[...]``) and the sweeps' ``seeds_aggregate``.

Two algorithms' seeds are compared with :func:`difference_ci` (a bootstrap interval of the difference of their
statistics) and :func:`permutation_p_value` (a two-sided permutation test of that difference)."""

from __future__ import annotations

import itertools
import math
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


def difference_ci(
    a: np.ndarray, b: np.ndarray, statistic: Callable[..., np.ndarray] = mean, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """95% percentile-bootstrap interval of ``statistic(a) - statistic(b)``, one value per seed in each.

    The two are independent samples (the seeds of two algorithms), so each is resampled on its own.
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    rng = np.random.default_rng(seed)
    resampled_a = statistic(a[rng.integers(0, len(a), size=(n_resamples, len(a)))], axis=-1)
    resampled_b = statistic(b[rng.integers(0, len(b), size=(n_resamples, len(b)))], axis=-1)
    low, high = np.percentile(resampled_a - resampled_b, [2.5, 97.5])
    return float(low), float(high)


def permutation_p_value(
    a: np.ndarray,
    b: np.ndarray,
    statistic: Callable[..., np.ndarray] = mean,
    max_exact: int = 20_000,
    n_resamples: int = 20_000,
    seed: int = 0,
) -> float:
    """Two-sided p-value of ``statistic(a) - statistic(b)`` under the null hypothesis that the labels do not matter.

    The share of the ways to split the pooled values into groups of ``len(a)`` and ``len(b)`` whose difference is at
    least as large (in absolute value) as the observed one. Exact, over every split, when there are at most
    ``max_exact`` of them (5 seeds against 5: 252 splits); else a Monte Carlo estimate from ``n_resamples`` random
    splits, counted as ``(k + 1) / (n + 1)`` so that it is never 0. Note the floor of an exact test with few seeds:
    3 against 3 cannot give less than 0.1, 5 against 5 not less than 0.008.
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    pooled, k = np.concatenate([a, b]), len(a)
    observed = abs(float(statistic(a, axis=-1) - statistic(b, axis=-1)))
    tolerance = 1e-9 * max(1.0, observed)  # the same split summed in another order must count as "as large"
    exact = math.comb(len(pooled), k) <= max_exact
    if exact:
        firsts = np.array(list(itertools.combinations(range(len(pooled)), k)))  # (splits, k)
    else:
        firsts = np.argsort(np.random.default_rng(seed).random((n_resamples, len(pooled))), axis=1)[:, :k]
    in_first = np.zeros((len(firsts), len(pooled)), dtype=bool)
    np.put_along_axis(in_first, firsts, True, axis=1)
    first = pooled[firsts]  # (splits, k)
    second = np.broadcast_to(pooled, in_first.shape)[~in_first].reshape(len(firsts), len(pooled) - k)
    as_large = int(np.sum(np.abs(statistic(first, axis=-1) - statistic(second, axis=-1)) >= observed - tolerance))
    return as_large / len(firsts) if exact else (as_large + 1) / (len(firsts) + 1)
