"""Stop signals, in every process of the framework: a signal, then a checkpoint, then the exit.

The stop signals are SIGINT (Ctrl+C), SIGTERM (``kill``, ``scancel``, and what SLURM sends before it kills a job that
is cancelled, preempted or requeued, ``KillWait`` before SIGKILL) and, in a function submitit runs on SLURM, submitit's
time-out signal (``SIGUSR2`` unless ``SUBMITIT_PREEMPT_SIGNAL`` says otherwise; sent ``signal_delay_s`` before the time
limit). One policy for all of them:

1. **The signal.** What trains asks its checkpointers to stop (:class:`StopOnSignal`); the run checkpoints at its next
   rollout boundary and raises :class:`~sb3_td3x.experiment.errors.TrainingInterrupted`. The first signal restores
   the handlers that were there before, so a second Ctrl+C stops at once (the last periodic checkpoint is still there).
2. **Where it lands.** Every process that can receive one is one of these:

   - a run (``run.py``, the API, a sweep's trial, a seed process): :class:`StopOnSignal` while it learns;
   - ``run.py`` training ``seeds=[...]`` in seed processes: :func:`passed_on` hands each signal to the processes (they
     run in process groups of their own), except in a SLURM job, where the scheduler signals every process itself;
   - a sweep worker: :class:`HeldSignals` holds them while a trial is created or its result recorded and lets them act
     while the trial trains; outside its loop SIGTERM acts as Ctrl+C (:func:`interrupting`), and once the worker has
     said what became of its trial, a signal while the interpreter shuts down changes nothing (:func:`ignore`).
3. **The exit** (:func:`after_stop`), once the checkpoint is written: submitit's signal hands over to submitit, which
   requeues the job; SIGTERM or SIGINT inside a SLURM job exits without a result (SLURM says how the job goes on);
   elsewhere the caller exits with 128 + the signal, saying how to resume.

This is the one module that installs signal handlers. Signals can only be handled in the main thread; elsewhere (a
thread pool) nothing is installed and a run cannot be stopped by a signal.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any, Protocol

from sb3_td3x.experiment import jobs


def requeue_signal() -> signal.Signals | None:
    """submitit's time-out and preemption signal, in a function submitit runs on SLURM; None elsewhere."""
    if not jobs.in_submitit_job() or jobs.current_job() is None:
        return None
    return getattr(signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2"), None)


def stop_signals() -> tuple[signal.Signals, ...]:
    """The signals that make a run checkpoint and stop: SIGINT, SIGTERM, and submitit's in a submitit job."""
    extra = requeue_signal()
    return (signal.SIGINT, signal.SIGTERM) + ((extra,) if extra is not None else ())


class _Stops:
    """What this process was told to do by a signal, for its top level to act on once its checkpoint is written."""

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self.scheduler_handler: Callable[[int, Any], Any] | None = None  # submitit's, replaced by ours


_stops = _Stops()


def _ours(handler: Callable[..., Any]) -> Callable[..., Any]:
    """Mark a handler (a function, or the function of a method) as this module's, so that :func:`_install` never keeps
    one of ours as submitit's."""
    handler._sb3_td3x = True  # type: ignore[attr-defined]
    return handler


def _install(signals: tuple[int, ...], handler: Any) -> dict[int, Any]:
    """``handler`` for ``signals``; returns the handlers it replaced. submitit's handler of its signal is kept, to hand
    over to once the checkpoint is written (:func:`after_stop`)."""
    previous = {}
    for sig in signals:
        previous[sig] = signal.signal(sig, handler)
        replaced = previous[sig]
        if sig == requeue_signal() and callable(replaced) and not getattr(replaced, "_sb3_td3x", False):
            _stops.scheduler_handler = replaced
    return previous


def _restore(previous: dict[int, Any]) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler if handler is not None else signal.SIG_DFL)  # None: one installed outside Python


def note_signal(signum: int) -> None:
    """A stop signal arrived (the first one counts)."""
    if _stops.received is None:
        _stops.received = signal.Signals(signum)


def received() -> signal.Signals | None:
    """The first stop signal this process received, if any."""
    return _stops.received


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


# 1. A run ------------------------------------------------------------------------------------------------------------
class Stoppable(Protocol):
    """What a signal asks to stop: a run's checkpointer (:class:`~sb3_td3x.experiment.run.callbacks.Checkpointer`)."""

    def request_stop(self, signal_name: str, exit_code: int) -> None: ...


class StopOnSignal:
    """While active, a stop signal asks the checkpointers (one per seed of a batch) to save and stop instead of killing
    the process. The first signal restores the previous handlers, so a second one acts at once. Outside the main
    thread this does nothing (Hydra's joblib launcher runs jobs in worker processes, whose main thread is fine)."""

    def __init__(self, *checkpointers: Stoppable) -> None:
        self.checkpointers = checkpointers  # one per seed in a seed batch
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> StopOnSignal:
        if _in_main_thread():
            self.previous = _install(stop_signals(), self._handle)
        return self

    @_ours
    def _handle(self, signum: int, frame: Any) -> None:
        self._restore()
        note_signal(signum)
        for checkpointer in self.checkpointers:
            checkpointer.request_stop(signal.Signals(signum).name, 128 + signum)

    def _restore(self) -> None:
        _restore(self.previous)
        self.previous = {}

    def __exit__(self, *exc: object) -> None:
        self._restore()


# 2. The processes of seeds=[...] --------------------------------------------------------------------------------------
@contextlib.contextmanager
def passed_on(children: list[Any]) -> Iterator[None]:
    """While the processes run, a stop signal to this one is passed on to them (the first makes each checkpoint and
    stop; a second Ctrl+C stops them at once, as it stops a lone run). They run in process groups of their own, so
    this is the only way a signal reaches them; in a SLURM job they stay in this one's, the scheduler signals each
    process itself, and the signal is only noted here."""

    @_ours
    def handle(signum: int, frame: Any) -> None:
        note_signal(signum)
        if jobs.current_job() is not None:
            return
        for child in children:
            if child.pid is not None and child.exitcode is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(child.pid, signum)

    previous = _install(stop_signals(), handle)
    try:
        yield
    finally:
        _restore(previous)


def stop_when_orphaned() -> None:
    """SIGTERM to this process, once, when the process that started it has ended (``run.py`` killed with SIGKILL, say):
    a seed process then checkpoints its seeds and stops instead of training on with nobody to report to. A thread
    watches the parent's pid (Linux's ``PR_SET_PDEATHSIG`` was seen to signal twice here, and a second SIGTERM stops
    a run at once)."""
    import time

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="orphan-watch", daemon=True).start()


# 3. A sweep worker ---------------------------------------------------------------------------------------------------
class SignalInterrupt(KeyboardInterrupt):
    """A signal that arrived while a trial ran; ``signal_name`` is ``"SIGINT"``, ``"SIGTERM"`` (or submitit's)."""

    def __init__(self, signal_name: str) -> None:
        self.signal_name = signal_name
        super().__init__(signal_name)


class HeldSignals:
    """A sweep worker's stop signals, held for as long as the ``with`` block runs: :attr:`received` names the first.

    A signal that lands between Optuna creating a trial and the worker telling Optuna how it ended would leave the
    trial RUNNING with nobody to finish it. So the worker holds the signals: one that arrives is remembered, and the
    worker acts on it at the next safe point, after the trial is created or its result is written. Only while the trial
    runs (:meth:`live`) does a signal act at once: during training the run turns the first one into a checkpoint and a
    clean stop (:class:`StopOnSignal`), and anywhere else in the trial it raises :class:`SignalInterrupt`, which the
    worker records as an interrupted trial. A signal held while the worker waits for the storage's budget lock acts
    once the lock is free; the lock is held only for the moment another worker creates a trial.

    A signal handler raises where the main thread happens to be, and two places must not be interrupted:

    - the study's database code (SQLAlchemy, its drivers, Optuna's storages), which the trial calls to report: an
      interrupt raised as one of SQLite's statements returns (a SELECT most of all) can leave its connection holding
      the lock until the garbage collector finds it, and the worker's next write fails ("database is locked", seen in
      CI after a double Ctrl-C). A signal that lands there is not raised but sent again a millisecond later, until it
      lands outside;
    - a finalizer or a weakref callback run by the garbage collector (SQLAlchemy has some), where Python drops the
      exception with an "Exception ignored" traceback: such a dropped :class:`SignalInterrupt` is sent again too.

    So the interrupt acts in the trial's own code; it is never lost, and no traceback is printed. A signal is sent
    again only while the trial runs: once it has ended, the one remembered in :attr:`received` is acted on.
    """

    def __init__(self) -> None:
        self.received: str | None = None  #: "SIGINT" or "SIGTERM", once one has arrived
        self._previous: dict[int, Any] = {}
        self._active = _in_main_thread()
        self._signals = stop_signals()
        self._live = False  # signals act (raise) now; a signal is sent again only while this holds
        self._live_lock = threading.Lock()  # ... so that none is sent once hold() has begun

    def __enter__(self) -> HeldSignals:
        if self._active:
            self._previous = _install(self._signals, self._remember)
        return self

    def __exit__(self, *exc: object) -> None:
        _restore(self._previous)
        self._previous = {}

    def hold(self) -> None:
        """Remember signals instead of acting on them (again, after :meth:`live`)."""
        with self._live_lock:
            self._live = False
        if self._active:
            _install(self._signals, self._remember)

    @contextlib.contextmanager
    def live(self) -> Iterator[None]:
        """Let signals act while the block runs: each is remembered and raises :class:`SignalInterrupt`."""
        if self._active:
            _install(self._signals, self._interrupt)
            self._live = True
        previous_hook = sys.unraisablehook
        if self._active:
            sys.unraisablehook = self._deliver_again(previous_hook)
        try:
            yield
        finally:
            sys.unraisablehook = previous_hook
            self.hold()

    def _send_again(self, signum: int) -> None:
        """Send ``signum`` to this process again, from another thread a millisecond later, if the trial still runs
        then: it is handled in the main thread wherever that is by then."""

        def send() -> None:
            with self._live_lock:
                if self._live:
                    os.kill(os.getpid(), signum)

        threading.Timer(0.001, send).start()

    def _deliver_again(self, previous: Any) -> Any:
        """An unraisable hook that sends a signal whose :class:`SignalInterrupt` Python dropped (raised in a finalizer or
        a weakref callback) again (:meth:`_send_again`): it is then handled in the main thread's own code, once the
        callback has returned. A signal that lands while the hook starts that thread is sent again too. Anything else
        goes to ``previous``."""

        def hook(unraisable: Any) -> None:
            if not isinstance(unraisable.exc_value, SignalInterrupt):
                previous(unraisable)
                return
            dropped = [unraisable.exc_value]
            while dropped:
                signum = getattr(signal, dropped.pop().signal_name)
                try:
                    self._send_again(signum)
                except SignalInterrupt as another:  # a second signal while the timer starts: raised here, in the
                    dropped.append(another)  # hook, where Python drops it (and prints it) too; sent again as well

        return hook

    @_ours
    def _remember(self, signum: int, frame: Any) -> None:
        self.received = self.received or signal.Signals(signum).name
        note_signal(signum)

    @_ours
    def _interrupt(self, signum: int, frame: Any) -> None:
        self._remember(signum, frame)
        if _in_storage_code(frame):
            self._send_again(signum)  # raised here, it could leave a database connection holding its lock
            return
        raise SignalInterrupt(signal.Signals(signum).name)


#: Where a signal must not raise: the study's database code, whose connection could keep its lock (see HeldSignals).
_STORAGE_MODULES = ("sqlalchemy", "optuna.storages", "sqlite3", "psycopg", "pymysql")


def _in_storage_code(frame: Any) -> bool:
    """Whether ``frame``, or a frame that called it, runs in the database code of :data:`_STORAGE_MODULES`."""
    while frame is not None:
        if frame.f_globals.get("__name__", "").startswith(_STORAGE_MODULES):
            return True
        frame = frame.f_back
    return False


@contextlib.contextmanager
def interrupting() -> Iterator[None]:
    """SIGTERM (``scancel``, ``kill``) raises :class:`KeyboardInterrupt` while the block runs, as Ctrl+C does."""

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = _install((signal.SIGTERM,), interrupt) if _in_main_thread() else {}
    try:
        yield
    finally:
        _restore(previous)


def ignore() -> None:
    """From now on the stop signals do nothing: the process has said what became of its work and only exits."""
    _install((signal.SIGINT, signal.SIGTERM), signal.SIG_IGN)


# 4. The exit ---------------------------------------------------------------------------------------------------------
def killed_by_its_own_requeue(error: subprocess.CalledProcessError) -> bool:
    """Whether ``error`` is submitit's ``scontrol requeue`` killed by SIGTERM or SIGKILL (what SLURM sends to the
    processes of a job it requeues)."""
    command = [str(part) for part in error.cmd] if isinstance(error.cmd, (list, tuple)) else str(error.cmd).split()
    return command[:2] == ["scontrol", "requeue"] and error.returncode in (-signal.SIGTERM, -signal.SIGKILL)


def after_stop(exit_code: int, message: str) -> None:
    """The top level of a run or a sweep worker stopped on a signal, its checkpoint written: end the process.

    - submitit's signal: hand over to submitit's handler, which resubmits the function and requeues the job (or,
      after ``max_num_timeout`` time-outs, ends it with an error); it exits this process. Its ``scontrol requeue``
      stopped by the requeue's own SIGTERM exits this process too, without a result.
    - SIGTERM or SIGINT inside a SLURM job: exit without a result (``SystemExit``), so that submitit reads the
      result of the job that SLURM starts again after a requeue, or sees a cancelled job end without one.
    - otherwise: return; the caller exits as it always did.
    """
    got = _stops.received
    if got is None:
        return
    if got == requeue_signal() and _stops.scheduler_handler is not None:
        print(f"{message} Handing over to submitit to requeue the job.", file=sys.stderr, flush=True)
        try:
            _stops.scheduler_handler(int(got), None)
        except subprocess.CalledProcessError as error:
            if not killed_by_its_own_requeue(error):
                raise
            # SLURM signals every process of a job it requeues, submitit's `scontrol requeue` among them when it has
            # not returned yet (seen on a loaded machine): the requeue was taken. submitit would raise, and its
            # process_job would write that error as the job's result, which whoever waits on the job reads as its
            # end. Exit without a result instead, as submitit does after a requeue: the job's next start writes it.
            print(
                f"`{' '.join(map(str, error.cmd))}` was stopped by {signal.Signals(-error.returncode).name}, as SLURM "
                "stops every process of a job it requeues: the job is requeued (or, at its time limit, ended); this "
                "start exits without a result.",
                file=sys.stderr,
                flush=True,
            )
            raise SystemExit(-1) from None
        return
    if jobs.current_job() is not None:
        print(message, file=sys.stderr, flush=True)
        raise SystemExit(exit_code)
