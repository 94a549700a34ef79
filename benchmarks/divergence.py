"""How fast seeded TD3X and SB3's TD3 runs drift apart: the largest actor-weight difference against steps.

    python benchmarks/divergence.py                      # Hopper-v5, the results pages' config (algo=td3 / sb3_td3)
    python benchmarks/divergence.py --env walker2d --steps 5000

Both models are built by the experiment runner from ``algo=td3`` and ``algo=sb3_td3`` with the same seed, so they
start from the same weights, draw the same batches and the same noise. They compute the same updates up to float
rounding (fused against for-each Adam, summation order), and a training loop amplifies rounding: this prints how
quickly. It explains why the results pages compare the two over seeds, not seed by seed. Not part of the test suite
(``tests/equivalence/test_same_learning.py`` asserts the equality over the first steps).
"""

from __future__ import annotations

import argparse

import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_td3x.experiment.configs.algos import build_algorithm
from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.run.envs import make_train_env


class ActorSnapshots(BaseCallback):
    """The actor's parameters, flattened, at the given steps."""

    def __init__(self, steps: set[int]) -> None:
        super().__init__()
        self.steps = steps
        self.snapshots: dict[int, th.Tensor] = {}

    def _on_step(self) -> bool:
        if self.model.num_timesteps in self.steps:
            parameters = [p.detach().flatten().clone() for p in self.model.actor.parameters()]
            self.snapshots[self.model.num_timesteps] = th.cat(parameters)
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="hopper", help="a config of conf/env/ (default: hopper)")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)

    snapshots = {}
    for algo in ("td3", "sb3_td3"):
        cfg = compose_config([f"algo={algo}", f"env={args.env}", "device=cpu", f"seed={args.seed}"])
        start = cfg.algo.learning_starts
        steps = {start + 1, start + 10, start + 100} | {start + k * (args.steps - start) // 8 for k in range(1, 9)}
        callback = ActorSnapshots({step for step in steps if step <= args.steps})
        env = make_train_env(cfg.env, 1, args.seed)
        build_algorithm(cfg, env).learn(args.steps, callback=callback)
        env.close()
        snapshots[algo] = callback.snapshots
    print(f"{cfg.env.id}, seed {args.seed}, training from step {start}")
    print("step    gradient steps   max |actor weight, TD3X - SB3 TD3|")
    for step in sorted(snapshots["td3"]):
        difference = (snapshots["td3"][step] - snapshots["sb3_td3"][step]).abs().max().item()
        print(f"{step:6d}  {max(step - start, 0):14d}   {difference:.3g}")


if __name__ == "__main__":
    main()
