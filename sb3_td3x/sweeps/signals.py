"""SIGINT and SIGTERM in a sweep worker: held while a trial is created or its result recorded, acting while it trains.

A signal that lands between Optuna creating a trial and the worker telling Optuna how it ended would leave the
trial RUNNING with nobody to finish it. So the worker holds both signals (:class:`HeldSignals`): one that arrives
is remembered, and the worker acts on it at the next safe point, after the trial is created or its result is
written. Only while the trial runs (:meth:`HeldSignals.live`) does a signal act at once: during training the
runner turns the first one into a checkpoint and a clean stop (``StopOnSignal``), and anywhere else in the trial
it raises :class:`SignalInterrupt` (a :class:`KeyboardInterrupt`), which the worker records as an interrupted trial.

A signal held while the worker waits for the storage's budget lock acts once the lock is free; the lock is held only
for the moment another worker creates a trial.

A signal handler raises where the main thread happens to be, and that can be a finalizer or a weakref callback run by
the garbage collector (SQLAlchemy has some), where Python drops the exception with an "Exception ignored" traceback.
While the trial runs, such a dropped :class:`SignalInterrupt` is sent again a millisecond later, so that it acts in the
trial's own code; it is never lost, and the traceback is not printed.

In a worker that submitit runs on SLURM, submitit's time-out signal (``SIGUSR2``) is held and acts like the others;
once the trial is recorded and queued again, :func:`sb3_td3x.experiment.jobs.after_stop` hands over to submitit, which
requeues the job.

Signals can only be handled in the main thread; elsewhere this does nothing.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

from sb3_td3x.experiment import jobs


class SignalInterrupt(KeyboardInterrupt):
    """A signal that arrived while a trial ran; ``signal_name`` is ``"SIGINT"``, ``"SIGTERM"`` (or submitit's)."""

    def __init__(self, signal_name: str) -> None:
        self.signal_name = signal_name
        super().__init__(signal_name)


class HeldSignals:
    """Hold SIGINT and SIGTERM (and submitit's signal in its jobs) for as long as the ``with`` block runs;
    :attr:`received` names the first that came."""

    def __init__(self) -> None:
        self.received: str | None = None  #: "SIGINT" or "SIGTERM", once one has arrived
        self._previous: dict[int, Any] = {}
        self._active = threading.current_thread() is threading.main_thread()
        self._signals = jobs.stop_signals()

    def __enter__(self) -> HeldSignals:
        if self._active:
            self._previous = {sig: signal.getsignal(sig) for sig in self._signals}
            for sig, handler in self._previous.items():
                jobs.keep_handler(sig, handler)
            self.hold()
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def hold(self) -> None:
        """Remember signals instead of acting on them (again, after :meth:`live`)."""
        self._install(self._remember)

    @contextlib.contextmanager
    def live(self) -> Iterator[None]:
        """Let signals act while the block runs: each is remembered and raises :class:`SignalInterrupt`."""
        self._install(self._interrupt)
        previous_hook = sys.unraisablehook
        if self._active:
            sys.unraisablehook = self._deliver_again(previous_hook)
        try:
            yield
        finally:
            sys.unraisablehook = previous_hook
            self.hold()

    @staticmethod
    def _deliver_again(previous: Any) -> Any:
        """An unraisable hook that sends a signal whose :class:`SignalInterrupt` Python dropped (raised in a finalizer or
        a weakref callback) again, from another thread a millisecond later: it is then handled in the main thread's
        own code, once the callback has returned. A signal that lands while the hook starts that thread is sent again
        too. Anything else goes to ``previous``."""

        def hook(unraisable: Any) -> None:
            if not isinstance(unraisable.exc_value, SignalInterrupt):
                previous(unraisable)
                return
            dropped = [unraisable.exc_value]
            while dropped:
                signum = getattr(signal, dropped.pop().signal_name)
                try:
                    threading.Timer(0.001, os.kill, (os.getpid(), signum)).start()
                except SignalInterrupt as another:  # a second signal while the timer starts: raised here, in the
                    dropped.append(another)  # hook, where Python drops it (and prints it) too; sent again as well

        return hook

    def _install(self, handler: Any) -> None:
        if self._active:
            for sig in self._signals:
                signal.signal(sig, handler)

    @jobs.ours
    def _remember(self, signum: int, frame: Any) -> None:
        self.received = self.received or signal.Signals(signum).name
        jobs.note_signal(signum)

    @jobs.ours
    def _interrupt(self, signum: int, frame: Any) -> None:
        self._remember(signum, frame)
        raise SignalInterrupt(signal.Signals(signum).name)
