"""The config ``run.py`` trains: composed from ``conf/`` and checked.

- :func:`compose_config`: what ``python run.py <overrides>`` runs, composed without starting a Hydra app (the sweeps,
  the API, and ``run.py``'s check of its command line before Hydra writes anything);
- :func:`check_config`: ranges and names that the types of :mod:`~sb3_td3x.experiment.configs.schemas` cannot express
  (``algo.tau`` in [0, 1] as TD3X's constructor checks it, a registered gymnasium id, ...), as one
  :class:`~sb3_td3x.experiment.errors.ConfigError` listing every problem.
"""

from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import get_type_hints

import gymnasium as gym
import torch
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override
from omegaconf import DictConfig

from sb3_td3x.experiment.configs.algos import argument_problems
from sb3_td3x.experiment.configs.schemas import (
    CONF_DIR,
    AlgoConfig,
    CheckpointConfig,
    EnvConfig,
    EvalConfig,
    ExperimentConfig,
    LoggerConfig,
    VideoConfig,
    constructor_fields,
)
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.td3x.policies import N_CRITICS, valid_n_critics, valid_net_arch
from sb3_td3x.td3x.td3x import TD3X


def _integer_keys() -> set[str]:
    """The dotted keys of the integer fields of the schemas (``total_timesteps``, ``algo.buffer_size``, ...)."""
    groups = {"algo": AlgoConfig, "env": EnvConfig, "eval": EvalConfig, "checkpoint": CheckpointConfig,
              "logger": LoggerConfig, "video": VideoConfig, "": ExperimentConfig}
    keys = set()
    for prefix, schema in groups.items():
        for name, hint in get_type_hints(schema).items():
            if hint in (int, int | None):
                keys.add(f"{prefix}.{name}" if prefix else name)
    return keys


def whole_float_problems(overrides: list[str] | list[Override]) -> list[str]:
    """For each whole float given to an integer field (``total_timesteps=1e6``: Hydra reads a float, which the field
    refuses), how to write it: ``total_timesteps=1000000``, or Hydra's cast ``total_timesteps=int(1e6)``. The
    overrides as written, or as Hydra's parser read them; one it cannot read is Hydra's to explain."""
    keys = _integer_keys()
    problems = []
    for override in overrides:
        if isinstance(override, str):
            try:
                override = OverridesParser.create().parse_override(override)
            except Exception:  # noqa: BLE001  (Hydra's syntax errors: reported by Hydra when it composes)
                continue
        key = override.key_or_group
        if key not in keys or override.is_sweep_override() or override.is_delete():
            continue
        value = override.value()
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            text = override.input_line.split("=", 1)[1]
            problems.append(f"{override.input_line}: {key} is an integer, write {key}={int(value)} or {key}=int({text})")
    return problems


def compose_config(
    overrides: list[str] | None = None, conf_dir: Path = CONF_DIR, config_name: str = "config", with_hydra: bool = False
) -> DictConfig:
    """The config ``python run.py <overrides>`` would run, composed without starting a Hydra app.

    ``run_dir`` keeps its default interpolation; set it before :func:`~sb3_td3x.experiment.runner.run_experiment`.

    :param with_hydra: keep Hydra's own node (``cfg.hydra``: the launcher, the run and sweep folders), as ``run.py``
        launches with it
    """
    overrides = list(overrides or [])
    problems = whole_float_problems(overrides)
    if problems:
        raise ConfigError("; ".join(problems) + ".")
    with initialize_config_dir(config_dir=str(Path(conf_dir).resolve()), version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides, return_hydra_config=with_hydra)


def check_config(cfg: DictConfig, on_this_machine: bool = True) -> None:
    """Check ranges and names that the types cannot; raise one :class:`ConfigError` listing every problem.

    :param on_this_machine: the run trains on this machine, so its device must be here (``run.py`` checks a launch
        to SLURM's nodes without it)
    """
    problems: list[str] = []

    def need(condition: bool, message: str) -> None:
        if not condition:
            problems.append(message)

    need(cfg.total_timesteps > 0, f"total_timesteps={cfg.total_timesteps} must be a positive number of steps")
    need(cfg.n_envs >= 1, f"n_envs={cfg.n_envs} must be at least 1")
    need(cfg.seed >= 0, f"seed={cfg.seed} must be >= 0")
    if cfg.seeds is not None:
        seeds = list(cfg.seeds)
        if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
            problems.append(f"seeds={seeds} must list distinct seeds >= 0, e.g. seeds=[0,1,2]")
        elif cfg.seed not in seeds:
            problems.append(f"seed={cfg.seed} is not one of seeds={seeds}; drop seed= (it is then the first seed)")
        if cfg.seed_run_dirs is not None and len(cfg.seed_run_dirs) != len(seeds):
            problems.append(f"seed_run_dirs has {len(cfg.seed_run_dirs)} folders for {len(seeds)} seeds; leave it unset")
    need(cfg.torch_threads is None or cfg.torch_threads >= 1, f"torch_threads={cfg.torch_threads} must be >= 1 or null")
    need(
        cfg.get("seed_processes") is None or cfg.seed_processes >= 1,
        f"seed_processes={cfg.get('seed_processes')} must be >= 1 or null (one process per core on a CPU)",
    )
    problems += _device_problems(cfg.device, on_this_machine)

    algo = cfg.algo
    problems += argument_problems(algo)  # every key against the signature of the class algo._target_ names
    # The constructor's own range checks (TD3X.hyperparameter_problems): one source of truth for both.
    for name, allowed in TD3X.hyperparameter_problems(**{name: algo[name] for name in constructor_fields()}):
        problems.append(f"algo.{name}={algo[name]} must be {allowed}")
    need(
        algo.train_freq_unit in ("step", "episode"),
        f"algo.train_freq_unit={algo.train_freq_unit!r} must be 'step' or 'episode'",
    )
    need(algo.exploration_noise >= 0, f"algo.exploration_noise={algo.exploration_noise} must be >= 0")
    need(
        algo.net_arch is None or (len(algo.net_arch) > 0 and valid_net_arch(list(algo.net_arch))),
        f"algo.net_arch={algo.net_arch} must list positive layer widths, or be null for the policy's default",
    )
    need(valid_n_critics(algo.n_critics), f"algo.n_critics={algo.n_critics} must be {N_CRITICS}")

    problems += _env_id_problems(cfg.env.id)
    need(cfg.env.max_episode_steps is None or cfg.env.max_episode_steps >= 1, "env.max_episode_steps must be >= 1 or null")
    need(cfg.eval.freq >= 1, f"eval.freq={cfg.eval.freq} must be >= 1 environment step")
    need(cfg.eval.n_episodes >= 1, f"eval.n_episodes={cfg.eval.n_episodes} must be >= 1")
    need(
        0 <= cfg.eval.value_horizon_tolerance <= 1,
        f"eval.value_horizon_tolerance={cfg.eval.value_horizon_tolerance} must be in [0, 1]",
    )
    need(cfg.checkpoint.freq >= 1, f"checkpoint.freq={cfg.checkpoint.freq} must be >= 1 environment step")
    need(cfg.logger.log_interval >= 1, f"logger.log_interval={cfg.logger.log_interval} must be >= 1 episode")
    if cfg.logger.wandb is not None:
        mode = cfg.logger.wandb.mode
        need(
            mode in ("auto", "online", "offline", "disabled"),
            f"logger.wandb.mode={mode!r} must be auto, online, offline or disabled",
        )
    if cfg.video is not None:
        need(cfg.video.format in ("gif", "mp4"), f"video.format={cfg.video.format!r} must be 'gif' or 'mp4'")
        need(cfg.video.n_episodes >= 1, f"video.n_episodes={cfg.video.n_episodes} must be >= 1")

    if problems:
        raise ConfigError("Invalid configuration: " + "; ".join(problems) + ".")


def _device_problems(device: str, on_this_machine: bool) -> list[str]:
    if device == "auto":
        return []
    try:
        parsed = torch.device(device)
    except RuntimeError:
        return [f"device={device!r} is not a torch device; use auto, cpu, cuda or cuda:N"]
    if on_this_machine and parsed.type == "cuda" and not torch.cuda.is_available():
        return [f"device={device!r} but this machine has no CUDA GPU; use device=cpu or device=auto"]
    return []


def _env_id_problems(env_id: str) -> list[str]:
    if env_id in gym.registry:
        return []
    close = difflib.get_close_matches(env_id, list(gym.registry), n=3)
    hint = f" Did you mean {', '.join(close)}?" if close else ""
    return [f"env.id={env_id!r} is not a registered gymnasium environment.{hint}"]
