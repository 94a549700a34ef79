"""Whether this process's threads wait for cores that other work holds: Linux's scheduler statistics, read now and then.

With more torch threads than the cores a process gets (other processes on its cores, two runs started side by side),
each of OpenMP's parallel regions waits for a thread that is not running, and libgomp's waiting threads spin on the
cores for a while before they sleep (300,000 times by default), keeping the missing thread off them. The compiled update
runs dozens of parallel regions a gradient step (Inductor's kernels, MKL's products). Measured on a 2-core Intel Xeon
(``docs/performance_log.md``, 2026-11-29): stock TD3X on Hopper-v5 with 2 threads and one core's time (busy processes of
another session beside it) **453 ms an environment step against 4.3 ms with 1 thread**; SB3's eager ``TD3`` 17, 73 and 640 ms
a gradient step so (4.75 on free cores). ``OMP_WAIT_POLICY=passive`` (set before Python starts) ends the collapse, at
2.8x the time on free cores.

:class:`CoreWaits` reads how long this process's threads waited, runnable, for a core (``run_delay`` of each
``/proc/self/task/*/schedstat``), per second of wall time: 0.01 on free cores there, 1.0 with one core's time;
:meth:`CoreWaits.warn_once`, after each ``train()`` on a CPU with two threads or more, says so once with the fix (for
SB3's ``TD3`` run by run.py, its callback :class:`~sb3_td3x.experiment.run.callbacks.CoreWaitsCheck`). Nothing where
Linux does not give the numbers.
"""

from __future__ import annotations

import glob
import time
import warnings

import torch as th

#: Seconds of training between two readings.
WINDOW_S = 60.0
#: Thread-seconds waited for a core per second of wall time above which :meth:`CoreWaits.poll` reports.
TOO_MANY = 0.25

_said = False  # once a process: the models of a seed batch share its cores


def _waited_s() -> float | None:
    """Seconds this process's threads have waited for a core since each started (threads that ended not counted)."""
    total, seen = 0, False
    for path in glob.glob("/proc/self/task/*/schedstat"):
        try:
            with open(path) as stats:
                total += int(stats.read().split()[1])
        except (OSError, IndexError, ValueError):  # a thread that ended meanwhile, or a kernel without the field
            continue
        seen = True
    return total / 1e9 if seen else None


class CoreWaits:
    """The waits of this process's threads for a core, per second, over windows of :data:`WINDOW_S` seconds."""

    def __init__(self) -> None:
        self.start, self.waited = time.monotonic(), _waited_s()

    def poll(self) -> float | None:
        """Thread-seconds waited per second over the window that just ended, when it ended and that is above
        :data:`TOO_MANY`; else ``None`` (also where the scheduler's statistics cannot be read)."""
        now = time.monotonic()
        if self.waited is None or now - self.start < WINDOW_S:
            return None
        waited = _waited_s()
        if waited is None:
            self.waited = None
            return None
        rate = (waited - self.waited) / (now - self.start)
        self.start, self.waited = now, waited
        return rate if rate > TOO_MANY else None

    def warn_once(self) -> None:
        """A warning, once a process, when the window that just ended had too many waits and torch runs two threads or
        more."""
        global _said
        if _said or self.waited is None or th.get_num_threads() < 2:
            return
        rate = self.poll()
        if rate is None:
            return
        _said = True
        warnings.warn(
            f"This process's threads waited for a core {rate:.2f} s of each second over the last {WINDOW_S:.0f} s, with "
            f"{th.get_num_threads()} torch threads: other work shares its cores, and each parallel region of the update "
            "waits for a thread that is not running (measured: 4 to 190 times slower). Give the process cores of its own, "
            "or fewer threads (torch.set_num_threads, or run.py's torch_threads=...), or set OMP_WAIT_POLICY=passive "
            "before Python starts (2.8x slower on free cores).",
            stacklevel=2,
        )
