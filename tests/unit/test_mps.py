"""CUDA MPS for several processes on one GPU: the decision, and the daemon's start and stop around a launch.

The machine of CI has no GPU: the decision steps aside there (the first test, with the machine as it is). The start
and stop are checked with a stand-in for ``nvidia-cuda-mps-control`` that records how it was called (the real daemon
needs a GPU: scripts/gpu_session.sh runs the 16-seed benchmark with it on a lent one).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
import torch

from sb3_td3x.experiment.launch import mps


def test_on_this_machine_the_decision_steps_aside_with_its_reason(tmp_path):
    decision = mps.decide(processes=4, wants_gpu=True, enabled=True, folder=tmp_path)
    if not torch.cuda.is_available():
        assert not decision.start and decision.pipe is None and decision.reason == "no CUDA GPU on this machine"
    assert mps.decide(4, wants_gpu=False, enabled=True, folder=tmp_path).reason == "the processes run on the CPU"
    assert mps.decide(1, wants_gpu=True, enabled=True, folder=tmp_path).reason == "one process at a time: nothing to share"
    assert mps.decide(4, wants_gpu=True, enabled=False, folder=tmp_path).reason.startswith("mps=false")


@pytest.fixture
def fake_control(tmp_path, monkeypatch):
    """A stand-in ``nvidia-cuda-mps-control`` that logs its arguments, its pipe folder and its standard input, and
    makes the pipe's ``control`` file as the daemon does."""
    log = tmp_path / "calls.log"
    script = tmp_path / "bin" / mps.CONTROL
    script.parent.mkdir()
    script.write_text(
        "#!/bin/bash\n"
        f'echo "args=$* pipe=$CUDA_MPS_PIPE_DIRECTORY stdin=$([ "$1" = -d ] || cat)" >> {log}\n'
        '[ "$1" = -d ] && touch "$CUDA_MPS_PIPE_DIRECTORY/control"\n'
        "exit 0\n"
    )
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", f"{script.parent}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.delenv(mps.PIPE_ENV, raising=False)
    return script, log


def test_a_daemon_is_started_for_the_processes_and_stopped_at_the_end(fake_control, tmp_path):
    script, log = fake_control
    folder = tmp_path / "mps"
    decision = mps.decide(3, wants_gpu=True, enabled=True, folder=folder, cuda_check=lambda: True)
    assert decision.start and decision.pipe == folder / "pipe"
    said = []
    with mps.SharedGpu(decision, folder, say=said.append):
        assert os.environ[mps.PIPE_ENV] == str(folder / "pipe")  # what the processes started here inherit
        assert mps.running_daemon() == folder / "pipe"
    assert mps.PIPE_ENV not in os.environ and not folder.exists()  # the launch's own folder, removed
    calls = log.read_text().splitlines()
    assert calls == [f"args=-d pipe={folder / 'pipe'} stdin=", f"args= pipe={folder / 'pipe'} stdin=quit"]
    assert len(said) == 1 and "started an MPS control daemon" in said[0] and "stops at the end" in said[0]


def test_a_running_daemon_is_used_and_left_running(fake_control, tmp_path, monkeypatch):
    script, log = fake_control
    theirs = tmp_path / "their-pipe"
    theirs.mkdir()
    (theirs / "control").touch()
    monkeypatch.setenv(mps.PIPE_ENV, str(theirs))
    decision = mps.decide(3, wants_gpu=True, enabled=True, folder=tmp_path / "mps", cuda_check=lambda: True)
    assert not decision.start and decision.pipe == theirs and "already runs" in decision.reason
    with mps.SharedGpu(decision, tmp_path / "mps", say=lambda line: None):
        pass
    assert not log.exists(), "neither started nor stopped"
    assert os.environ[mps.PIPE_ENV] == str(theirs)


def test_without_the_binary_the_processes_share_by_time_slices(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    decision = mps.decide(3, wants_gpu=True, enabled=True, folder=tmp_path, cuda_check=lambda: True)
    assert not decision.start and decision.pipe is None and "is not installed" in decision.reason


CONF = Path(__file__).resolve().parents[2] / "conf"


def test_a_multirun_on_this_machine_decides_from_its_command_line(fake_control, monkeypatch, capsys):
    from sb3_td3x.experiment.cli import check_command_line

    def launch(*args: str) -> None:
        command = check_command_line(list(args), CONF)
        with command.launch.shared_gpu(command.device, command.mps):
            pass

    script, log = fake_control
    launch("seed=0", "debug=smoke")  # not a multirun
    launch("-m", "seed=0,1", "device=cpu")  # on the CPU
    launch("-m", "seed=0,1", "hydra/launcher=submitit_slurm", "device=cuda")  # the cluster decides
    assert not log.exists() and capsys.readouterr().err == ""
    monkeypatch.setattr(mps, "has_cuda", lambda: True)  # as on a GPU machine
    launch("-m", "seed=0,1,2", "hydra.launcher.n_jobs=1")  # one job at a time
    assert not log.exists() and capsys.readouterr().err == ""  # nothing to share, nothing to say
    launch("-m", "seed=0,1,2", "mps=false")
    assert not log.exists() and "mps=false" in capsys.readouterr().err
    command = check_command_line(["-m", "seed=0,1,2", "hydra.launcher.n_jobs=2"], CONF)
    with command.launch.shared_gpu(command.device, command.mps):
        assert mps.running_daemon() is not None
    err = capsys.readouterr().err
    assert "2 processes share the GPU: started an MPS control daemon" in err, err
    assert [line.split()[0] for line in log.read_text().splitlines()] == ["args=-d", "args="]


def test_local_sweep_workers_share_the_gpu_only_while_wait_waits(fake_control, monkeypatch, capsys):
    from sb3_td3x.sweeps.cli import main
    from sb3_td3x.sweeps.launch import SweepWorkers

    def workers(cluster: str, wait: bool) -> SweepWorkers:
        return SweepWorkers(cluster, {}, 2, [], main, wait, Path("study"))

    script, log = fake_control
    monkeypatch.setattr(mps, "has_cuda", lambda: True)
    with workers("local", wait=False).shared_gpu("auto", True, say=print):  # without --wait nothing would stop a daemon
        pass
    assert not log.exists() and "without --wait nothing would stop it" in capsys.readouterr().out
    with workers("slurm", wait=True).shared_gpu("auto", True, say=print):  # the cluster decides
        pass
    with workers("local", wait=True).shared_gpu("cpu", True, say=print):
        pass
    assert not log.exists()
    with workers("local", wait=True).shared_gpu("auto", True, say=print):
        assert mps.running_daemon() is not None
    assert [line.split()[0] for line in log.read_text().splitlines()] == ["args=-d", "args="]
