"""The one interface behind every way of starting the processes that train.

A launch starts processes: ``run.py``'s seed processes (:mod:`~sb3_td3x.experiment.launch.seed_processes`), a Hydra
multirun's jobs through Hydra's launcher plugins (joblib on this machine's cores, submitit locally or on SLURM:
:mod:`~sb3_td3x.experiment.launch.hydra_jobs`), or sweep workers as submitit jobs (:mod:`sb3_td3x.sweeps.launch`).
What a launch means for the machine follows from two facts that each launcher states, and is decided here once:

- how many of its processes run side by side on this machine (:attr:`Launcher.side_by_side`): their torch threads
  share its cores (:meth:`Launcher.threads_per_process`), and on a GPU they share it through CUDA MPS
  (:meth:`Launcher.run`, :mod:`~sb3_td3x.experiment.launch.mps`);
- whether this process waits for them (:attr:`Launcher.not_waiting`): only then can it stop an MPS daemon it started.

A new launcher subclasses :class:`Launcher`: it sets those two and starts its processes in :meth:`Launcher.start`.
How a stop signal reaches its processes is :mod:`sb3_td3x.experiment.stops`'s.
"""

from __future__ import annotations

import contextlib
import sys
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

from sb3_td3x.experiment.launch import mps


class Launcher(ABC):
    """One way of starting the processes of a launch (see the module's docstring)."""

    #: None when this process waits for its processes to end; else why not (then no MPS daemon is started for them)
    not_waiting: str | None = None

    @property
    @abstractmethod
    def side_by_side(self) -> int:
        """How many of its processes run at once on this machine: 0 where they run elsewhere (SLURM places them), 1
        where one runs at a time."""

    @abstractmethod
    def start(self) -> Any:
        """Start the processes (and wait for them, unless :attr:`not_waiting` says why not); what they give back."""

    def threads_per_process(self, cores: int) -> int | None:
        """Torch threads for each process: ``cores`` shared among those that run at once; None (torch's default: all
        the cores) where one runs at a time."""
        if self.side_by_side <= 1:
            return None
        return max(1, cores // self.side_by_side)

    def shared_gpu(self, device: str, enabled: bool, say: Callable[[str], None] | None = None) -> contextlib.AbstractContextManager:
        """CUDA MPS for the processes that run side by side on this machine's GPU (``device``: a config's, ``auto``
        being CUDA where torch sees a GPU; ``enabled``: its ``mps``), as :func:`~sb3_td3x.experiment.launch.mps.decide`
        decides; one line (``say``, standard error by default) says what it did where they use a GPU."""
        say = say or (lambda line: print(line, file=sys.stderr))
        return mps.around_launch(self.side_by_side, device, enabled, say=say, unstoppable=self.not_waiting)

    def run(self, device: str, enabled: bool, say: Callable[[str], None] | None = None) -> Any:
        """:meth:`start` inside :meth:`shared_gpu`."""
        with self.shared_gpu(device, enabled, say):
            return self.start()


def jobs_at_once(n_jobs: int, cores: int) -> int:
    """How many jobs joblib runs side by side with ``n_jobs`` (-1 one per core, -2 all cores but one, ...)."""
    return n_jobs if n_jobs > 0 else max(1, cores + 1 + n_jobs)
