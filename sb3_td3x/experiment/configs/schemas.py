"""Typed schemas of the configuration tree in ``conf/``, and the resolvers its YAML files use.

The dataclasses are registered in Hydra's ``ConfigStore`` when this module is imported; every YAML in ``conf/``
extends one of them (``defaults: [base_algo, _self_]``), so a misspelt key or a value of the wrong type fails while
Hydra composes the config, before anything is built. :mod:`~sb3_td3x.experiment.configs.compose` composes the config
and checks what types cannot express.
"""

from __future__ import annotations

import inspect
import time
import types
import typing
from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import II, MISSING, OmegaConf
from stable_baselines3.td3.policies import TD3Policy

from sb3_td3x.td3x.presets import PRESETS
from sb3_td3x.td3x.td3x import TD3X

# conf/ of a source checkout (run.py's config_path).
CONF_DIR = Path(__file__).resolve().parents[3] / "conf"

# TD3X's constructor arguments that the run sets, not the algo config: seed and device (top-level fields), verbose,
# and TensorBoard (the logger group).
SET_BY_THE_RUN = ("seed", "device", "verbose", "tensorboard_log")
_SIMPLE_TYPES: dict[str, type] = {"int": int, "float": float, "bool": bool, "str": str}


def plain_type(annotation: Any) -> tuple[type, bool] | None:
    """The one plain type (``int``, ``float``, ``bool`` or ``str``) that a constructor argument's annotation allows,
    and whether it allows None too: ``float | Schedule | None`` gives ``(float, True)``. None when it allows none or
    several (an object such as ``action_noise``, or no annotation). Reads annotations written as text (``from
    __future__ import annotations``) and as types alike."""
    if isinstance(annotation, str):
        names = [member.strip() for member in annotation.split("|")]
    else:
        union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
        members = typing.get_args(annotation) if union else (annotation,)
        names = ["None" if member is type(None) else getattr(member, "__name__", str(member)) for member in members]
    plain = [_SIMPLE_TYPES[name] for name in names if name in _SIMPLE_TYPES]
    if len(plain) != 1:
        return None
    return plain[0], "None" in names


def constructor_fields(cls: type = TD3X) -> dict[str, tuple[Any, Any]]:
    """``{name: (type, default)}`` of the arguments of ``cls.__init__`` that the algo config holds under the same
    name: those with a default and a plain type, except :data:`SET_BY_THE_RUN` and private ones."""
    result = {}
    for name, parameter in inspect.signature(cls.__init__).parameters.items():
        if parameter.default is inspect.Parameter.empty or name.startswith("_") or name in SET_BY_THE_RUN:
            continue
        kind = plain_type(parameter.annotation)
        if kind is not None:
            result[name] = (kind[0] | None if kind[1] else kind[0], parameter.default)
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
    # (sb3_td3x/experiment/run/value_bias.py): eval/value_estimate, true_value, overestimation, normalized_bias
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
    # through CUDA MPS where the machine has it (sb3_td3x/experiment/launch/mps.py); false: time slices of the driver
    mps: bool = True


def register_configs() -> None:
    """Register the schemas; ``conf/`` refers to them by these names."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=ExperimentConfig)
    # The algo node takes keys beyond TD3X's typed fields: the arguments of the class algo._target_ names, which
    # configs.algos.argument_problems checks against that class's signature before anything is built.
    algo = OmegaConf.structured(AlgoConfig)
    OmegaConf.set_struct(algo, False)
    cs.store(group="algo", name="base_algo", node=algo)
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


def _records_subdir(resume: str | None, restarts: Any = 0) -> str:
    """``hydra.output_subdir``: where Hydra writes its record of a launch in the run folder. The first launch's stays
    in ``.hydra``; a resume adds ``.hydra/resumed_<date>``, a SLURM job started again ``.hydra/requeued_<n>``
    (``restarts``: conf/config.yaml passes ``SLURM_RESTART_COUNT``, read in the job itself). Cached, so that every
    reading names the same folder (a resume's is dated); the restart count is part of the cache's key, so a requeued
    job names its own even with the first start's cache (Hydra's submitit launcher copies the launching process's
    cache into each job)."""
    if resume is not None:
        return f".hydra/resumed_{time.strftime('%Y-%m-%d_%H-%M-%S')}"
    try:
        count = int(restarts)
    except (TypeError, ValueError):
        count = 0
    return f".hydra/requeued_{count}" if count > 0 else ".hydra"


def _first_seed(seeds: Any) -> int:
    """The default ``seed``: 0, or the first of ``seeds=[...]``, whose folder Hydra then makes (layout.seed_folders
    names the others alike)."""
    return int(seeds[0]) if seeds else 0


def _seed_label(seed: int, seeds: Any) -> str:
    """``seed3``, or ``seeds1-3`` for a batch (``seeds=[1,3]``): a multirun job's folder name."""
    return f"seed{seed}" if seeds is None else "seeds" + "-".join(str(s) for s in seeds)


register_configs()
if not OmegaConf.has_resolver("td3x.records_subdir"):
    # conf/config.yaml: Hydra's record of each launch; a resumed or requeued run adds its own beside the first
    OmegaConf.register_new_resolver("td3x.records_subdir", _records_subdir, use_cache=True)
if not OmegaConf.has_resolver("td3x.first_seed"):
    OmegaConf.register_new_resolver("td3x.first_seed", _first_seed)
if not OmegaConf.has_resolver("td3x.seed_label"):
    # conf/config.yaml: a multirun job's folder names its seed, or its batch's seeds
    OmegaConf.register_new_resolver("td3x.seed_label", _seed_label)


#: Config groups of conf/config.yaml; a resumed run keeps the choices it was started with.
CONFIG_GROUPS = ("algo", "env", "eval", "logger", "video", "debug")
