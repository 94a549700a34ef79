"""Time per gradient step of N seeds through one MlpUpdate of their N models against N lone MlpUpdate steps.

    python benchmarks/seed_stack.py                       # Hopper-v5 shapes, net [400, 300], batch 100, N = 1 2 4 8
    python benchmarks/seed_stack.py --seeds 1 4 --steps 20 --repeats 3

Both run in this process on one thread (``torch.set_num_threads(1)``), from buffers filled with random transitions
(the update's cost does not depend on the data). Each repeat times ``steps`` gradient steps of the N lone models, one
``model.train()`` after the other, then the same number of steps of the N models stacked (each model drawing from
its own detached random streams, as in a ``SeedBatch``); the medians are printed. Not part of the test suite
(``tests/equivalence/test_mlp_update_seeds.py`` checks the results).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import time

import numpy as np
import torch as th
from stable_baselines3.common.logger import configure

from sb3_td3x import TD3X
from sb3_td3x.td3x.update_paths.mlp import MlpUpdate


def cpu_name() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, subprocess.CalledProcessError, StopIteration):
        return platform.processor() or "unknown CPU"


def filled_model(env: str, seed: int, net: list[int], transitions: int) -> TD3X:
    """A model whose buffer holds ``transitions`` random transitions, past its optimizers' first step."""
    model = TD3X("MlpPolicy", env, policy_kwargs={"net_arch": net}, buffer_size=transitions, learning_starts=0, seed=seed)
    model.set_logger(configure(None, []))
    obs_dim, action_dim = model.observation_space.shape[0], model.action_space.shape[0]
    rng = np.random.default_rng(seed)
    for _ in range(transitions):
        model.replay_buffer.add(
            rng.standard_normal((1, obs_dim)).astype(np.float32),
            rng.standard_normal((1, obs_dim)).astype(np.float32),
            rng.uniform(-1, 1, (1, action_dim)).astype(np.float32),
            rng.standard_normal(1).astype(np.float32),
            np.zeros(1, dtype=np.float32),
            [{}],
        )
    model.random_streams.detach()
    return model


def stacked_steps(update: MlpUpdate, steps: int, batch_size: int) -> None:
    """``steps`` gradient steps of every model of ``update``, the actors updated every second step."""
    for step in range(steps):
        batches = [model.sample_batch(batch_size) for model in update.models]
        update.step(batches, [step % 2 == 1] * len(batches))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--net", type=int, nargs="+", default=[400, 300])
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--steps", type=int, default=40, help="gradient steps per timing")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--transitions", type=int, default=2_000)
    args = parser.parse_args()
    th.set_num_threads(1)
    print(
        f"{cpu_name()}, torch {th.__version__}, 1 thread; {args.env}, net {args.net}, batch {args.batch_size}"
    )
    print(f"{'N':>3} {'lone ms/step':>13} {'stacked ms/step':>16} {'speed-up':>9} {'stacked ms/seed':>16}")
    for n in args.seeds:
        lone = [filled_model(args.env, seed, args.net, args.transitions) for seed in range(n)]
        stacked = MlpUpdate([filled_model(args.env, seed, args.net, args.transitions) for seed in range(n)])
        for model in lone:  # warm-up: the update chosen, the optimizers' states created
            model.train(4, args.batch_size)
        stacked_steps(stacked, 4, args.batch_size)
        lone_times, stacked_times = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            for model in lone:
                model.train(args.steps, args.batch_size)
            lone_times.append((time.perf_counter() - start) / args.steps)
            start = time.perf_counter()
            stacked_steps(stacked, args.steps, args.batch_size)
            stacked_times.append((time.perf_counter() - start) / args.steps)
        lone_ms, stacked_ms = 1e3 * statistics.median(lone_times), 1e3 * statistics.median(stacked_times)
        print(f"{n:>3} {lone_ms:>13.2f} {stacked_ms:>16.2f} {lone_ms / stacked_ms:>8.2f}x {stacked_ms / n:>16.2f}")


if __name__ == "__main__":
    main()
