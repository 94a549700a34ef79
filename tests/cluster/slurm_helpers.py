"""Helpers of the cluster layer (tests/cluster): a job's fields, waiting, requeueing. The ``slurm`` fixture is in
tests/conftest.py."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
from kill_loop import evaluations, tensors  # noqa: E402  (a final checkpoint's tensors; evaluations but the wall time)

__all__ = ["REPO", "evaluations", "job_fields", "python", "requeue_now", "tensors", "wait_for"]


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
    # slurmd refuses to launch a job again whose credential it revoked at the kill within the same second as the new
    # credential ("Job 166 already killed, do not launch batch job": the job then ends FAILED without a result; seen
    # on a loaded machine): wait for the node to finish the old start, then let a second pass (what SLURM's own delay
    # of a requeued job's start, its BeginTime, leaves room for).
    wait_for(lambda: "completing" not in _node_states(), "the node to finish the job's earlier start", 90)
    time.sleep(1.5)
    subprocess.run(["scontrol", "update", f"jobid={job_id}", "StartTime=now"], check=True, capture_output=True, timeout=30)


def _node_states() -> str:
    return subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=30).stdout.lower()


def python() -> str:
    return sys.executable
