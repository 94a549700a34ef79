"""Bad input to run.py: a non-zero exit and a one-paragraph message saying what was wrong, never a traceback.

Two cases run ``run.py`` in a subprocess (the check before Hydra, and an error raised inside the task); the
others call the same functions in-process, which is faster and checks the same message and exit status.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from sb3_td3x.experiment.cli import EXIT_CONFIG_ERROR, check_command_line
from sb3_td3x.experiment.configs.schemas import CONF_DIR

REPO = Path(__file__).resolve().parents[2]


def run_py(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], check=False, cwd=REPO, capture_output=True, text=True, timeout=120
    )


def assert_one_paragraph(message: str, *needles: str) -> None:
    assert "Traceback" not in message
    message = message.strip()
    assert message.startswith("Error:") and "\n" not in message, message
    for needle in needles:
        assert needle in message, message


def test_unknown_env(tmp_path):
    result = run_py("env=antt", f"run_dir={tmp_path}/run")
    assert result.returncode == EXIT_CONFIG_ERROR
    assert "Traceback" not in result.stdout
    assert_one_paragraph(result.stderr, "env=antt", "Did you mean env=ant?", "halfcheetah")
    assert not (tmp_path / "run").exists()


def test_out_of_range_values_fail_before_training(tmp_path):
    result = run_py("algo.tau=2", "total_timesteps=-1", f"run_dir={tmp_path}/run")
    assert result.returncode == EXIT_CONFIG_ERROR
    assert "Traceback" not in result.stdout
    assert_one_paragraph(result.stderr, "algo.tau=2.0 must be a float in [0, 1]", "total_timesteps=-1 must be a positive")
    assert not (tmp_path / "run" / "checkpoints").exists()


def exit_message(args: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_info:
        check_command_line(args, CONF_DIR)
    assert exit_info.value.code == EXIT_CONFIG_ERROR
    return capsys.readouterr().err


def test_unknown_env_in_a_multirun_sweep(capsys):
    assert_one_paragraph(exit_message(["-m", "env=ant,hoper", "seed=0,1"], capsys), "env=hoper", "env=hopper")


def test_resume_of_a_folder_that_does_not_exist(tmp_path, capsys):
    assert_one_paragraph(exit_message([f"resume={tmp_path}/nowhere"], capsys), "no such folder")


def test_resume_of_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert_one_paragraph(exit_message([f"resume={tmp_path}"], capsys), "config.yaml does not exist")


def test_resume_of_a_run_without_checkpoint(tmp_path, capsys):
    (tmp_path / "config.yaml").write_text("seed: 0\n")  # a run killed before its first checkpoint
    assert_one_paragraph(exit_message([f"resume={tmp_path}"], capsys), f"resume={tmp_path}", "no complete checkpoint")


def test_good_command_lines_pass_the_check(tmp_path):
    check_command_line(["-m", "env=ant,hopper", "algo=td3,ddpg", "seed=0,1", "video=final", "algo.tau=0.01"], CONF_DIR)
