"""What a user's change, and each variant of ``sb3_td3x.variants``, costs against the stock TD3X: one process, chunks
alternated A B C ... C B A (the order reversed every other round), every model the default of a long run
(``compile_update=None`` compiles the hooks as written on a CPU, whatever they are).

    python benchmarks/user_changes.py                                   # Hopper-v5, batch 100, 2 threads
    python benchmarks/user_changes.py --cases stock huber td3_lap td3_c51 --chunks 8
    python benchmarks/user_changes.py --json docs/assets/user_changes.json
    python benchmarks/user_changes.py --cases stock stock_again huber noise layernorm_policy --chunks 30 --chunk-steps 150

The cases:

- ``stock``: ``TD3X`` as it is;
- ``stock_again``: a second stock ``TD3X`` (opt-in, ``--cases stock_again ...``): the A/A control, whose ratio to
  ``stock`` is what the host's noise alone gives;
- ``huber``: the README's Huber ``critic_loss``;
- ``noise``: ``target_policy_smoothing_noise`` overridden (a uniform noise in place of the Gaussian one);
- ``layernorm_policy``: LayerNorm critics through a policy subclass (``make_critic``), as before the network hooks;
- ``stacked_policy``: the twin critics stacked through a policy subclass: each layer's weights one ``[n_critics, out,
  in]`` parameter, from SB3's initial weights, and one ``baddbmm`` a hidden layer for both critics; the output layer
  (one unit) runs per critic. What a stacked default critic would gain (opt-in, ``--cases stacked_policy ...``). Its
  seeded eager ``learn()`` is the stock one's bit for bit with Adam's loop or ``foreach`` kernel
  (tests/equivalence/test_stacked_critic.py): ATen's batched product rounds as its single product does, except for
  a one-unit output, where the stacked product differs (1e-5 in a weight's gradient). Under torch's fused CPU Adam
  (TD3X's default) a stacked bias of 2 by 300 leaves the separate ones by one rounding (1e-10) within a few gradient
  steps: the kernel takes a tensor's last ``numel % 8`` elements through a scalar tail that rounds otherwise than its
  vector body, and stacking moves the separate biases' tails into the body;
- ``no_bias_pass``: the stock TD3X compiled without ``graph_passes``'s pass (opt-in): what it gains (each bias after
  its product; since ``231eb66`` also Adam's scalars computed once);
- ``td3_lap``, ``td3_nstep``, ``td3_layernorm``, ``td3_c51``: the variants.

Prints each case's end-to-end steps/s (collection and training), its cores used, its update path, and the median of
its per-chunk ratios to ``stock``. Not part of the test suite; needs a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch as th
import torch.nn.functional as F
from stable_baselines3.common.torch_layers import create_mlp
from throughput import make_model

from sb3_td3x import TD3X
from sb3_td3x.td3x.policies import TD3XCritic, TD3XPolicy
from sb3_td3x.td3x.update_paths.compiled import CompiledUpdate
from sb3_td3x.variants import TD3C51, TD3LAP, TD3LayerNorm, TD3NStep


class HuberTD3(TD3X):
    """The README's example."""

    def critic_loss(self, current_q, target_q):  # current_q: (n_critics, batch, 1)
        loss = sum(F.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}


class UniformNoiseTD3(TD3X):
    """Step 6 with a uniform noise of the same spread, clipped as TD3's."""

    def target_policy_smoothing_noise(self, actions):
        noise = (th.rand_like(actions) * 2 - 1) * self.target_policy_noise * 3**0.5
        return noise.clamp(-self.target_noise_clip, self.target_noise_clip)


def add_layer_norms(critic: th.nn.Module) -> None:
    """Rebuild each of an SB3-style critic's networks with a LayerNorm after each hidden Linear."""
    for i in range(len(critic.q_networks)):
        first = critic.q_networks[i][0]
        widths = [m.out_features for m in critic.q_networks[i] if isinstance(m, th.nn.Linear)][:-1]
        net = th.nn.Sequential(*create_mlp(first.in_features, 1, widths, th.nn.ReLU, post_linear_modules=[th.nn.LayerNorm]))
        critic.add_module(f"qf{i}", net)
        critic.q_networks[i] = net


class LayerNormCritic(TD3XCritic):
    """SB3's critic with a LayerNorm after each hidden layer, built the way a user did before the network hooks."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        add_layer_norms(self)


class LayerNormPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return LayerNormCritic(**critic_kwargs).to(self.device)


class StackedCritic(TD3XCritic):
    """SB3's critics with each layer's weights stacked over the critics: one batched product a hidden layer for all of
    them and the one-unit output per critic (``q_values``), the first critic's slice alone for the actor's loss
    (``q1_forward``)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)  # SB3's networks, drawn as SB3 draws them, then stacked
        layers = [[m for m in q_net if isinstance(m, th.nn.Linear)] for q_net in self.q_networks]
        self.weights = th.nn.ParameterList(th.stack([net[i].weight.detach() for net in layers])
                                           for i in range(len(layers[0])))  # fmt: skip
        self.biases = th.nn.ParameterList(th.stack([net[i].bias.detach() for net in layers]).unsqueeze(1)
                                          for i in range(len(layers[0])))  # fmt: skip
        for i in range(len(self.q_networks)):
            delattr(self, f"qf{i}")
        self.q_networks = []

    def _input(self, obs, actions, grad: bool):
        with th.set_grad_enabled(grad):
            features = self.extract_features(obs, self.features_extractor)
        return th.cat([features, actions], dim=1)

    def q_values(self, obs, actions):
        x = self._input(obs, actions, not self.share_features_extractor)
        h = x.expand(len(self.weights[0]), *x.shape)
        for i in range(len(self.weights) - 1):
            h = th.baddbmm(self.biases[i], h, self.weights[i].mT).relu()
        weight, bias = self.weights[-1], self.biases[-1]  # one unit: per critic, as SB3's product rounds it
        return th.stack([th.addmm(bias[i], h[i], weight[i].t()) for i in range(len(weight))])

    def forward(self, obs, actions):
        return tuple(self.q_values(obs, actions).unbind(0))

    def q1_forward(self, obs, actions):
        h = self._input(obs, actions, False)
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            h = th.addmm(bias[0], h, weight[0].t())
            h = h.relu() if i < len(self.weights) - 1 else h
        return h


class NoBiasPassTD3(TD3X):
    """The stock TD3X, its update compiled without Inductor's post-grad pass of ``graph_passes`` (each ``addmm`` left
    as it is, Adam's scalars inlined): ``CompiledUpdate.options`` set for the length of each ``train()`` call, where
    the update is compiled."""

    def train(self, *args, **kwargs):
        saved = CompiledUpdate.options
        CompiledUpdate.options = {"post_grad_custom_post_pass": None}
        try:
            return super().train(*args, **kwargs)
        finally:
            CompiledUpdate.options = saved


class StackedPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return StackedCritic(**critic_kwargs).to(self.device)


CASES = {
    "stock": (TD3X, {}),
    "stock_again": (TD3X, {}),  # a second stock TD3X: the A/A control, what the host's noise and the order alone give
    "huber": (HuberTD3, {}),
    "noise": (UniformNoiseTD3, {}),
    "layernorm_policy": (TD3X, {"policy": LayerNormPolicy}),
    "stacked_policy": (TD3X, {"policy": StackedPolicy}),
    "no_bias_pass": (NoBiasPassTD3, {}),
    "td3_lap": (TD3LAP, {}),
    "td3_nstep": (TD3NStep, {}),
    "td3_layernorm": (TD3LayerNorm, {}),
    "td3_c51": (TD3C51, {"v_min": -10.0, "v_max": 400.0}),
}


def build_model(cls: type, env_id: str, batch_size: int, policy: type | None = None, **kwargs) -> TD3X:
    """``cls`` with the benchmark's settings (``throughput.make_model``), built with the user's policy class if given."""
    algo = cls if policy is None else (lambda _mlp, env, **kw: cls(policy, env, **kw))
    return make_model(algo, env_id, 0, {"batch_size": batch_size, **kwargs})


def build(name: str, env_id: str, batch_size: int) -> TD3X:
    cls, kwargs = CASES[name]
    return build_model(cls, env_id, batch_size, **kwargs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2)
    opt_in = ("stock_again", "stacked_policy", "no_bias_pass")
    parser.add_argument("--cases", nargs="+", default=[c for c in CASES if c not in opt_in],
                        choices=list(CASES))
    parser.add_argument("--chunks", type=int, default=6)
    parser.add_argument("--chunk-steps", type=int, default=400)
    parser.add_argument("--warmup", type=int, default=1_500, help="steps before timing (1000 random, then compilation)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    cases = ["stock", *[c for c in args.cases if c != "stock"]]
    models = {name: build(name, args.env, args.batch_size) for name in cases}
    for model in models.values():
        model.learn(args.warmup)
    rates: dict[str, list[float]] = {name: [] for name in cases}
    cores: dict[str, list[float]] = {name: [] for name in cases}
    order = list(models.items())
    for round_ in range(args.chunks):
        # The order reversed every other round, so that no case always runs right after the same one, or first.
        for name, model in order if round_ % 2 == 0 else order[::-1]:
            start, cpu = time.perf_counter(), time.process_time()
            model.learn(args.chunk_steps, reset_num_timesteps=False)
            wall = time.perf_counter() - start
            rates[name].append(args.chunk_steps / wall)
            cores[name].append((time.process_time() - cpu) / wall)
    print(f"\n{args.env}, batch {args.batch_size}, {args.threads} torch threads, {platform.processor() or platform.machine()}")
    result = {"env": args.env, "batch_size": args.batch_size, "threads": args.threads, "cases": {}}
    for name in cases:
        ratios = [r / s for r, s in zip(rates[name], rates["stock"])]
        row = {
            "steps_per_s": statistics.median(rates[name]),
            "cores_used": statistics.median(cores[name]),
            "ratio_to_stock": statistics.median(ratios),
            "ratios": ratios,
            "update_path": models[name].update_path,
            "update_reason": models[name].update_reason,
        }
        result["cases"][name] = row
        print(f"  {name:18s} {row['steps_per_s']:7.1f} steps/s  {row['cores_used']:.2f} cores  "
              f"{row['ratio_to_stock']:.2f}x stock  ({row['update_path']})  per chunk {[round(r, 2) for r in ratios]}")
    if args.json:
        with open(args.json, "w") as file:
            json.dump(result, file, indent=1)


if __name__ == "__main__":
    main()
