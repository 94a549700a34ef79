"""Pictures of runs: a run's learning curve, and the steps axis every plot of the analysis shares."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed; set before pyplot is imported

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import EngFormatter


def steps_axis(ax) -> None:
    """Label ``ax``'s x axis as environment steps, ticks written 50k, 100k, 1M (full numbers overlap at 200k)."""
    ax.set_xlabel("environment steps")
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))


def plot_learning_curve(history: list[dict[str, float]], path: Path, title: str) -> Path:
    """Mean evaluation return against environment steps, with a band of one standard deviation over episodes.

    When the evaluations measured the critic's value (``value_estimate``, ``true_value``: ``eval.value_bias``), a
    second panel shows the critic's estimate and the true discounted return of the visited states over training.
    """
    steps = np.array([row["timesteps"] for row in history])
    mean = np.array([row["mean_return"] for row in history])
    std = np.array([row["std_return"] for row in history])
    estimate, true = (np.array([_number(row.get(key)) for row in history]) for key in ("value_estimate", "true_value"))
    with_values = bool(np.isfinite(estimate).any() or np.isfinite(true).any())
    if with_values:
        fig, (ax, value_ax) = plt.subplots(2, 1, figsize=(6, 6.5), dpi=100, sharex=True, height_ratios=(1, 1))
    else:
        fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ax.plot(steps, mean, marker="o", markersize=3)
    ax.fill_between(steps, mean - std, mean + std, alpha=0.2, linewidth=0)
    ax.set_ylabel("evaluation return (deterministic policy)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if with_values:
        value_ax.plot(steps, estimate, marker="o", markersize=3, color="tab:red", label="critic estimate Q1(s, a)")
        value_ax.plot(steps, true, marker="o", markersize=3, color="tab:green", linestyle="--", label="true discounted return")
        value_ax.set_ylabel("value of the visited states (mean)")
        value_ax.grid(alpha=0.3)
        value_ax.legend(loc="best", fontsize="small")
        ax = value_ax
    steps_axis(ax)
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    try:  # written whole or not at all: a full disk leaves the previous curve, not an empty file
        fig.savefig(tmp)
        tmp.replace(path)
    finally:
        plt.close(fig)
        tmp.unlink(missing_ok=True)
    return path


def _number(value: object) -> float:
    """A value of an evaluation row as a float; missing or empty (a row from before the value measurement) is NaN."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")
