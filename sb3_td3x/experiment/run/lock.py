"""One owner per run folder: an OS lock on ``<run_dir>/.lock`` held for the whole run.

The lock is ``flock(2)`` on an open file, so the kernel drops it when the process ends, however it ends: a run killed
with SIGKILL, or a node that loses power, never leaves a stale lock behind. The file itself stays and says who held
it last (pid, host, command, start time); that text is only read to name the holder in the message, never trusted
to decide anything.

On a local disk the guarantee is exact. On a shared file system it depends on how it is mounted: NFSv4 and Linux
NFSv3 clients turn ``flock`` into a byte-range lock that the server arbitrates, so two nodes exclude each other;
Lustre does only with the ``flock`` mount option (with ``localflock`` it excludes processes of the same node only);
some file systems refuse ``flock`` altogether, which is reported (set ``SB3_TD3X_UNLOCKED_RUNS=1`` to run without
the lock there, at your own risk).
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
import sys
import time
from pathlib import Path

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment.errors import ConfigError

log = logging.getLogger(__name__)

LOCK_FILE = ".lock"
UNLOCKED_ENV = "SB3_TD3X_UNLOCKED_RUNS"


class RunFolderBusy(ConfigError):
    """Another process owns the run folder."""


class RunFolderLock:
    """The lock of one run folder, held from :meth:`acquire` to :meth:`release` (or the end of the process)."""

    def __init__(self, run_dir: Path, fd: int | None) -> None:
        self.run_dir = run_dir
        self._fd = fd

    @classmethod
    def acquire(cls, run_dir: Path | str) -> RunFolderLock:
        """Create ``run_dir`` if needed and take its lock; :class:`RunFolderBusy` names the holder when another
        process has it."""
        run_dir = Path(run_dir)
        if run_dir.exists() and not run_dir.is_dir():
            raise ConfigError(f"run_dir={run_dir} is a file, not a folder. Pass a folder for the run's records.")
        run_dir.mkdir(parents=True, exist_ok=True)
        path = run_dir / LOCK_FILE
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            _flock_soon(fd)
        except OSError as error:
            os.close(fd)
            if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RunFolderBusy(_busy_message(run_dir)) from None
            if os.environ.get(UNLOCKED_ENV) == "1":
                log.warning("The file system of %s cannot lock files (%s); running without the lock", run_dir, error)
                return cls(run_dir, None)
            raise ConfigError(
                f"The run folder {run_dir} cannot be locked ({error.strerror}): its file system does not support "
                f"flock, so two processes could write the same run. Put runs on a file system that does (a local disk, "
                f"NFS, Lustre mounted with -o flock), or set {UNLOCKED_ENV}=1 to run without the lock."
            ) from None
        holder = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": " ".join(redact([Path(sys.argv[0]).name, *sys.argv[1:]])),  # a key given on the command line masked
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(holder) + "\n").encode(), 0)
        return cls(run_dir, fd)

    @staticmethod
    def check_free(run_dir: Path | str) -> None:
        """Raise :class:`RunFolderBusy` if another process holds the lock of ``run_dir`` now (creates nothing)."""
        path = Path(run_dir) / LOCK_FILE
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            return  # no lock file: never locked, or not a run folder (the caller says what is missing)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RunFolderBusy(_busy_message(Path(run_dir))) from None
        finally:
            os.close(fd)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the file drops the lock
            self._fd = None


def _flock_soon(fd: int, tries: int = 20) -> None:
    """Take the exclusive lock, trying again for a moment: :meth:`RunFolderLock.check_free` of another process may
    hold a shared lock for an instant."""
    for attempt in range(tries):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except OSError as error:
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN) or attempt == tries - 1:
                raise
            time.sleep(0.05)


def _busy_message(run_dir: Path) -> str:
    try:
        holder = json.loads((run_dir / LOCK_FILE).read_text())
        who = f"process {holder['pid']} on {holder['host']} (started {holder['started']}: {holder['command']})"
    except (OSError, ValueError, KeyError, TypeError):
        who = "another process"
    return (
        f"The run folder {run_dir} is in use by {who}. A run folder has one owner at a time: wait for that process to "
        f"end (or stop it; it checkpoints on SIGTERM), then resume with: python run.py resume={run_dir}"
    )
