"""The algo config's arguments, checked against the class ``algo._target_`` names (its ``__init__``, and its bases' where
it passes ``**kwargs`` on): a misspelt or ill-typed one is refused before anything trains or is written, and a user's
own subclass with its own argument trains from ``run.py`` and from a sweep with exactly what ``config.yaml`` records.

The user's class lives in a module of the test's folder (``mymodule.py``), found from the folder ``run.py`` starts in
or from ``PYTHONPATH``, as docs/experiments.md tells a user.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf
from conftest import importable_from

from sb3_td3x.experiment.configs.algos import accepted_arguments, argument_problems
from sb3_td3x.experiment.configs.compose import check_config, compose_config
from sb3_td3x.experiment.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
SMOKE = ["debug=smoke", "progress_bar=false", "logger=none", "total_timesteps=300", "algo.learning_starts=100",
         "eval.freq=300", "eval.n_episodes=1"]  # fmt: skip

MYMODULE = '''
from sb3_td3x import TD3X


class MyTD3(TD3X):
    """A user's TD3X with one argument of its own, which scales the critic loss."""

    def __init__(self, *args, my_arg: float = 1.0, **kwargs):
        self.my_arg = my_arg
        super().__init__(*args, **kwargs)

    def critic_loss(self, current_q_values, target_q_values):
        loss, info = super().critic_loss(current_q_values, target_q_values)
        return self.my_arg * loss, info


class Strict(TD3X):
    """No **kwargs: only the arguments it names."""

    def __init__(self, policy, env, tau: float = 0.005, seed=None, device="auto", policy_kwargs=None, train_freq=1,
                 action_noise=None):
        super().__init__(policy, env, tau=tau, seed=seed, device=device, policy_kwargs=policy_kwargs,
                         train_freq=train_freq, action_noise=action_noise)
'''


@pytest.fixture
def mymodule(tmp_path, monkeypatch):
    (tmp_path / "mymodule.py").write_text(MYMODULE)
    importable_from(tmp_path, monkeypatch)
    return tmp_path


def run_py(*args: str, cwd: Path = REPO, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(pythonpath), str(REPO), env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, str(REPO / "run.py"), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def assert_refused(result: subprocess.CompletedProcess, run_dir: Path, *needles: str) -> None:
    message = result.stderr.strip()
    assert result.returncode == 2, result.stderr[-3000:]
    assert "Traceback" not in result.stderr and message.startswith("Error:") and "\n" not in message, message
    for needle in needles:
        assert needle in message, message
    assert not run_dir.exists(), "nothing is written before the check"


# The check, in-process ------------------------------------------------------------------------------------------------
def test_a_misspelt_argument_of_td3x_is_refused_with_the_close_match():
    cfg = compose_config(["debug=smoke", "+algo.polcy_delay=3"])
    with pytest.raises(ConfigError, match=r"algo\.polcy_delay=3: TD3X .* takes no argument 'polcy_delay'\. Did you mean algo\.policy_delay\?"):
        check_config(cfg)
    cfg = compose_config(["debug=smoke", "algo.polcy_delay=3"])  # the algo node takes new keys: the check decides
    with pytest.raises(ConfigError, match="polcy_delay"):
        check_config(cfg)


def test_the_arguments_are_the_chosen_classs_and_its_bases_through_kwargs(mymodule):
    from mymodule import MyTD3, Strict

    assert {"my_arg", "tau", "policy_delay"} <= accepted_arguments(MyTD3).keys()  # its own, and TD3X's through **kwargs
    assert "policy_delay" not in accepted_arguments(Strict) and "tau" in accepted_arguments(Strict)
    mine = compose_config(["debug=smoke", "algo._target_=mymodule.MyTD3", "+algo.my_arg=0.5"])
    assert argument_problems(mine.algo) == []
    for wrong, needle in [("+algo.my_ag=0.5", "Did you mean algo.my_arg?"), ("+algo.my_arg=abc", "takes my_arg as a float"),
                          ("+algo.my_arg=true", "takes my_arg as a float"), ("+algo.seed=3", "the run sets it (seed=)")]:  # fmt: skip
        cfg = compose_config(["debug=smoke", "algo._target_=mymodule.MyTD3", wrong])
        (problem,) = argument_problems(cfg.algo)
        assert needle in problem, problem
    strict = compose_config(["algo._target_=mymodule.Strict"])
    refused = {problem.split("=")[0] for problem in argument_problems(strict.algo)}
    assert refused == {"algo.batch_size", "algo.learning_starts"}  # algo=td3's values that Strict does not take
    strict = compose_config(["algo._target_=mymodule.Strict", "algo.policy_delay=3"])  # TD3X's default: left out
    assert "algo.policy_delay" in {problem.split("=")[0] for problem in argument_problems(strict.algo)}


def test_sb3_td3_refuses_a_td3x_only_argument_set_away_from_its_default():
    cfg = compose_config(["debug=smoke", "algo=sb3_td3", "algo.critic_learning_rate=0.01"])
    with pytest.raises(ConfigError, match=r"algo\.critic_learning_rate=0\.01: TD3 .* has no such argument"):
        check_config(cfg)
    check_config(compose_config(["debug=smoke", "algo=sb3_td3"]))


# run.py ---------------------------------------------------------------------------------------------------------------
def test_run_py_refuses_a_misspelt_argument_before_writing_anything(tmp_path):
    result = run_py(*SMOKE, "+algo.polcy_delay=3", f"run_dir={tmp_path / 'run'}")
    assert_refused(result, tmp_path / "run", "algo.polcy_delay=3", "Did you mean algo.policy_delay?")


def test_a_users_subclass_trains_with_its_argument_and_config_yaml_records_it(tmp_path, monkeypatch):
    """From ``PYTHONPATH``; then from the folder run.py starts in; a misspelt argument of it is refused before anything
    is written (a value of the wrong type is refused by the same check: test_the_arguments_are_the_chosen_classs...)."""
    (tmp_path / "mymodule.py").write_text(MYMODULE)
    run_dir = tmp_path / "run"
    result = run_py(*SMOKE, "algo=td3", "algo._target_=mymodule.MyTD3", "+algo.my_arg=0.5", f"run_dir={run_dir}",
                    pythonpath=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert OmegaConf.load(run_dir / "config.yaml").algo.my_arg == 0.5
    importable_from(tmp_path, monkeypatch)
    from mymodule import MyTD3

    model = MyTD3.load(run_dir / "checkpoints" / "last" / "model.zip")
    assert model.my_arg == 0.5 and model.num_timesteps == 300

    here = tmp_path / "here"
    result = run_py(*SMOKE, "algo._target_=mymodule.MyTD3", "algo.my_arg=0.25", f"run_dir={here}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert OmegaConf.load(here / "config.yaml").algo.my_arg == 0.25

    refused = tmp_path / "refused"
    result = run_py(*SMOKE, "algo._target_=mymodule.MyTD3", "+algo.my_ag=0.5", f"run_dir={refused}", pythonpath=tmp_path)
    assert_refused(result, refused, "algo.my_ag=0.5", "Did you mean algo.my_arg?")


# A sweep --------------------------------------------------------------------------------------------------------------
def sweep_file(tmp_path: Path, searched: str) -> Path:
    spec = {
        "study_name": "mine", "metric": "eval/mean_return", "direction": "maximize", "n_trials": 1, "seed": 0,
        "overrides": ["env=pendulum", "algo._target_=mymodule.MyTD3", *SMOKE],
        "sampler": {"_target_": "optuna.samplers.RandomSampler", "seed": 0},
        "pruner": {"_target_": "optuna.pruners.NopPruner"},
        "search_space": {searched: {"low": 0.1, "high": 0.9}},
    }  # fmt: skip
    path = tmp_path / f"{searched}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def test_a_sweep_searches_an_argument_of_the_users_class_and_refuses_a_misspelt_one(tmp_path):
    (tmp_path / "mymodule.py").write_text(MYMODULE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO), os.environ.get("PYTHONPATH", "")])}

    def sweep(path: Path) -> subprocess.CompletedProcess:
        command = [sys.executable, "-m", "sb3_td3x.sweeps", str(path), "--output-dir", str(tmp_path / "out")]
        return subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)

    refused = sweep(sweep_file(tmp_path, "algo.my_ag"))
    assert refused.returncode == 2 and "Did you mean algo.my_arg?" in refused.stderr, refused.stderr[-3000:]
    assert not (tmp_path / "out" / "mine").exists()
    done = sweep(sweep_file(tmp_path, "algo.my_arg"))
    assert done.returncode == 0, done.stderr[-3000:]
    recorded = OmegaConf.load(tmp_path / "out" / "mine" / "trial_0000" / "config.yaml").algo
    assert recorded._target_ == "mymodule.MyTD3" and 0.1 <= recorded.my_arg <= 0.9
