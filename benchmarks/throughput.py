"""Throughput of TD3X against SB3's TD3: same env, same hyperparameters, one process, chunks alternated A B A B.

    python benchmarks/throughput.py                          # Ant-v5 and HalfCheetah-v5, defaults, fp32
    python benchmarks/throughput.py --env Ant-v5 --td3x bf16=true
    python benchmarks/throughput.py --json docs/assets/bench.json

Prints end-to-end environment steps/s of each (collection and training), the median ratio over chunks, the time per
gradient step, the achieved GFLOP/s of the update (FLOPs counted by torch's FlopCounterMode) against the machine's
measured matmul peak, and the replay buffer's bytes per transition. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise
from torch.utils.flop_counter import FlopCounterMode

from sb3_td3x import TD3X


def parse_value(text: str):
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def matmul_peak_gflops(dtype: th.dtype = th.float32, n: int = 2048, reps: int = 10) -> float:
    a = th.randn(n, n, dtype=dtype)
    for _ in range(2):
        a @ a
    start = time.perf_counter()
    for _ in range(reps):
        a @ a
    return 2 * n**3 * reps / (time.perf_counter() - start) / 1e9


def make_model(algo: type, env_id: str, seed: int, extra: dict) -> TD3:
    env = gym.make(env_id)
    action_dim = env.action_space.shape[0]
    model = algo(
        "MlpPolicy",
        env,
        learning_starts=1_000,
        action_noise=NormalActionNoise(np.zeros(action_dim), 0.1 * np.ones(action_dim)),
        seed=seed,
        **extra,
    )
    model.set_logger(configure(None, []))
    return model


def gradient_step_time(model: TD3, steps: int) -> float:
    model.train(gradient_steps=5, batch_size=model.batch_size)
    start = time.perf_counter()
    model.train(gradient_steps=steps, batch_size=model.batch_size)
    if model.device.type == "cuda":
        th.cuda.synchronize()
    return (time.perf_counter() - start) / steps


def flops_per_gradient_step(model: TD3) -> float:
    delay = model.policy_delay
    with FlopCounterMode(display=False) as counter:
        model.train(gradient_steps=delay, batch_size=model.batch_size)
    return counter.get_total_flops() / delay


def bytes_per_transition(model: TD3) -> float:
    buffer = model.replay_buffer
    if hasattr(buffer, "nbytes") and callable(buffer.nbytes):
        total = buffer.nbytes()
    else:
        total = sum(getattr(buffer, name).nbytes for name in ("observations", "actions", "rewards", "dones", "timeouts"))
        if not buffer.optimize_memory_usage:
            total += buffer.next_observations.nbytes
    return total / (buffer.buffer_size * buffer.n_envs)


def bench_env(env_id: str, args: argparse.Namespace, td3x_kwargs: dict) -> dict:
    sb3 = make_model(TD3, env_id, args.seed, {"buffer_size": args.buffer_size})
    td3x = make_model(TD3X, env_id, args.seed, {"buffer_size": args.buffer_size, **td3x_kwargs})
    models = {"sb3": sb3, "td3x": td3x}
    # Warm-up: fill past learning_starts and let compilation/graph capture happen outside the timed chunks.
    for model in models.values():
        model.learn(args.warmup, reset_num_timesteps=True)
    rates: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.chunks):
        for name, model in models.items():  # A B A B ...
            start = time.perf_counter()
            model.learn(args.chunk_steps, reset_num_timesteps=False)
            rates[name].append(args.chunk_steps / (time.perf_counter() - start))
    ratios = [b / a for a, b in zip(rates["sb3"], rates["td3x"])]
    result = {"env": env_id, "steps_per_s": {k: statistics.median(v) for k, v in rates.items()}, "chunks": rates,
              "median_ratio": statistics.median(ratios), "ratios": ratios}
    peak = matmul_peak_gflops()
    for name, model in models.items():
        step_s = gradient_step_time(model, args.grad_steps)
        flops = flops_per_gradient_step(model)
        result[name] = {
            "ms_per_gradient_step": 1e3 * step_s,
            "gflop_per_gradient_step": flops / 1e9,
            "achieved_gflops": flops / step_s / 1e9,
            "fraction_of_fp32_matmul_peak": flops / step_s / 1e9 / peak,
            "replay_bytes_per_transition": bytes_per_transition(model),
        }
    result["fp32_matmul_peak_gflops"] = peak
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Ant-v5", "HalfCheetah-v5"])
    parser.add_argument("--chunks", type=int, default=4, help="timed chunks per algorithm, alternated")
    parser.add_argument("--chunk-steps", type=int, default=1_500)
    parser.add_argument("--warmup", type=int, default=1_500)
    parser.add_argument("--grad-steps", type=int, default=200)
    parser.add_argument("--buffer-size", type=int, default=1_000_000)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--td3x", nargs="*", default=[], metavar="KEY=VALUE", help="extra TD3X arguments (opt-in flags)")
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args()

    th.set_num_threads(args.threads)
    td3x_kwargs = {k: parse_value(v) for k, v in (item.split("=", 1) for item in args.td3x)}
    machine = {
        "processor": platform.processor() or platform.machine(),
        "cpu_model": next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
        if os.path.exists("/proc/cpuinfo") else "?",
        "cores": os.cpu_count(),
        "torch_threads": th.get_num_threads(),
        "torch": th.__version__,
    }
    print(f"machine: {machine}\nTD3X extra arguments: {td3x_kwargs or 'none (defaults, fp32)'}")
    results = []
    for env_id in args.env:
        r = bench_env(env_id, args, td3x_kwargs)
        results.append(r)
        print(f"\n{env_id}")
        print(f"  end-to-end steps/s   SB3 TD3 {r['steps_per_s']['sb3']:8.1f}   TD3X {r['steps_per_s']['td3x']:8.1f}")
        print(f"  ratio TD3X / SB3     median {r['median_ratio']:.2f}x   per chunk {[round(x, 2) for x in r['ratios']]}")
        for name in ("sb3", "td3x"):
            s = r[name]
            print(
                f"  {name:5s} {s['ms_per_gradient_step']:6.2f} ms/gradient step, {s['gflop_per_gradient_step']:.2f} GFLOP, "
                f"{s['achieved_gflops']:6.1f} GFLOP/s = {100 * s['fraction_of_fp32_matmul_peak']:4.1f}% of the fp32 matmul "
                f"peak ({r['fp32_matmul_peak_gflops']:.0f} GFLOP/s), replay {s['replay_bytes_per_transition']:.0f} B/transition"
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": machine, "td3x_kwargs": td3x_kwargs, "args": vars(args), "results": results}, f, indent=2)


if __name__ == "__main__":
    main()
