"""Errors a sweep reports to its user as one clear message, without a traceback.

Every error here says what was wrong and how to fix it; the command line prints ``str(error)`` and exits with
status 2. Errors inside a trial (a diverged run, a crash in training) are not these: they are recorded on the trial
and the study goes on (see :mod:`sb3_td3x.sweeps.worker`).
"""

from __future__ import annotations


class SweepError(Exception):
    """A problem with the sweep's inputs or surroundings that the user must fix before the sweep can run."""


class SweepSpecError(SweepError):
    """The search-space file is malformed: a missing or mistyped field, a bad range, an unknown config path."""


class StorageError(SweepError):
    """The study storage cannot be opened: unreachable server, wrong credentials, unwritable file."""
