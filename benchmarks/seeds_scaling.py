"""Seeds scaling (issue 17): total seed-steps/s of N seeds trained together in one process (SeedBatch) against N
separate processes of TD3X and of SB3's TD3, for N = 1, 2, 4, 8 (16 on a GPU).

    python benchmarks/seeds_scaling.py --env Hopper-v5 --batch-size 100 --json hopper_seeds.json
    python benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --json ant_seeds.json
    python benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --device cuda --seeds 1 2 4 8 16
    python benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --device cuda --seeds 16 --modes td3x_procs \
        --td3x cuda_graph=true                                      # TD3X's models with one of its own options
    python benchmarks/seeds_scaling.py --env Pendulum-v1 --seeds 1 2 --steps 200 --warmup 150 --learning-starts 100 \
        --net 64 64 --threads 1                                                       # smoke run, half a minute

**What is measured.** Seed-steps/s: environment steps summed over all seeds, divided by wall time, training
included. Every model first runs ``learning_starts`` random steps and ``--warmup`` training steps (untimed: buffers
past ``learning_starts``, optimizer states created, the update path chosen), so that each timed step is one
environment step and one gradient step. Then ``--steps`` steps per seed are timed (``learn(steps,
reset_num_timesteps=False)``, a GPU synchronized at both ends). Four ways to train N seeds:

- ``batched``: one process, ``SeedBatch(make_model, seeds=range(N)).learn(...)``, torch threads = ``--threads``
  (default: every core this process may run on), with SeedBatch's defaults: the seeds collect one after the other,
  pi(s) batched across seeds on a GPU, each seed's gradient steps its own update. Its rate is N * steps / the timed
  call's wall time. The table notes the seeds' update paths.
- ``batched_threads``: the same batch with the seeds collecting in ``--threads`` threads (``collect_threads``).
- ``batched_per_core``: ``min(N, threads)`` processes side by side, each a ``SeedBatch`` of every P-th seed, with
  the threads shared among them (one each on a CPU with as many cores as threads): what ``python run.py -m
  seeds=[0,2,4,6],[1,3,5,7]`` runs. On a CPU, one thread per process beats two threads in one for these small
  products.
- ``td3x_procs``: N processes, each a lone ``TD3X`` of seed i, started together and sharing the cores, each with
  torch threads = max(1, threads // N): ``threads_per_job`` of ``sb3_td3x.experiment.launch.hydra_jobs``, what a Hydra multirun of
  N jobs side by side gets. The processes are not pinned to cores. With N above the core count they time-share the
  cores (a joblib multirun with ``n_jobs=-1`` would run as many jobs as cores at once and queue the rest).
- ``sb3_procs``: the same with ``stable_baselines3.TD3``. One SB3 process (N = 1) is always measured: it is the
  baseline of the last column (the issue's goal on a GPU: 16 seeds batched at 10x one SB3 TD3 process).
- ``sbx_procs``: the same with SBX's (JAX) ``TD3`` (``pip install -e ".[peers]"``), the peer users pick for speed:
  JAX's GPU memory is not preallocated (``XLA_PYTHON_CLIENT_PREALLOCATE=false``: 16 processes share one GPU), and
  with one thread per process XLA's CPU thread pools are asked for one thread, as ``benchmarks/throughput.py`` does.

**CUDA MPS** (``--mps on``, ``off`` or ``both``): the separate-process modes run with an MPS control daemon started
for them (``sb3_td3x.experiment.launch.mps``, as ``run.py -m`` starts one on a GPU machine), or without (the driver's time
slices), or both, each measurement labelled ``<mode>+mps`` when under MPS. Needs a GPU and
``nvidia-cuda-mps-control``; elsewhere ``on`` and ``both`` stop with a message.

**Separate processes, overlapping windows.** Each process times its own window of ``--steps`` steps; the mode's
rate is the sum of the N processes' rates (steps / own window), the usual measure of throughput of concurrent
jobs. The windows overlap: every process waits at a start barrier after its warm-up, so all start timing together,
and a process whose window ended keeps training (untimed, in chunks of 50 steps) until every window has ended, so
that none is timed on a machine the others have left. The JSON also holds the conservative rate, N * steps / (last
window end - first window start), and the windows' overlap (the time all N were timed / that span).

**Same configuration everywhere**: TD3's (Fujimoto et al. 2018, Table 3; ``conf/algo/td3.yaml``): net ``--net``
(400 300), Adam 1e-3 for actor and critics, tau 0.005, gamma 0.99, policy delay 2, target smoothing N(0, 0.2)
clipped to 0.5, exploration N(0, 0.1), train_freq 1, one gradient step per environment step; the environment,
batch size, replay buffer size and ``learning_starts`` from the command line (``learning_starts`` default 1000, as
in ``benchmarks/throughput.py``; the paper's 10k on Ant would only lengthen the untimed warm-up). TD3X runs with its
defaults otherwise (fp32, the update of a long run: compiled on a CPU). Seed i is seed i in every mode.

Every measurement runs in fresh processes (the batched one too), so none inherits another's thread pool, allocator
or caches. On CPU they start from a fork server that imported torch, SB3 and this package once; on a GPU (or where
there is no fork server) they are spawned, so that each creates its own CUDA context. ``--repeats`` runs the whole
plan again (the modes alternated) and the table shows medians. The numbers mean something on a quiet machine only:
other jobs on the cores change the separate-process modes and the batched one differently, and a process with more
torch threads than the cores free to it can slow down tenfold (its threads wait for each other at every operator).
Not part of the test suite (``tests/unit/test_seeds_scaling_script.py`` checks its arguments and arithmetic).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import queue
import shlex
import statistics
import subprocess
import sys
import threading
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import stable_baselines3
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.utils import get_device
from throughput import as_part_of_a_run, td3x_arguments, write_record

from sb3_td3x import TD3X, SeedBatch

MODES = ("batched", "batched_threads", "batched_per_core", "td3x_procs", "sb3_procs", "sbx_procs")
BATCHED_MODES = ("batched", "batched_threads", "batched_per_core")
ALGORITHMS = {"td3x_procs": TD3X, "sb3_procs": TD3}  # sbx_procs: sbx_td3(), imported in its own processes
MPS_SUFFIX = "+mps"


def base_mode(mode: str) -> str:
    """The way of training of a measurement's label (``td3x_procs+mps`` is ``td3x_procs`` under CUDA MPS)."""
    return mode.removesuffix(MPS_SUFFIX)


def sbx_td3(threads: int) -> type:
    """SBX's TD3, imported in a worker process: JAX's GPU memory allocated as needed (not 75% of the GPU per process),
    and with one thread XLA's CPU pools of one thread (they are sized when JAX starts)."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if threads == 1:
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
        ).strip()
    from sbx import TD3 as SbxTD3

    return SbxTD3
# TD3's hyperparameters (Fujimoto et al. 2018, Table 3; conf/algo/td3.yaml), the same for every mode.
PAPER = {
    "learning_rate": 1e-3,
    "tau": 0.005,
    "gamma": 0.99,
    "train_freq": 1,
    "gradient_steps": 1,
    "policy_delay": 2,
    "target_policy_noise": 0.2,
    "target_noise_clip": 0.5,
}
EXPLORATION_NOISE = 0.1
PAD_STEPS = 50  # the untimed chunks a process trains after its window, until every window has ended
REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Config:
    """What every model of a run shares (sent to the worker processes)."""

    env: str
    batch_size: int
    net: tuple[int, ...]
    buffer_size: int
    learning_starts: int
    warmup: int
    steps: int
    device: str
    run_length: int = 1_000_000  # a TD3X has the defaults of a run this long (compile_update=None decides from it)
    td3x_kwargs: tuple[tuple[str, Any], ...] = ()  # --td3x: TD3X's own arguments (its models only, batches included)


def make_model(algo: type, config: Config, seed: int) -> TD3:
    """Seed ``seed``'s model: TD3's hyperparameters, the run's environment and sizes, no logger output."""
    env = gym.make(config.env)
    action_dim = env.action_space.shape[0]
    model = algo(
        "MlpPolicy",
        env,
        buffer_size=config.buffer_size,
        learning_starts=config.learning_starts,
        batch_size=config.batch_size,
        action_noise=NormalActionNoise(np.zeros(action_dim), EXPLORATION_NOISE * np.ones(action_dim)),
        policy_kwargs={"net_arch": list(config.net)},
        seed=seed,
        device=config.device,
        **PAPER,
        **(dict(config.td3x_kwargs) if issubclass(algo, TD3X) else {}),
    )
    model.set_logger(configure(None, []))
    return as_part_of_a_run(model, config.run_length)


def _synchronize(device: str) -> None:
    if th.device(device).type == "cuda":
        th.cuda.synchronize()


def worker(config: Config, mode: str, seeds: list[int], threads: int, pad: bool, barrier, done, results) -> None:
    """One process of a measurement: build, warm up, wait at the barrier, time ``config.steps`` steps per seed and
    put the record in ``results``; then, with ``pad``, train on untimed until ``done`` is set."""
    try:
        th.set_num_threads(threads)
        mode = base_mode(mode)
        if mode in BATCHED_MODES:
            collect_threads = threads if mode == "batched_threads" else 1
            trainer = SeedBatch(lambda seed: make_model(TD3X, config, seed), seeds, collect_threads=collect_threads)
        elif mode == "sbx_procs":
            trainer = make_model(sbx_td3(threads), config, seeds[0])
        else:
            trainer = make_model(ALGORITHMS[mode], config, seeds[0])
        trainer.learn(config.learning_starts + config.warmup)  # past learning_starts: every step from here trains
        _synchronize(config.device)
        barrier.wait()
        wall_start, start = time.time(), time.perf_counter()
        trainer.learn(config.steps, reset_num_timesteps=False)
        _synchronize(config.device)
        seconds, wall_end = time.perf_counter() - start, time.time()
        steps = config.steps * len(seeds)
        results.put(
            {
                "seeds": seeds,
                "steps": steps,
                "seconds": seconds,
                "steps_per_s": steps / seconds,
                "start": wall_start,
                "end": wall_end,
                "threads": th.get_num_threads(),
                "update_path": trainer[0].update_path if isinstance(trainer, SeedBatch) else getattr(trainer, "update_path", None),
                "collection": getattr(trainer, "collection", None),
                "pid": os.getpid(),
            }
        )
        while pad and not done.is_set():  # keep the cores as loaded as they were for the windows still running
            trainer.learn(PAD_STEPS, reset_num_timesteps=False)
    except threading.BrokenBarrierError:
        return  # another process failed (it reports why) or the measurement was stopped
    except Exception:  # noqa: BLE001  (whatever stopped this process: the parent raises it, with its traceback)
        results.put({"seeds": seeds, "error": traceback.format_exc()})
        barrier.abort()


def _context(device: str) -> mp.context.BaseContext:
    """A fork server on CPU (torch, SB3 and this package imported once, for all the processes); ``spawn`` on a GPU,
    where a forked process cannot use CUDA once the process it was forked from has initialized the driver."""
    if th.device(device).type == "cpu" and "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        # This script with its imports, and what the first torch optimizer imports (seconds per process otherwise).
        ctx.set_forkserver_preload(["__main__", "torch._dynamo"])
        return ctx
    return mp.get_context("spawn")


def measure(config: Config, mode: str, n_seeds: int, threads: int, total_threads: int) -> dict:
    """One measurement of ``mode`` with ``n_seeds`` seeds: its processes started together, their records combined
    by :func:`combine`."""
    ctx = _context(config.device)
    groups = seed_groups(mode, n_seeds, total_threads)
    barrier, done, results = ctx.Barrier(len(groups)), ctx.Event(), ctx.Queue()
    pad = len(groups) > 1
    processes = [
        ctx.Process(target=worker, args=(config, mode, seeds, threads, pad, barrier, done, results), daemon=True)
        for seeds in groups
    ]
    for process in processes:
        process.start()
    records: list[dict] = []
    try:
        while len(records) < len(processes):
            try:
                record = results.get(timeout=1.0)
            except queue.Empty:
                dead = [p.exitcode for p in processes if p.exitcode not in (None, 0)]
                if dead:
                    raise RuntimeError(f"{mode}, {n_seeds} seeds: a worker process died (exit code {dead[0]})") from None
                continue
            if "error" in record:
                raise RuntimeError(
                    f"{mode}, {n_seeds} seeds: the process of seeds {record['seeds']} failed:\n{record['error']}"
                )
            records.append(record)
    finally:
        done.set()
        barrier.abort()
        for process in processes:
            process.join(timeout=120)
            if process.is_alive():
                process.terminate()
                process.join()
    return combine(mode, n_seeds, threads, sorted(records, key=lambda r: r["seeds"]))


def combine(mode: str, n_seeds: int, threads: int, records: list[dict]) -> dict:
    """A measurement from its processes' records: the sum of their rates, and the conservative rate and the
    overlap of their windows (see the module's docstring)."""
    first_start, last_end = min(r["start"] for r in records), max(r["end"] for r in records)
    span = last_end - first_start
    shared = max(0.0, min(r["end"] for r in records) - max(r["start"] for r in records))
    paths = {r["update_path"] for r in records}
    return {
        "mode": mode,
        "n_seeds": n_seeds,
        "processes": len(records),
        "threads_per_process": threads,
        "seed_steps_per_s": sum(r["steps_per_s"] for r in records),
        "seed_steps_per_s_over_span": sum(r["steps"] for r in records) / span,
        "overlap": shared / span,
        "update_path": paths.pop() if len(paths) == 1 else sorted(map(str, paths)),
        "per_process": records,
    }


def seed_groups(mode: str, n_seeds: int, threads: int) -> list[list[int]]:
    """The seeds of each process: all in one (``batched``), one batch per thread (``batched_per_core``: as even as
    possible, ``min(N, threads)`` processes), or one seed each."""
    mode = base_mode(mode)
    if mode in ("batched", "batched_threads"):
        return [list(range(n_seeds))]
    if mode == "batched_per_core":
        processes = min(n_seeds, threads)
        return [list(range(n_seeds))[p::processes] for p in range(processes)]
    return [[seed] for seed in range(n_seeds)]


def threads_for(mode: str, n_seeds: int, threads: int) -> int:
    """Torch threads of each process: all of ``threads`` for the batch, the cores shared among the processes else."""
    from sb3_td3x.experiment.launch.hydra_jobs import threads_per_job

    if base_mode(mode) in ("batched", "batched_threads"):
        return threads
    return threads_per_job(len(seed_groups(mode, n_seeds, threads)), threads)


def plan(modes: list[str], seeds: list[int]) -> list[tuple[str, int]]:
    """The measurements of one repeat, N after N, the modes alternated; one SB3 process first if not among them."""
    runs = [(mode, n) for n in seeds for mode in modes]
    if ("sb3_procs", 1) not in runs:
        runs.insert(0, ("sb3_procs", 1))
    return runs


def summarize(measurements: list[dict]) -> dict[tuple[str, int], dict]:
    """(mode, N) -> the median over repeats of its rates, with the repeats' values."""
    rows: dict[tuple[str, int], dict] = {}
    for m in measurements:
        row = rows.setdefault(
            (m["mode"], m["n_seeds"]),
            {
                "mode": m["mode"],
                "n_seeds": m["n_seeds"],
                "processes": m["processes"],
                "threads_per_process": m["threads_per_process"],
                "repeats": [],
                "update_paths": [],
            },
        )
        row["repeats"].append(m["seed_steps_per_s"])
        row["update_paths"].append(m["update_path"])
    for row in rows.values():
        row["seed_steps_per_s"] = statistics.median(row["repeats"])
    return rows


def ratios(rows: dict[tuple[str, int], dict], seeds: list[int]) -> list[dict]:
    """For each N measured batched: its rate over each other mode's at that N (None where not measured) and over
    one SB3 process's."""
    baseline = rows[("sb3_procs", 1)]["seed_steps_per_s"]
    out = []
    for n in seeds:
        for batched_mode in BATCHED_MODES:
            if (batched_mode, n) not in rows:
                continue
            batched = rows[(batched_mode, n)]["seed_steps_per_s"]
            entry: dict = {"n_seeds": n, "mode": batched_mode}
            for mode in ("td3x_procs", "sb3_procs"):
                entry[f"batched_over_{mode}"] = batched / rows[(mode, n)]["seed_steps_per_s"] if (mode, n) in rows else None
            entry["batched_over_one_sb3_process"] = batched / baseline
            out.append(entry)
    return out


def print_table(rows: dict[tuple[str, int], dict], seeds: list[int]) -> None:
    baseline = rows[("sb3_procs", 1)]["seed_steps_per_s"]
    print(f"\n{'N':>3}  {'mode':<16} {'procs x threads':>15} {'seed-steps/s':>13} {'per seed':>9} {'/ one SB3 proc':>15}")
    order = lambda item: (item[0][1], MODES.index(base_mode(item[0][0])), item[0][0])  # noqa: E731
    for (mode, n), row in sorted(rows.items(), key=order):
        rate = row["seed_steps_per_s"]
        note = ""
        if mode in BATCHED_MODES and row["processes"] < n:
            note = f"  (update_path {sorted(set(map(str, row['update_paths'])))})"
        print(
            f"{n:>3}  {mode:<16} {row['processes']:>7} x {row['threads_per_process']:<5} {rate:>13.1f} {rate / n:>9.1f} "
            f"{rate / baseline:>14.2f}x{note}"
        )
    print(f"\n{'N':>3}  {'batched mode':<17} {'/ td3x_procs':>13} {'/ sb3_procs':>12} {'/ one SB3 proc':>15}")
    for entry in ratios(rows, seeds):
        cells = [
            "-" if entry[key] is None else f"{entry[key]:.2f}x"
            for key in ("batched_over_td3x_procs", "batched_over_sb3_procs", "batched_over_one_sb3_process")
        ]
        print(f"{entry['n_seeds']:>3}  {entry['mode']:<17} {cells[0]:>13} {cells[1]:>12} {cells[2]:>15}")


def cpu_model() -> str:
    """The CPU's model name, as ``benchmarks/throughput.py`` reads it ("?" where /proc/cpuinfo is missing)."""
    if not os.path.exists("/proc/cpuinfo"):
        return "?"
    with open("/proc/cpuinfo") as f:
        return next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "?")


def machine_info(device: str) -> dict:
    from sb3_td3x.experiment.jobs import available_cores

    info = {
        "processor": platform.processor() or platform.machine(),
        "cpu_model": cpu_model(),
        "cores": available_cores(),
        "os_cpu_count": os.cpu_count(),
        "torch": th.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "python": platform.python_version(),
        "device": device,
    }
    if th.device(device).type == "cuda":
        info["gpu"] = th.cuda.get_device_name(th.device(device))
    return info


def git_commit() -> dict:
    """The commit measured, and whether tracked files differed from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True).stdout
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None}
    return {"commit": head.strip(), "dirty": bool(status.strip())}


def parse_arguments(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked: a clear ``parser.error`` (exit 2) for what would fail later, in a worker."""
    from sb3_td3x.experiment.jobs import available_cores

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4, 8], help="the N to measure")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=[m for m in MODES if m not in ("sbx_procs", "batched_threads")])
    parser.add_argument("--steps", type=int, default=2_000, help="timed environment steps per seed")
    parser.add_argument("--warmup", type=int, default=500, help="untimed training steps past learning_starts")
    parser.add_argument("--learning-starts", type=int, default=1_000)
    parser.add_argument(
        "--run-length", type=int, default=1_000_000,
        help="TD3X has the defaults of a run of this many steps (compile_update=None compiles a long one)",
    )
    parser.add_argument("--buffer-size", type=int, default=1_000_000)
    parser.add_argument("--net", type=int, nargs="+", default=[400, 300])
    parser.add_argument(
        "--threads",
        type=int,
        default=available_cores(),
        help="the batch's torch threads, and the cores the processes share (default: the cores this process may run on)",
    )
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:1, auto (SB3's: cuda when there is one)")
    parser.add_argument("--repeats", type=int, default=1, help="runs of the whole plan; the table shows medians")
    parser.add_argument(
        "--json", help="write every measurement, the machine, the commit and the command here (after each measurement)"
    )
    parser.add_argument(
        "--mps", choices=("off", "on", "both"), default="off", help="the separate-process modes under CUDA MPS (GPU)"
    )
    parser.add_argument(
        "--td3x", nargs="*", default=[], metavar="KEY=VALUE",
        help="TD3X's own arguments for its models (td3x_procs and the batches), such as cuda_graph=true",
    )
    args = parser.parse_args(argv)
    fixed = {name: "TD3's, the same for every mode" for name in PAPER} | {
        name: f"--{name.replace('_', '-')}" for name in ("buffer_size", "learning_starts", "batch_size", "device")
    } | {"seed": "seed i in every mode", "action_noise": "N(0, 0.1) in every mode", "policy_kwargs": "--net"}
    args.td3x_kwargs = td3x_arguments(parser, args.td3x, fixed)
    if args.env not in gym.registry:
        parser.error(f"--env: no gymnasium environment {args.env!r} (for example Hopper-v5, Ant-v5, Pendulum-v1)")
    env = gym.make(args.env)
    action_space = env.action_space
    env.close()
    if not isinstance(action_space, gym.spaces.Box):
        parser.error(f"--env: {args.env} has {action_space} actions; TD3 needs continuous (Box) actions")
    if min(args.seeds) < 1:
        parser.error(f"--seeds: each N must be at least 1 (got {args.seeds})")
    if len(set(args.seeds)) != len(args.seeds):
        parser.error(f"--seeds: an N is given twice ({args.seeds})")
    for name in ("batch_size", "steps", "warmup", "buffer_size", "threads", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1 (got {getattr(args, name)})")
    if args.learning_starts < 0:
        parser.error(f"--learning-starts must be at least 0 (got {args.learning_starts})")
    if min(args.net) < 1:
        parser.error(f"--net: layer sizes must be at least 1 (got {args.net})")
    try:
        requested = th.device(args.device) if args.device != "auto" else None
    except RuntimeError as error:
        parser.error(f"--device {args.device}: {error}")
    if requested is not None and requested.type == "cuda" and not th.cuda.is_available():  # SB3 would fall back to CPU
        parser.error(f"--device {args.device}: torch sees no CUDA device here")
    args.device = str(get_device(args.device))
    args.modes = list(dict.fromkeys(args.modes))
    if "sbx_procs" in args.modes:
        try:
            import sbx  # noqa: F401
        except ImportError:
            parser.error('--modes sbx_procs: sbx-rl is not installed (pip install -e ".[peers]")')
    if args.mps != "off":
        from sb3_td3x.experiment.launch import mps

        if th.device(args.device).type != "cuda" or mps.decide(2, True, True, Path("/tmp")).reason.startswith(
            ("no CUDA", mps.CONTROL)
        ):
            parser.error(f"--mps {args.mps}: needs a CUDA device and {mps.CONTROL} (device {args.device})")
        if args.mps == "on":
            args.modes = [m + MPS_SUFFIX if m not in BATCHED_MODES else m for m in args.modes]
        else:
            args.modes += [m + MPS_SUFFIX for m in args.modes if m not in BATCHED_MODES]
    return args


def shared_gpu(mode: str, n_seeds: int):
    """An MPS control daemon for the processes of a ``+mps`` measurement (started before them, stopped after),
    else nothing."""
    import contextlib

    from sb3_td3x.experiment.launch import mps

    if not mode.endswith(MPS_SUFFIX):
        return contextlib.nullcontext()
    return mps.around_launch(n_seeds, "cuda", True)


def main(argv: list[str] | None = None) -> None:
    args = parse_arguments(argv)
    config = Config(
        args.env,
        args.batch_size,
        tuple(args.net),
        args.buffer_size,
        args.learning_starts,
        args.warmup,
        args.steps,
        args.device,
        args.run_length,
        tuple(args.td3x_kwargs.items()),
    )
    machine = machine_info(args.device)
    print(f"machine: {machine}")
    print(
        f"{config.env}, batch {config.batch_size}, net {list(config.net)}, {config.device}; {config.steps} timed steps "
        f"per seed after {config.learning_starts} random + {config.warmup} training steps; {args.threads} threads"
        + (f"; TD3X with {' '.join(args.td3x)}" if args.td3x else "")
    )
    measurements: list[dict] = []
    command = shlex.join([sys.executable, *sys.argv]) if argv is None else shlex.join(argv)
    planned = plan(args.modes, args.seeds)
    for repeat in range(args.repeats):
        for mode, n in planned:
            with shared_gpu(mode, n):
                m = measure(config, mode, n, threads_for(mode, n, args.threads), args.threads)
            m["repeat"] = repeat
            measurements.append(m)
            rates = ", ".join(f"{r['steps_per_s']:.1f}" for r in m["per_process"])
            print(
                f"  N={n} {mode}: {m['seed_steps_per_s']:.1f} seed-steps/s ({m['processes']} x {m['threads_per_process']} "
                f"threads; per process {rates}; windows overlap {100 * m['overlap']:.0f}%; update {m['update_path'] or '-'})",
                flush=True,
            )
            if args.json:  # after each measurement: a run cut by a time limit keeps what it measured
                complete = len(measurements) == args.repeats * len(planned)
                write_json(args, command, machine, config, measurements, complete)
    print_table(summarize(measurements), args.seeds)


def write_json(
    args: argparse.Namespace, command: str, machine: dict, config: Config, measurements: list[dict], complete: bool
) -> None:
    """The measurements so far, their summary and ratios, the machine, the commit and the command, into ``args.json``
    (replaced whole, so a kill leaves the last complete file); ``complete``: whether the whole plan was measured."""
    rows = summarize(measurements)
    baseline = rows[("sb3_procs", 1)]["seed_steps_per_s"]
    summary = [{**row, "ratio_to_one_sb3_process": row["seed_steps_per_s"] / baseline} for row in rows.values()]
    record = {
        "machine": machine,
        **git_commit(),
        "command": command,
        "complete": complete,
        "config": {**asdict(config), "paper_hyperparameters": PAPER, "exploration_noise": EXPLORATION_NOISE},
        "args": vars(args),
        "summary": summary,
        "ratios": ratios(rows, args.seeds),
        "measurements": measurements,
    }
    write_record(args.json, record)


if __name__ == "__main__":
    main()
