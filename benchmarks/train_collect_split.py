"""Where TD3X and SBX's TD3 differ per environment step: in ``train()`` or in collection, in one process.

    python benchmarks/train_collect_split.py --env Hopper-v5 --batch-size 100 --threads 2 --rounds 8

Both models are built with ``benchmarks/throughput.py``'s settings (400-300, lr 1e-3, 1000 random steps, N(0, 0.1)
exploration; TD3X as part of a long run, so compiled) and warmed up by 1,300 steps of ``learn()``. Then, in rounds,
each in turn:

- ``learn``: 300 steps of ``learn()``, with ``train()`` and ``collect_rollouts()`` timed inside it (milliseconds per
  environment step; the rest is ``learn()``'s own loop);
- ``train(1)``: 100 calls of ``train(gradient_steps=1)``, as ``learn()`` makes them (no collection between);
- ``train(100)``: one call of ``train(gradient_steps=100)``: SBX runs its gradient steps in one XLA loop, so this is
  its compiled step without the cost of a call.

It prints the medians over the rounds and the per-round ratio TD3X / SBX of each (above 1: TD3X slower). Rounds
alternate the two models, so a slow phase of the machine hits both. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from throughput import make_model, sbx_td3

from sb3_td3x import TD3X


class _Stop(BaseCallback):
    def __init__(self, steps: int):
        super().__init__()
        self.steps, self.calls = steps, 0

    def _on_step(self) -> bool:
        self.calls += 1
        return self.calls < self.steps


def _timed(model, name: str, spent: dict[str, float]) -> None:
    """Wrap ``model.<name>`` so that its time adds up in ``spent[name]``."""
    method = getattr(model, name)

    def timed(*args, **kwargs):
        start = time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            spent[name] += time.perf_counter() - start

    setattr(model, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=8)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    sbx = sbx_td3(args.threads)
    if sbx is None:
        raise SystemExit("SBX is not installed (pip install -e '.[peers]')")
    kinds = (("td3x", TD3X), ("sbx", sbx))
    models = {name: make_model(cls, args.env, 0, {"batch_size": args.batch_size}) for name, cls in kinds}
    spent = {name: {"train": 0.0, "collect_rollouts": 0.0} for name in models}
    for name, model in models.items():
        model.learn(1_000_000, callback=_Stop(1_300), reset_num_timesteps=False)
        _timed(model, "train", spent[name])
        _timed(model, "collect_rollouts", spent[name])
    columns = ("learn", "of which train", "of which collection", "train(1)", "train(100)")
    rows: dict[tuple[str, str], list[float]] = {(name, what): [] for name in models for what in columns}
    for _ in range(args.rounds):
        for name, model in models.items():
            before = dict(spent[name])
            start = time.perf_counter()
            model.learn(1_000_000, callback=_Stop(300), reset_num_timesteps=False)
            rows[(name, "learn")].append((time.perf_counter() - start) / 300 * 1e3)
            rows[(name, "of which train")].append((spent[name]["train"] - before["train"]) / 300 * 1e3)
            collected = spent[name]["collect_rollouts"] - before["collect_rollouts"]
            rows[(name, "of which collection")].append(collected / 300 * 1e3)
            start = time.perf_counter()
            for _ in range(100):
                model.train(gradient_steps=1, batch_size=args.batch_size)
            rows[(name, "train(1)")].append((time.perf_counter() - start) / 100 * 1e3)
            start = time.perf_counter()
            model.train(gradient_steps=100, batch_size=args.batch_size)
            rows[(name, "train(100)")].append((time.perf_counter() - start) / 100 * 1e3)
    print(f"{args.env}, batch {args.batch_size}, {args.threads} threads, {args.rounds} rounds; ms per step (median)")
    for what in columns:
        td3x, sbx_ = rows[("td3x", what)], rows[("sbx", what)]
        ratios = [a / b for a, b in zip(td3x, sbx_)]
        print(f"  {what:20s} td3x {statistics.median(td3x):6.2f}   sbx {statistics.median(sbx_):6.2f}   "
              f"td3x/sbx {statistics.median(ratios):.2f} (rounds {min(ratios):.2f} to {max(ratios):.2f})")  # fmt: skip


if __name__ == "__main__":
    main()
