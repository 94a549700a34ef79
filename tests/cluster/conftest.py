"""The cluster layer: ``run.py`` multiruns and sweep workers as jobs of a real SLURM (``.ci/slurm.sh``: Debian's
``slurm-wlm`` and ``munge``, one node). Skipped where no SLURM answers; an error in CI, which starts one."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
HOW = "export SLURM_CONF=\"$(bash .ci/slurm.sh)\" (as root; it installs slurm-wlm and munge when missing)"


@pytest.fixture(scope="session")
def slurm() -> dict[str, str]:
    """The environment for commands that use the cluster (``SLURM_CONF``), once a node answers idle or busy."""
    problem = None
    if shutil.which("sinfo") is None:
        problem = "SLURM's commands are not installed"
    else:
        done = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True, timeout=30)
        states = done.stdout.split()
        if done.returncode != 0:
            problem = f"sinfo fails: {' '.join(done.stderr.split())}"
        elif not any(state.rstrip("*") in ("idle", "mixed", "allocated") for state in states):
            problem = f"no SLURM node is up (states: {states or 'none'})"
    if problem is not None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{problem}; CI must start SLURM first: {HOW}")
        pytest.skip(f"{problem}: start a one-node SLURM with {HOW}")
    return {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), "PYTHONUNBUFFERED": "1"}


def job_fields(job_id: str) -> dict[str, str]:
    """``scontrol show job``'s fields of one job ({} once the controller has forgotten it)."""
    done = subprocess.run(["scontrol", "-o", "show", "job", job_id], capture_output=True, text=True, timeout=30)
    if done.returncode != 0 or not done.stdout.strip():
        return {}
    return dict(re.findall(r"(\w+)=(\S*)", done.stdout.splitlines()[0]))


def wait_for(condition, what: str, timeout: float, proc: subprocess.Popen | None = None, poll: float = 0.5):
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"the command exited with {proc.returncode} before {what}:\n{out[-3000:]}\n{err[-3000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(poll)


def requeue_now(job_id: str, how: str = "scontrol requeue") -> None:
    """Requeue the job, then let it start again at once: SLURM holds a requeued job for a while (its BeginTime,
    about two minutes) before it may start again.

    :param how: ``"scontrol requeue"`` (as an operator, or a preemption with requeue: SLURM sends SIGTERM), or
        ``"time limit"``: submitit's signal, as SLURM sends it ``signal_delay_s`` before the time limit (``scancel
        --signal=USR2``, as submitit's own tests do), after which submitit requeues the job itself
    """
    if how == "scontrol requeue":
        command = ["scontrol", "requeue", job_id]
    else:
        assert how == "time limit", how
        command = ["scancel", "--signal=USR2", job_id]
    subprocess.run(command, check=True, capture_output=True, timeout=30)
    wait_for(lambda: job_fields(job_id).get("JobState") == "PENDING", f"job {job_id} to be pending again", 90)
    subprocess.run(["scontrol", "update", f"jobid={job_id}", "StartTime=now"], check=True, capture_output=True, timeout=30)


def python() -> str:
    return sys.executable
