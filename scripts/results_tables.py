"""Fill the tables of docs/results.md from the published results (run by scripts/publish_results.sh).

Each table sits between two markers of the page, ``<!-- NAME -->`` and ``<!-- /NAME -->``, and is rewritten from
``<results docs dir>/<group>/aggregate.csv`` and ``per_seed.csv`` (what ``sb3_td3x.experiment.analysis.aggregate`` wrote:
the finished seeds of each algorithm, or all its seeds as far as they have all got while none has finished) and the
runs' records under ``<results docs dir>/runs/<env>/<algo>/seed<S>/``, which say how far each seed has got. Nothing
in the tables is typed by hand, so publishing again after more runs brings the page up to date.

The groups (which run folders are aggregated together, and under which name) are defined here only, in ``GROUPS``;
``scripts/publish_results.sh`` reads them with ``--groups``. The overestimation table (``VALUE_BIAS``, the paper's
Figure 1) comes from ``value_bias/value_bias.csv``: the critic's value estimate against the true value at the last
evaluation, over the seeds whose evaluations measured it (runs made before ``eval.value_bias`` existed are said so).
The TD3X-against-SB3 table (``HOPPER_SB3``) is followed by the difference between the two, from ``compare.csv``
(a bootstrap interval and a permutation test over the seeds).

Each row lists seeds 0, 1, 2 (0 to 4 in the overestimation and TD3X-against-SB3 tables) and any further seed that has
a run folder, unless ``--seeds`` names them.

    python scripts/results_tables.py [--docs-dir docs/assets/results] [--page docs/results.md] [--seeds 0 1 2]
    python scripts/results_tables.py --groups    # one line per group: its name, then its <env>/<algo> folders
    python scripts/results_tables.py --shorter-runs runs/results   # runs whose published record reached more steps

A group whose published aggregate was made from runs whose records are no longer under ``<docs dir>/runs`` (records
of an earlier machine, say) is left as it is, aggregate and table: rewriting it would drop those runs from the page.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

ABLATION = {  # algo preset -> the row's name, in the paper's order
    "td3": "TD3 (`td3`)",
    "ddpg": "DDPG (`ddpg`)",
    "td3_no_smoothing": "TD3 without target policy smoothing (`td3_no_smoothing`)",
    "td3_no_cdq": "TD3 without clipped double-Q (`td3_no_cdq`)",
    "td3_no_delay": "TD3 without delayed policy updates (`td3_no_delay`)",
}
MUJOCO = {"halfcheetah": "HalfCheetah-v5", "hopper": "Hopper-v5", "walker2d": "Walker2d-v5", "ant": "Ant-v5"}
GROUPS = {  # aggregate folder -> the run folders <env>/<algo> aggregated into it
    "hopper_td3x_vs_sb3": ["hopper/td3", "hopper/sb3_td3"],
    "hopper_ablation": [f"hopper/{algo}" for algo in ABLATION],
    "td3x_mujoco": [f"{env}/td3" for env in MUJOCO],
    "value_bias": ["hopper/td3", "hopper/ddpg", "hopper/td3_no_cdq", "walker2d/td3", "walker2d/ddpg"],
}
VALUE_BIAS_ROWS = [  # (row name, env id, run folder <env>/<algo>): the paper's Figure 1, and TD3 without clipped double-Q
    ("Hopper-v5, TD3 (`td3`)", "Hopper-v5", "hopper/td3"),
    ("Hopper-v5, DDPG (`ddpg`)", "Hopper-v5", "hopper/ddpg"),
    ("Hopper-v5, TD3 without clipped double-Q (`td3_no_cdq`)", "Hopper-v5", "hopper/td3_no_cdq"),
    ("Walker2d-v5, TD3 (`td3`)", "Walker2d-v5", "walker2d/td3"),
    ("Walker2d-v5, DDPG (`ddpg`)", "Walker2d-v5", "walker2d/ddpg"),
]
VALUE_BIAS_SEEDS = 5  # the paper's Figure 1 averages 5 runs
HOPPER_SB3 = [("TD3X (`td3`)", "Hopper-v5", "hopper/td3"), ("SB3 `TD3` (`sb3_td3`)", "Hopper-v5", "hopper/sb3_td3")]
HOPPER_SB3_SEEDS = 5
VALUE_HEADER = [
    "| run | seeds: steps reached | steps | value estimate | true value | overestimation, mean (95% CI) "
    "| normalised bias, mean (95% CI) | overestimation per seed |",
    "|---|---|---|---|---|---|---|---|",
]
HEADER = [
    "| {first} | seeds: steps reached | steps | final return, mean (95% CI) | final return per seed | best mean |",
    "|---|---|---|---|---|---|",
]


def evaluations_of(run_dir: Path) -> pd.DataFrame | None:
    """A run folder's ``evaluations.csv``, or ``None`` when it has none."""
    return pd.read_csv(run_dir / "evaluations.csv") if (run_dir / "evaluations.csv").is_file() else None


def last_step(evaluations: pd.DataFrame | None) -> int:
    """The step of a run's last evaluation (0 without one)."""
    return int(evaluations["timesteps"].iloc[-1]) if evaluations is not None and len(evaluations) else 0


def seed_progress(run_dir: Path, needs_values: bool = False) -> str:
    """'200k', '85k of 200k', 'not started' or 'started, no evaluation yet' for one seed's run folder.

    :param needs_values: say 'made without the value columns' for a run whose evaluations lack ``value_estimate``
    """
    if not run_dir.is_dir():
        return "not started"
    target = None
    if (run_dir / "config.yaml").is_file():
        target = (yaml.safe_load((run_dir / "config.yaml").read_text()) or {}).get("total_timesteps")
    evaluations = evaluations_of(run_dir)
    reached = last_step(evaluations)
    if reached == 0:
        return "started, no evaluation yet"
    if needs_values and "value_estimate" not in evaluations:
        return f"{steps(reached)}, made without the value columns"
    if target is None or reached >= int(target):
        return steps(reached)
    return f"{steps(reached)} of {steps(int(target))}"


def row_seeds(runs: Path, seeds: list[int] | None, planned: int = 3) -> list[int]:
    """The seeds a row lists: ``seeds`` when given, else the ``planned`` first ones and every seed<N> folder of the
    row's runs."""
    if seeds is not None:
        return seeds
    found = {int(path.name[4:]) for path in runs.glob("seed*") if path.is_dir() and path.name[4:].isdigit()}
    return sorted(set(range(planned)) | found)


def steps(n: int) -> str:
    return f"{n // 1000}k" if n >= 1000 and n % 1000 == 0 else f"{n:,}"


def row(
    name: str,
    aggregate: pd.DataFrame,
    per_seed: pd.DataFrame,
    env_id: str,
    algo: str,
    runs: Path,
    seeds: list[int] | None,
    planned: int = 3,
) -> str:
    progress = ", ".join(f"{seed}: {seed_progress(runs / f'seed{seed}')}" for seed in row_seeds(runs, seeds, planned))
    found = aggregate[(aggregate["env_id"] == env_id) & (aggregate["algo"] == algo)] if len(aggregate) else aggregate
    if found.empty:
        return f"| {name} | {progress} | | | | |"
    r = found.iloc[0]
    final = f"{r.final_mean:.1f} ({r.ci_low:.1f} to {r.ci_high:.1f})" if r.n_runs > 1 else f"{r.final_mean:.1f} (one seed)"
    finals = per_seed[(per_seed["env_id"] == env_id) & (per_seed["algo"] == algo)].sort_values(["seed", "run_dir"])
    per_seed_text = ", ".join(f"{seed}: {value:.1f}" for seed, value in zip(finals["seed"], finals["final_return"]))
    return f"| {name} | {progress} | {int(r.timesteps):,} | {final} | {per_seed_text} | {r.best_mean:.1f} |"


def read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path) if path.is_file() else pd.DataFrame(columns=["env_id", "algo", "seed", "run_dir"])


def value_row(name: str, values: pd.DataFrame, env_id: str, algo: str, runs: Path, seeds: list[int] | None) -> str:
    """One row of the overestimation table, from ``value_bias.csv`` (the last step all the measured seeds reached)."""
    seed_list = row_seeds(runs, seeds, planned=VALUE_BIAS_SEEDS)
    progress = ", ".join(f"{seed}: {seed_progress(runs / f'seed{seed}', needs_values=True)}" for seed in seed_list)
    found = values[(values["env_id"] == env_id) & (values["algo"] == algo)] if len(values) else values
    if found.empty:
        return f"| {name} | {progress} | | | | | | |"
    r = found.iloc[0]

    def with_ci(metric: str, digits: int) -> str:
        value, low, high = r[metric], r[f"{metric}_ci_low"], r[f"{metric}_ci_high"]
        if r.n_runs <= 1:
            return f"{value:.{digits}f} (one seed)"
        return f"{value:.{digits}f} ({low:.{digits}f} to {high:.{digits}f})"

    seeds_of_row, overestimations = str(r.seeds).split(", "), str(r.per_seed_overestimation).split(", ")
    per_seed = ", ".join(f"{seed}: {value}" for seed, value in zip(seeds_of_row, overestimations))
    return (
        f"| {name} | {progress} | {int(r.timesteps):,} | {r.value_estimate:.1f} | {r.true_value:.1f} "
        f"| {with_ci('overestimation', 1)} | {with_ci('normalized_bias', 3)} | {per_seed} |"
    )


def value_table(docs_dir: Path, seeds: list[int] | None) -> str:
    """The overestimation table, then per env DDPG's overestimation minus TD3's, and TD3 without clipped double-Q's
    minus TD3's where it has seeds (from ``value_bias_compare.csv``)."""
    values = read_csv(docs_dir / "value_bias" / "value_bias.csv")
    rows = list(VALUE_HEADER)
    for name, env_id, folder in VALUE_BIAS_ROWS:
        rows.append(value_row(name, values, env_id, folder.split("/")[1], docs_dir / "runs" / folder, seeds))
    tables = ["\n".join(rows)]
    for env in dict.fromkeys(folder.split("/")[0] for _, _, folder in VALUE_BIAS_ROWS):
        env_id = MUJOCO[env]
        td3 = ("TD3 (`td3`)", env_id, f"{env}/td3")
        for other in (f"{env_id}: DDPG (`ddpg`)", env_id, f"{env}/ddpg"), (
            f"{env_id}: TD3 without clipped double-Q (`td3_no_cdq`)", env_id, f"{env}/td3_no_cdq"
        ):
            tables.append(difference_table(docs_dir, "value_bias", other, td3, "value_bias_compare.csv", "overestimation"))
    return "\n\n".join(filter(None, tables))


def table(
    docs_dir: Path, group: str, first: str, rows_of: list[tuple[str, str, str]], seeds: list[int] | None, planned: int = 3
) -> str:
    """One table: a row per (row name, env id, run folder <env>/<algo>), from the group's aggregate."""
    aggregate = read_csv(docs_dir / group / "aggregate.csv")
    per_seed = read_csv(docs_dir / group / "per_seed.csv")
    rows = [h.format(first=first) for h in HEADER]
    for name, env_id, folder in rows_of:
        algo = folder.split("/")[1]
        rows.append(row(name, aggregate, per_seed, env_id, algo, docs_dir / "runs" / folder, seeds, planned))
    return "\n".join(rows)


def difference_table(
    docs_dir: Path,
    group: str,
    first: tuple[str, str, str],
    second: tuple[str, str, str],
    csv: str = "compare.csv",
    quantity: str = "return",
) -> str:
    """The difference first minus second (row name, env id, run folder <env>/<algo> each) from the group's
    ``compare.csv`` (or ``value_bias_compare.csv``, ``quantity="overestimation"``): the final value and the mean over
    all evaluations, 95% bootstrap interval, permutation p. Empty while the two have no seeds to compare."""
    (name_a, env_id, folder_a), (name_b, _, folder_b) = first, second
    algo_a, algo_b = folder_a.split("/")[1], folder_b.split("/")[1]
    compared = read_csv(docs_dir / group / csv)
    if compared.empty or "algo_a" not in compared:
        return ""
    sign = 1.0
    found = compared[(compared.env_id == env_id) & (compared.algo_a == algo_a) & (compared.algo_b == algo_b)]
    if found.empty:  # compare.csv holds each pair once, in name order
        sign = -1.0
        found = compared[(compared.env_id == env_id) & (compared.algo_a == algo_b) & (compared.algo_b == algo_a)]
    if found.empty:
        return ""
    r = found.iloc[0]
    n_a, n_b = (int(r.n_a), int(r.n_b)) if sign > 0 else (int(r.n_b), int(r.n_a))
    lines = [
        f"| {name_a} minus {name_b} ({n_a} seed{'s' * (n_a != 1)} against {n_b}) | difference of the means (95% CI) "
        "| permutation test p |",
        "|---|---|---|",
    ]
    final = "final return" if quantity == "return" else f"{quantity} at the last step"
    for what, label in (("final", f"{final} ({steps(int(r.timesteps))})"),
                        ("curve", f"mean {quantity} over all {int(r.n_evaluations)} evaluations")):
        difference = sign * r[f"{what}_difference"]
        low, high = sorted((sign * r[f"{what}_ci_low"], sign * r[f"{what}_ci_high"]))
        interval = "no interval with one seed" if pd.isna(low) else f"{low:+.1f} to {high:+.1f}"
        lines.append(f"| {label} | {difference:+.1f} ({interval}) | {r[f'{what}_p_value']:.3f} |")
    return "\n".join(lines)


def missing_runs(docs_dir: Path, group: str) -> list[str]:
    """The runs a group's published aggregate was made from whose records are not under ``<docs dir>/runs``: no
    folder, or a folder holding another run, whose return at the step the aggregate ended on is not the one
    aggregated (the same env, algo and seed made again elsewhere and published where the first run's records, never
    committed, would have been). A run that has gone on since still has the aggregated return at that step.

    Aggregating such a group again, or rewriting its table, would drop those runs from the page (or mix their numbers
    with those of other runs): ``scripts/publish_results.sh`` and :func:`tables` leave such a group as it is.
    """
    per_seed = docs_dir / group / "per_seed.csv"
    if not per_seed.is_file():
        return []
    missing = []
    for run in read_csv(per_seed).itertuples():
        relative = str(run.run_dir).split("/runs/", 1)[-1]
        folder = docs_dir / "runs" / relative
        if not folder.is_dir():
            missing.append(relative)
            continue
        evaluations = evaluations_of(folder)
        at = evaluations[evaluations["timesteps"] == run.timesteps] if evaluations is not None else pd.DataFrame()
        if at.empty or not np.isclose(at["mean_return"].iloc[0], run.final_return, rtol=1e-9, atol=1e-6):
            missing.append(f"{relative} (holds another run)")
    return missing


def shorter_runs(runs: Path, docs_dir: Path) -> list[str]:
    """The runs under ``runs`` whose published record (the same ``<env>/<algo>/seed<S>`` under ``<docs dir>/runs``)
    reached more steps: publishing them would replace a longer run with a shorter one (a 100k-step table made in the
    folders of the published 200k-step runs, say), so ``scripts/publish_results.sh`` refuses while there is one."""
    shorter = []
    for local in sorted(runs.rglob("evaluations.csv")):
        if "checkpoints" in local.relative_to(runs).parts:
            continue
        relative = local.parent.relative_to(runs)
        ours, published = (last_step(evaluations_of(folder)) for folder in (local.parent, docs_dir / "runs" / relative))
        if published > ours:
            shorter.append(f"{relative} reached {ours:,} steps, its published record {published:,}")
    return shorter


def hopper_sb3_tables(docs_dir: Path, seeds: list[int] | None) -> str:
    """TD3X against SB3's TD3 on Hopper: the two rows, then their difference (once both have finished seeds)."""
    rows = table(docs_dir, "hopper_td3x_vs_sb3", "algo", HOPPER_SB3, seeds, HOPPER_SB3_SEEDS)
    difference = difference_table(docs_dir, "hopper_td3x_vs_sb3", *HOPPER_SB3)
    return f"{rows}\n\n{difference}" if difference else rows


def tables(docs_dir: Path, seeds: list[int] | None) -> dict[str, str]:
    """The page's tables, except those of groups whose published runs' records are missing (left as they are)."""
    ablation = [(name, "Hopper-v5", f"hopper/{algo}") for algo, name in ABLATION.items()]
    mujoco = [(env_id, env_id, f"{env}/td3") for env, env_id in MUJOCO.items()]
    made = {
        "HOPPER_SB3": ("hopper_td3x_vs_sb3", lambda: hopper_sb3_tables(docs_dir, seeds)),
        "ABLATION": ("hopper_ablation", lambda: table(docs_dir, "hopper_ablation", "variant", ablation, seeds)),
        "MUJOCO": ("td3x_mujoco", lambda: table(docs_dir, "td3x_mujoco", "env (TD3X, `algo=td3`)", mujoco, seeds)),
        "VALUE_BIAS": ("value_bias", lambda: value_table(docs_dir, seeds)),
    }
    filled = {}
    for name, (group, make) in made.items():
        if missing := missing_runs(docs_dir, group):
            print(f"warning: table {name} left as it is: its aggregate ({group}) was made from runs whose records are "
                  f"not under {docs_dir / 'runs'}: {', '.join(missing[:6])}{' ...' if len(missing) > 6 else ''}",
                  file=sys.stderr)  # fmt: skip
            continue
        filled[name] = make()
    return filled


def fill(page: str, filled: dict[str, str]) -> str:
    for name, table in filled.items():
        pattern = re.compile(rf"<!-- {name} -->\n.*?<!-- /{name} -->", flags=re.S)
        if not pattern.search(page):
            raise ValueError(f"the page has no <!-- {name} --> ... <!-- /{name} --> markers to put the table between")
        page = pattern.sub(lambda _: f"<!-- {name} -->\n{table}\n<!-- /{name} -->", page)
    return page


def main(argv: list[str] | None = None) -> int:
    root = Path(__file__).resolve().parents[1]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--docs-dir", type=Path, default=root / "docs" / "assets" / "results")
    parser.add_argument("--page", type=Path, default=root / "docs" / "results.md")
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=None, help="the seeds every row lists (default: 0, 1, 2 and any other found)"
    )
    parser.add_argument("--groups", action="store_true", help="print the groups to aggregate and exit")
    parser.add_argument(
        "--missing-runs", metavar="GROUP", help="print the runs GROUP's aggregate was made from whose records are missing; "
        "exit 3 when there are any"
    )  # fmt: skip
    parser.add_argument(
        "--shorter-runs", metavar="RUNS", type=Path, help="print the runs under RUNS whose published record reached more "
        "steps; exit 3 when there are any"
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.groups:
        for name, folders in GROUPS.items():
            print(name, *folders)
        return 0
    if args.shorter_runs:
        shorter = shorter_runs(args.shorter_runs, args.docs_dir)
        print("\n".join(shorter))
        return 3 if shorter else 0
    if args.missing_runs:
        missing = missing_runs(args.docs_dir, args.missing_runs)
        print("\n".join(missing))
        return 3 if missing else 0
    if not args.page.is_file():
        print(f"error: no page {args.page} to fill", file=sys.stderr)
        return 2
    try:
        page = fill(args.page.read_text(), tables(args.docs_dir, args.seeds))
    except ValueError as error:
        print(f"error: {args.page}: {error}", file=sys.stderr)
        return 2
    args.page.write_text(page)
    print(f"filled the tables of {args.page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
