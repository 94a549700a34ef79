"""Where the time of a seed-step goes, lone and batched: the floors that bound what batching seeds can gain.

    python benchmarks/seeds_floors.py --env Hopper-v5 --batch-size 100 --seeds 8
    python benchmarks/seeds_floors.py --env Ant-v5 --batch-size 256 --seeds 8

One process, one torch thread (the setting of one core of ``batched_per_core`` and of each ``td3x_procs`` process in
``benchmarks/seeds_scaling.py``). After ``learning_starts`` and a warm-up, ``--steps`` rounds are timed twice: a lone
``TD3X`` (N = 1, its own ``learn``) and a ``SeedBatch`` of ``--seeds`` seeds. For each, per seed-step:

- ``total``: wall time of ``learn`` / seed-steps;
- ``collection``: time inside ``collect_rollouts`` (environment step, exploration action, buffer, callbacks);
- ``update``: time inside the gradient steps (``TD3X.train``, or ``SeedBatch._train_together``);
- ``products``: self time of the matrix products (``aten::mm``, ``addmm``, ``bmm``, ``baddbmm``), from the torch
  profiler over a separate window of the same length.

Batching divides the update's per-step overhead by N but not its products (the same floating-point work per seed),
nor collection (one environment and one exploration action per seed). So ``collection + products`` of the batch,
per seed-step, is the floor of its time, and ``lone total / that floor`` the most any batching of these seeds could
gain over lone processes on this machine.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from torch.profiler import ProfilerActivity, profile

from sb3_td3x import TD3X, SeedBatch

PRODUCTS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def make(env_id: str, batch_size: int, learning_starts: int) -> Callable[[int], TD3X]:
    def model(seed: int) -> TD3X:
        env = gym.make(env_id)
        action_dim = env.action_space.shape[0]
        m = TD3X(
            "MlpPolicy",
            env,
            learning_starts=learning_starts,
            batch_size=batch_size,
            buffer_size=200_000,
            policy_kwargs={"net_arch": [400, 300]},
            action_noise=NormalActionNoise(np.zeros(action_dim), 0.1 * np.ones(action_dim)),
            seed=seed,
        )
        m.set_logger(configure(None, []))
        return m

    return model


class Timers:
    """Time spent inside the wrapped methods (class attributes replaced for the duration)."""

    def __init__(self) -> None:
        self.seconds = {"collection": 0.0, "update": 0.0}
        self._saved: list[tuple[type, str, Any]] = []

    def wrap(self, cls: type, name: str, key: str) -> None:
        original = getattr(cls, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds[key] += time.perf_counter() - start

        self._saved.append((cls, name, original))
        setattr(cls, name, timed)

    def __enter__(self) -> Timers:
        self.wrap(OffPolicyAlgorithm, "collect_rollouts", "collection")
        self.wrap(TD3X, "train", "update")
        self.wrap(SeedBatch, "_train_together", "update")
        return self

    def __exit__(self, *exc: object) -> None:
        for cls, name, original in reversed(self._saved):
            setattr(cls, name, original)


def measure(trainer: TD3X | SeedBatch, n_seeds: int, steps: int) -> dict[str, float]:
    with Timers() as timers:
        start = time.perf_counter()
        trainer.learn(steps, reset_num_timesteps=False)
        total = time.perf_counter() - start
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        trainer.learn(steps, reset_num_timesteps=False)
    products_us = sum(e.self_cpu_time_total for e in prof.key_averages() if e.key in PRODUCTS)
    seed_steps = steps * n_seeds
    return {
        "total_ms": 1e3 * total / seed_steps,
        "collection_ms": 1e3 * timers.seconds["collection"] / seed_steps,
        "update_ms": 1e3 * timers.seconds["update"] / seed_steps,
        "products_ms": 1e-3 * products_us / seed_steps,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--steps", type=int, default=300, help="timed rounds (each window)")
    parser.add_argument("--warmup", type=int, default=300, help="training steps before timing")
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    factory = make(args.env, args.batch_size, args.learning_starts)
    rows = {}
    lone = factory(0)
    lone.learn(args.learning_starts + args.warmup)
    rows["lone"] = measure(lone, 1, args.steps)
    batch = SeedBatch(factory, range(args.seeds))
    batch.learn(args.learning_starts + args.warmup)
    rows[f"batch of {args.seeds}"] = measure(batch, args.seeds, args.steps)
    print(f"{args.env}, batch {args.batch_size}, net [400, 300], {args.threads} thread(s); ms per seed-step")
    print(f"{'':<12} {'total':>7} {'collection':>11} {'update':>7} {'products':>9} {'other':>6}")
    for name, r in rows.items():
        other = r["total_ms"] - r["collection_ms"] - r["update_ms"]
        print(f"{name:<12} {r['total_ms']:>7.2f} {r['collection_ms']:>11.2f} {r['update_ms']:>7.2f} {r['products_ms']:>9.2f} {other:>6.2f}")
    b = rows[f"batch of {args.seeds}"]
    floor = b["collection_ms"] + b["products_ms"]
    print(
        f"floor of the batch (collection + products): {floor:.2f} ms per seed-step; "
        f"lone total / floor = {rows['lone']['total_ms'] / floor:.2f}x at most over lone processes"
    )
    if args.json:
        with open(args.json, "w") as file:
            json.dump({"args": vars(args), "rows": rows, "floor_ms": floor}, file, indent=2)


if __name__ == "__main__":
    main()
