"""Several processes on one GPU share it through CUDA MPS (the Multi-Process Service).

Without MPS the driver time-slices the GPU between processes: on an H200 with 16 processes of TD3X each got what 8 got
(docs/performance.md). With an MPS control daemon their kernels run side by side: the same 16 processes ran 6.5x
faster. So whatever starts several GPU processes of this project on one machine (a Hydra multirun with the joblib
launcher, sweep workers with ``--launcher sweeps/launcher/local.yaml --wait``) does it under MPS:

- where the machine has a CUDA GPU and ``nvidia-cuda-mps-control``, more than one process will run, the config does not
  opt out (``mps=false``), and no daemon runs yet, a daemon is started with a pipe folder of the run's own
  (``CUDA_MPS_PIPE_DIRECTORY``), the processes are pointed at it through their environment, and it is stopped at the
  end; one line says so;
- a daemon that already runs (the user's, or a cluster's) is used as it is, and left running;
- elsewhere (no GPU, no MPS binary, one process) nothing happens, and one line says why where a GPU was asked for.

On SLURM the cluster decides: ask for MPS with ``--gres=mps:<share>`` (``additional_parameters: {gres: mps:100}`` in
the launcher file) where the cluster offers it, or for a whole node (``--exclusive``) and run a multirun or a sweep of
local workers inside it (docs/cluster.md).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

CONTROL = "nvidia-cuda-mps-control"
PIPE_ENV, LOG_ENV = "CUDA_MPS_PIPE_DIRECTORY", "CUDA_MPS_LOG_DIRECTORY"
DEFAULT_PIPE = "/tmp/nvidia-mps"  # where the driver's clients look when CUDA_MPS_PIPE_DIRECTORY is unset


def has_cuda() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except ImportError:
        return False


def running_daemon(environ: dict[str, str] | None = None) -> Path | None:
    """The pipe folder of an MPS control daemon this process's CUDA clients would reach, or None."""
    env = os.environ if environ is None else environ
    pipe = Path(env.get(PIPE_ENV) or DEFAULT_PIPE)
    return pipe if (pipe / "control").exists() else None


@dataclass
class MpsDecision:
    """Whether to start a daemon (``start``), use a running one (``pipe`` without ``start``), or nothing; and why."""

    start: bool
    pipe: Path | None
    reason: str


def decide(
    processes: int,
    wants_gpu: bool,
    enabled: bool,
    folder: Path,
    cuda_check: Callable[[], bool] | None = None,
    control: str | None = None,
) -> MpsDecision:
    """What to do about MPS for ``processes`` processes that will use the GPU (``wants_gpu``: their device resolves to
    CUDA), with MPS ``enabled`` by the config, the daemon's folders under ``folder``."""
    if not enabled:
        return MpsDecision(False, None, "mps=false: the processes share the GPU by time slices")
    if not wants_gpu:
        return MpsDecision(False, None, "the processes run on the CPU")
    if processes < 2:
        return MpsDecision(False, None, "one process at a time: nothing to share")
    if not (cuda_check or has_cuda)():
        return MpsDecision(False, None, "no CUDA GPU on this machine")
    control = control if control is not None else shutil.which(CONTROL)
    if control is None:
        return MpsDecision(False, None, f"{CONTROL} is not installed: the {processes} processes share the GPU by time slices")
    running = running_daemon()
    if running is not None:
        return MpsDecision(False, running, f"an MPS daemon already runs (pipe {running}): the {processes} processes use it")
    return MpsDecision(True, folder / "pipe", f"{processes} processes share the GPU: started an MPS control daemon")


class SharedGpu:
    """A context manager around the launch of several GPU processes: MPS as :func:`decide` says, stopped at the end
    when this started it. The processes inherit ``CUDA_MPS_PIPE_DIRECTORY`` from this process's environment."""

    def __init__(
        self, decision: MpsDecision, folder: Path, control: str | None = None, say: Callable[[str], None] = print
    ) -> None:
        self.decision = decision
        self.folder = folder
        self.control = control or shutil.which(CONTROL) or CONTROL
        self.say = say
        self._environ: dict[str, str | None] = {}
        self._started = False

    def __enter__(self) -> SharedGpu:
        decision = self.decision
        if decision.pipe is None:
            return self
        pipe = decision.pipe
        if decision.start:
            pipe.mkdir(parents=True, exist_ok=True)
            (self.folder / "log").mkdir(parents=True, exist_ok=True)
            env = {**os.environ, PIPE_ENV: str(pipe), LOG_ENV: str(self.folder / "log")}
            done = subprocess.run([self.control, "-d"], env=env, capture_output=True, text=True, timeout=60)
            if done.returncode != 0:
                why = " ".join(done.stderr.split()) or done.returncode
                self.say(f"CUDA MPS: {CONTROL} -d failed ({why}): the processes share the GPU by time slices")
                return self
            self._started = True
        for name, value in ((PIPE_ENV, str(pipe)), (LOG_ENV, str(self.folder / "log") if decision.start else None)):
            if value is not None:
                self._environ[name] = os.environ.get(name)
                os.environ[name] = value
        self.say(f"CUDA MPS: {decision.reason} (pipe folder {pipe})" + ("; it stops at the end" if self._started else ""))
        return self

    def __exit__(self, *exc: object) -> None:
        for name, value in self._environ.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        self._environ = {}
        if self._started:
            env = {**os.environ, PIPE_ENV: str(self.decision.pipe)}
            try:
                subprocess.run([self.control], input="quit\n", env=env, capture_output=True, text=True, timeout=60)
            except (OSError, subprocess.SubprocessError) as error:
                how = f"echo quit | {PIPE_ENV}={self.decision.pipe} {CONTROL}"
                log.warning("CUDA MPS: stopping the daemon failed: %s; stop it with: %s", error, how)
            else:
                shutil.rmtree(self.folder, ignore_errors=True)  # the launch's own pipe and log folders
            self._started = False


def around_launch(
    processes: int, device: str, enabled: bool, say: Callable[[str], None] = print, unstoppable: str | None = None
) -> contextlib.AbstractContextManager:
    """What a launch of ``processes`` processes on ``device`` (a config's ``device``: ``auto`` is CUDA where torch
    sees a GPU) runs inside: :class:`SharedGpu` as :func:`decide` says, with its pipe folder of the launch's own
    (``/tmp/td3x-mps-<pid>``: short, the pipe is a Unix socket path), or nothing where the processes do not share a
    GPU. One line (``say``) tells what it did, or why not. ``unstoppable``: why nothing would stop a daemon started
    here (a launch that does not wait for its processes): then none is started, and the line says so."""
    wants_gpu = device.startswith("cuda") or (device == "auto" and has_cuda())
    if not wants_gpu or processes < 2:
        return contextlib.nullcontext()
    folder = Path(tempfile.gettempdir()) / f"td3x-mps-{os.getpid()}"
    decision = decide(processes, wants_gpu, enabled, folder)
    if decision.start and unstoppable is not None:
        say(f"CUDA MPS: not started: {unstoppable}; start one with {CONTROL} -d")
        return contextlib.nullcontext()
    if decision.pipe is None:
        say(f"CUDA MPS: not used: {decision.reason}")
    return SharedGpu(decision, folder, say=say)
