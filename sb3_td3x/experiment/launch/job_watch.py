"""Following SLURM jobs that submitit submitted, on clusters with accounting and without.

submitit asks ``sacct`` for the state of its jobs. Many small clusters run without accounting, where ``sacct`` fails
and submitit logs a warning at every poll ("Bypassing sacct error"). :class:`SlurmWatcher` asks ``sacct`` first and,
once it fails, says so in one line and asks ``scontrol show job`` instead, which knows every job the controller holds
(running, pending, requeued, and finished ones for ``MinJobAge`` seconds, 300 by default). It also reads how often a
job was requeued (``Restarts``).

:func:`install` puts it in place of submitit's watcher for the SLURM jobs of this process: Hydra's submitit launcher
(``run.py -m hydra/launcher=submitit_slurm``) and the sweep workers (``--launcher sweeps/launcher/slurm.yaml``).
"""

from __future__ import annotations

import logging
import re
import subprocess
import time
from typing import Any

try:
    from submitit.slurm.slurm import SlurmInfoWatcher, SlurmJob
except ImportError:  # without the cluster extra: nothing to follow
    SlurmInfoWatcher = SlurmJob = None  # type: ignore[assignment,misc]

log = logging.getLogger(__name__)

_FIELD = re.compile(r"(\w+)=(\S*)")


class SlurmWatcher(SlurmInfoWatcher or object):  # type: ignore[misc]
    """submitit's SLURM watcher, with ``scontrol`` where ``sacct`` does not answer."""

    def __init__(self, delay_s: int = 60) -> None:
        super().__init__(delay_s=delay_s)
        self.accounting: bool | None = None  # unknown until sacct first answers or fails

    def update(self) -> None:
        to_check = {job_id.split("_")[0] for job_id in self._registered - self._finished}
        if not to_check:
            return
        self._num_calls += 1
        if self.accounting is not False:
            self._ask_sacct(to_check)
        if self.accounting is False:
            for job_id in sorted(to_check):
                self._ask_scontrol(job_id)
        self._last_status_check = time.time()
        for job_id in self._registered - self._finished:
            if self.is_done(job_id, mode="cache"):
                self._finished.add(job_id)

    def _ask_sacct(self, to_check: set[str]) -> None:
        command = self._make_command()
        if command is None:
            return
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.SubprocessError) as error:
            done = subprocess.CompletedProcess(command, 1, "", str(error))
        if done.returncode == 0:
            self.accounting = True
            self._info_dict.update(self.read_info(done.stdout))
            return
        if self.accounting is None:  # never answered: a cluster without accounting, or no sacct at all
            self.accounting = False
            said = " ".join((done.stderr or done.stdout or f"exit status {done.returncode}").split())
            log.info("sacct does not answer here (%s): following the jobs with scontrol instead", said)
        else:  # it answered before: a passing fault of the database
            log.debug("sacct failed this once: %s", done.stderr)

    def _ask_scontrol(self, job_id: str) -> None:
        try:
            done = subprocess.run(["scontrol", "-o", "show", "job", job_id], capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.SubprocessError):
            return
        if done.returncode != 0:  # gone from the controller (older than MinJobAge): keep what was last seen
            return
        self._info_dict.update(read_scontrol(done.stdout))


def read_scontrol(text: str) -> dict[str, dict[str, str]]:
    """``scontrol -o show job`` (one line per job or array task) as submitit's job infos: ``{"12_3": {"State":
    "RUNNING", "Restarts": "1", ...}}``, keyed as submitit names jobs (``<array job>_<task>`` for an array task)."""
    infos = {}
    for line in text.splitlines():
        fields = dict(_FIELD.findall(line))
        if "JobId" not in fields:
            continue
        array, task = fields.get("ArrayJobId"), fields.get("ArrayTaskId")
        name = f"{array}_{task}" if array and task and task.isdigit() else fields["JobId"]
        infos[name] = {
            "JobID": name,
            "State": fields.get("JobState", "UNKNOWN"),
            "NodeList": fields.get("NodeList", ""),
            "Restarts": fields.get("Restarts", "0"),
            "ExitCode": fields.get("ExitCode", ""),
        }
    return infos


def install() -> Any | None:
    """Make submitit follow this process's SLURM jobs with :class:`SlurmWatcher`; returns it (None without
    submitit). Idempotent."""
    if SlurmJob is None:
        return None
    if not isinstance(SlurmJob.watcher, SlurmWatcher):
        SlurmJob.watcher = SlurmWatcher(delay_s=60)
    return SlurmJob.watcher


#: submitit's states of a job that has not ended (SLURM's, and submitit's local ones)
_NOT_ENDED = {"READY", "PENDING", "RUNNING", "UNKNOWN", "REQUEUED", "COMPLETING", "PREEMPTED", "CONFIGURING", "SUSPENDED"}


def job_end(job: Any, settle_s: float = 120.0) -> dict[str, Any]:
    """How a submitit job ended, once it has (its function's result or error is there): its state in SLURM (a job
    that has written its result may still be RUNNING or COMPLETING for a moment: waited for, up to ``settle_s``), how
    often SLURM started it again, and its function's result or why there is none."""
    job.wait()
    end: dict[str, Any] = {"job": str(job.job_id), "state": "UNKNOWN", "requeued": 0}
    deadline = time.monotonic() + settle_s
    while True:
        try:
            info = job.watcher.get_info(job.job_id, mode="force")
        except NotImplementedError:  # submitit's local jobs: their state is the process's
            info = {}
        end["state"] = (info.get("State") or job.state or "UNKNOWN").split()[0]
        if end["state"].upper() not in _NOT_ENDED or not info or time.monotonic() > deadline:
            break
        time.sleep(1.0)
    try:
        end["requeued"] = int(info.get("Restarts", 0))
    except ValueError:
        pass
    try:
        end["result"] = job.result()
    except Exception as error:  # noqa: BLE001  (submitit's FailedJobError, UncompletedJobError: the job's log says why)
        end["error"] = (str(error).strip().splitlines() or [type(error).__name__])[0]
    return end
