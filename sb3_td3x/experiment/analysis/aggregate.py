"""Aggregate finished runs into a table and learning-curve plots, with 95% bootstrap confidence intervals.

    python -m sb3_td3x.experiment.analysis.aggregate runs/multirun/2026-01-01_12-00-00 [more folders] [--stat iqm] [--out DIR]

Every run folder below the given paths (a folder with ``evaluations.csv`` and ``config.yaml``) is grouped by (env
id, algo name), one folder a seed (two folders of one seed are refused, never averaged as two); the seeds of a group
are aligned on the evaluation steps they all have. The statistic over seeds is the mean or the interquartile mean
(IQM, the mean of the middle 50%, as recommended by Agarwal et al. 2021, "Deep RL at the Edge of the Statistical
Precipice"); its 95% confidence interval is a percentile bootstrap over seeds. Writes ``aggregate.csv``,
``aggregate.md`` (with each seed's final return), ``per_seed.csv`` (one row per run: env id, algo, seed, run folder,
steps, final return) and ``aggregate_<env>.png`` to ``--out``.

Runs whose evaluations measured the critic's value (the ``evaluations.csv`` columns ``value_estimate``,
``true_value``, ``overestimation``, ``normalized_bias``: ``eval.value_bias``) are also aggregated into
``value_bias.csv`` (the same statistic and bootstrap interval over seeds, at the last step that all the group's
runs with these columns reached) and ``value_bias_<env>.png``: one panel per algo with the critic's estimate and
the true value over training, as in Figure 1 of the TD3 paper. Runs without the columns (made before they existed)
are left out of these two only.

Where an environment has runs of two or more algos, each pair is compared in ``compare.csv``: the difference of
their statistic (``algo_a`` minus ``algo_b``) of the final return and of the mean return over all evaluations
(the area under the curve, divided by its length), each with a 95% bootstrap interval (each algo's seeds resampled
on their own) and the p-value of a two-sided permutation test (exact up to 20,000 splits of the seeds), at the
evaluation steps that both algos' runs have all reached. The critic's overestimation is compared the same way in
``value_bias_compare.csv`` (its value at the last step, and its mean over all evaluations).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from sb3_td3x.experiment.analysis.plots import steps_axis
from sb3_td3x.experiment.analysis.statistics import (  # noqa: F401  (iqm and mean: this module's API too)
    STATISTICS,
    difference_ci,
    iqm,
    mean,
    permutation_p_value,
)
from sb3_td3x.experiment.layout import CONFIG_FILE, EVALUATIONS_CSV, VALUE_FIELDS

# The value columns aggregated over seeds (value_states is a count, kept per run only)
VALUE_METRICS = ("value_estimate", "true_value", "overestimation", "normalized_bias")
VALUE_BIAS_CSV = "value_bias.csv"
COMPARE_CSV = "compare.csv"
VALUE_COMPARE_CSV = "value_bias_compare.csv"


def bootstrap_ci(
    values: np.ndarray, statistic: Callable[..., np.ndarray], n_resamples: int = 2000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """95% percentile-bootstrap interval of ``statistic`` over the last axis (seeds) of ``values`` (steps, seeds)."""
    rng = np.random.default_rng(seed)
    n_seeds = values.shape[-1]
    picks = rng.integers(0, n_seeds, size=(n_resamples, n_seeds))  # (n_resamples, n_seeds)
    resampled = statistic(values[:, picks], axis=-1)  # (steps, n_resamples)
    return np.percentile(resampled, 2.5, axis=-1), np.percentile(resampled, 97.5, axis=-1)


class SeedTwiceError(ValueError):
    """Two run folders of one env, algo and seed below the paths given: averaged, they would count as two seeds."""


def load_runs(paths: list[Path]) -> pd.DataFrame:
    """One row per evaluation of every run below ``paths``: env_id, algo, seed, run_dir, timesteps, mean_return,
    and the value columns (NaN for a run without them). A folder reached through two of the paths counts once; two
    folders of the same env, algo and seed raise :class:`SeedTwiceError` (a copy, a run made again, another
    hyperparameter's run: never two seeds)."""
    frames, seen = [], set()
    for path in paths:
        for csv_path in sorted(path.rglob(EVALUATIONS_CSV)):
            run_dir = csv_path.parent
            if not (run_dir / CONFIG_FILE).is_file() or run_dir.resolve() in seen:
                continue
            seen.add(run_dir.resolve())
            config = OmegaConf.load(run_dir / CONFIG_FILE)
            evaluations = pd.read_csv(csv_path).reindex(columns=["timesteps", "mean_return", *VALUE_FIELDS])
            frames.append(
                evaluations.assign(
                    env_id=config.env.id,
                    algo=config.algo.name,
                    algo_class=str(config.algo.get("_target_", "")).rpartition(".")[2],
                    seed=config.seed,
                    run_dir=str(run_dir),
                )
            )
    if not frames:
        raise FileNotFoundError(f"No run folder (with {EVALUATIONS_CSV} and {CONFIG_FILE}) below {', '.join(map(str, paths))}")
    runs = pd.concat(frames, ignore_index=True)
    folders = runs.drop_duplicates("run_dir")
    key = ["env_id", "algo", "seed"]
    twice = folders[folders.duplicated(key, keep=False)].groupby(key, sort=True)
    if twice.ngroups:
        (env_id, algo, seed), group = next(iter(twice))
        more = f" ({twice.ngroups - 1} more seeds have two folders or more)" if twice.ngroups > 1 else ""
        raise SeedTwiceError(
            f"{len(group)} run folders of {env_id}, algo {algo}, seed {seed}, which averaged would count as {len(group)} "
            f"seeds: {', '.join(group.run_dir)}{more}. A copy, a run made again, or runs of other settings (a multirun "
            "over hyperparameters): name the run folders to aggregate, or move the others out of the folders given"
        )
    return runs


def aggregate(runs: pd.DataFrame, stat: str = "mean") -> tuple[pd.DataFrame, dict[tuple[str, str], pd.DataFrame]]:
    """The summary table (one row per env and algo) and, per group, the curve: statistic and CI per step."""
    statistic = STATISTICS[stat]
    rows, seed_rows, curves = [], [], {}
    if "algo_class" not in runs:
        runs = runs.assign(algo_class="")
    for (env_id, algo), group in runs.groupby(["env_id", "algo"], sort=True):
        # (steps, seeds), only the steps every run of the group has reached
        table = group.pivot_table(index="timesteps", columns="run_dir", values="mean_return").dropna()
        values = table.to_numpy()
        low, high = bootstrap_ci(values, statistic)
        curve = pd.DataFrame({"timesteps": table.index, stat: statistic(values, axis=-1), "ci_low": low, "ci_high": high})
        classes = sorted(set(group["algo_class"]) - {""})
        curve.attrs["label"] = f"{algo} ({', '.join(classes)})" if classes else algo  # e.g. "td3 (TD3X)" in plots
        curve.attrs["per_seed"] = table  # (steps, runs): drawn as thin lines under the statistic
        curves[(env_id, algo)] = curve
        final = curve.iloc[-1]
        seed_of = group.drop_duplicates("run_dir").set_index("run_dir")["seed"]
        order = sorted(table.columns, key=lambda run_dir: (seed_of[run_dir], run_dir))
        rows.append(
            {
                "env_id": env_id,
                "algo": algo,
                "n_runs": values.shape[1],
                "timesteps": int(final["timesteps"]),
                f"final_{stat}": final[stat],
                "ci_low": final["ci_low"],
                "ci_high": final["ci_high"],
                f"best_{stat}": curve[stat].max(),
                "seeds": ", ".join(str(seed_of[run_dir]) for run_dir in order),
                "per_seed_final": ", ".join(f"{table[run_dir].iloc[-1]:.1f}" for run_dir in order),
            }
        )
        seed_rows += [
            {"env_id": env_id, "algo": algo, "seed": seed_of[run_dir], "run_dir": str(run_dir),
             "timesteps": int(final["timesteps"]), "final_return": table[run_dir].iloc[-1]}
            for run_dir in order
        ]
    summary = pd.DataFrame(rows)
    # One row per run (env_id, algo, seed, run_dir, timesteps, final_return): the per-seed finals in long format
    summary.attrs["per_seed"] = pd.DataFrame(
        seed_rows, columns=["env_id", "algo", "seed", "run_dir", "timesteps", "final_return"]
    )
    return summary, curves


def aggregate_values(runs: pd.DataFrame, stat: str = "mean") -> tuple[pd.DataFrame, dict[tuple[str, str], pd.DataFrame]]:
    """The critic's value estimate against the true value, over seeds: a table (one row per env and algo with
    the columns) and, per group, the curves (``<metric>``, ``<metric>_ci_low``, ``<metric>_ci_high`` per step).

    A group's runs without the value columns are left out; the others are aligned on the steps at which all of
    them have a finite estimate and true value. The final row holds each metric's statistic over seeds and its 95%
    bootstrap interval (``normalized_bias`` is NaN at a step where one seed's is).
    """
    statistic = STATISTICS[stat]
    rows, curves = [], {}
    if not set(VALUE_METRICS) <= set(runs.columns):
        return pd.DataFrame(), {}
    for (env_id, algo), group in runs.groupby(["env_id", "algo"], sort=True):
        measured = group.dropna(subset=["value_estimate", "true_value"])
        if measured.empty:
            continue
        tables = {metric: measured.pivot_table(index="timesteps", columns="run_dir", values=metric, dropna=False)
                  for metric in VALUE_METRICS}
        steps = tables["value_estimate"].dropna().index.intersection(tables["true_value"].dropna().index)
        if steps.empty:
            continue
        curve = pd.DataFrame({"timesteps": steps})
        for metric, table in tables.items():
            values = table.reindex(index=steps, columns=tables["value_estimate"].columns).to_numpy()
            low, high = bootstrap_ci(values, statistic)
            curve[metric], curve[f"{metric}_ci_low"], curve[f"{metric}_ci_high"] = statistic(values, axis=-1), low, high
        classes = sorted(set(group["algo_class"]) - {""}) if "algo_class" in group else []
        run_dirs = list(tables["value_estimate"].columns)
        curve.attrs["label"] = f"{algo} ({', '.join(classes)})" if classes else algo
        curve.attrs["n_runs"] = len(run_dirs)
        curve.attrs["per_seed"] = tables["overestimation"].reindex(index=steps, columns=run_dirs)  # for compare()
        curves[(env_id, algo)] = curve
        final = curve.iloc[-1]
        seed_of = group.drop_duplicates("run_dir").set_index("run_dir")["seed"]
        order = sorted(run_dirs, key=lambda run_dir: (seed_of[run_dir], run_dir))
        last = tables["overestimation"].loc[int(final["timesteps"])]
        row = {"env_id": env_id, "algo": algo, "n_runs": len(run_dirs), "timesteps": int(final["timesteps"])}
        for metric in VALUE_METRICS:
            row.update({metric: final[metric], f"{metric}_ci_low": final[f"{metric}_ci_low"],
                        f"{metric}_ci_high": final[f"{metric}_ci_high"]})
        row["seeds"] = ", ".join(str(seed_of[run_dir]) for run_dir in order)
        row["per_seed_overestimation"] = ", ".join(f"{last[run_dir]:.1f}" for run_dir in order)
        rows.append(row)
    return pd.DataFrame(rows), curves


def compare(curves: dict[tuple[str, str], pd.DataFrame], stat: str = "mean") -> pd.DataFrame:
    """Every pair of algos of one env, from :func:`aggregate`'s (or :func:`aggregate_values`') curves: one row per
    pair (``algo_a`` before ``algo_b`` in name order), the difference ``algo_a - algo_b`` of the statistic over seeds
    of the curves' per-seed values (``attrs["per_seed"]``, (steps, runs): the return, or the overestimation):

    - ``final``: the value at the last evaluation step that every run of both algos reached, and
    - ``curve``: each run's mean value over all the evaluation steps that every run of both reached,

    each with its 95% bootstrap interval (``*_ci_low``, ``*_ci_high``; NaN when one of the two has a single seed)
    and permutation-test p-value (``*_p_value``).
    """
    statistic = STATISTICS[stat]
    rows = []
    for env_id in sorted({env_id for env_id, _ in curves}):
        algos = sorted(algo for curve_env, algo in curves if curve_env == env_id)
        for algo_a, algo_b in itertools.combinations(algos, 2):
            table_a = curves[(env_id, algo_a)].attrs["per_seed"]  # (steps, runs)
            table_b = curves[(env_id, algo_b)].attrs["per_seed"]
            steps = table_a.index.intersection(table_b.index)
            if steps.empty:
                continue
            row = {"env_id": env_id, "algo_a": algo_a, "algo_b": algo_b, "n_a": table_a.shape[1],
                   "n_b": table_b.shape[1], "timesteps": int(steps.max()), "n_evaluations": len(steps)}
            for name, a, b in (
                ("final", table_a.loc[steps.max()], table_b.loc[steps.max()]),
                ("curve", table_a.loc[steps].mean(axis=0), table_b.loc[steps].mean(axis=0)),
            ):
                a, b = a.to_numpy(dtype=float), b.to_numpy(dtype=float)
                # One seed has no spread to resample: an interval would pass for one that covers both algos' seeds
                low, high = difference_ci(a, b, statistic) if min(len(a), len(b)) > 1 else (np.nan, np.nan)
                row.update({f"{name}_a": float(statistic(a)), f"{name}_b": float(statistic(b)),
                            f"{name}_difference": float(statistic(a) - statistic(b)), f"{name}_ci_low": low,
                            f"{name}_ci_high": high, f"{name}_p_value": permutation_p_value(a, b, statistic)})
            rows.append(row)
    return pd.DataFrame(rows)


def plot_value_curves(curves: dict[tuple[str, str], pd.DataFrame], stat: str, out_dir: Path) -> list[Path]:
    """One PNG per environment, one panel per algo: the critic's value estimate and the true discounted return of
    the visited states against steps, each with its 95% CI band over seeds (the TD3 paper's Figure 1)."""
    paths = []
    for env_id in sorted({env_id for env_id, _ in curves}):
        algos = [(algo, curve) for (curve_env, algo), curve in sorted(curves.items()) if curve_env == env_id]
        fig, axes = plt.subplots(1, len(algos), figsize=(4.2 * len(algos) + 0.6, 3.8), dpi=100, sharey=True, squeeze=False)
        for ax, (algo, curve) in zip(axes[0], algos):
            steps = curve["timesteps"]
            for metric, color, style, label in (
                ("value_estimate", "tab:red", "-", "critic estimate"),
                ("true_value", "tab:green", "--", "true value"),
            ):
                ax.plot(steps, curve[metric], color=color, linestyle=style, label=label)
                ax.fill_between(steps, curve[f"{metric}_ci_low"], curve[f"{metric}_ci_high"], color=color, alpha=0.2,
                                linewidth=0)
            n_runs = curve.attrs.get("n_runs", 0)
            ax.set_title(curve.attrs.get("label", algo) + f", {n_runs} seed{'s' if n_runs != 1 else ''}", fontsize="medium")
            steps_axis(ax)
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel(f"value of the visited states ({stat}, 95% CI)")
        axes[0][0].legend(loc="upper left", fontsize="small")
        fig.suptitle(f"{env_id}: value estimate against true value")
        fig.tight_layout()
        path = out_dir / f"value_bias_{env_id}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


def plot_curves(curves: dict[tuple[str, str], pd.DataFrame], stat: str, out_dir: Path) -> list[Path]:
    """One PNG per environment: the statistic of every algo against steps, with its 95% CI band and each seed's
    curve as a thin line."""
    paths = []
    for env_id in sorted({env_id for env_id, _ in curves}):
        fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
        for (curve_env, algo), curve in sorted(curves.items()):
            if curve_env != env_id:
                continue
            (line,) = ax.plot(curve["timesteps"], curve[stat], label=curve.attrs.get("label", algo))
            color = line.get_color()
            ax.fill_between(curve["timesteps"], curve["ci_low"], curve["ci_high"], alpha=0.2, linewidth=0, color=color)
            per_seed = curve.attrs.get("per_seed")
            if per_seed is not None and per_seed.shape[1] > 1:
                ax.plot(per_seed.index, per_seed.to_numpy(), color=color, alpha=0.35, linewidth=0.7)
        steps_axis(ax)
        ax.set_ylabel(f"evaluation return ({stat}, 95% CI)")
        ax.set_title(env_id)
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        path = out_dir / f"aggregate_{env_id}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sb3_td3x.experiment.analysis.aggregate", description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="folders holding run folders (searched recursively)")
    parser.add_argument("--stat", choices=sorted(STATISTICS), default="mean", help="statistic over seeds (default: mean)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: the first path)")
    args = parser.parse_args(argv)
    try:
        runs = load_runs(args.paths)
    except (FileNotFoundError, SeedTwiceError) as error:
        print(f"Error: {error}", file=sys.stderr)
        return 2
    table, curves = aggregate(runs, args.stat)
    out_dir = args.out or args.paths[0]
    out_dir.mkdir(parents=True, exist_ok=True)
    table.to_csv(out_dir / "aggregate.csv", index=False)
    table.attrs["per_seed"].to_csv(out_dir / "per_seed.csv", index=False)
    markdown = to_markdown(table)
    (out_dir / "aggregate.md").write_text(markdown + "\n")
    plots = plot_curves(curves, args.stat, out_dir)
    print(markdown)
    written = [out_dir / "aggregate.csv", out_dir / "aggregate.md", out_dir / "per_seed.csv", *plots]
    written += write_differences(curves, args.stat, out_dir / COMPARE_CSV, "final return, and mean return over all evaluations")
    value_table, value_curves = aggregate_values(runs, args.stat)
    if not value_table.empty:
        value_table.to_csv(out_dir / VALUE_BIAS_CSV, index=False)
        shown = value_table[["env_id", "algo", "n_runs", "timesteps", *VALUE_METRICS, "per_seed_overestimation"]].copy()
        shown["normalized_bias"] = shown["normalized_bias"].map(lambda value: f"{value:.3f}")  # a ratio: 3 decimals
        print("\nValue estimate against true value (the critic's overestimation):\n" + to_markdown(shown))
        written += [out_dir / VALUE_BIAS_CSV, *plot_value_curves(value_curves, args.stat, out_dir)]
    written += write_differences(
        value_curves, args.stat, out_dir / VALUE_COMPARE_CSV, "overestimation at the last step, and mean over all evaluations"
    )
    print(f"\nWrote {', '.join(map(str, written))}")
    return 0


def write_differences(curves: dict[tuple[str, str], pd.DataFrame], stat: str, path: Path, what: str) -> list[Path]:
    """:func:`compare` the curves' algos into ``path`` and print the table; no file (an earlier call's removed) when
    no env has two algos. Returns the paths written."""
    path.unlink(missing_ok=True)  # from an earlier call on other runs
    differences = compare(curves, stat)
    if differences.empty:
        return []
    differences.to_csv(path, index=False)
    print_differences(differences, stat, what)
    return [path]


def print_differences(differences: pd.DataFrame, stat: str, what: str) -> None:
    """Print :func:`compare`'s table: each difference with its 95% interval, and its permutation-test p."""
    shown = differences[["env_id", "algo_a", "algo_b", "n_a", "n_b", "timesteps"]].copy()
    for name in ("final", "curve"):
        shown[f"{name}: a - b (95% CI)"] = [
            f"{r[f'{name}_difference']:.1f} ("
            + ("one seed, no interval" if np.isnan(r[f"{name}_ci_low"]) else f"{r[f'{name}_ci_low']:.1f} to {r[f'{name}_ci_high']:.1f}")
            + ")"
            for _, r in differences.iterrows()
        ]
        shown[f"{name}: p"] = differences[f"{name}_p_value"].map(lambda p: f"{p:.3f}")
    print(f"\nDifferences between algos ({stat} of a minus {stat} of b; {what}; permutation-test p):\n" + to_markdown(shown))


def to_markdown(table: pd.DataFrame) -> str:
    """A Markdown table, floats with one decimal (pandas' own ``to_markdown`` needs the tabulate package)."""
    cells = [
        [f"{value:.1f}" if isinstance(value, float) else str(value) for value in row] for row in table.itertuples(index=False)
    ]
    lines = ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])


if __name__ == "__main__":
    sys.exit(main())
