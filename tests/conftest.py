import os

import pytest
import torch as th

# Two cores: keep torch from oversubscribing them when tests run in parallel processes.
th.set_num_threads(int(os.environ.get("SB3_TD3X_TEST_THREADS", "1")))


@pytest.fixture(scope="session", autouse=True)
def _sb3_logdir(tmp_path_factory):
    """SB3's ``configure(None, ...)`` (every ``learn()`` without ``tensorboard_log``, and the tests' silent loggers)
    creates a new directory under /tmp each time unless SB3_LOGDIR names one: thousands per test run."""
    if "SB3_LOGDIR" not in os.environ:
        os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3_logdir"))


@pytest.fixture(autouse=True)
def _headless_rendering(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
