"""Typed schemas of the configuration tree in ``conf/``, and the range checks types cannot express.

The dataclasses are registered in Hydra's ``ConfigStore`` when this module is imported; every YAML in
``conf/`` extends one of them (``defaults: [base_algo, _self_]``), so a misspelt key or a value of the
wrong type fails while Hydra composes the config, before anything is built. :func:`check_config` then
checks ranges and names (``algo.tau`` in [0, 1] as TD3X's constructor checks it, a registered gymnasium id,
...) and raises one :class:`~sb3_td3x.experiment.errors.ConfigError` listing every problem.
"""

from __future__ import annotations

import difflib
import inspect
import math
import re
from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Any, get_type_hints

import gymnasium as gym
import torch
from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from omegaconf import II, MISSING, DictConfig, OmegaConf
from stable_baselines3.td3.policies import TD3Policy

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.td3x.presets import PRESETS
from sb3_td3x.td3x.td3x import TD3X

# conf/ of a source checkout (run.py's config_path).
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"

# TD3X's constructor arguments that the run sets, not the algo config: seed and device (top-level fields), verbose,
# and TensorBoard (the logger group).
SET_BY_THE_RUN = ("seed", "device", "verbose", "tensorboard_log")
_SIMPLE_TYPES: dict[str, type] = {"int": int, "float": float, "bool": bool, "str": str}


def _field_type(annotation: str) -> Any:
    """The config type of a constructor argument annotated ``annotation`` (``float | Schedule | None`` gives
    ``float | None``): its one plain type, or None when it has none (an object such as ``action_noise``)."""
    members = [member.strip() for member in annotation.split("|")]
    plain = [_SIMPLE_TYPES[member] for member in members if member in _SIMPLE_TYPES]
    if len(plain) != 1:
        return None
    return plain[0] | None if "None" in members else plain[0]


def constructor_fields(cls: type = TD3X) -> dict[str, tuple[Any, Any]]:
    """``{name: (type, default)}`` of the arguments of ``cls.__init__`` that the algo config holds under the same
    name: those with a default and a plain type, except :data:`SET_BY_THE_RUN` and private ones."""
    result = {}
    for name, parameter in inspect.signature(cls.__init__).parameters.items():
        if parameter.default is inspect.Parameter.empty or name.startswith("_") or name in SET_BY_THE_RUN:
            continue
        annotation = parameter.annotation
        kind = _field_type(annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation)))
        if kind is not None:
            result[name] = (kind, parameter.default)
    return result


def _algo_config() -> type:
    """The schema of ``conf/algo/``: every argument of :func:`constructor_fields` with TD3X's own default, so that a
    default is written once (TD3X's signature) and a YAML says only where it departs (the paper's values in
    ``conf/algo/td3.yaml``). Plus the arguments SB3 takes as objects, with the values that give TD3X's defaults."""
    policy_defaults = inspect.signature(TD3Policy.__init__).parameters
    translated = [
        ("_target_", str, field(default="sb3_td3x.TD3X")),  # the algorithm class
        ("name", str, field(default=MISSING)),  # short name used in run folders and tables, e.g. "td3"
        ("policy", str, field(default="MlpPolicy")),
        # std of the Gaussian exploration noise N(0, sigma) in units of the [-1, 1] action scale (SB3's
        # action_noise); 0: none, TD3X's default
        ("exploration_noise", float, field(default=0.0)),
        # policy_kwargs: the layer widths (None: the policy's default, 400-300 for MlpPolicy) and the number of critics
        ("net_arch", list[int] | None, field(default=policy_defaults["net_arch"].default)),
        ("n_critics", int, field(default=policy_defaults["n_critics"].default)),
        ("train_freq_unit", str, field(default="step")),  # with train_freq, SB3's (train_freq, unit): "step" or "episode"
    ]
    derived = [(name, kind, field(default=default)) for name, (kind, default) in constructor_fields().items()]
    schema = make_dataclass("AlgoConfig", translated[:3] + derived + translated[3:])
    schema.__module__ = __name__
    schema.__doc__ = (
        "Constructor arguments of :class:`sb3_td3x.TD3X` (same names and defaults, read from its signature), plus "
        "``exploration_noise`` (SB3's ``action_noise``), ``net_arch`` and ``n_critics`` (``policy_kwargs``) and "
        "``train_freq_unit`` (with ``train_freq``, SB3's tuple)."
    )
    return schema


AlgoConfig = _algo_config()


@dataclass
class EnvConfig:
    """One gymnasium environment and the per-environment settings of the paper."""

    name: str = MISSING  # short name used in run folders, e.g. "ant"
    id: str = MISSING  # gymnasium id, e.g. "Ant-v5"
    total_timesteps: int = 1_000_000
    learning_starts: int = 1_000
    eval_freq: int = 5_000
    max_episode_steps: int | None = None  # None: the id's registered limit
    normalize_obs: bool = False  # wrap in VecNormalize (statistics are saved with every checkpoint)
    normalize_reward: bool = False
    kwargs: dict[str, Any] = field(default_factory=dict)  # passed to gymnasium.make


@dataclass
class EvalConfig:
    """Periodic deterministic evaluation on a separate environment."""

    freq: int = II("env.eval_freq")  # environment steps between evaluations
    n_episodes: int = 10
    deterministic: bool = True
    seed_offset: int = 1_000_000  # the evaluation env is seeded with seed + seed_offset before every evaluation
    # The critic's value estimate against the true discounted return on the evaluation episodes
    # (sb3_td3x/experiment/value_bias.py): eval/value_estimate, true_value, overestimation, normalized_bias
    value_bias: bool = True
    # A state of a time-limit-truncated episode counts when its missing return tail weighs gamma^k <= this
    value_horizon_tolerance: float = 0.01


@dataclass
class CheckpointConfig:
    """Checkpoints under ``<run_dir>/checkpoints/{last,best}``."""

    freq: int = 50_000  # environment steps between 'last' checkpoints (also written at the end and on SIGINT/SIGTERM)
    save_best: bool = True  # write 'best' whenever an evaluation beats the previous best
    best_replay_buffer: bool = False  # also copy the replay buffer into 'best' (it is always in 'last')


@dataclass
class WandbConfig:
    project: str = "sb3-td3x"
    entity: str | None = None
    group: str | None = None
    tags: list[str] = field(default_factory=list)
    mode: str = "auto"  # "auto" (online when an API key is configured, else offline), "online", "offline", "disabled"


@dataclass
class LoggerConfig:
    name: str = "tensorboard"
    tensorboard: bool = True  # events under <run_dir>/tb
    log_interval: int = 4  # episodes between two dumps of SB3's training metrics
    wandb: WandbConfig | None = None


@dataclass
class VideoConfig:
    """A video of the final deterministic policy, written to ``<run_dir>/video.<format>``."""

    n_episodes: int = 1
    fps: int | None = None  # None: the environment's render_fps
    width: int = 480
    height: int = 480
    format: str = "gif"  # "gif" (Pillow) or "mp4" (needs imageio-ffmpeg)


@dataclass
class ExperimentConfig:
    algo: AlgoConfig = MISSING
    env: EnvConfig = MISSING
    eval: EvalConfig = MISSING
    logger: LoggerConfig = MISSING
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    video: VideoConfig | None = None
    seed: int = II("td3x.first_seed:${seeds}")  # 0, or with seeds=[...] the first of them (its run folder is Hydra's)
    # Several seeds trained together (sb3_td3x.SeedBatch, in seed_processes processes), each as its lone seed= run
    seeds: list[int] | None = None
    # How many processes train them: null (auto) one per core of the run, at most one per seed (every P-th seed
    # each: a seed computes what its lone run computes however they are grouped; on a GPU under CUDA MPS)
    seed_processes: int | None = None
    # Set by the run (not by hand): each seed's run folder, saved in every seed's config.yaml so that resume=<any
    # seed's folder> resumes the whole batch
    seed_run_dirs: list[str] | None = None
    n_envs: int = 1
    device: str = "auto"
    total_timesteps: int = II("env.total_timesteps")
    resume: str | None = None  # a run folder to continue; the run goes on in that folder with its saved config
    run_dir: str = "runs/${env.name}/${algo.name}/seed${seed}/${now:%Y-%m-%d_%H-%M-%S}"
    # None: all cores for a single run; in a multirun, the cores shared among the jobs running at once (one each
    # with the default launcher settings); in a sweep trial, 1. A number: exactly that.
    torch_threads: int | None = None
    progress_bar: bool = True
    # Several processes of a launch on one GPU (a joblib or submitit_local multirun, local sweep workers) share it
    # through CUDA MPS where the machine has it (sb3_td3x/experiment/mps.py); false: time slices of the driver
    mps: bool = True


def register_configs() -> None:
    """Register the schemas; ``conf/`` refers to them by these names."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=ExperimentConfig)
    cs.store(group="algo", name="base_algo", node=AlgoConfig)
    for name, kwargs in PRESETS.items():  # conf/algo/<preset>.yaml: `- preset@_here_: <preset>` in its defaults
        cs.store(group="algo/preset", name=name, node=preset_config(kwargs))
    cs.store(group="env", name="base_env", node=EnvConfig)
    cs.store(group="eval", name="base_eval", node=EvalConfig)
    cs.store(group="logger", name="base_logger", node=LoggerConfig)
    cs.store(group="video", name="base_video", node=VideoConfig)


def preset_config(kwargs: dict[str, Any]) -> dict[str, Any]:
    """A preset's ``TD3X`` keyword arguments (:data:`sb3_td3x.PRESETS`) as algo config fields: ``policy_kwargs``'s
    ``net_arch`` and ``n_critics`` become fields of their own."""
    config = {key: value for key, value in kwargs.items() if key != "policy_kwargs"}
    config.update(kwargs.get("policy_kwargs", {}))
    unknown = sorted(set(config) - {f.name for f in fields(AlgoConfig)})
    if unknown:
        raise ValueError(f"a preset sets {', '.join(unknown)}, which the algo config has no field for")
    return config


def _run_dir(resume: str | None, run_dir: str) -> str:
    from sb3_td3x.experiment.run_folder import hydra_run_dir

    return hydra_run_dir(resume, run_dir)


def _records_subdir(resume: str | None, restarts: Any = 0) -> str:
    """Cached, so that every reading names the same folder (a resume's is dated). ``restarts`` (the SLURM job's
    restart count) is in the cache's key only: a requeued job names its own even with the first start's cache
    (Hydra's submitit launcher copies the launching process's cache into each job)."""
    from sb3_td3x.experiment.run_folder import hydra_records_subdir

    return hydra_records_subdir(resume)


def _first_seed(seeds: Any) -> int:
    """The default ``seed``: 0, or the first of ``seeds=[...]``, whose folder Hydra then makes (checkpoints.seed_folders
    names the others alike)."""
    return int(seeds[0]) if seeds else 0


def _seed_label(seed: int, seeds: Any) -> str:
    """``seed3``, or ``seeds1-3`` for a batch (``seeds=[1,3]``): a multirun job's folder name."""
    return f"seed{seed}" if seeds is None else "seeds" + "-".join(str(s) for s in seeds)


register_configs()
if not OmegaConf.has_resolver("td3x.run_dir"):
    # conf/config.yaml: the folder a run trains in; a resumed run, or a job started again, goes on in its own
    OmegaConf.register_new_resolver("td3x.run_dir", _run_dir)
if not OmegaConf.has_resolver("td3x.records_subdir"):
    # conf/config.yaml: Hydra's record of each launch; a resumed or requeued run adds its own beside the first
    OmegaConf.register_new_resolver("td3x.records_subdir", _records_subdir, use_cache=True)
if not OmegaConf.has_resolver("td3x.first_seed"):
    OmegaConf.register_new_resolver("td3x.first_seed", _first_seed)
if not OmegaConf.has_resolver("td3x.seed_label"):
    # conf/config.yaml: a multirun job's folder names its seed, or its batch's seeds
    OmegaConf.register_new_resolver("td3x.seed_label", _seed_label)


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


def whole_float_problems(overrides: list[str]) -> list[str]:
    """For each whole float given to an integer field (``total_timesteps=1e6``: Hydra reads a float, which the field
    refuses), how to write it: ``total_timesteps=1000000``, or Hydra's cast ``total_timesteps=int(1e6)``."""
    keys = _integer_keys()
    problems = []
    for arg in overrides:
        match = re.match(r"^[+~]{0,2}([A-Za-z_][\w.]*)=([-+]?[0-9._]*(?:[eE][-+]?[0-9]+)?)$", arg)
        if match is None or match.group(1) not in keys or re.fullmatch(r"[-+]?[0-9_]+", match.group(2)):
            continue
        try:
            value = float(match.group(2))
        except ValueError:
            continue
        if math.isfinite(value) and value.is_integer():
            key, text = match.groups()
            problems.append(f"{arg}: {key} is an integer, write {key}={int(value)} or {key}=int({text})")
    return problems


#: Config groups of conf/config.yaml; a resumed run keeps the choices it was started with.
CONFIG_GROUPS = ("algo", "env", "eval", "logger", "video", "debug")


def compose_config(overrides: list[str] | None = None, conf_dir: Path = CONF_DIR) -> DictConfig:
    """The config ``python run.py <overrides>`` would run, composed without starting a Hydra app.

    ``run_dir`` keeps its default interpolation; set it before :func:`~sb3_td3x.experiment.runner.run_experiment`.
    """
    overrides = list(overrides or [])
    problems = whole_float_problems(overrides)
    if problems:
        raise ConfigError("; ".join(problems) + ".")
    with initialize_config_dir(config_dir=str(Path(conf_dir).resolve()), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def check_config(cfg: DictConfig) -> None:
    """Check ranges and names that the types cannot; raise one :class:`ConfigError` listing every problem."""
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
    problems += _device_problems(cfg.device)

    algo = cfg.algo
    # The constructor's own range checks (TD3X.hyperparameter_problems): one source of truth for both.
    for name, allowed in TD3X.hyperparameter_problems(**{name: algo[name] for name in constructor_fields()}):
        problems.append(f"algo.{name}={algo[name]} must be {allowed}")
    need(algo.train_freq >= 1, f"algo.train_freq={algo.train_freq} must be >= 1")
    need(
        algo.train_freq_unit in ("step", "episode"),
        f"algo.train_freq_unit={algo.train_freq_unit!r} must be 'step' or 'episode'",
    )
    need(algo.exploration_noise >= 0, f"algo.exploration_noise={algo.exploration_noise} must be >= 0")
    need(
        algo.net_arch is None or (len(algo.net_arch) > 0 and min(algo.net_arch) >= 1),
        f"algo.net_arch={algo.net_arch} must list positive layer widths, or be null for the policy's default",
    )
    need(algo.n_critics >= 1, f"algo.n_critics={algo.n_critics} must be >= 1")

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


def _device_problems(device: str) -> list[str]:
    if device == "auto":
        return []
    try:
        parsed = torch.device(device)
    except RuntimeError:
        return [f"device={device!r} is not a torch device; use auto, cpu, cuda or cuda:N"]
    if parsed.type == "cuda" and not torch.cuda.is_available():
        return [f"device={device!r} but this machine has no CUDA GPU; use device=cpu or device=auto"]
    return []


def _env_id_problems(env_id: str) -> list[str]:
    if env_id in gym.registry:
        return []
    close = difflib.get_close_matches(env_id, list(gym.registry), n=3)
    hint = f" Did you mean {', '.join(close)}?" if close else ""
    return [f"env.id={env_id!r} is not a registered gymnasium environment.{hint}"]


def public_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as plain containers, with its secrets masked (``***``) by
    :func:`sb3_td3x.common.redaction.redact`: the value under a credential-like key, the password of a URL.

    This is what is saved in the run folder and sent to W&B. The schemas have no credential field (W&B reads its
    key from ``WANDB_API_KEY`` or ``wandb login``), but free-form dicts such as ``env.kwargs`` could receive one.
    """
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    return redact(container)  # type: ignore[return-value]
