"""Throughput of TD3X against SB3's TD3 and SBX's (JAX) TD3: same env, same hyperparameters, one process, chunks
alternated A B C A B C. SBX runs when it is installed (``pip install -e ".[peers]"``; ``--no-sbx`` leaves it out).

    python benchmarks/throughput.py                          # Ant-v5 and HalfCheetah-v5, defaults, fp32
    python benchmarks/throughput.py --env Hopper-v5 --batch-size 100 --threads 1   # the paper's batch, one thread
    python benchmarks/throughput.py --env Ant-v5 --td3x bf16=true
    python benchmarks/throughput.py --json docs/assets/bench.json

Prints end-to-end environment steps/s of each (collection and training) and the cores each used (the process's CPU
seconds per second of the chunk), the median ratio over chunks, the time per
gradient step, the achieved GFLOP/s of the update (FLOPs counted by torch's FlopCounterMode) against the machine's
measured matmul peak, and the replay buffer's bytes per transition. Not part of the test suite.

It also prints two floors, to say how far each model is from what the machine allows at these sizes: the *matmul
floor* of a gradient step (the matrix products of one update, recorded with their shapes and dtypes, each replayed
and timed on its own, summed) and the bare environment step (random actions, no policy). SB3's end-to-end time per
step divided by their sum is the speed-up a TD3 with no overhead at all (no Python, no elementwise work, no
optimizer, no replay buffer) would reach on this machine. Two more floors replay the operators one update
dispatched, back to back with the tensors they ran on and with the bare environment step: the products alone, then
every operator (TD3X without the Python above the dispatcher); their operands come from L3 as in training. They
run between the timed chunks, so that they see the same host, and the model's state is put back after each.
``--breakdown`` also times TD3X's operators one by one inside that replay.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise
from torch.utils import flop_counter
from torch.utils._python_dispatch import TorchDispatchMode
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


#: The run a benchmark's TD3X stands for (``--run-length``): its chunks are learn() calls of a few hundred steps, and
#: ``compile_update=None`` (auto) decides from the length of the run (TD3X.compile_auto_min_steps).
RUN_LENGTH = 1_000_000


def as_part_of_a_run(model: TD3, run_length: int) -> TD3:
    """A TD3X whose auto settings decide as in a run of ``run_length`` steps: the default of such a run. Other
    algorithms are returned as they are."""
    if isinstance(model, TD3X):
        long = run_length - model.learning_starts >= type(model).compile_auto_min_steps
        model.compile_auto_min_steps = 0 if long else 2**62
    return model


def make_model(algo: type, env_id: str, seed: int, extra: dict, run_length: int = RUN_LENGTH) -> TD3:
    """``algo`` on ``env_id`` with the benchmark's settings: 1000 random steps, N(0, 0.1) exploration; the learning
    rate (1e-3) and networks (400-300) written out, since SBX's defaults differ from SB3's; a TD3X with the defaults
    of a run of ``run_length`` steps (:func:`as_part_of_a_run`)."""
    env = gym.make(env_id)
    action_dim = env.action_space.shape[0]
    kwargs = {"learning_rate": 1e-3, "policy_kwargs": {"net_arch": [400, 300]}, **extra}
    model = algo(
        "MlpPolicy",
        env,
        learning_starts=1_000,
        action_noise=NormalActionNoise(np.zeros(action_dim), 0.1 * np.ones(action_dim)),
        seed=seed,
        **kwargs,
    )
    model.set_logger(configure(None, []))
    return as_part_of_a_run(model, run_length)


def sbx_td3(threads: int) -> type | None:
    """SBX's (JAX) TD3 when ``sbx-rl`` is installed (``pip install -e ".[peers]"``), else None. XLA's CPU thread
    pools are sized when JAX starts, so one thread is asked for before the import."""
    if threads == 1:
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
        ).strip()
    try:
        from sbx import TD3 as SbxTD3
    except ImportError:
        return None
    return SbxTD3


def gradient_step_time(model: TD3, steps: int) -> float:
    model.train(gradient_steps=5, batch_size=model.batch_size)
    start = time.perf_counter()
    model.train(gradient_steps=steps, batch_size=model.batch_size)
    if model.device.type == "cuda":
        th.cuda.synchronize()
    return (time.perf_counter() - start) / steps


_LINEAR_POINTWISE = getattr(getattr(th.ops, "mkldnn", None), "_linear_pointwise", None)
# Registered once per process (this file may be loaded twice: by a benchmark importing it and by a test).
if _LINEAR_POINTWISE is not None and _LINEAR_POINTWISE not in flop_counter.flop_registry:
    from torch.utils.flop_counter import register_flop_formula

    @register_flop_formula(_LINEAR_POINTWISE)
    def _linear_pointwise_flops(x_shape, w_shape, *args, **kwargs) -> int:
        """oneDNN's fused linear (what Inductor may call for a linear layer on a CPU): 2 M N K, like addmm."""
        return 2 * (x_shape[0] * x_shape[1]) * w_shape[0] if len(x_shape) == 2 else 0


def flops_per_gradient_step(model: TD3) -> float:
    delay = model.policy_delay
    with FlopCounterMode(display=False) as counter:
        model.train(gradient_steps=delay, batch_size=model.batch_size)
    return counter.get_total_flops() / delay


class _Listed(tuple):
    """A list argument (oneDNN linear's scalars and algorithm), hashable for the record, a list again for the call."""


# The matrix products (oneDNN's fused linear where torch has it): the matmul floor's and the replay's "products".
PRODUCT_OPS = {th.ops.aten.mm.default, th.ops.aten.addmm.default, th.ops.aten.bmm.default, th.ops.aten.baddbmm.default}
if _LINEAR_POINTWISE is not None:
    PRODUCT_OPS.add(_LINEAR_POINTWISE.default)


class _OpRecorder(TorchDispatchMode):
    """Records every operator dispatched while active, with its live arguments and its outputs."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        self.calls.append((func, args, kwargs, out))
        return out


def _recorded_step(model: TD3) -> list[tuple]:
    """The operators of ``policy_delay`` real gradient steps, as :class:`_OpRecorder` records them."""
    recorder = _OpRecorder()
    with recorder:
        model.train(gradient_steps=model.policy_delay, batch_size=model.batch_size)
    return recorder.calls


def _signature(args: tuple) -> tuple:
    """A product's arguments as (shape, strides, dtype) for tensors, hashable, to time it again on random ones."""
    return tuple(
        (tuple(a.shape), a.stride(), a.dtype) if isinstance(a, th.Tensor) else _Listed(a) if isinstance(a, list) else a
        for a in args
    )


def _random_strided(shape: tuple, stride: tuple, dtype: th.dtype, device: th.device) -> th.Tensor:
    """Random values with the given shape and strides (broadcast inputs, with stride 0, included)."""
    size = 1 + sum((n - 1) * s for n, s in zip(shape, stride))
    return th.randn(size, dtype=dtype, device=device).as_strided(shape, stride)


def matmul_floor_ms(model: TD3, reps: int = 50) -> float:
    """Milliseconds per gradient step that the update's matrix products take when each is run alone (median of
    ``reps`` calls per distinct product), averaged over ``policy_delay`` steps like the FLOP count."""
    delay = model.policy_delay
    device = model.device
    total = 0.0
    timed: dict[tuple, float] = {}
    for func, args, kwargs, _ in _recorded_step(model):
        if func not in PRODUCT_OPS:
            continue
        signature, kwargs = _signature(args), tuple(sorted(kwargs.items()))
        key = (func, signature, kwargs)
        if key not in timed:
            args = [
                list(a) if isinstance(a, _Listed)
                else _random_strided(*a, device=device) if isinstance(a, tuple) and len(a) == 3 and isinstance(a[2], th.dtype)
                else a
                for a in signature
            ]
            times = []
            for _ in range(reps + 5):
                start = time.perf_counter()
                func(*args, **dict(kwargs))
                if device.type == "cuda":
                    th.cuda.synchronize()
                times.append(time.perf_counter() - start)
            timed[key] = statistics.median(times[5:])
        total += timed[key]
    return 1e3 * total / delay


def _tensors_out(out) -> list:
    """An operator's outputs as a list of tensors (none for the in-place foreach operators)."""
    if isinstance(out, th.Tensor):
        return [out]
    if isinstance(out, (tuple, list)):
        return [o for o in out if isinstance(o, th.Tensor)]
    return []


def _chain(calls: list[tuple]) -> list[tuple]:
    """A replay plan: each call with the positions of the arguments that an earlier call of the list produced, so
    that the replay passes the new outputs on as training does (fresh in cache) instead of the recorded ones."""
    produced: dict[int, tuple[int, int]] = {}  # id of a recorded output -> (call, output position)
    plan = []
    for i, (func, args, kwargs, out) in enumerate(calls):
        links = []
        for p, arg in enumerate(args):
            if isinstance(arg, th.Tensor) and id(arg) in produced:
                links.append((p, None, *produced[id(arg)]))
            elif isinstance(arg, (list, tuple)):
                links += [
                    (p, q, *produced[id(a)]) for q, a in enumerate(arg) if isinstance(a, th.Tensor) and id(a) in produced
                ]
        for k, tensor in enumerate(_tensors_out(out)):
            produced[id(tensor)] = (i, k)
        plan.append((func, args, kwargs, links))
    # Drop each new output after its last use, as training frees its intermediates (the allocator reuses warm memory).
    last_use = {i: i for i in range(len(plan))}
    for i, (*_, links) in enumerate(plan):
        for _, _, j, _ in links:
            last_use[j] = i
    frees: list[list[int]] = [[] for _ in plan]
    for j, i in last_use.items():
        frees[i].append(j)
    return [(*call, dead) for call, dead in zip(plan, frees)]


class RandomActions:
    """The bare environment stepped with uniformly random actions, reset when an episode ends."""

    def __init__(self, env_id: str, seed: int) -> None:
        self.env = gym.make(env_id)
        self.env.reset(seed=seed)
        self.env.action_space.seed(seed)

    def step(self) -> None:
        _, _, terminated, truncated, _ = self.env.step(self.env.action_space.sample())
        if terminated or truncated:
            self.env.reset()

    def close(self) -> None:
        self.env.close()


def state_tensors(model: TD3) -> list[th.Tensor]:
    """The tensors training changes: the policy's weights (targets included) and the optimizers' states."""
    optimizers = [model.actor.optimizer, model.critic.optimizer]
    return list(model.policy.state_dict().values()) + [
        value for opt in optimizers for state in opt.state.values() for value in state.values() if isinstance(value, th.Tensor)
    ]


class InSequenceReplay:
    """The update's operators replayed back to back with the tensors they ran on, without the Python above them.

    Records every operator ``policy_delay`` gradient steps dispatch (sampling, products, elementwise work, Adam,
    Polyak) and replays the list, with the bare environment stepped once per gradient step, as training alternates
    them: the operands come from where they come from in training (L3, not L2), unlike the matmul floor's products
    run alone. Each output is passed on to the calls that used it, as in training; arguments made outside the list
    (weights, optimizer states, the buffer, and for the products alone what the elementwise work made) are the
    recorded tensors; each new output is dropped after its last use. The replay loop's own Python (about a
    microsecond per call) is included. :meth:`time` replays the matrix products only (``"products"``) or every
    operator (``"kernels"``, TD3X with no Python cost above the dispatcher), in milliseconds per environment step,
    bare environment step included. Replaying repeats the optimizer steps; the model's weights and optimizer states
    are put back in place after :meth:`time` and :meth:`breakdown`, so the timed ``learn()`` chunks around them
    train as before. Not for a compiled or CUDA-graphed update, whose kernels do not all pass the dispatcher
    (:meth:`applies`).
    """

    def __init__(self, model: TD3, env_id: str, seed: int) -> None:
        from sb3_td3x.common import denormals

        self.model = model
        self.delay = model.policy_delay
        self.flush = denormals.flush_denormals
        self.flush_on = model.device.type == "cpu" and getattr(model, "flush_denormals", False)
        with self.flush(self.flush_on):
            self.recorded = _recorded_step(model)  # kept alive: the plans refer to its outputs by identity
        self.plans = {
            "kernels": _chain(self.recorded),
            "products": _chain([c for c in self.recorded if c[0] in PRODUCT_OPS]),
        }
        self.state = state_tensors(model)
        self.env = RandomActions(env_id, seed)

    @staticmethod
    def applies(model: TD3) -> bool:
        """Not for a compiled update (asked for, or chosen by auto at the warm-up's first ``train()``): recording it
        under a dispatch mode would compile it again, and its kernels do not all pass the dispatcher."""
        compiled = getattr(model, "compile_update", False) or getattr(model, "update_compiled", False)
        return not compiled and not getattr(model, "cuda_graph", False)

    def replay(self, which: str, clock: dict | None = None) -> None:
        """One replay of the recorded operators (``"kernels"``) or of their products (``"products"``); with a
        ``clock`` dict, each operator's time is added to ``clock[name]``. Without autograd: the recorded operators
        include the backward pass's own, replayed as kernels."""
        with th.no_grad():
            self._replay(which, clock)

    def _replay(self, which: str, clock: dict | None) -> None:
        outs: list = []
        for func, args, kwargs, links, dead in self.plans[which]:
            if links:
                args = [list(a) if isinstance(a, (list, tuple)) else a for a in args]
                for p, q, j, k in links:
                    if q is None:
                        args[p] = outs[j][k]
                    else:
                        args[p][q] = outs[j][k]
            if clock is None:
                outs.append(_tensors_out(func(*args, **kwargs)))
            else:
                start = time.perf_counter()
                outs.append(_tensors_out(func(*args, **kwargs)))
                clock[func._opname] = clock.get(func._opname, 0.0) + time.perf_counter() - start
            for j in dead:
                outs[j] = None

    @contextmanager
    def _put_back(self) -> Iterator[None]:
        """Denormals flushed as in training, and the model's weights and optimizer states restored on exit."""
        saved = [t.clone() for t in self.state]
        try:
            with self.flush(self.flush_on):
                yield
        finally:
            with th.no_grad():
                for tensor, value in zip(self.state, saved):
                    tensor.copy_(value)

    def breakdown(self, rounds: int = 200) -> dict[str, dict[str, float]]:
        """Milliseconds per environment step and calls per step of each operator, timed one by one inside the
        in-sequence replay of every operator."""
        clock: dict[str, float] = {}
        with self._put_back():
            for _ in range(3):
                self.replay("kernels")
            for _ in range(rounds):
                self.replay("kernels", clock)
                for _ in range(self.delay):
                    self.env.step()
        calls: dict[str, int] = {}
        for func, *_ in self.plans["kernels"]:
            calls[func._opname] = calls.get(func._opname, 0) + 1
        steps = rounds * self.delay
        products = {op._opname for op in PRODUCT_OPS}
        return {
            name: {"ms_per_step": 1e3 * t / steps, "calls_per_step": calls[name] / self.delay, "product": name in products}
            for name, t in sorted(clock.items(), key=lambda item: -item[1])
        }

    def time(self, which: str, rounds: int) -> float:
        times = []
        with self._put_back():
            for _ in range(rounds + 3):
                start = time.perf_counter()
                self.replay(which)
                for _ in range(self.delay):
                    self.env.step()
                if self.model.device.type == "cuda":
                    th.cuda.synchronize()
                times.append(time.perf_counter() - start)
        return 1e3 * statistics.median(times[3:]) / self.delay


def bare_env_step_ms(env_id: str, steps: int = 3000, seed: int = 0) -> float:
    """Milliseconds per step of the bare environment with uniformly random actions (resets included)."""
    env = RandomActions(env_id, seed)
    start = time.perf_counter()
    for _ in range(steps):
        env.step()
    elapsed = time.perf_counter() - start
    env.close()
    return 1e3 * elapsed / steps


def bytes_per_transition(model: TD3) -> float:
    buffer = model.replay_buffer
    if hasattr(buffer, "nbytes") and callable(buffer.nbytes):
        total = buffer.nbytes()
    else:
        total = sum(getattr(buffer, name).nbytes for name in ("observations", "actions", "rewards", "dones", "timeouts"))
        if not buffer.optimize_memory_usage:
            total += buffer.next_observations.nbytes
    return total / (buffer.buffer_size * buffer.n_envs)


def bench_env(env_id: str, args: argparse.Namespace, td3x_kwargs: dict, peer: type | None = None) -> dict:
    common = {"buffer_size": args.buffer_size, "batch_size": args.batch_size}
    sb3 = make_model(TD3, env_id, args.seed, common)
    td3x = make_model(TD3X, env_id, args.seed, {**common, **td3x_kwargs}, args.run_length)
    models = {"sb3": sb3, "td3x": td3x}
    if peer is not None:
        models["sbx"] = make_model(peer, env_id, args.seed, common)
    # Warm-up: fill past learning_starts and let compilation/graph capture happen outside the timed chunks.
    for model in models.values():
        model.learn(args.warmup, reset_num_timesteps=True)
    replay = InSequenceReplay(td3x, env_id, args.seed) if InSequenceReplay.applies(td3x) else None
    rates: dict[str, list[float]] = {name: [] for name in models}
    cores: dict[str, list[float]] = {name: [] for name in models}  # CPU seconds of the process per second
    replayed: dict[str, list[float]] = {"kernels": [], "products": []}
    for _ in range(args.chunks):
        for name, model in models.items():  # A B C A B C ...
            start, cpu = time.perf_counter(), time.process_time()
            model.learn(args.chunk_steps, reset_num_timesteps=False)
            wall = time.perf_counter() - start
            rates[name].append(args.chunk_steps / wall)
            cores[name].append((time.process_time() - cpu) / wall)
        if replay is not None:  # the in-sequence floors, between the chunks so that they see the same host
            for which in replayed:
                replayed[which].append(replay.time(which, rounds=max(1, args.chunk_steps // (10 * replay.delay))))
    ratios = [b / a for a, b in zip(rates["sb3"], rates["td3x"])]
    result = {"env": env_id, "batch_size": args.batch_size, "td3x_update_path": td3x.update_path, "steps_per_s": {k: statistics.median(v) for k, v in rates.items()},
              "chunks": rates, "median_ratio": statistics.median(ratios), "ratios": ratios,
              "cores_used": {k: statistics.median(v) for k, v in cores.items()}}
    if "sbx" in models:
        result["ratio_to_sb3"] = {name: statistics.median([b / a for a, b in zip(rates["sb3"], rates[name])]) for name in models}
        result["td3x_over_sbx"] = statistics.median([a / b for a, b in zip(rates["td3x"], rates["sbx"])])
        # Steps per CPU-second: what each costs when cores are the limit (many runs side by side)
        result["steps_per_cpu_s"] = {name: result["steps_per_s"][name] / result["cores_used"][name] for name in models}
    peak = matmul_peak_gflops()
    env_ms = bare_env_step_ms(env_id, seed=args.seed)
    for name, model in ((name, models[name]) for name in ("sb3", "td3x")):  # torch's counters: not for the JAX peer
        step_s = gradient_step_time(model, args.grad_steps)
        flops = flops_per_gradient_step(model)
        result[name] = {
            "ms_per_step_end_to_end": 1e3 / result["steps_per_s"][name],
            "ms_per_gradient_step": 1e3 * step_s,
            "matmul_floor_ms_per_gradient_step": matmul_floor_ms(model),
            "gflop_per_gradient_step": flops / 1e9,
            "achieved_gflops": flops / step_s / 1e9,
            "fraction_of_fp32_matmul_peak": flops / step_s / 1e9 / peak,
            "replay_bytes_per_transition": bytes_per_transition(model),
        }
    result["fp32_matmul_peak_gflops"] = peak
    result["bare_env_ms_per_step"] = env_ms
    sb3_ms = result["sb3"]["ms_per_step_end_to_end"]
    # The fastest a TD3 of these sizes could go here: TD3X's matrix products alone plus the bare environment.
    result["no_overhead_ceiling_ratio"] = sb3_ms / (result["td3x"]["matmul_floor_ms_per_gradient_step"] + env_ms)
    # The same, with the products (then every operator) run in sequence as in training, timed between the chunks.
    if replay is not None:
        in_sequence = {which: statistics.median(times) for which, times in replayed.items()}
        result["td3x"]["in_sequence_ms_per_step"] = in_sequence
        result["td3x"]["in_sequence_chunks"] = replayed
        result["in_sequence_ceiling_ratio"] = {name: sb3_ms / ms for name, ms in in_sequence.items()}
        # What Python (TD3X's, SB3's loop, the env wrappers) adds to the kernels, per step: chunk by chunk.
        td3x_ms = [1e3 / rate for rate in rates["td3x"]]
        result["td3x"]["python_ms_per_step"] = statistics.median(
            [ms - kernels for ms, kernels in zip(td3x_ms, replayed["kernels"])]
        )
        if args.breakdown:
            result["td3x"]["in_sequence_breakdown"] = replay.breakdown()
        replay.env.close()
    return result


def td3x_arguments(parser: argparse.ArgumentParser, items: list[str], fixed: dict[str, str]) -> dict:
    """The TD3X keyword arguments of ``--td3x KEY=VALUE ...``, values parsed (:func:`parse_value`); a clear
    ``parser.error`` (exit 2) for a malformed item, an argument TD3X does not take, or one of ``fixed`` (the
    benchmark's own, the same for every model: name -> where it is set)."""
    malformed = [item for item in items if "=" not in item or not item.split("=", 1)[0]]
    if malformed:
        parser.error(f"--td3x takes KEY=VALUE pairs, such as bf16=true; got {' '.join(malformed)}")
    td3x_kwargs = {k: parse_value(v) for k, v in (item.split("=", 1) for item in items)}
    known = set(inspect.signature(TD3X.__init__).parameters) - {"self", "policy", "env", "_init_setup_model"}
    unknown = sorted(set(td3x_kwargs) - known)
    if unknown:
        parser.error(f"--td3x: TD3X has no argument {', '.join(unknown)}; it takes {', '.join(sorted(known - set(fixed)))}")
    for name in sorted(set(td3x_kwargs) & set(fixed)):
        parser.error(f"--td3x: {name} is the benchmark's, the same for every model ({fixed[name]})")
    return td3x_kwargs


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """The TD3X keyword arguments of ``--td3x``; a clear ``parser.error`` (exit 2) for what would fail later."""
    fixed = {"buffer_size": "--buffer-size", "batch_size": "--batch-size", "seed": "--seed",
             "learning_starts": "1000 for both models", "action_noise": "N(0, 0.1) for both models"}
    td3x_kwargs = td3x_arguments(parser, args.td3x, fixed)
    for env_id in args.env:
        if env_id not in gym.registry:
            parser.error(f"--env: no gymnasium environment {env_id!r} (for example Ant-v5, HalfCheetah-v5, Hopper-v5)")
    for name in ("chunks", "chunk_steps", "grad_steps", "buffer_size", "batch_size", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1 (got {getattr(args, name)})")
    if args.warmup < 1_000 + 1:
        parser.error(f"--warmup must be past learning_starts=1000 so that both models train (got {args.warmup})")
    return td3x_kwargs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Ant-v5", "HalfCheetah-v5"])
    parser.add_argument("--chunks", type=int, default=4, help="timed chunks per algorithm, alternated")
    parser.add_argument("--chunk-steps", type=int, default=1_500)
    parser.add_argument("--warmup", type=int, default=1_500)
    parser.add_argument("--grad-steps", type=int, default=200)
    parser.add_argument("--buffer-size", type=int, default=1_000_000)
    parser.add_argument("--batch-size", type=int, default=256, help="256 is SB3's default, 100 the paper's")
    parser.add_argument(
        "--no-sbx", action="store_true", help="leave out SBX's TD3 (run beside the others when sbx-rl is installed)"
    )
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--td3x", nargs="*", default=[], metavar="KEY=VALUE", help="extra TD3X arguments (opt-in flags)")
    parser.add_argument(
        "--run-length", type=int, default=RUN_LENGTH,
        help="TD3X runs with the defaults of a run of this many steps (compile_update=None compiles a long one)",
    )
    parser.add_argument("--json", help="write the results to this file")
    parser.add_argument(
        "--breakdown", action="store_true", help="also time TD3X's operators one by one in the in-sequence replay"
    )
    args = parser.parse_args()

    th.set_num_threads(args.threads)
    td3x_kwargs = check_arguments(parser, args)
    machine = {
        "processor": platform.processor() or platform.machine(),
        "cpu_model": next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
        if os.path.exists("/proc/cpuinfo") else "?",
        "cores": os.cpu_count(),
        "torch_threads": th.get_num_threads(),
        "torch": th.__version__,
    }
    peer = None if args.no_sbx else sbx_td3(args.threads)
    if peer is not None:
        import jax

        machine["jax"] = jax.__version__
    print(f"machine: {machine}\nTD3X extra arguments: {td3x_kwargs or 'none (defaults, fp32)'}; "
          f"the defaults of a run of {args.run_length:,} steps")
    if peer is None and not args.no_sbx:
        print('SBX is not installed (pip install -e ".[peers]"): SB3 and TD3X only')
    results = []
    for env_id in args.env:
        r = bench_env(env_id, args, td3x_kwargs, peer)
        results.append(r)
        if args.json:  # after each environment: a run cut by a time limit keeps what it measured
            write_record(args.json, {"machine": machine, "td3x_kwargs": td3x_kwargs, "args": vars(args), "results": results,
                                     "complete": len(results) == len(args.env)})
        print(f"\n{env_id}, batch {args.batch_size}; TD3X's update: {r['td3x_update_path']}")
        names = {"sb3": "SB3 TD3", "td3x": "TD3X", "sbx": "SBX TD3"}
        print("  end-to-end steps/s  " + "   ".join(f"{names[k]} {v:8.1f}" for k, v in r["steps_per_s"].items()))
        print("  cores used          " + "   ".join(f"{names[k]} {v:8.2f}" for k, v in r["cores_used"].items()))
        print(f"  ratio TD3X / SB3     median {r['median_ratio']:.2f}x   per chunk {[round(x, 2) for x in r['ratios']]}")
        if "sbx" in r["steps_per_s"]:
            print(
                f"  ratio SBX / SB3      median {r['ratio_to_sb3']['sbx']:.2f}x;   TD3X / SBX median {r['td3x_over_sbx']:.2f}x;   "
                "steps per CPU-second " + ", ".join(f"{names[k]} {v:.1f}" for k, v in r["steps_per_cpu_s"].items())
            )
        for name in ("sb3", "td3x"):
            s = r[name]
            print(
                f"  {name:5s} {s['ms_per_gradient_step']:6.2f} ms/gradient step, {s['gflop_per_gradient_step']:.2f} GFLOP, "
                f"{s['achieved_gflops']:6.1f} GFLOP/s = {100 * s['fraction_of_fp32_matmul_peak']:4.1f}% of the fp32 matmul "
                f"peak ({r['fp32_matmul_peak_gflops']:.0f} GFLOP/s), "
                f"replay {s['replay_bytes_per_transition']:.0f} B/transition"
            )
            print(
                f"        {s['ms_per_step_end_to_end']:6.2f} ms/step end to end; matmul floor "
                f"{s['matmul_floor_ms_per_gradient_step']:.2f} ms/gradient step (the products alone)"
            )
        print(
            f"  bare env step {r['bare_env_ms_per_step']:.3f} ms; a TD3 with no overhead (TD3X's matmul floor + bare env) "
            f"would be {r['no_overhead_ceiling_ratio']:.2f}x SB3 here"
        )
        if "in_sequence_ceiling_ratio" in r:
            seq, ceiling = r["td3x"]["in_sequence_ms_per_step"], r["in_sequence_ceiling_ratio"]
            print(
                f"  replayed in sequence with the bare env step, per step: TD3X's products {seq['products']:.2f} ms "
                f"({ceiling['products']:.2f}x SB3), all of TD3X's operators without Python {seq['kernels']:.2f} ms "
                f"({ceiling['kernels']:.2f}x SB3); Python adds {r['td3x']['python_ms_per_step']:.2f} ms per step"
            )
        if "in_sequence_breakdown" in r["td3x"]:
            rows = r["td3x"]["in_sequence_breakdown"]
            for kind, is_product in (("matrix products", True), ("other operators", False)):
                total = sum(row["ms_per_step"] for row in rows.values() if row["product"] == is_product)
                print(f"  TD3X's {kind} in sequence: {total:.2f} ms per step")
            print("  the 20 slowest operators (ms per step, calls per step):")
            for name, row in list(rows.items())[:20]:
                tag = " (product)" if row["product"] else ""
                print(f"    {row['ms_per_step']:6.3f} {row['calls_per_step']:5.1f}  {name}{tag}")


def write_record(path: str, record: dict) -> None:
    """``record`` as JSON at ``path``, replaced whole (a kill while writing leaves the previous complete file): the
    benchmarks write after each measurement, so that a run cut by a time limit keeps what it measured."""
    partial = f"{path}.partial"
    with open(partial, "w") as f:
        json.dump(record, f, indent=2)
    os.replace(partial, path)


if __name__ == "__main__":
    main()
