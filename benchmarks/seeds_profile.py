"""Where a SeedBatch's time goes: cProfile of N seeds trained together, collection against the update.

    python benchmarks/seeds_profile.py --seeds 16 --device cuda          # what docs/performance_log.md quotes (H100)
    python benchmarks/seeds_profile.py --seeds 2 --device cpu --env Hopper-v5
    python benchmarks/seeds_profile.py --seeds 8 --device cpu --env Hopper-v5 --threads 2 --collect-threads 2

cProfile sees the caller's thread only: with ``--collect-threads`` above 1, the seeds' collection shows as the
cumulative time of ``SeedBatch._collect_round`` (the caller waiting for the threads), the update as ``_train``.

TD3's Ant-v5 settings of benchmarks/seeds_scaling.py (400-300 networks, batch 256). The models first run
``learning_starts`` random steps and ``--warmup`` training steps, untimed; then ``--steps`` rounds (every seed one
environment step and one gradient step) run under cProfile. Prints the rate, then the functions by cumulative and
by own time. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parent))
from seeds_scaling import Config, make_model  # noqa: E402

from sb3_td3x import TD3X, SeedBatch  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=16, help="how many seeds in the batch")
    parser.add_argument("--env", default="Ant-v5")
    parser.add_argument("--device", default="cuda" if th.cuda.is_available() else "cpu")
    parser.add_argument("--steps", type=int, default=150, help="profiled rounds")
    parser.add_argument("--warmup", type=int, default=100, help="untimed training steps after learning_starts")
    parser.add_argument("--rows", type=int, default=28, help="functions listed per table")
    parser.add_argument("--threads", type=int, default=th.get_num_threads(), help="torch threads")
    parser.add_argument("--collect-threads", type=int, default=1, help="SeedBatch's collect_threads")
    args = parser.parse_args()
    if min(args.seeds, args.steps, args.threads, args.collect_threads) < 1 or args.warmup < 0:
        parser.error("--seeds, --steps, --threads and --collect-threads must be at least 1, --warmup at least 0")
    th.set_num_threads(args.threads)
    if args.device.startswith("cuda") and not th.cuda.is_available():
        parser.error("--device cuda: torch sees no CUDA device here; use --device cpu")
    config = Config(args.env, 256, (400, 300), 20_000, 1000, args.warmup, args.steps, args.device)
    seeds = list(range(args.seeds))
    batch = SeedBatch(lambda seed: make_model(TD3X, config, seed), seeds, collect_threads=args.collect_threads)
    batch.learn(config.learning_starts + args.warmup)
    if th.device(args.device).type == "cuda":
        th.cuda.synchronize()
    profile = cProfile.Profile()
    start = time.perf_counter()
    profile.enable()
    batch.learn(args.steps, reset_num_timesteps=False)
    if th.device(args.device).type == "cuda":
        th.cuda.synchronize()
    profile.disable()
    wall = time.perf_counter() - start
    print(f"{args.env}, {args.seeds} seeds on {args.device}: {args.seeds * args.steps / wall:.1f} seed-steps/s under "
          f"cProfile, {1000 * wall / args.steps:.1f} ms per round; update path {batch[0].update_path}; "
          f"collection: {batch.collection}; {th.get_num_threads()} torch threads")
    stats = pstats.Stats(profile)
    stats.sort_stats("cumulative").print_stats(args.rows)
    stats.sort_stats("tottime").print_stats(15)


if __name__ == "__main__":
    main()
