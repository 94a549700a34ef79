"""Two or more TD3 implementations or commits trained side by side, in separate processes, chunk by chunk.

    python benchmarks/alternated.py --env Hopper-v5 --batch-size 100 --chunks 14 --chunk-steps 400 \\
        old=/tmp/old514:td3x new=.:td3x                       # two checkouts of this repository (git worktree add)
    python benchmarks/alternated.py --env Ant-v5 --batch-size 256 new=.:td3x compiled=.:td3x:compile_update=true sbx=.:sbx
    python benchmarks/alternated.py --mode train old=/tmp/old:td3x new=.:td3x   # gradient steps only, no collection
    python benchmarks/alternated.py t2=.:td3x t1=.:td3x:threads=1 sbx=.:sbx      # one side on one torch thread

Each ``NAME=TREE:ALGO[:KEY=VALUE,...]`` is a process that imports this package from ``TREE`` (a checkout; ``.``
is this one) and trains ``ALGO`` (``td3x``, ``sb3`` or ``sbx``) with ``benchmarks/throughput.py``'s settings of that
tree (400-300, lr 1e-3, 1000 random steps, N(0, 0.1) exploration). After a warm-up, one at a time, the driver asks each
process in turn for a chunk of ``--chunk-steps`` steps (``learn``, or ``train`` with ``--mode train``): only one
process runs at a time, and a slow phase of the machine hits the chunks around it alike. ``threads=N`` among a side's
``KEY=VALUE`` sets that side's torch (or XLA) threads in place of ``--threads``. It prints each one's
median steps/s, its cores used (process CPU seconds per second) and the median of its per-chunk ratios to the first.

Use it where one process cannot hold both sides (two commits of this package), or to compare across processes: on
the project's virtual machines a process can run for minutes at one of two speeds (docs/performance_log.md, "the
host has two speeds"), so only alternated chunks, compared chunk by chunk, say which side is faster.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve()


def worker(tree: str, algo: str, env: str, batch_size: int, threads: int, extra: list[str], mode: str) -> None:
    """One side: build the model, warm up, then run a chunk per ``go N`` line on stdin and print its rate."""
    sys.path[:0] = [tree, os.path.join(tree, "benchmarks")]
    import torch as th
    from throughput import make_model, parse_value  # the tree's own: its settings

    kwargs = {k: parse_value(v) for k, v in (item.split("=", 1) for item in extra)}
    threads = int(kwargs.pop("threads", threads))  # this side's own thread count, not a model argument
    th.set_num_threads(threads)
    if algo == "sbx":
        from throughput import sbx_td3

        cls = sbx_td3(threads)
        if cls is None:
            raise SystemExit("sbx: SBX is not installed (pip install -e '.[peers]')")
    elif algo == "sb3":
        from stable_baselines3 import TD3 as cls
    else:
        import sb3_td3x

        if not Path(sb3_td3x.__file__).resolve().is_relative_to(Path(tree).resolve()):
            raise SystemExit(f"td3x: imported {sb3_td3x.__file__}, not the one in {tree}")
        cls = sb3_td3x.TD3X
    model = make_model(cls, env, 0, {"batch_size": batch_size, **kwargs})
    model.learn(1_500)  # past learning_starts=1000, and any compilation
    print("ready", flush=True)
    for line in sys.stdin:
        steps = int(line.split()[1])
        start, cpu = time.perf_counter(), time.process_time()
        if mode == "train":
            model.train(gradient_steps=steps, batch_size=batch_size)
        else:
            model.learn(steps, reset_num_timesteps=False)
        wall = time.perf_counter() - start
        print(f"{steps / wall:.4f} {(time.process_time() - cpu) / wall:.4f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sides", nargs="*", metavar="NAME=TREE:ALGO[:KEY=VALUE,...]")
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--chunks", type=int, default=12)
    parser.add_argument("--chunk-steps", type=int, default=400)
    parser.add_argument("--mode", choices=("learn", "train"), default="learn")
    parser.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        tree, algo, *extra = args.worker
        worker(tree, algo, args.env, args.batch_size, args.threads, extra, args.mode)
        return
    if not args.sides:
        parser.error("give at least one side, NAME=TREE:ALGO[:KEY=VALUE,...], such as new=.:td3x")
    sides = {}
    for spec in args.sides:
        name, sep, rest = spec.partition("=")
        parts = rest.split(":")
        if not sep or len(parts) < 2 or parts[1] not in ("td3x", "sb3", "sbx") or not Path(parts[0]).is_dir():
            parser.error(f"{spec!r}: give NAME=TREE:ALGO[:KEY=VALUE,...], TREE a folder, ALGO td3x, sb3 or sbx")
        extra = parts[2].split(",") if len(parts) > 2 and parts[2] else []
        command = [sys.executable, str(HERE), "--env", args.env, "--batch-size", str(args.batch_size),
                   "--threads", str(args.threads), "--mode", args.mode, "--worker", parts[0], parts[1], *extra]  # fmt: skip
        sides[name] = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if sides[name].stdout.readline().strip() != "ready":  # warm-ups one at a time, too
            raise SystemExit(f"{name}: the process ended before its warm-up did")
    rates: dict[str, list[float]] = {name: [] for name in sides}
    cores: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(args.chunks):
        for name, process in sides.items():
            process.stdin.write(f"go {args.chunk_steps}\n")
            process.stdin.flush()
            rate, used = map(float, process.stdout.readline().split())
            rates[name].append(rate)
            cores[name].append(used)
    for process in sides.values():
        process.stdin.close()
        process.wait()
    unit = "gradient steps/s" if args.mode == "train" else "steps/s"
    print(f"{args.env}, batch {args.batch_size}, {args.threads} threads, {args.chunks} chunks of {args.chunk_steps}")
    first = next(iter(sides))
    for name in sides:
        rate, used = statistics.median(rates[name]), statistics.median(cores[name])
        line = f"  {name:12s} {rate:8.1f} {unit}  cores {used:.2f}  per CPU-second {rate / used:7.1f}"
        if name != first:
            ratios = [b / a for a, b in zip(rates[first], rates[name])]
            line += f"  {name}/{first} median {statistics.median(ratios):.3f} (per chunk {min(ratios):.2f} to {max(ratios):.2f})"
        print(line)


if __name__ == "__main__":
    main()
