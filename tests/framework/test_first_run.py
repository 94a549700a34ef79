"""The README's first command, ``python run.py``, in a fresh folder: it runs and prints nothing at WARNING level or
above (no logged warning or error, no Python warning)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# A logged record at WARNING or above ("[...][WARNING] - ...") or a Python warning ("...: UserWarning: ...").
ALARM = re.compile(r"\[(WARNING|ERROR|CRITICAL)\]|\b\w*Warning: ")


def test_the_readme_first_run_prints_no_warning(tmp_path):
    # The README's config, shortened from 10k steps to 1500: the evaluation at step 1000 (the first, where Pendulum's
    # value measurement has no state to use) and 500 steps of training come before the final evaluation.
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HOME": str(tmp_path)}
    result = subprocess.run(
        [sys.executable, str(REPO / "run.py"), "total_timesteps=1500"],
        check=False, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    assert "Done: final evaluation" in output
    alarms = [line for line in output.splitlines() if ALARM.search(line)]
    assert not alarms, "\n".join(alarms)
    (run_dir,) = (tmp_path / "runs" / "pendulum" / "td3" / "seed0").iterdir()  # the folder the README names
    assert {"evaluations.csv", "checkpoints", "learning_curve.png", "tb"} <= {path.name for path in run_dir.iterdir()}
    assert any((run_dir / "tb").glob("events.out.tfevents.*"))
