"""The scheduler job a process runs in, and how a requeued job finds its run folder (by its id, not the clock).

The cluster layer (tests/cluster) runs all of it on a real SLURM; these tests pin the rules without one, with the
environment SLURM gives a job.
"""

from __future__ import annotations

import json
import signal
import subprocess

import pytest

from sb3_td3x.experiment import jobs, stops
from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.configs.schemas import _records_subdir
from sb3_td3x.experiment.launch.hydra_jobs import JOBLIB, SUBMITIT_LOCAL, HydraJobs
from sb3_td3x.experiment.launch.job_watch import read_scontrol
from sb3_td3x.experiment.run.folder import (
    NEW,
    REQUEUED,
    RESTARTED,
    RunFolder,
    check_new,
    folder_to_train_in,
    requeued_folder,
    where_to_start,
)
from sb3_td3x.experiment.run.lock import RunFolderBusy, RunFolderLock

SLURM_VARS = ("SLURM_JOB_ID", "SLURM_CLUSTER_NAME", "SLURM_RESTART_COUNT", "SLURM_ARRAY_JOB_ID", "SLURM_ARRAY_TASK_ID",
              "SLURM_CPUS_PER_TASK", "SLURM_CPUS_ON_NODE", "SUBMITIT_FOLDER")  # fmt: skip


@pytest.fixture
def job(monkeypatch):
    """Act as SLURM job 42 of cluster c1: ``job(restarts)`` sets its start."""
    for name in SLURM_VARS:
        monkeypatch.delenv(name, raising=False)

    def start(restarts: int | None, job_id: str = "42") -> None:
        if restarts is None:
            monkeypatch.delenv("SLURM_JOB_ID", raising=False)
            return
        monkeypatch.setenv("SLURM_JOB_ID", job_id)
        monkeypatch.setenv("SLURM_CLUSTER_NAME", "c1")
        monkeypatch.setenv("SLURM_RESTART_COUNT", str(restarts))

    return start


def _session(folder, **job_record):
    folder.mkdir(parents=True, exist_ok=True)
    record = {"started": "2026-01-01T00:00:00", "at_step": 0, "start": NEW}
    if job_record:
        record["job"] = {"scheduler": "slurm", "cluster": "c1", "name": job_record["job_id"], **job_record}
    with open(folder / "provenance.jsonl", "a") as file:
        file.write(json.dumps(record) + "\n")
    (folder / "config.yaml").write_text("seed: 0\n")


def test_current_job_reads_slurms_environment(job, monkeypatch):
    job(None)
    assert jobs.current_job() is None and jobs.job_cores() is None
    job(2)
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "41")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "1")
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "3")
    current = jobs.current_job()
    assert (current.job_id, current.name, current.cluster, current.restarts) == ("42", "41_1", "c1", 2)
    assert jobs.job_cores() == 3
    assert current.is_earlier_run_of_this_job({"scheduler": "slurm", "cluster": "c1", "job_id": "42", "restarts": 1})
    assert not current.is_earlier_run_of_this_job({"scheduler": "slurm", "cluster": "c1", "job_id": "42", "restarts": 2})
    assert not current.is_earlier_run_of_this_job({"scheduler": "slurm", "cluster": "c2", "job_id": "42", "restarts": 0})
    assert not current.is_earlier_run_of_this_job({"scheduler": "slurm", "cluster": "c1", "job_id": "43", "restarts": 0})
    assert not current.is_earlier_run_of_this_job(None)


def test_a_requeued_job_finds_its_folder_by_its_id_not_by_the_clock(job, tmp_path):
    seed_dir = tmp_path / "runs" / "pendulum" / "td3" / "seed0"
    mine, other = seed_dir / "2026-01-01_10-00-00", seed_dir / "2026-01-01_10-00-05"
    _session(mine, job_id="42", restarts=0)
    _session(other, job_id="7", restarts=0)  # another job's run, started later
    new_name = seed_dir / "2026-01-01_11-30-00"  # what ${now} names when the job starts again
    job(0)
    assert requeued_folder(new_name) is None and folder_to_train_in(None, str(new_name)) == new_name
    job(1)
    assert requeued_folder(new_name) == mine and folder_to_train_in(None, str(new_name)) == mine
    assert requeued_folder(mine) == mine  # a fixed run_dir, or a multirun job's folder
    assert folder_to_train_in(str(other), str(new_name)) == other  # resume= decides
    job(None)
    assert requeued_folder(new_name) is None


def test_hydras_record_of_a_launch_goes_beside_the_first_ones():
    """conf/config.yaml passes SLURM_RESTART_COUNT (read in the job itself): a requeued job's record, or a resume's,
    goes beside the first launch's ``.hydra``."""
    assert _records_subdir(None, 0) == ".hydra" and _records_subdir(None, "0") == ".hydra"
    assert _records_subdir(None, "2") == ".hydra/requeued_2"
    assert _records_subdir("runs/x", "0").startswith(".hydra/resumed_")


def test_a_job_continues_only_its_own_earlier_start(job, tmp_path):
    folder = tmp_path / "run"
    _session(folder, job_id="42", restarts=1)
    job(1)  # the same start again (a second run.py in one job script): a new run, refused as usual
    with pytest.raises(Exception, match="already holds a run"):
        check_new(folder)
    job(2)
    check_new(folder)  # its own earlier start: continued
    job(2, job_id="43")
    with pytest.raises(Exception, match="already holds a run"):
        check_new(folder)


def test_where_to_start_resumes_with_a_checkpoint_and_restarts_without(job, tmp_path):
    folder = tmp_path / "run"
    _session(folder, job_id="42", restarts=0)
    cfg = compose_config([f"run_dir={folder}", "debug=smoke"])
    job(1)
    start = where_to_start(cfg)
    assert (start.run_dir, start.resume, start.how) == (folder, None, RESTARTED)
    meta = folder / "checkpoints" / "last" / "meta.json"
    meta.parent.mkdir(parents=True)
    meta.write_text(json.dumps({"num_timesteps": 1000}))
    start = where_to_start(cfg)
    assert (start.run_dir, start.resume, start.how) == (folder, folder, REQUEUED)


def test_a_second_live_owner_is_refused_even_for_the_requeued_job(job, tmp_path):
    folder = tmp_path / "run"
    _session(folder, job_id="42", restarts=0)
    held = RunFolderLock.acquire(folder)  # still owned (say, by a start that has not ended)
    try:
        job(1)
        with pytest.raises(RunFolderBusy):
            check_new(folder)
        with pytest.raises(RunFolderBusy):
            RunFolder.claim(folder, REQUEUED)
    finally:
        held.release()
    RunFolder.claim(folder, REQUEUED).release()


def test_torch_threads_follow_the_jobs_cores(job, monkeypatch):
    def threads(multirun: bool, launcher: dict) -> int | None:
        return HydraJobs(launcher, multirun).threads_per_process(8)

    job(None)
    assert threads(False, {}) is None
    assert threads(True, {"_target_": JOBLIB, "n_jobs": 1}) == 8 and threads(True, {"_target_": JOBLIB, "n_jobs": 2}) == 4
    assert threads(True, {"_target_": SUBMITIT_LOCAL, "cpus_per_task": 3, "timeout_min": 60}) == 3
    assert threads(True, {"timeout_min": 60}) is None  # no say of the launcher: torch's default
    job(0)
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "2")
    assert threads(False, {}) == 2 and threads(True, {"_target_": JOBLIB, "n_jobs": -1}) == 2


def test_scontrol_lines_become_submitits_job_infos():
    text = (
        "JobId=12 ArrayJobId=11 ArrayTaskId=1 JobName=run UserId=root(0) JobState=PENDING Reason=BeginTime "
        "Requeue=1 Restarts=1 BatchFlag=1 ExitCode=0:0 NodeList=(null)\n"
        "JobId=13 JobName=x JobState=COMPLETED Reason=None Restarts=0 ExitCode=0:0 NodeList=vm\n"
    )
    infos = read_scontrol(text)
    assert infos["11_1"]["State"] == "PENDING" and infos["11_1"]["Restarts"] == "1"
    assert infos["13"]["State"] == "COMPLETED" and infos["13"]["NodeList"] == "vm"


def test_outside_a_submitit_job_the_stop_signals_are_sigint_and_sigterm(job, monkeypatch):
    import signal

    job(0)
    assert stops.stop_signals() == (signal.SIGINT, signal.SIGTERM)
    monkeypatch.setenv("SUBMITIT_FOLDER", "/tmp/x")
    assert stops.stop_signals() == (signal.SIGINT, signal.SIGTERM, signal.SIGUSR2)
    monkeypatch.setenv("SUBMITIT_PREEMPT_SIGNAL", "USR1")
    assert stops.requeue_signal() == signal.SIGUSR1


def test_a_requeued_worker_fails_and_queues_again_the_trial_its_earlier_start_left_running(job, tmp_path):
    """A worker job killed before it could record its trial (SIGKILL past KillWait) finds that trial when SLURM starts
    it again: its earlier start has ended, so the trial is failed and queued to resume at once, not after the
    heartbeat's grace period. Trials of other jobs, and of this start, are left alone."""
    import optuna
    from optuna.trial import TrialState

    from sb3_td3x.sweeps.objective import RESUMABLE
    from sb3_td3x.sweeps.worker import fail_trials_of_earlier_start

    study = optuna.create_study(storage=f"sqlite:///{tmp_path / 'study.db'}", study_name="s")
    record = {"scheduler": "slurm", "cluster": "c1", "name": "42"}
    for job_record in ({**record, "job_id": "42", "restarts": 0}, {**record, "job_id": "7", "restarts": 0}, None):
        trial = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)})
        trial.set_user_attr("job", job_record)
        trial.set_user_attr("run_dir", str(tmp_path / f"trial_{trial.number:04d}"))
    job(0)
    assert fail_trials_of_earlier_start(study) == []  # the first start: nothing of an earlier one
    job(1)
    assert fail_trials_of_earlier_start(study) == [0]
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.RUNNING, TrialState.RUNNING, TrialState.WAITING]
    assert "was stopped (requeued) before it recorded the trial" in trials[0].user_attrs["fail_reason"]
    assert trials[3].user_attrs[RESUMABLE] and trials[3].user_attrs["run_dir"] == trials[0].user_attrs["run_dir"]
    assert trials[3].params == trials[0].params
    assert fail_trials_of_earlier_start(study) == []  # once


@pytest.mark.parametrize(
    ("returncode", "command", "ends"),
    [
        (-signal.SIGTERM, ["scontrol", "requeue", "42"], SystemExit),  # the requeue's own SIGTERM: requeued
        (-signal.SIGKILL, ["scontrol", "requeue", "42"], SystemExit),
        (1, ["scontrol", "requeue", "42"], subprocess.CalledProcessError),  # refused: submitit's error stands
        (-signal.SIGTERM, ["scontrol", "show", "job"], subprocess.CalledProcessError),
    ],
)
def test_submitits_requeue_stopped_by_the_requeue_exits_without_a_result(job, monkeypatch, capsys, returncode, command, ends):
    """submitit's ``scontrol requeue`` stopped by the SIGTERM that SLURM sends to every process of a job it requeues
    (a cluster test met it on a loaded machine): the job is requeued, so the process exits without a result
    (SystemExit, as submitit after a requeue), not with submitit's error, which would be read as the job's end."""
    job(0)
    monkeypatch.setenv("SUBMITIT_FOLDER", "/tmp/submitit")
    told = stops._Stops()
    told.received = stops.requeue_signal()

    def handler(signum, frame):
        raise subprocess.CalledProcessError(returncode, command)

    told.scheduler_handler = handler
    monkeypatch.setattr(stops, "_stops", told)
    with pytest.raises(ends) as raised:
        stops.after_stop(0, "Stopped on SIGUSR2.")
    if ends is SystemExit:
        assert raised.value.code == -1
        assert "this start exits without a result" in capsys.readouterr().err
