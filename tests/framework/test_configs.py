"""Every YAML in conf/ composes against its schema, passes the range checks and builds its object."""

from __future__ import annotations

import inspect
import shutil
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from stable_baselines3 import TD3

from sb3_td3x import DDPG, PRESETS, TD3X
from sb3_td3x.common.redaction import MASK
from sb3_td3x.experiment.configs.algos import algorithm_kwargs, build_algorithm
from sb3_td3x.experiment.configs.compose import check_config, compose_config
from sb3_td3x.experiment.configs.schemas import CONF_DIR, AlgoConfig, constructor_fields
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.experiment.run.callbacks import PeriodicEvaluation
from sb3_td3x.experiment.run.envs import make_eval_env, make_train_env
from sb3_td3x.experiment.run.folder import public_config
from sb3_td3x.experiment.run.loggers import build_logger, wandb_mode
from sb3_td3x.variants import TD3C51, TD3LAP, TD3LayerNorm, TD3NStep


# The variants of sb3_td3x.variants, each with its config (docs/variants.md).
VARIANTS = {"td3_lap": TD3LAP, "td3_nstep": TD3NStep, "td3_layernorm": TD3LayerNorm, "td3_c51": TD3C51}


def options(group: str) -> list[str]:
    return sorted(path.stem for path in (CONF_DIR / group).glob("*.yaml"))


def test_the_groups_hold_what_the_issue_asks_for():
    assert set(options("algo")) >= {"td3", "ddpg", "td3_no_smoothing", "td3_no_cdq", "td3_no_delay", *VARIANTS}
    assert set(options("env")) >= {
        "ant", "halfcheetah", "hopper", "walker2d", "humanoid", "inverted_pendulum", "inverted_double_pendulum", "reacher",
        "pendulum",
    }  # fmt: skip
    assert options("logger") and options("eval") and options("video") and options("debug")


def test_the_default_config_is_the_quick_pendulum_run_with_optional_groups_off():
    cfg = compose_config()
    check_config(cfg)
    assert (cfg.env.id, cfg.algo.name, cfg.logger.name) == ("Pendulum-v1", "td3", "tensorboard")
    assert cfg.video is None and cfg.resume is None and cfg.logger.wandb is None
    assert cfg.total_timesteps <= 20_000


@pytest.mark.parametrize("name", options("algo"))
def test_every_algo_config_builds_its_algorithm(name):
    cfg = compose_config([f"algo={name}", "algo.buffer_size=1000", "device=cpu"])
    check_config(cfg)
    env = make_train_env(cfg.env, n_envs=1, seed=0)
    model = build_algorithm(cfg, env)
    assert type(model) is {"ddpg": DDPG, "sb3_td3": TD3, **VARIANTS}.get(name, TD3X)
    assert model.policy_delay == cfg.algo.policy_delay and model.tau == cfg.algo.tau and model.gamma == cfg.algo.gamma
    assert model.batch_size == cfg.algo.batch_size and model.target_policy_noise == cfg.algo.target_policy_noise
    if name != "sb3_td3":  # SB3's TD3 has neither switch; its config keeps TD3X's defaults (tested below)
        assert model.target_policy_smoothing == cfg.algo.target_policy_smoothing
        assert model.clipped_double_q == cfg.algo.clipped_double_q
    assert len(model.critic.q_networks) == cfg.algo.n_critics and model.n_steps == cfg.algo.n_steps
    assert model.learning_starts == cfg.env.learning_starts
    np.testing.assert_allclose(model.action_noise._sigma, cfg.algo.exploration_noise)
    widths = [layer.out_features for layer in model.actor.mu if hasattr(layer, "out_features")]
    assert widths[:-1] == list(cfg.algo.net_arch)
    model.learn(10)  # one short rollout: the object works, not only builds
    env.close()


def test_sb3_td3_config_runs_the_td3_settings_and_refuses_td3x_only_switches():
    """algo=sb3_td3 is SB3's TD3 with algo/td3.yaml's hyper-parameters, the baseline of the results pages."""
    td3 = algorithm_kwargs(compose_config(["algo=td3"]).algo, n_actions=1)
    sb3 = algorithm_kwargs(compose_config(["algo=sb3_td3"]).algo, n_actions=1)
    td3_only = {"critic_learning_rate", "target_policy_smoothing", "clipped_double_q", "bf16", "compile_update",
                "cuda_graph", "flush_denormals"}
    assert set(td3) - set(sb3) == td3_only
    for key in sb3:
        if key != "action_noise":
            assert sb3[key] == td3[key], key
    for override in ("algo.target_policy_smoothing=false", "algo.clipped_double_q=false", "algo.critic_learning_rate=3e-4",
                     "algo.compile_update=true", "algo.cuda_graph=false", "algo.cuda_graph=true"):
        with pytest.raises(ConfigError, match=r"TD3 \(algo._target_=stable_baselines3.TD3\) has no such argument"):
            algorithm_kwargs(compose_config(["algo=sb3_td3", override]).algo, n_actions=1)


def test_the_accelerations_are_config_switches():
    """algo.bf16, algo.compile_update and algo.cuda_graph reach TD3X; algo.compile_update and algo.cuda_graph are
    null (auto, the default), true or false; cuda_graph=true without a GPU is a config error."""
    cfg = compose_config(["algo=td3", "algo.buffer_size=1000", "device=cpu", "algo.compile_update=true", "algo.bf16=true"])
    check_config(cfg)
    env = make_train_env(cfg.env, n_envs=1, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bf16 on a CPU without AMX warns (test_acceleration.py)
        model = build_algorithm(cfg, env)
    assert (model.bf16, model.compile_update, model.cuda_graph) == (True, True, False)
    defaults = build_algorithm(compose_config(["algo=td3", "algo.buffer_size=1000", "device=cpu"]), env)
    assert (defaults.bf16, defaults.compile_update, defaults.cuda_graph) == (False, None, False)
    for value, request in (("null", None), ("false", False), ("true", True)):
        assert compose_config([f"algo.compile_update={value}"]).algo.compile_update is request
    assert defaults.cuda_graph_request is None and defaults.cuda_graph_reason == "cuda_graph=None (auto): no CUDA device"
    for value, request in (("null", None), ("false", False), ("true", True)):
        assert compose_config([f"algo.cuda_graph={value}"]).algo.cuda_graph is request
    opted_out = build_algorithm(compose_config(["algo=td3", "algo.buffer_size=1000", "device=cpu", "algo.cuda_graph=false"]), env)
    assert (opted_out.cuda_graph_request, opted_out.cuda_graph) == (False, False)
    with pytest.raises(ConfigError, match="cuda_graph=True needs a CUDA device"):
        build_algorithm(compose_config(["algo=td3", "algo.buffer_size=1000", "device=cpu", "algo.cuda_graph=true"]), env)
    env.close()


@pytest.mark.parametrize("name", options("algo"))
def test_no_algo_config_restates_a_value_it_inherits(name, tmp_path):
    """Each line of conf/algo/<name>.yaml changes the composed config: composed without that line (a copy of conf/),
    the value differs. TD3X's defaults come from the schema, the presets' switches from sb3_td3x.PRESETS, and td3.yaml
    says only the paper's values that neither has."""
    own = OmegaConf.load(CONF_DIR / "algo" / f"{name}.yaml")
    composed = OmegaConf.to_container(compose_config([f"algo={name}"]).algo, resolve=False)
    restated = []
    for key in [key for key in own if key != "defaults"]:
        conf_dir = tmp_path / key
        shutil.copytree(CONF_DIR, conf_dir)
        without = OmegaConf.load(conf_dir / "algo" / f"{name}.yaml")
        del without[key]
        OmegaConf.save(without, conf_dir / "algo" / f"{name}.yaml")
        inherited = OmegaConf.to_container(compose_config([f"algo={name}"], conf_dir).algo, resolve=False)
        if inherited[key] == composed[key]:
            restated.append(f"{key}: {composed[key]}")
    assert not restated, f"conf/algo/{name}.yaml restates what it inherits: {', '.join(restated)}"


def test_the_schema_has_td3x_defaults_and_the_preset_configs_are_the_presets():
    """The algo schema is read from TD3X's signature (every argument with a plain type, compile_update and
    flush_denormals included), and each preset's config is td3.yaml with exactly sb3_td3x.PRESETS's switches."""
    schema = OmegaConf.structured(AlgoConfig)
    parameters = inspect.signature(TD3X.__init__).parameters
    assert constructor_fields().keys() >= {"compile_update", "flush_denormals", "critic_learning_rate", "n_steps", "bf16"}
    for name in constructor_fields():
        assert schema[name] == parameters[name].default, name
    td3 = OmegaConf.to_container(compose_config(["algo=td3"]).algo, resolve=False)
    assert set(PRESETS) <= set(options("algo"))
    for name, kwargs in PRESETS.items():
        algo = OmegaConf.to_container(compose_config([f"algo={name}"]).algo, resolve=False)
        switches = {key: value for key, value in algo.items() if td3[key] != value and key not in ("name", "_target_")}
        assert switches == {**{k: v for k, v in kwargs.items() if k != "policy_kwargs"}, **kwargs.get("policy_kwargs", {})}


@pytest.mark.parametrize("name", options("env"))
def test_every_env_config_makes_its_envs_with_the_paper_settings(name):
    cfg = compose_config([f"env={name}"])
    check_config(cfg)
    if name != "pendulum":
        assert cfg.env.id.endswith("-v5") and cfg.env.id == gym.spec(cfg.env.id).id
        assert cfg.total_timesteps == 1_000_000 and cfg.eval.freq == 5000 and cfg.eval.n_episodes == 10
        assert cfg.algo.learning_starts == (10_000 if name in ("ant", "halfcheetah") else 1_000)
    assert cfg.algo.exploration_noise == 0.1
    train_env, eval_env = make_train_env(cfg.env, n_envs=2, seed=0), make_eval_env(cfg.env)
    for env in (train_env, eval_env):
        obs = env.reset()
        assert obs.shape == (env.num_envs, *env.observation_space.shape)
        env.step(np.stack([env.action_space.sample() for _ in range(env.num_envs)]))
        env.close()


@pytest.mark.parametrize("name", options("logger"))
def test_every_logger_config_builds_its_logger(name, tmp_path):
    cfg = compose_config([f"logger={name}"])
    check_config(cfg)
    logger = build_logger(cfg.logger, tmp_path, wandb_run=None)  # the W&B run itself: tests/framework/test_run_e2e.py
    logger.record("eval/mean_reward", 1.0)
    logger.dump(1)
    logger.close()
    assert any((tmp_path / "tb").glob("events.out.tfevents.*")) == cfg.logger.tensorboard
    assert (cfg.logger.wandb is not None) == (name == "wandb")


def test_every_eval_video_and_debug_config_composes_and_checks(tmp_path):
    for group in ("eval", "video", "debug"):
        for name in options(group):
            cfg = compose_config([f"{group}={name}"])
            check_config(cfg)
    cfg = compose_config(["eval=default"])
    env = make_eval_env(cfg.env)
    evaluation = PeriodicEvaluation(
        env, tmp_path, cfg.eval.freq, cfg.eval.n_episodes, eval_seed=cfg.seed + cfg.eval.seed_offset
    )
    assert evaluation.freq == 1000 and evaluation.n_episodes == 10
    env.close()


def test_overrides_reach_every_field_the_sweeps_search():
    paths = {
        "algo.learning_rate": 3e-4, "algo.critic_learning_rate": 1e-4, "algo.batch_size": 256, "algo.tau": 0.01,
        "algo.gamma": 0.98, "algo.exploration_noise": 0.2, "algo.policy_delay": 3, "algo.target_policy_noise": 0.1,
        "algo.target_noise_clip": 0.3, "algo.net_arch": [64, 64], "algo.train_freq": 2, "algo.gradient_steps": 2,
        "seed": 7, "n_envs": 2, "device": "cpu", "total_timesteps": 1234,
    }  # fmt: skip
    overrides = [f"{key}={value}".replace(" ", "") for key, value in paths.items()]
    cfg = compose_config(overrides)
    check_config(cfg)
    for key, value in paths.items():
        assert OmegaConf.select(cfg, key) == value, key


@pytest.mark.parametrize("override", ["algo.batch_size=abc", "algo.net_arch=wide", "seed=1.5", "logger.tensorboard=maybe"])
def test_a_typo_or_a_wrong_type_fails_while_composing(override):
    with pytest.raises(ConfigCompositionException):
        compose_config([override])


def test_a_typo_under_algo_is_refused_against_the_class_signature():
    """The algo node takes the chosen class's own arguments (tests/framework/test_algo_arguments.py), so a misspelt
    key composes and the check refuses it, with the argument meant."""
    with pytest.raises(ConfigError, match=r"algo\.taau=0\.1: TD3X .* takes no argument 'taau'\. Did you mean algo\.tau\?"):
        check_config(compose_config(["algo.taau=0.1"]))


@pytest.mark.parametrize(
    "override, field",
    [
        ("algo.tau=2", "algo.tau"),
        ("algo.tau=-0.1", "algo.tau"),  # tau=0 is valid (the constructor allows it: frozen targets)
        ("algo.gradient_steps=-2", "algo.gradient_steps"),
        ("total_timesteps=-1", "total_timesteps"),
        ("algo.gamma=1.5", "algo.gamma"),
        ("algo.learning_rate=0", "algo.learning_rate"),
        ("algo.batch_size=0", "algo.batch_size"),
        ("algo.train_freq_unit=epoch", "algo.train_freq_unit"),
        ("algo.net_arch=[]", "algo.net_arch"),
        ("n_envs=0", "n_envs"),
        ("eval.freq=0", "eval.freq"),
        ("env.id=Antt-v5", "env.id"),
        ("device=tpu", "device"),
    ],
)
def test_out_of_range_values_fail_the_check_naming_the_field(override, field):
    cfg = compose_config([override])
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        check_config(cfg)


def test_the_saved_config_has_no_credentials():
    cfg = compose_config(["+env.kwargs.api_key=hunter2", "logger=wandb"])
    saved = public_config(cfg)
    assert saved["env"]["kwargs"]["api_key"] == MASK
    assert "hunter2" not in OmegaConf.to_yaml(OmegaConf.create(saved))


def test_wandb_logs_offline_without_an_api_key(monkeypatch, tmp_path):
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.netrc
    monkeypatch.setenv("NETRC", str(tmp_path / ".netrc"))
    assert wandb_mode("auto") == "offline"
    (tmp_path / ".netrc").write_text("machine api.wandb.ai\n  login user\n  password 0123456789\n")
    (tmp_path / ".netrc").chmod(0o600)
    assert wandb_mode("auto") == "online"
    monkeypatch.setenv("WANDB_MODE", "disabled")
    assert wandb_mode("auto") == "disabled"
    assert Path(CONF_DIR / "logger" / "wandb.yaml").read_text().count("mode: auto") == 1
