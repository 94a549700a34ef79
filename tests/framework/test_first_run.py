"""The README's first command, ``python run.py``, in a fresh folder: it runs and prints nothing at WARNING level or
above (no logged warning or error, no Python warning), and its screen reads well: no log line cuts the progress bar,
and the value measurement that Pendulum cannot make is one short line (the reason is in summary.json)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# A logged record at WARNING or above ("[...][WARNING] - ...") or a Python warning ("...: UserWarning: ...").
ALARM = re.compile(r"\[(WARNING|ERROR|CRITICAL)\]|\b\w*Warning: ")
# A log line: "[2026-01-01 12:00:00,000][logger][INFO] - message"
LOG_LINE = re.compile(r"\[\d{4}-\d\d-\d\d [\d:,]+\]\[[\w.]+\]\[[A-Z]+\] - ")


def test_the_readme_first_run_prints_no_warning(tmp_path):
    # The README's config, shortened from 10k steps to 1200: the evaluation at step 1000 (the first, where Pendulum's
    # value measurement has no state to use) and one episode of training (200 steps of the 400-300 networks on all
    # the cores, the slowest part) come before the final evaluation.
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HOME": str(tmp_path)}
    result = subprocess.run(
        [sys.executable, str(REPO / "run.py"), "total_timesteps=1200"],
        check=False, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=300,
    )  # fmt: skip
    output = result.stdout  # the log lines (stdout) and the bar (stderr) as a terminal shows them, interleaved
    assert result.returncode == 0, output[-3000:]
    assert "Done: final evaluation" in output
    alarms = [line for line in output.splitlines() if ALARM.search(line)]
    assert not alarms, "\n".join(alarms)
    # tqdm redraws the bar after a carriage return: a log line starts a line, or follows the \r that cleared the bar
    pieces = [piece for line in output.split("\n") for piece in line.split("\r")]
    cut = [piece for piece in pieces if LOG_LINE.search(piece) and not LOG_LINE.match(piece.lstrip())]
    assert not cut, "log lines written into the progress bar:\n" + "\n".join(cut)
    (value_line,) = [line for line in output.split("\n") if "Value measurement" in line]
    assert len(LOG_LINE.split(value_line)[-1]) < 120, value_line
    (run_dir,) = (tmp_path / "runs" / "pendulum" / "td3" / "seed0").iterdir()  # the folder the README names
    assert {"evaluations.csv", "checkpoints", "learning_curve.png", "tb"} <= {path.name for path in run_dir.iterdir()}
    (note,) = json.loads((run_dir / "summary.json").read_text())["value_measurement_notes"]
    assert note["expected"] and "eval.value_horizon_tolerance=" in note["why"]  # the reason, and what to change
    assert any((run_dir / "tb").glob("events.out.tfevents.*"))
