import os

import pytest
import torch as th

# Two cores: keep torch from oversubscribing them when tests run in parallel processes.
th.set_num_threads(int(os.environ.get("SB3_TD3X_TEST_THREADS", "1")))


@pytest.fixture(autouse=True)
def _headless_rendering(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
