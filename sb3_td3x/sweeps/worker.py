"""A sweep worker: takes trials from the shared study until its budget of trials is spent.

Any number of workers, on one machine or many, may run against the same storage and study name. Each loop:

1. under the storage's budget lock (:mod:`sb3_td3x.sweeps.storage`), mark trials of dead workers FAIL (heartbeat),
   count the study's trials and, if fewer than ``n_trials`` (or a trial is queued), create the next one;
2. run it (:class:`~sb3_td3x.sweeps.objective.TrialObjective`) while a heartbeat thread keeps it alive;
3. tell Optuna how it ended: COMPLETE with its value, PRUNED, or FAIL with ``fail_reason`` in its user attributes.

When the budget is spent the worker waits for trials still running elsewhere to end (or to be marked FAIL by the
heartbeat), and the last worker writes the results (:mod:`sb3_td3x.sweeps.results`).

Three rules keep the study's records true:

* Every worker of a study uses the heartbeat settings the study was created with (recorded in its user attributes),
  so that no worker marks another's healthy trial stale.
* A worker that was cut off for longer than the grace period finds its trial already FAIL when it comes back. It
  stops the trial at its next evaluation, keeps what it measured as the study's user attribute
  ``late_result_trial_<n>`` (:func:`keep_late_result`) and goes on with the next trial.
* SIGINT and SIGTERM are held while a trial is created and while its result is recorded
  (:class:`sb3_td3x.experiment.stops.HeldSignals`). During training the runner checkpoints and stops; the worker then marks the trial
  FAIL ("interrupted"), queues a copy with the same parameters (which resumes from the checkpoint) and stops with
  :class:`SweepInterrupted`, whose message says what became of the trial.
"""

from __future__ import annotations

import datetime
import logging
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import optuna
from optuna.storages import RetryHeartbeatStaleTrialCallback, fail_stale_trials
from optuna.trial import FrozenTrial, TrialState

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment.stops import HeldSignals
from sb3_td3x.sweeps.errors import SweepError
from sb3_td3x.sweeps.objective import RESUMABLE, TrialObjective, TrialResult, worker_id
from sb3_td3x.sweeps.spec import SweepSpec
from sb3_td3x.sweeps.storage import StudyStorage, heartbeat

logger = logging.getLogger(__name__)

#: How often a worker with nothing left to start looks whether the others' trials have ended.
WAIT_POLL_S = 2.0

#: The study's user attribute that holds the heartbeat settings it was created with.
HEARTBEAT_ATTR = "heartbeat"

#: Study user attribute ``late_result_trial_<n>``: what a cut-off worker measured on trial n after it was failed.
LATE_RESULT_PREFIX = "late_result_trial_"


class SweepInterrupted(Exception):
    """The worker was stopped by Ctrl-C or SIGTERM; ``what`` says what became of its trial."""

    def __init__(self, trial_number: int | None, what: str) -> None:
        self.trial_number = trial_number
        super().__init__(f"Interrupted: {what}; run the same command again to continue the study.")


@dataclass
class WorkerSummary:
    """What one worker did, for its last log line and for tests."""

    ran: list[int]  #: numbers of the trials this worker ran
    study_finished: bool  #: no trial left to run or running anywhere; this worker wrote the results


def open_study(spec: SweepSpec, study_storage: StudyStorage, study_name: str, fixed_overrides: list[str]) -> optuna.Study:
    """Create the study, or load it when it exists; check that it tunes the same thing in the same direction."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        study = optuna.create_study(
            storage=study_storage.storage,
            study_name=study_name,
            direction=spec.direction,
            sampler=spec.make_sampler(),
            pruner=spec.make_pruner(),
            load_if_exists=True,
        )
    if study.direction.name.lower() != spec.direction:
        raise SweepError(
            f"study {study_name!r} in {study_storage.display_url} was created to {study.direction.name.lower()}, "
            f"but {spec.source} says direction: {spec.direction}; use another --study-name"
        )
    space = {param.path: repr(param.distribution) for param in spec.params}
    fixed_overrides = redact(fixed_overrides)  # the study's records hold no secret
    recorded = study.user_attrs.get("search_space")
    if recorded is None:
        if study_storage.heartbeat_settings() is not None:  # what decides staleness, shared by every worker
            study.set_user_attr(HEARTBEAT_ATTR, study_storage.heartbeat_settings())
        study.set_user_attr("search_space", space)
        study.set_user_attr("metric", spec.metric)
        study.set_user_attr("sweep_file", redact(str(spec.source)))
        study.set_user_attr("overrides", fixed_overrides)
    elif recorded != space or study.user_attrs.get("overrides") != fixed_overrides:
        logger.warning(
            "study %s was started with another search space or other fixed overrides than %s now gives; "
            "earlier trials keep theirs (see their user attributes), new trials use the new ones",
            study_name,
            spec.source,
        )
    return study


def budget_used(trials: list[FrozenTrial]) -> int:
    """Trials that count against ``n_trials``: all of them, except failed ones that were queued again."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        retried = {RetryHeartbeatStaleTrialCallback.retried_trial_number(t) for t in trials} - {None}
    return len(trials) - len(retried)


def claim_trial(study: optuna.Study, spec: SweepSpec, study_storage: StudyStorage, n_trials: int) -> optuna.Trial | None:
    """Create the next trial, or take a queued one; ``None`` when the study has its ``n_trials``.

    Runs under the budget lock, so that two workers never both take the last slot.
    """
    with study_storage.budget_lock(), warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        # ask() warns that heartbeats are meant for Study.optimize; this loop records them itself (storage.heartbeat)
        warnings.filterwarnings("ignore", message="Heartbeat of storage is supposed to be used", category=UserWarning)
        fail_trials_of_earlier_start(study)
        fail_stale_trials(study)
        trials = study.get_trials(deepcopy=False)
        queued = any(t.state == TrialState.WAITING for t in trials)
        if not queued and budget_used(trials) >= n_trials:
            return None
        # Reseed per trial: workers sharing the sampler seed would otherwise draw the same startup points.
        study.sampler = spec.make_sampler(seed_offset=len(trials))
        trial = study.ask()
        if study_storage.heartbeat_interval is not None:  # a trial without any heartbeat could never go stale
            study_storage.storage.record_heartbeat(trial._trial_id)
        return trial


def fail_trials_of_earlier_start(study: optuna.Study) -> list[int]:
    """In a SLURM job that started again (requeued), the trials its earlier start left RUNNING: that start has
    ended (SLURM starts a job again only once it has), so each is marked FAIL and queued again at once, resuming
    from its folder's checkpoint, instead of waiting for the heartbeat's grace period. Returns their numbers."""
    from sb3_td3x.experiment import jobs

    job = jobs.current_job()
    if job is None or job.restarts == 0:
        return []
    failed = []
    for frozen in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        if not job.is_earlier_run_of_this_job(frozen.user_attrs.get("job")):
            continue
        reason = f"its worker, SLURM job {job.name}, was stopped (requeued) before it recorded the trial"
        study._storage.set_trial_user_attr(frozen._trial_id, "fail_reason", reason)
        study._storage.set_trial_user_attr(frozen._trial_id, RESUMABLE, True)
        try:
            study._storage.set_trial_state_values(frozen._trial_id, state=TrialState.FAIL)
        except optuna.exceptions.UpdateFinishedTrialError:
            continue
        requeue(study, frozen.number)
        logger.info("trial %d: %s; queued again to resume from its checkpoint", frozen.number, reason)
        failed.append(frozen.number)
    return failed


def check_heartbeat_settings(study: optuna.Study, study_storage: StudyStorage, record: bool = True) -> None:
    """Refuse this worker's heartbeat settings when they differ from the study's (recorded by :func:`open_study`):
    a worker with a shorter grace period would fail the healthy trials of the others. A study made before the
    settings were recorded gets this worker's (``record``)."""
    mine = study_storage.heartbeat_settings()
    if mine is None:  # no heartbeat (journal storage): nothing can go stale
        return
    with study_storage.budget_lock():  # two workers creating the study together record one setting
        recorded = study.user_attrs.get(HEARTBEAT_ATTR)
        if recorded is None:
            if record:
                study.set_user_attr(HEARTBEAT_ATTR, mine)
            return
    if recorded == mine:
        return
    theirs_interval, theirs_grace = recorded.get("heartbeat_interval"), recorded.get("grace_period")
    raise SweepError(
        f"study {study.study_name!r} in {study_storage.display_url} was created with a heartbeat interval of "
        f"{theirs_interval}s and a grace period of {theirs_grace}s, but this worker has --heartbeat-interval "
        f"{mine['heartbeat_interval']} and a grace period of {mine['grace_period']}s. Every worker of a study must use "
        f"the same ones, or a worker with a shorter grace period marks other workers' healthy trials FAIL. Start this "
        f"worker with --heartbeat-interval {theirs_interval} --grace-period {theirs_grace}, or use another --study-name."
    )


def tell(study: optuna.Study, trial: optuna.Trial, result: TrialResult) -> None:
    if result.reason is not None:
        trial.set_user_attr("fail_reason" if result.state == TrialState.FAIL else "prune_reason", redact(result.reason))
    if result.state == TrialState.COMPLETE:
        study.tell(trial, result.value)
        logger.info("trial %d finished: %s = %.3f", trial.number, study.user_attrs.get("metric", "value"), result.value)
    else:
        study.tell(trial, state=result.state)
        logger.info("trial %d %s: %s", trial.number, result.state.name, result.reason)


def record(study: optuna.Study, trial: optuna.Trial, result: TrialResult) -> bool:
    """Tell Optuna how the trial ended and queue an interrupted one again; ``False`` when another worker had already
    finished it, whose result then goes to :func:`keep_late_result` instead."""
    if not result.finished_elsewhere and not _is_finished(study, trial):
        try:
            if result.interrupted:
                trial.set_user_attr(RESUMABLE, True)  # its queued copy continues from the checkpoint
            tell(study, trial, result)
            if result.interrupted:
                requeue(study, trial.number)
            return True
        except (optuna.exceptions.UpdateFinishedTrialError, ValueError):  # ValueError: "Cannot tell a FAIL trial"
            if not _is_finished(study, trial):
                raise
    keep_late_result(study, trial, result)
    return False


def _is_finished(study: optuna.Study, trial: optuna.Trial) -> bool:
    return study._storage.get_trial(trial._trial_id).state.is_finished()


def keep_late_result(study: optuna.Study, trial: optuna.Trial, result: TrialResult) -> None:
    """Keep what this worker measured on a trial another worker had finished, as the study's user attribute
    ``late_result_trial_<n>``: the trial's own record stays as the study decided it."""
    state = study._storage.get_trial(trial._trial_id).state
    late = {
        "value": result.value,
        "step": result.step,
        "outcome": "stopped" if result.finished_elsewhere else result.state.name,
        "reason": redact(result.reason) if result.reason else None,
        "worker": worker_id(),
        "state_in_study": state.name,
        "recorded": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    study.set_user_attr(f"{LATE_RESULT_PREFIX}{trial.number}", late)
    logger.warning(
        "trial %d was marked %s by another worker while this one was cut off (no heartbeat for longer than the grace "
        "period); its result here (value %s at step %s) is kept as the study's user attribute %s%d",
        trial.number,
        state.name,
        result.value,
        result.step,
        LATE_RESULT_PREFIX,
        trial.number,
    )


def requeue(study: optuna.Study, trial_number: int) -> None:
    """Queue a copy of a failed trial with the same parameters (Optuna's retry, which links the two)."""
    frozen = next(t for t in study.get_trials(deepcopy=True) if t.number == trial_number)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        RetryHeartbeatStaleTrialCallback(max_retry=None)(study, frozen)


def run_worker(
    study: optuna.Study,
    spec: SweepSpec,
    study_storage: StudyStorage,
    objective: TrialObjective,
    n_trials: int,
    max_consecutive_failures: int = 5,
    on_finished: Callable[[optuna.Study], None] | None = None,
) -> WorkerSummary:
    """Run trials until the study holds ``n_trials`` and none is running; see the module docstring.

    :param max_consecutive_failures: stop this worker after so many trials in a row crashed (not diverged):
        that is a bug or a broken setup, not a bad hyper-parameter
    :param on_finished: called with the study once no trial is left anywhere (writes the results)
    :raises SweepError: the heartbeat settings differ from the study's, or too many trials crashed in a row
    :raises SweepInterrupted: SIGINT or SIGTERM arrived
    """
    check_heartbeat_settings(study, study_storage)
    ran: list[int] = []
    crashes: list[str] = []
    with HeldSignals() as signals:
        while True:
            trial = claim_trial(study, spec, study_storage, n_trials)
            if trial is None:
                finished = _wait_for_others(study, study_storage, signals)
                if signals.received:
                    raise SweepInterrupted(None, "no trial of this worker was running")
                if not finished:
                    return WorkerSummary(ran, study_finished=False)
                if any(t.state == TrialState.WAITING for t in study.get_trials(deepcopy=False)):
                    continue  # a dead worker's trial was queued again: run it
                if on_finished is not None:
                    on_finished(study)
                return WorkerSummary(ran, study_finished=True)

            result = _run_trial(trial, objective, study_storage, signals)
            told = record(study, trial, result)
            ran.append(trial.number)
            if signals.received or result.interrupted:
                raise SweepInterrupted(trial.number, _what_became_of(trial.number, result, told))
            if result.crashed:
                crashes.append(
                    f"trial {trial.number}: {result.reason} (see {objective.run_dir(trial.number)}/sweep_error.txt)"
                )
                if len(crashes) >= max_consecutive_failures:
                    raise SweepError(
                        f"{len(crashes)} trials in a row crashed, so this worker stopped; the last ones:\n  "
                        + "\n  ".join(crashes[-3:])
                    )
            else:
                crashes.clear()


def _run_trial(
    trial: optuna.Trial, objective: TrialObjective, study_storage: StudyStorage, signals: HeldSignals
) -> TrialResult:
    """Train the trial with signals acting; one that arrived while it was created ends it before it starts."""
    if signals.received:
        return TrialResult(TrialState.FAIL, reason=f"interrupted by {signals.received} before it started", interrupted=True)
    result = None
    try:
        with heartbeat(study_storage, trial._trial_id), signals.live():
            result = objective(trial)
    except KeyboardInterrupt:  # a signal outside the runner's own handling (composing the config, a second Ctrl-C)
        signals.hold()
    if result is None:
        return TrialResult(TrialState.FAIL, reason=f"interrupted by {signals.received or 'SIGINT'}", interrupted=True)
    if signals.received and result.state == TrialState.FAIL and not (result.interrupted or result.finished_elsewhere):
        # A library that caught the interrupt and raised its own error (Hydra's composition, half-built objects):
        # the signal ended the trial, so it is queued again rather than counted as a crash.
        reason = f"interrupted by {signals.received} ({result.reason})"
        return TrialResult(TrialState.FAIL, reason=reason, interrupted=True, step=result.step)
    return result


def _what_became_of(number: int, result: TrialResult, told: bool) -> str:
    """The truth about a trial whose worker stops on a signal, for :class:`SweepInterrupted`."""
    if not told:
        return (
            f"trial {number} had been finished by another worker; this worker's result is kept as the study's user "
            f"attribute {LATE_RESULT_PREFIX}{number}, and no trial of this worker is running"
        )
    if result.interrupted:
        return f"trial {number} was marked FAIL (interrupted) and queued again"
    return f"trial {number} ended {result.state.name} and was recorded before the worker stopped; no trial of it is running"


def _wait_for_others(study: optuna.Study, study_storage: StudyStorage, signals: HeldSignals) -> bool:
    """Wait until no trial is running in another worker; ``False`` if that cannot be known (no heartbeat) or a
    signal arrived."""
    reported = False
    while not signals.received:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            fail_stale_trials(study)
        running = [t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))]
        if not running:
            return True
        if study_storage.heartbeat_interval is None:
            logger.info(
                "no trial left to start; trials %s are still running elsewhere (this storage has no heartbeat, so a "
                "killed worker's trial stays RUNNING): the last worker to finish writes the results",
                running,
            )
            return False
        if not reported:
            logger.info("no trial left to start; waiting for trials %s running in other workers", running)
            reported = True
        time.sleep(min(study_storage.heartbeat_interval, WAIT_POLL_S))
    return False
