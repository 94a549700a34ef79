"""What running TD3's two critics as one stacked computation could gain on this CPU, measured alone: the forward and
backward of two MLP critics (SB3's layout, 400-300) one after the other, against the same two stacked, each product a
``baddbmm`` over the pair; eagerly and compiled, with the given threads.

    python benchmarks/twin_critics.py --threads 2              # Hopper-v5's sizes: 11 + 3 inputs, batch 100
    python benchmarks/twin_critics.py --threads 1 --batch-size 256 --inputs 35

A measurement of a lever, not a path TD3X runs: the default critics stay two ``nn.Sequential`` (SB3's parameters and
its equality). Not part of the test suite; needs a quiet machine. Results: docs/performance_log.md ("Two threads that
do not pay").
"""

from __future__ import annotations

import argparse
import time

import torch as th
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--inputs", type=int, default=14, help="observation plus action size (Hopper-v5: 11 + 3)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    widths = [400, 300]
    q1, q2 = (nn.Sequential(*create_mlp(args.inputs, 1, widths)) for _ in range(2))  # as SB3 builds each critic
    x, y = th.randn(args.batch_size, args.inputs), th.randn(args.batch_size, 1)
    stacked = [th.stack([a, b]).detach().requires_grad_() for a, b in zip(q1.parameters(), q2.parameters())]

    def one_after_the_other() -> None:
        (((q1(x) - y) ** 2).mean() + ((q2(x) - y) ** 2).mean()).backward()

    def together() -> None:
        h = x.expand(2, *x.shape)
        for i in range(0, len(stacked), 2):
            weight, bias = stacked[i], stacked[i + 1]
            h = th.baddbmm(bias.unsqueeze(1), h, weight.transpose(1, 2))
            if i + 2 < len(stacked):
                h = th.relu(h)
        ((h - y) ** 2).mean(dim=(1, 2)).sum().backward()

    def ms(fn) -> float:
        for _ in range(30):
            fn()
        start = time.perf_counter()
        for _ in range(args.steps):
            fn()
        return (time.perf_counter() - start) / args.steps * 1e3

    compiled = th.compile(one_after_the_other), th.compile(together)
    shape = f"{args.inputs}-{'-'.join(map(str, widths))}-1"
    print(f"two critics {shape}, batch {args.batch_size}, {args.threads} threads: ms per forward and backward")
    for _ in range(args.repeats):
        eager = ms(one_after_the_other), ms(together)
        comp = ms(compiled[0]), ms(compiled[1])
        print(f"  eager: one after the other {eager[0]:.3f}, stacked {eager[1]:.3f} ({eager[0] / eager[1]:.2f}x);  "
              f"compiled: {comp[0]:.3f}, {comp[1]:.3f} ({comp[0] / comp[1]:.2f}x)", flush=True)


if __name__ == "__main__":
    main()
