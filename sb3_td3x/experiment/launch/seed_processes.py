"""``seeds=[...]``: the seeds trained in one process per core, every P-th seed in each.

One process runs its Python (SB3's collection loop, the update's dispatch) on one core at a time, so on a CPU with P
cores N seeds train fastest in P processes side by side, each a :class:`~sb3_td3x.SeedBatch` of every P-th seed with
one torch thread (docs/performance.md: on 2 cores, two seeds in two processes trained 1.26x as fast as in one). A
seed computes what its lone run computes however the seeds are grouped (bit for bit on a CPU), so the grouping is a
speed setting only: ``seed_processes`` (null: one per core of the run, at most one per seed; 1: this process).

This process (``run.py``'s) starts the others (``spawn``: each imports torch afresh) and waits. Each trains its seeds
with :func:`~sb3_td3x.experiment.run.seeds.train_seed_group`, in the seeds' own folders, which it owns (the lock) as a
lone run does; every seed's ``config.yaml`` lists all the seeds and folders, so ``resume=`` with any of them
continues them all, in processes again. This process then reports as one batch would: the aggregate table, or what
stopped a seed (an interruption first). Stopping: SIGINT and SIGTERM (and submitit's signal) are passed on to the
processes, and each checkpoints its seeds; in a SLURM job the scheduler signals every process itself, so nothing is
passed on. With ``report`` callbacks (a sweep's trials) the seeds train in one process, which reports.
On a GPU the processes share it through CUDA MPS where the machine has it (:mod:`~sb3_td3x.experiment.launch.mps`, as a
multirun's jobs do): 16 Ant seeds on an H200 trained at 6694 seed-steps/s in 16 processes under MPS (1037 without),
against 620 in one process (docs/seeds.md); each seed is then exactly its lone run.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import queue
import sys
import traceback
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from sb3_td3x.common.redaction import redact_log_records
from sb3_td3x.experiment import jobs, stops
from sb3_td3x.experiment.errors import (
    ConfigError,
    RunFilesNotWritten,
    SeedProcessLost,
    TrainingDiverged,
    TrainingInterrupted,
)
from sb3_td3x.experiment.launch.launcher import Launcher
from sb3_td3x.experiment.layout import LOG_FORMAT
from sb3_td3x.experiment.run.seeds import end_of_batch, train_seed_group

log = logging.getLogger(__name__)


def processes_for(cfg: DictConfig) -> int:
    """How many processes train ``cfg.seeds``: ``seed_processes``, or (null) one per core of this run (its
    ``torch_threads`` when set, else the cores this process may use); never more than the seeds. The same on a GPU,
    where each process's Python needs a core too and the processes share the GPU through CUDA MPS."""
    n_seeds = len(cfg.seeds)
    if cfg.get("seed_processes") is not None:
        return max(1, min(n_seeds, int(cfg.seed_processes)))
    return max(1, min(n_seeds, _run_cores(cfg)))


def _run_cores(cfg: DictConfig) -> int:
    """The cores of this run: its ``torch_threads`` when set, else the cores this process may use."""
    return int(cfg.torch_threads or jobs.available_cores())


def groups_of(n_seeds: int, processes: int) -> list[list[int]]:
    """The seeds' indices each process trains: every ``processes``-th, so that seeds of any speed spread evenly."""
    return [list(range(k, n_seeds, processes)) for k in range(processes)]


class SeedProcesses(Launcher):
    """``cfg.seeds`` trained in ``processes`` processes (see the module's docstring); :meth:`start` returns the seeds'
    ``statistic`` of their final mean returns, or raises what stopped a seed, as one batch would.

    :param how: how the seeds start in their folders (:func:`~sb3_td3x.experiment.run.folder.where_to_start`)
    """

    def __init__(self, cfg: DictConfig, how: str, statistic: str, processes: int) -> None:
        self.cfg, self.how, self.statistic, self.processes = cfg, how, statistic, processes

    @property
    def side_by_side(self) -> int:
        return self.processes

    def start(self) -> float:
        cfg, processes = self.cfg, self.processes
        seeds, dirs = [int(s) for s in cfg.seeds], [Path(d) for d in cfg.seed_run_dirs]
        groups = groups_of(len(seeds), processes)
        threads = self.threads_per_process(_run_cores(cfg)) or 1
        log.info(
            "Training seeds %s in %d processes of %d torch thread(s), one per core (seed_processes=%s; "
            "seed_processes=1 trains them in this one): %s. Each seed computes what its lone run computes.",
            seeds, processes, threads, cfg.get("seed_processes"),
            "; ".join(f"seeds {[seeds[i] for i in group]}" for group in groups),
        )  # fmt: skip
        context = mp.get_context("spawn")
        results = context.Queue()
        config = OmegaConf.to_container(cfg, resolve=True)
        children = [
            context.Process(
                target=_train_group, args=(config, self.how, group, threads, self.statistic, k, results), name=f"seeds-{k}"
            )
            for k, group in enumerate(groups)
        ]
        with stops.passed_on(children):
            for child in children:
                child.start()
            outcomes = _wait_for(children, results)
        finals, errors = _outcomes(outcomes, groups, seeds, dirs)
        return end_of_batch(seeds, dirs, finals, errors, self.statistic)


def _wait_for(children: list[Any], results: Any) -> dict[int, tuple[Any, ...]]:
    """What each process put in ``results`` (``("died", exit code)`` for one that ended without putting anything)."""
    outcomes: dict[int, tuple[Any, ...]] = {}
    while len(outcomes) < len(children):
        try:
            k, outcome = results.get(timeout=0.5)
            outcomes[k] = outcome
        except queue.Empty:
            for k, child in enumerate(children):
                if k not in outcomes and child.exitcode is not None:
                    with contextlib.suppress(queue.Empty):  # its result may still be on its way
                        k2, outcome = results.get(timeout=2.0)
                        outcomes[k2] = outcome
                    if k not in outcomes:
                        outcomes[k] = ("died", child.exitcode)
    for child in children:
        child.join()
    return outcomes


def _outcomes(
    outcomes: dict[int, tuple[Any, ...]], groups: list[list[int]], seeds: list[int], dirs: list[Path]
) -> tuple[dict[int, float], dict[int, BaseException]]:
    """Each finished seed's final mean return, and what stopped each other one (keyed by seed)."""
    finals: dict[int, float] = {}
    errors: dict[int, BaseException] = {}
    for k, outcome in sorted(outcomes.items()):
        group_seeds = [seeds[i] for i in groups[k]]
        if outcome[0] == "done":
            finals.update(outcome[1])
            errors.update({seed: _rebuilt(error) for seed, error in outcome[2].items()})
        elif outcome[0] == "failed":
            errors.update(dict.fromkeys(group_seeds, _rebuilt(outcome[1])))
        else:  # died: killed (out of memory, SIGKILL) before it could say anything
            errors.update(dict.fromkeys(group_seeds, SeedProcessLost(
                f"The process training seeds {group_seeds} ended with exit code {outcome[1]} and no result (killed: "
                f"out of memory, SIGKILL?); the other seeds went on. Each seed's folder keeps its last checkpoint: "
                f"continue them all with python run.py resume={dirs[0]}"
            )))  # fmt: skip
    return finals, errors


def _train_group(config: dict, how: str, indices: list[int], threads: int, statistic: str, k: int, results: Any) -> None:
    """A process of :class:`SeedProcesses`: its seeds trained with ``threads`` torch threads; the outcome put in
    ``results`` as ``(k, outcome)``."""
    if jobs.current_job() is None:
        os.setpgrp()  # a Ctrl+C at the terminal reaches run.py only, which passes it on
    stops.stop_when_orphaned()
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT, stream=sys.stdout)
    redact_log_records()
    torch.set_num_threads(threads)
    cfg = OmegaConf.create(config)
    cfg.torch_threads = threads
    try:
        finals, errors = train_seed_group(cfg, how, indices, statistic)
        outcome: tuple[Any, ...] = ("done", finals, {seed: _portable(error) for seed, error in errors.items()})
    except BaseException as error:  # noqa: BLE001  (whatever it is, run.py reports it for these seeds)
        outcome = ("failed", _portable(error))
    results.put((k, outcome))
    results.close()
    results.join_thread()


def _portable(error: BaseException) -> tuple[Any, ...]:
    """An exception as plain values (the framework's errors take several arguments; pickling would lose them)."""
    if isinstance(error, TrainingInterrupted):
        return ("interrupted", error.signal_name, error.exit_code, error.num_timesteps, error.run_dir)
    if isinstance(error, TrainingDiverged):
        return ("diverged", error.what, error.value, error.num_timesteps)
    if isinstance(error, (ConfigError, RunFilesNotWritten)):
        return (type(error).__name__, str(error))
    return ("other", "".join(traceback.format_exception(error)))


def _rebuilt(portable: tuple[Any, ...]) -> BaseException:
    kind, *values = portable
    if kind == "interrupted":
        return TrainingInterrupted(*values)
    if kind == "diverged":
        return TrainingDiverged(*values)
    if kind == "ConfigError":
        return ConfigError(values[0])
    if kind == "RunFilesNotWritten":
        return RunFilesNotWritten(values[0])
    return RuntimeError(f"a seed process failed:\n{values[0]}")


__all__ = ["SeedProcesses", "groups_of", "processes_for"]
