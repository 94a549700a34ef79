"""What LayerNorm critics cost the update alone: ``train()``'s time per gradient step, stock critics against LayerNorm
critics (``user_changes.py``'s ``layernorm_policy``: a LayerNorm after each hidden Linear), for TD3X's default of a
long run (the hooks compiled as written) and for SB3's ``TD3`` with the same critics, chunks of 100 gradient steps
alternated in one process after 1,500 environment steps (``throughput.py``'s settings: 400-300, lr 1e-3).

    python benchmarks/layernorm_cost.py                      # Hopper-v5, batch 100, 2 threads
    python benchmarks/layernorm_cost.py --profile            # and one chunk each profiled: operators, where time goes
    TORCHINDUCTOR_FORCE_DISABLE_CACHES=1 python benchmarks/layernorm_cost.py --aten-layernorm

``--aten-layernorm`` keeps ATen's own LayerNorm kernels (forward and backward) inside the compiled graph in place of
the kernels Inductor generates from its decomposition (a probe of Inductor's internals, for this measurement only:
run it with the caches off, since the cache key does not see the change). Not part of the test suite; needs a quiet
machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.td3.policies import TD3Policy
from user_changes import LayerNormPolicy, add_layer_norms, build_model

from sb3_td3x import TD3X


class SB3LayerNormCritic(ContinuousCritic):
    """SB3's critic with a LayerNorm after each hidden layer (``user_changes.LayerNormCritic`` for SB3's ``TD3``)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        add_layer_norms(self)


class SB3LayerNormPolicy(TD3Policy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return SB3LayerNormCritic(**critic_kwargs).to(self.device)


def aten_layernorm_in_compiled_graphs() -> None:
    """Inductor calls ATen's LayerNorm kernels instead of generating its own from the decomposition."""
    from torch._inductor import decomposition, lowering

    aten = th.ops.aten
    for op in (aten.native_layer_norm.default, aten.native_layer_norm_backward.default):
        decomposition.decompositions.pop(op, None)
    lowering.make_fallback(aten.native_layer_norm, warn=False)
    lowering.make_fallback(aten.native_layer_norm_backward, warn=False)


#: Where ``--profile`` puts each profiler row (Inductor's kernels show by name under ``cpp.enable_kernel_profile``).
PARTS = ("products (ATen)", "Inductor's kernels", "compiled graphs' Python wrappers", "Dynamo's guards", "the rest")


def where(key: str) -> str:
    if key in ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm"):
        return PARTS[0]
    if key.startswith("graph_") and "_cpp_fused" in key:
        return PARTS[1]
    if "CompiledFxGraph" in key:
        return PARTS[2]
    if "TorchDynamo Cache Lookup" in key:
        return PARTS[3]
    return PARTS[4]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--chunks", type=int, default=12)
    parser.add_argument("--aten-layernorm", action="store_true")
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    if args.aten_layernorm:
        aten_layernorm_in_compiled_graphs()
    if args.profile:  # each Inductor kernel a row of the profile (part of the cache key: compiles anew)
        from torch._inductor import config as inductor_config

        inductor_config.cpp.enable_kernel_profile = True

    models = {
        "TD3X": build_model(TD3X, args.env, args.batch_size),
        "TD3X, LayerNorm critics": build_model(TD3X, args.env, args.batch_size, policy=LayerNormPolicy),
        "SB3 TD3": build_model(TD3, args.env, args.batch_size),
        "SB3 TD3, LayerNorm critics": build_model(TD3, args.env, args.batch_size, policy=SB3LayerNormPolicy),
    }
    for model in models.values():
        model.learn(1_500)
        model.train(gradient_steps=50, batch_size=args.batch_size)  # compiles TD3X's update
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.chunks):
        for name, model in models.items():
            start = time.perf_counter()
            model.train(gradient_steps=100, batch_size=args.batch_size)
            times[name].append((time.perf_counter() - start) * 1e3 / 100)
    ms = {name: statistics.median(chunk_times) for name, chunk_times in times.items()}
    print(f"{args.env}, batch {args.batch_size}, {args.threads} threads; ms per gradient step (median of {args.chunks})")
    for name in models:
        print(f"  {name:28s} {ms[name]:.3f}")
    print(f"LayerNorm / stock: TD3X {ms['TD3X, LayerNorm critics'] / ms['TD3X']:.3f}, "
          f"SB3 {ms['SB3 TD3, LayerNorm critics'] / ms['SB3 TD3']:.3f}")  # fmt: skip
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        shares = {}
        for name in ("TD3X", "TD3X, LayerNorm critics"):
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                models[name].train(gradient_steps=100, batch_size=args.batch_size)
            print(f"{name}: 100 gradient steps")
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))
            shares[name] = {}
            for event in prof.key_averages():
                part = where(event.key)
                shares[name][part] = shares[name].get(part, 0.0) + event.self_cpu_time_total / 100
        print("us of self time a gradient step (profiled), by where it goes")
        print(f"  {'':32s} {'stock':>8s} {'LayerNorm':>10s} {'added':>7s}")
        for part in PARTS:
            stock, layer_norm = shares["TD3X"].get(part, 0.0), shares["TD3X, LayerNorm critics"].get(part, 0.0)
            print(f"  {part:32s} {stock:8.1f} {layer_norm:10.1f} {layer_norm - stock:+7.1f}")


if __name__ == "__main__":
    main()
