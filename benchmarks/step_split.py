"""Where an environment step of TD3X goes: matrix products, optimizer and Polyak, other kernels, Python, environment.

    python benchmarks/step_split.py --env Hopper-v5 --batch-size 100 --threads 2
    python benchmarks/step_split.py --variants compile_update=false -   # the eager update and the default

Each variant is a TD3X (``benchmarks/throughput.py``'s settings: 400-300, lr 1e-3, 1000 random steps, N(0, 0.1)
exploration) with the given arguments (``-`` for none); all run in one process, chunks of ``learn()`` alternated.
Per variant, in milliseconds per environment step (medians over the chunks):

- *end to end*: a chunk's wall time, unprofiled;
- *environment*: the vectorized environment's ``step`` (the simulator, its wrappers, resets), timed in the same
  unprofiled chunks;
- *products*, *optimizer and Polyak*, *other kernels*: the self CPU time of the operators ``torch.profiler`` saw in
  one more chunk per variant, by name: matrix products (``mm``, ``addmm``, ``bmm``, ``baddbmm``, oneDNN's fused
  linear), Adam's and the target updates' operators (``_fused_adam_``, ``_foreach_*``, ``lerp_``), and the rest: every
  other operator, and the compiled graphs' own kernels (the self time of Inductor's ``CompiledFxGraph`` calls, which
  includes its generated wrapper's calls);
- *Python*: end to end less the four above (SB3's collection loop, the hooks, the dispatch above the operators).

The profiled chunk is slower than the others (the profiler's own cost per operator); its kernel times are taken as
measured and the Python column absorbs the difference, so it is an upper bound of the time outside the operators.
Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import torch as th
from throughput import RUN_LENGTH, make_model, parse_value

from sb3_td3x import TD3X

PRODUCTS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "mkldnn::_linear_pointwise")
OPTIMIZER_AND_POLYAK = ("_fused_adam", "_foreach_", "lerp")
COLUMNS = ("end_to_end", "products", "optimizer_and_polyak", "other_kernels", "python", "environment")


def parse_variant(text: str) -> dict:
    """``KEY=VALUE,KEY=VALUE`` (``-``: TD3X's defaults) as keyword arguments."""
    if text in ("-", ""):
        return {}
    pairs = [item.split("=", 1) for item in text.split(",")]
    return {key: parse_value(value) for key, value in pairs}


class EnvClock:
    """Seconds spent in ``model.env.step_wait`` while :attr:`on`."""

    def __init__(self, model: TD3X):
        self.seconds, self.on = 0.0, True
        venv = model.get_env()
        inner = venv.step_wait

        def timed():
            start = time.perf_counter()
            try:
                return inner()
            finally:
                self.seconds += time.perf_counter() - start

        venv.step_wait = timed  # type: ignore[method-assign]


def kernel_split(model: TD3X, steps: int) -> dict[str, float]:
    """Milliseconds per environment step of each operator category in one profiled chunk of ``learn()``."""
    with th.profiler.profile(activities=[th.profiler.ProfilerActivity.CPU]) as prof:
        model.learn(steps, reset_num_timesteps=False)
    totals = {"products": 0.0, "optimizer_and_polyak": 0.0, "other_kernels": 0.0}
    for event in prof.key_averages():
        name, self_us = event.key, event.self_cpu_time_total
        if name in PRODUCTS:
            totals["products"] += self_us
        elif any(part in name for part in OPTIMIZER_AND_POLYAK):
            totals["optimizer_and_polyak"] += self_us
        elif name.startswith(("aten::", "mkldnn::", "## Call CompiledFxGraph")):
            totals["other_kernels"] += self_us
    return {key: value / 1e3 / steps for key, value in totals.items()}


def run(env_id: str, args: argparse.Namespace) -> dict:
    variants = {text: parse_variant(text) for text in args.variants}
    common = {"buffer_size": args.buffer_size, "batch_size": args.batch_size}
    models = {text: make_model(TD3X, env_id, args.seed, {**common, **kw}, args.run_length) for text, kw in variants.items()}
    for model in models.values():
        model.learn(args.warmup, reset_num_timesteps=True)
    clocks = {text: EnvClock(model) for text, model in models.items()}
    end_to_end: dict[str, list[float]] = {text: [] for text in models}
    environment: dict[str, list[float]] = {text: [] for text in models}
    for _ in range(args.chunks):
        for text, model in models.items():  # A B A B ...
            clocks[text].seconds = 0.0
            start = time.perf_counter()
            model.learn(args.chunk_steps, reset_num_timesteps=False)
            end_to_end[text].append(1e3 * (time.perf_counter() - start) / args.chunk_steps)
            environment[text].append(1e3 * clocks[text].seconds / args.chunk_steps)
    result = {}
    for text, model in models.items():
        row = {"end_to_end": statistics.median(end_to_end[text]), "environment": statistics.median(environment[text])}
        row |= kernel_split(model, args.chunk_steps)
        row["python"] = row["end_to_end"] - sum(row[k] for k in ("environment", "products", "optimizer_and_polyak", "other_kernels"))
        row["update_path"] = model.update_path
        row["end_to_end_per_chunk"] = end_to_end[text]
        result[text] = row
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Hopper-v5"])
    parser.add_argument("--variants", nargs="+", default=["compile_update=false", "-"],
                        help="TD3X arguments per variant, KEY=VALUE,KEY=VALUE ('-': the defaults)")
    parser.add_argument("--chunks", type=int, default=5)
    parser.add_argument("--chunk-steps", type=int, default=500)
    parser.add_argument("--warmup", type=int, default=1_500)
    parser.add_argument("--buffer-size", type=int, default=1_000_000)
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--run-length", type=int, default=RUN_LENGTH, help="TD3X's defaults are those of a run this long")
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
    machine = {"cpu_model": cpu, "processor": platform.machine(), "cores": os.cpu_count(), "torch_threads": args.threads,
               "torch": th.__version__}
    print(f"machine: {machine}")
    results = {}
    for env_id in args.env:
        results[env_id] = run(env_id, args)
        print(f"\n{env_id}, batch {args.batch_size}, ms per environment step")
        print(f"  {'variant':28s} " + " ".join(f"{c:>20s}" for c in COLUMNS) + "  update path")
        for text, row in results[env_id].items():
            print(f"  {text:28s} " + " ".join(f"{row[c]:20.3f}" for c in COLUMNS) + f"  {row['update_path']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": machine, "args": vars(args), "results": results}, f, indent=2)


if __name__ == "__main__":
    main()
