"""Fill the tables of docs/results.md from the published results (run by scripts/publish_results.sh).

Each table sits between two markers of the page, ``<!-- NAME -->`` and ``<!-- /NAME -->``, and is rewritten from
``<results docs dir>/<group>/aggregate.csv`` (what ``sb3_td3x.experiment.aggregate`` wrote: the finished seeds of
each algorithm, or all its seeds as far as they have all got while none has finished) and the runs' records under
``<results docs dir>/runs/<env>/<algo>/seed<S>/``, which say how far each seed has got. Nothing in the tables
is typed by hand, so publishing again after more runs brings the page up to date.

    python scripts/results_tables.py [--docs-dir docs/assets/results] [--page docs/results.md] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

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
HEADER = [
    "| {first} | seeds: steps reached | steps | final return, mean (95% CI) | final return per seed | best mean |",
    "|---|---|---|---|---|---|",
]


def seed_progress(run_dir: Path) -> str:
    """'200k', '85k of 200k', 'not started' or 'started, no evaluation yet' for one seed's run folder."""
    if not run_dir.is_dir():
        return "not started"
    target = None
    if (run_dir / "config.yaml").is_file():
        target = (yaml.safe_load((run_dir / "config.yaml").read_text()) or {}).get("total_timesteps")
    evaluations = run_dir / "evaluations.csv"
    reached = int(pd.read_csv(evaluations)["timesteps"].iloc[-1]) if evaluations.is_file() else 0
    if reached == 0:
        return "started, no evaluation yet"
    if target is None or reached >= int(target):
        return steps(reached)
    return f"{steps(reached)} of {steps(int(target))}"


def steps(n: int) -> str:
    return f"{n // 1000}k" if n >= 1000 and n % 1000 == 0 else f"{n:,}"


def row(name: str, aggregate: pd.DataFrame, env_id: str, algo: str, runs: Path, seeds: list[int]) -> str:
    progress = ", ".join(f"{seed}: {seed_progress(runs / f'seed{seed}')}" for seed in seeds)
    found = aggregate[(aggregate["env_id"] == env_id) & (aggregate["algo"] == algo)] if len(aggregate) else aggregate
    if found.empty:
        return f"| {name} | {progress} | | | | |"
    r = found.iloc[0]
    final = f"{r.final_mean:.1f} ({r.ci_low:.1f} to {r.ci_high:.1f})" if r.n_runs > 1 else f"{r.final_mean:.1f} (one seed)"
    seeds_aggregated = str(r.seeds).split(", ")
    per_seed = ", ".join(f"{seed}: {value}" for seed, value in zip(seeds_aggregated, str(r.per_seed_final).split(", ")))
    return f"| {name} | {progress} | {int(r.timesteps):,} | {final} | {per_seed} | {r.best_mean:.1f} |"


def read_aggregate(path: Path) -> pd.DataFrame:
    return pd.read_csv(path) if path.is_file() else pd.DataFrame()


def tables(docs_dir: Path, seeds: list[int]) -> dict[str, str]:
    runs = docs_dir / "runs"
    ablation = read_aggregate(docs_dir / "hopper_ablation" / "aggregate.csv")
    mujoco = read_aggregate(docs_dir / "td3x_mujoco" / "aggregate.csv")
    rows = [h.format(first="variant") for h in HEADER]
    rows += [row(name, ablation, "Hopper-v5", algo, runs / "hopper" / algo, seeds) for algo, name in ABLATION.items()]
    out = {"ABLATION": "\n".join(rows)}
    rows = [h.format(first="env (TD3X, `algo=td3`)") for h in HEADER]
    rows += [row(env_id, mujoco, env_id, "td3", runs / env / "td3", seeds) for env, env_id in MUJOCO.items()]
    out["MUJOCO"] = "\n".join(rows)
    return out


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
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args(argv)
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
