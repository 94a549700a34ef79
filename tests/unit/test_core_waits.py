"""TD3X says, once, when its torch threads wait for cores that other work holds (``sb3_td3x.common.core_waits``)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from sb3_td3x.common import core_waits

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
    from sb3_td3x import TD3X
    from sb3_td3x.common import core_waits
    core_waits.WINDOW_S = 1.0
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=100, seed=0, compile_update=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.learn(int(sys.argv[2]))
    said = [str(w.message) for w in caught if "waited for a core" in str(w.message)]
    print(len(said), said[0] if said else "")
    """
)


def train_on_one_core(threads: int, steps: int) -> tuple[int, str]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    out = subprocess.run([sys.executable, "-c", TRAIN_ON_ONE_CORE, str(threads), str(steps)], env=env,
                         capture_output=True, text=True, timeout=300, check=True)  # fmt: skip
    count, _, message = out.stdout.strip().splitlines()[-1].partition(" ")
    return int(count), message


def test_threads_that_share_a_core_are_reported_once_with_the_fix():
    count, message = train_on_one_core(threads=2, steps=1100)
    assert count == 1, "two threads on one core wait for each other: one warning, and only one"
    assert "2 torch threads" in message and "torch_threads=" in message and "OMP_WAIT_POLICY=passive" in message


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
