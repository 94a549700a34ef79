"""TD3X says, once, when its torch threads wait for cores that other work holds (``sb3_td3x.common.core_waits``); so does
a run of SB3's ``TD3`` through run.py (its callback ``CoreWaitsCheck``)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from stable_baselines3 import TD3

from sb3_td3x import TD3X
from sb3_td3x.common import core_waits
from sb3_td3x.experiment.configs.compose import compose_config
from sb3_td3x.experiment.run.callbacks import CoreWaitsCheck
from sb3_td3x.experiment.run.folder import NEW
from sb3_td3x.experiment.run.train import close_run, prepare

pytestmark = pytest.mark.skipif(
    not os.path.exists(f"/proc/self/task/{os.getpid()}/schedstat") or not hasattr(os, "sched_setaffinity"),
    reason="needs Linux's per-thread scheduler statistics (/proc/self/task/*/schedstat) and CPU affinity",
)

# Two torch threads on one core: the OpenMP threads of each parallel region wait for each other as they would for a
# busy process's (libgomp, seeing more threads than CPUs, spins less than it would beside another process, so that
# this takes seconds, not minutes).
TRAIN_ON_ONE_CORE = textwrap.dedent(
    """
    import os, sys, warnings
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    import torch as th
    th.set_num_threads(int(sys.argv[1]))
    from stable_baselines3 import TD3
    from sb3_td3x import TD3X
    from sb3_td3x.common import core_waits
    from sb3_td3x.experiment.run.callbacks import CoreWaitsCheck
    core_waits.WINDOW_S = 1.0
    if sys.argv[3] == "td3x":
        model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=100, seed=0, compile_update=False)
    else:
        model = TD3("MlpPolicy", "Pendulum-v1", learning_starts=100, seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.learn(int(sys.argv[2]), callback=CoreWaitsCheck() if sys.argv[4] == "callback" else None)
    said = [str(w.message) for w in caught if "waited for a core" in str(w.message)]
    print(len(said), said[0] if said else "")
    """
)


def train_on_one_core(threads: int, steps: int, model: str = "td3x", callback: bool = False) -> tuple[int, str]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    args = [str(threads), str(steps), model, "callback" if callback else "none"]
    out = subprocess.run([sys.executable, "-c", TRAIN_ON_ONE_CORE, *args], env=env,
                         capture_output=True, text=True, timeout=300, check=True)  # fmt: skip
    count, _, message = out.stdout.strip().splitlines()[-1].partition(" ")
    return int(count), message


def test_threads_that_share_a_core_are_reported_once_with_the_fix():
    count, message = train_on_one_core(threads=2, steps=1100)
    assert count == 1, "two threads on one core wait for each other: one warning, and only one"
    assert "2 torch threads" in message and "torch_threads=" in message and "OMP_WAIT_POLICY=passive" in message


def run_callbacks(run_dir: str) -> list[object]:
    """The callbacks run.py gives a run of SB3's ``TD3`` (``algo=sb3_td3``), its folder prepared and closed."""
    run = prepare(compose_config(["algo=sb3_td3", "algo.buffer_size=1000", "device=cpu", f"run_dir={run_dir}"]), NEW)
    close_run(run)
    return run.callbacks


def test_sb3_td3_run_by_run_py_is_checked_too_and_td3x_once(tmp_path):
    # run.py adds the callback to every run: SB3's TD3 gets the check through it; TD3X checks in train(), not twice
    assert CoreWaitsCheck in {type(callback) for callback in run_callbacks(str(tmp_path / "run"))}
    count, message = train_on_one_core(threads=2, steps=600, model="sb3", callback=True)
    assert count == 1 and "2 torch threads" in message
    for model, checks in ((TD3("MlpPolicy", "Pendulum-v1"), True), (TD3X("MlpPolicy", "Pendulum-v1"), False)):
        check = CoreWaitsCheck()
        check.init_callback(model)
        check.on_training_start({}, {})
        assert (check.waits is not None) is checks, type(model).__name__


def test_one_thread_is_not_reported():
    count, _ = train_on_one_core(threads=1, steps=400)
    assert count == 0


def test_waits_below_the_bound_are_not_reported(monkeypatch):
    monkeypatch.setattr(core_waits, "WINDOW_S", 0.0)
    waits = core_waits.CoreWaits()
    monkeypatch.setattr(core_waits, "_waited_s", lambda: waits.waited + 1e-6)  # a microsecond waited since
    assert waits.poll() is None
    monkeypatch.setattr(core_waits, "_waited_s", lambda: waits.waited + 3600.0)  # an hour waited: far above
    assert waits.poll() > core_waits.TOO_MANY
