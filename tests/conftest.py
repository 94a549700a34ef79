"""Shared set-up and helpers of the test layers (``tests/README.md``).

Helpers are plain functions here, imported as ``from conftest import random_batches, feed``.
"""

import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
from stable_baselines3.common.callbacks import EvalCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import DummyVecEnv

# Two cores: keep torch from oversubscribing them when tests run in parallel processes.
th.set_num_threads(int(os.environ.get("SB3_TD3X_TEST_THREADS", "1")))


def _inductor_cache_for_test_processes() -> None:
    """Where the pytest-xdist processes (and what they start) keep Inductor's compiled graphs, kept between runs so that
    a second run finds them. On a CPU the workers share one folder (``<Inductor's default>/pytest``): a graph one of
    them compiled (about 25 s of CPU on a cold cache) is found by the others, and torch 2.13 compiles each kernel under
    a file lock. Where CUDA is, each worker has its own folder (``pytest_<worker>``): one folder shared by 14 workers
    compiling at once failed with "file too short" on a 16-core GPU machine (torch 2.11)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker and "TORCHINDUCTOR_CACHE_DIR" not in os.environ:
        from torch._inductor.runtime.cache_dir_utils import default_cache_dir

        folder = f"pytest_{worker}" if th.cuda.is_available() else "pytest"
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = os.path.join(default_cache_dir(), folder)


_inductor_cache_for_test_processes()


@pytest.fixture
def dynamo_graphs_only(monkeypatch):
    """The compiled update's graphs run by AOTAutograd's eager kernels (``aot_eager``), for tests whose claim is
    Dynamo's (the choice, guards and recompiles, which tensors a graph steps, a change captured in one graph): each
    graph Inductor compiles costs about 25 to 34 s on a cold cache. Inductor's own kernels are compared with the eager
    update in tests/equivalence/test_user_changes.py and by test_acceleration.py's Adam test."""
    from sb3_td3x.td3x.update_paths.compiled import CompiledUpdate

    monkeypatch.setattr(CompiledUpdate, "backend", "aot_eager")


def importable_from(folder: Path, monkeypatch, module: str = "mymodule") -> None:
    """``folder`` first on ``sys.path`` for this test, and no ``module`` imported by an earlier test of this worker kept
    in ``sys.modules`` (tests write modules of one name, e.g. ``mymodule.py``, with different classes): the test
    imports the one it wrote, and the next test the one it writes."""
    import sys

    monkeypatch.syspath_prepend(str(folder))
    sys.modules.pop(module, None)
    monkeypatch.setitem(sys.modules, module, None)  # monkeypatch now holds "absent" and removes it after the test
    del sys.modules[module]


@pytest.fixture(scope="session", autouse=True)
def _sb3_logdir(tmp_path_factory):
    """SB3's ``configure(None, ...)`` (every ``learn()`` without ``tensorboard_log``, and the tests' silent loggers)
    creates a new directory under /tmp each time unless SB3_LOGDIR names one: thousands per test run."""
    if "SB3_LOGDIR" not in os.environ:
        os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3_logdir"))


@pytest.fixture(autouse=True)
def _headless_rendering(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))


# Layers whose tests compare with CPU references and feed CPU tensors: on a GPU machine, device="auto" means the CPU
# for them (what it means on every machine CI runs on). The CUDA counterparts are in tests/gpu; the framework layer
# (run.py, sweeps) and the drop-in layer keep "auto", so on a GPU machine they run on the GPU.
CPU_LAYERS = {"unit", "equivalence"}


@pytest.fixture(autouse=True)
def _cpu_layers_keep_to_the_cpu(request, monkeypatch):
    if not th.cuda.is_available() or request.node.path.parent.name not in CPU_LAYERS:
        return
    from stable_baselines3.common import base_class, buffers, policies, utils

    from sb3_td3x.common import buffers as td3x_buffers

    def auto_is_the_cpu(device="auto"):
        return utils.get_device("cpu" if str(device) == "auto" else device)

    for module in (base_class, buffers, policies, td3x_buffers):
        monkeypatch.setattr(module, "get_device", auto_is_the_cpu)


@pytest.fixture
def pg_url() -> str:
    """The URL of the PostgreSQL server of the sweep tests (``.ci/postgres.sh``); skipped without one, an error in CI."""
    url = os.environ.get("SB3_TD3X_TEST_PG_URL")
    if url:
        return url
    how = 'export SB3_TD3X_TEST_PG_URL="$(bash .ci/postgres.sh)"'
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"SB3_TD3X_TEST_PG_URL is not set in CI; .ci/run must start PostgreSQL first: {how}")
    pytest.skip(f"no PostgreSQL server: SB3_TD3X_TEST_PG_URL is not set (start one with {how})")


SLURM_HOW = 'export SLURM_CONF="$(bash .ci/slurm.sh)" (as root; it installs slurm-wlm and munge when missing)'


@pytest.fixture(scope="session")
def slurm() -> dict[str, str]:
    """The environment for commands that use the cluster (``SLURM_CONF``), once a node answers idle or busy.

    A node that is finishing a job (``completing``, as when the other test worker's job has just ended) is up; a node
    in any other state is asked again for up to a minute (it may be starting) before the tests are failed or skipped.
    """
    problem = None
    if shutil.which("sinfo") is None:
        problem = "SLURM's commands are not installed"
    else:
        deadline = time.monotonic() + 60
        while True:
            done = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True, timeout=30)
            states = done.stdout.split()
            if done.returncode != 0:
                problem = f"sinfo fails: {' '.join(done.stderr.split())}"
                break
            if any(state.rstrip("*") in ("idle", "mixed", "allocated", "completing") for state in states):
                break
            if time.monotonic() > deadline:
                problem = f"no SLURM node is up after a minute (states: {states or 'none'})"
                break
            time.sleep(2)
    if problem is not None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{problem}; CI must start SLURM first: {SLURM_HOW}")
        pytest.skip(f"{problem}: start a one-node SLURM with {SLURM_HOW}")
    repo = str(Path(__file__).resolve().parents[1])
    return {**os.environ, "PYTHONPATH": repo + os.pathsep + os.environ.get("PYTHONPATH", ""), "PYTHONUNBUFFERED": "1"}


def random_batches(
    n: int, batch_size: int = 32, obs_dim: int = 3, action_dim: int = 1, seed: int = 0, done_probability: float = 0.2
) -> list[ReplayBufferSamples]:
    """``n`` hand-made replay batches (Pendulum-v1's shapes by default): observations N(0, 1), actions U(-1, 1),
    rewards N(0, 1), dones with probability ``done_probability``; the same batches for the same arguments."""
    g = th.Generator().manual_seed(seed)
    return [
        ReplayBufferSamples(
            observations=th.randn(batch_size, obs_dim, generator=g),
            actions=th.rand(batch_size, action_dim, generator=g) * 2 - 1,
            next_observations=th.randn(batch_size, obs_dim, generator=g),
            dones=(th.rand(batch_size, 1, generator=g) < done_probability).float(),
            rewards=th.randn(batch_size, 1, generator=g),
        )
        for _ in range(n)
    ]


def feed(model, batches: list[ReplayBufferSamples], seed: int | None = None) -> None:
    """Make ``model.sample_batch`` return ``batches`` in order (set on the instance: the fast paths call it too, so it
    does not switch them off); with ``seed``, also seed torch so that models fed alike draw the same noise."""
    it = iter(batches)
    model.sample_batch = lambda batch_size: next(it)
    if seed is not None:
        th.manual_seed(seed)


def eager_capture(fn, pool):
    """A CPU stand-in for CUDA graph capture (``GraphedGradientStep(model, capture=eager_capture)``): "replay" reruns
    the step and writes into the static outputs, so everything but the capture itself runs as on a GPU."""
    outputs = fn()

    def replay():
        new = fn()
        for static, fresh in zip(outputs, new):
            for key in static:
                static[key].copy_(fresh[key])

    return replay, outputs, pool


class _StopHere(Exception):
    pass


def stopped_and_resumed(overrides: list[str], runs: Path, stop_at: int) -> tuple[Path, Path]:
    """Two runs of ``run_experiment`` with ``overrides`` under ``runs``: ``reference``, never stopped, and ``stopped``,
    stopped by a report that raises at step ``stop_at`` (which checkpoints as a signal does; the checkpoint's step is
    checked) and resumed to its end. Returns their folders ``(reference, stopped)``."""
    import json

    from sb3_td3x.experiment.configs.compose import compose_config
    from sb3_td3x.experiment.run.checkpoints import META_FILE
    from sb3_td3x.experiment.runner import run_experiment

    reference, stopped = runs / "reference", runs / "stopped"
    run_experiment(compose_config([*overrides, f"run_dir={reference}"]))

    def stop(step: int, value: float) -> None:
        if step >= stop_at:
            raise _StopHere(step)

    with pytest.raises(_StopHere):
        run_experiment(compose_config([*overrides, f"run_dir={stopped}"]), report=stop)
    assert json.loads((stopped / "checkpoints" / "last" / META_FILE).read_text())["num_timesteps"] == stop_at
    run_experiment(compose_config([*overrides, f"resume={stopped}"]))
    return reference, stopped


@dataclass
class DummyEnv(gym.Env):
    """An env with the given spaces that returns random observations and never ends (wrap it in a TimeLimit)."""

    observation_space: gym.spaces.Space
    action_space: gym.spaces.Space

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


PENDULUM_BAR = -250.0  # random actions score about -1200 on Pendulum-v1, a learnt swing-up about -150


def learn_until_the_bar(name: str, model, max_steps: int, folder: Path, eval_seed: int = 10_000) -> list[tuple[int, float]]:
    """The learning checks' one measure (tests/learning): train ``model`` until its deterministic policy scores
    PENDULUM_BAR on Pendulum-v1 or ``max_steps`` pass, print its evaluations as (steps, mean return) pairs, and fail if
    none reached the bar. SB3's own EvalCallback evaluates every 500 steps (10 episodes) and
    StopTrainingOnRewardThreshold ends the run at the first evaluation over the bar (SB3's documented pairing):
    Pendulum's policies swing between evaluations, and one seed follows another trajectory on another CPU, so the
    policy at one fixed step is a fragile measure (tests/learning/test_variants_learn.py says what was measured)."""
    eval_env = DummyVecEnv([lambda: Monitor(gym.make("Pendulum-v1"))])
    eval_env.seed(eval_seed)
    evaluation = EvalCallback(
        eval_env,
        callback_on_new_best=StopTrainingOnRewardThreshold(reward_threshold=PENDULUM_BAR),
        eval_freq=500,
        n_eval_episodes=10,
        log_path=str(folder),  # keeps each evaluation's returns in evaluation.evaluations_results
        deterministic=True,
        verbose=0,
    )
    model.learn(total_timesteps=max_steps, callback=evaluation)
    means = [round(sum(returns) / len(returns), 1) for returns in evaluation.evaluations_results]
    evaluations = list(zip(evaluation.evaluations_timesteps, means))
    print(f"{name} ({model.update_path}): {evaluations}")
    best = max(means)
    assert best >= PENDULUM_BAR, f"{name}: best {best} < {PENDULUM_BAR} in {max_steps:,} steps; evaluations: {evaluations}"
    return evaluations
