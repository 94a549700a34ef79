"""The algorithm a config trains: the class that ``algo._target_`` names, the arguments the algo config gives it,
checked against that class's own signature, and the algorithm built from them.

The algo config holds :class:`sb3_td3x.TD3X`'s constructor arguments as typed fields with TD3X's defaults
(:data:`~sb3_td3x.experiment.configs.schemas.AlgoConfig`), four that become SB3's objects (``exploration_noise``,
``net_arch``, ``n_critics``, ``train_freq_unit``), and whatever a command line or a YAML file adds: the arguments of
another class, ``algo._target_=mymodule.MyTD3 +algo.my_arg=0.5``. :func:`argument_problems` checks every key against
the class ``_target_`` names: its ``__init__``, and its bases' for as long as each passes ``**kwargs`` on
(:func:`accepted_arguments`). A key the class does not take is refused, with the closest one it does take; so is a
value of another type than the argument's annotation says (``int``, ``float``, ``bool``, ``str``, optional or not). A
TD3X field that the class does not take (SB3's ``TD3`` has no ``critic_learning_rate``) is left out at its default and
refused when set. What is built is what ``config.yaml`` records.
"""

from __future__ import annotations

import difflib
import inspect
import logging
import os
from typing import Any

import numpy as np
from gymnasium import spaces
from hydra.utils import get_class
from omegaconf import DictConfig, ListConfig, OmegaConf
from stable_baselines3 import TD3
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.vec_env import VecEnv

from sb3_td3x import TD3X
from sb3_td3x.experiment.configs.schemas import SET_BY_THE_RUN, constructor_fields, plain_type
from sb3_td3x.experiment.errors import ConfigError

#: Keys of the algo config that are no constructor argument of their own: they name the class and the run, or become
#: SB3's objects (``exploration_noise``: ``action_noise``; ``net_arch``, ``n_critics``: ``policy_kwargs``;
#: ``train_freq_unit``: with ``train_freq``, SB3's tuple).
TRANSLATED = ("_target_", "name", "policy", "exploration_noise", "net_arch", "n_critics", "train_freq_unit")
#: Constructor arguments the algo config gives in another form (above), or that are not the algo config's.
_NOT_GIVEN_AS_IS = ("self", "env", "policy", "action_noise", "policy_kwargs", *SET_BY_THE_RUN)
#: The algo config's typed fields and their defaults (TD3X's).
_SCHEMA_DEFAULTS = {name: default for name, (_, default) in constructor_fields(TD3X).items()}


def algorithm_class(algo_cfg: DictConfig) -> type[TD3X | TD3]:
    """The class named by ``algo._target_``: :class:`sb3_td3x.TD3X`, SB3's ``TD3``, or a subclass of either."""
    hydra_log = logging.getLogger("hydra.utils")  # get_class logs its failure at ERROR, then raises it: said once below
    level = hydra_log.level
    hydra_log.setLevel(logging.CRITICAL)
    try:
        cls = get_class(algo_cfg._target_)
    except Exception as error:  # hydra wraps the ImportError/AttributeError in its own exception types
        raise ConfigError(
            f"algo._target_={algo_cfg._target_!r} cannot be imported ({error}). A class of your own goes in a module that "
            "Python finds: in the folder you start run.py from, or on PYTHONPATH."
        ) from None
    finally:
        hydra_log.setLevel(level)
    if not (isinstance(cls, type) and issubclass(cls, (TD3X, TD3))):
        raise ConfigError(
            f"algo._target_={algo_cfg._target_!r} is not sb3_td3x.TD3X, stable_baselines3.TD3 or a subclass of either."
        )
    return cls


def accepted_arguments(cls: type) -> dict[str, inspect.Parameter]:
    """The keyword arguments ``cls(...)`` takes: those of its ``__init__``, and of its bases' (in the method resolution
    order) for as long as each ``__init__`` takes ``**kwargs``, which it is taken to pass on."""
    accepted: dict[str, inspect.Parameter] = {}
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        parameters = inspect.signature(init).parameters.values()
        for parameter in parameters:
            if parameter.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY):
                accepted.setdefault(parameter.name, parameter)
        if not any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters):
            break
    return accepted


def argument_problems(algo_cfg: DictConfig) -> list[str]:
    """What is wrong with the arguments ``algo_cfg`` gives the class it names (see the module's docstring), one
    message each; an empty list when the class takes them all."""
    cls = algorithm_class(algo_cfg)
    accepted = accepted_arguments(cls)
    named = f"{cls.__name__} (algo._target_={algo_cfg._target_})"
    takes = sorted(name for name in accepted if name not in _NOT_GIVEN_AS_IS and not name.startswith("_"))
    problems = []
    for key in algo_cfg:
        key = str(key)
        if key in TRANSLATED:
            continue
        value = _plain(algo_cfg[key])
        if key in _NOT_GIVEN_AS_IS:
            problems.append(f"algo.{key}: {_given_elsewhere(key)}")
        elif key in accepted and not key.startswith("_"):
            wrong = _type_problem(value, accepted[key].annotation)
            if wrong is not None:
                problems.append(f"algo.{key}={value!r}: {named} takes {key} as {wrong}")
        elif key in _SCHEMA_DEFAULTS:
            if value != _SCHEMA_DEFAULTS[key]:
                problems.append(
                    f"algo.{key}={value}: {named} has no such argument (TD3X's, left out at its default "
                    f"{_SCHEMA_DEFAULTS[key]}); drop the override, or use a class that takes it (algo=td3: sb3_td3x.TD3X)"
                )
        else:
            close = difflib.get_close_matches(key, takes, n=1)
            hint = f" Did you mean algo.{close[0]}?" if close else ""
            problems.append(
                f"algo.{key}={value}: {named} takes no argument {key!r}.{hint} Its arguments: {', '.join(takes)}"
            )
    return problems


def _given_elsewhere(key: str) -> str:
    if key in SET_BY_THE_RUN:
        where = {"seed": "seed=", "device": "device=", "verbose": "the log level", "tensorboard_log": "logger.tensorboard"}
        return f"the run sets it ({where[key]}), not the algo config"
    if key == "action_noise":
        return "the algo config gives it as algo.exploration_noise (the std of a Gaussian; 0: none)"
    if key == "policy_kwargs":
        return "the algo config gives it as algo.net_arch and algo.n_critics"
    return "the run gives it (the environment and the policy: algo.policy)"


def _type_problem(value: Any, annotation: Any) -> str | None:
    """What ``value`` should be for an argument annotated ``annotation``, when it is not; None when it fits, or when
    the annotation names no plain type (``int``, ``float``, ``bool``, ``str``, optional or not)."""
    kind = plain_type(annotation)
    if kind is None:
        return None
    base, optional = kind
    if value is None:
        return None if optional else f"a {base.__name__}, not null"
    if isinstance(value, bool):
        fits = base is bool
    elif isinstance(value, int):
        fits = base in (int, float)
    else:
        fits = isinstance(value, base)
    return None if fits else f"a {base.__name__}{' or null' if optional else ''} (its annotation), not {value!r}"


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value


def algorithm_kwargs(algo_cfg: DictConfig, n_actions: int) -> dict[str, Any]:
    """The keyword arguments of the class ``algo_cfg`` names (without policy, env, seed, device): every key it takes
    (:func:`argument_problems` refuses the others), ``exploration_noise`` as ``NormalActionNoise(0, sigma)`` (no noise
    object when sigma is 0), ``net_arch`` and ``n_critics`` in ``policy_kwargs``, ``train_freq`` and
    ``train_freq_unit`` as SB3's tuple.

    :raises ConfigError: :func:`argument_problems`'s, all of them
    """
    problems = argument_problems(algo_cfg)
    if problems:
        raise ConfigError("; ".join(problems) + ".")
    accepted = accepted_arguments(algorithm_class(algo_cfg))
    kwargs = {str(key): _plain(algo_cfg[key]) for key in algo_cfg if key not in TRANSLATED and key in accepted}
    if algo_cfg.exploration_noise > 0:
        sigma = algo_cfg.exploration_noise * np.ones(n_actions, dtype=np.float32)
        kwargs["action_noise"] = NormalActionNoise(mean=np.zeros(n_actions, dtype=np.float32), sigma=sigma)
    net_arch = None if algo_cfg.net_arch is None else list(algo_cfg.net_arch)  # None: the policy's default
    kwargs["policy_kwargs"] = {"net_arch": net_arch, "n_critics": algo_cfg.n_critics}
    kwargs["train_freq"] = (algo_cfg.train_freq, algo_cfg.train_freq_unit)
    return kwargs


def build_algorithm(cfg: DictConfig, env: VecEnv) -> TD3X | TD3:
    """A fresh algorithm for ``env``; a ``ValueError`` of the constructor becomes a :class:`ConfigError`."""
    cls = algorithm_class(cfg.algo)
    kwargs = algorithm_kwargs(cfg.algo, n_actions=int(np.prod(env.action_space.shape)))
    _check_policy(cfg.algo.policy, env.observation_space, cfg.env.id)
    check_buffer_fits(cfg, env)
    try:
        return cls(cfg.algo.policy, env, seed=cfg.seed, device=cfg.device, **kwargs)
    except ValueError as error:
        raise ConfigError(f"The algorithm rejected the config: {error}") from None
    except MemoryError:
        raise ConfigError(
            f"algo.buffer_size={cfg.algo.buffer_size}: the replay buffer could not be allocated (out of memory). "
            "Lower algo.buffer_size."
        ) from None


def _check_policy(policy: str, observation_space: spaces.Space, env_id: str) -> None:
    """SB3's policy names against the observations they need: ``CnnPolicy`` images, ``MultiInputPolicy`` a Dict."""
    if policy == "CnnPolicy" and not is_image_space(observation_space, check_channels=False):
        raise ConfigError(
            f"algo.policy=CnnPolicy needs image observations, but {env_id} observes {observation_space}. "
            "Use algo.policy=MlpPolicy for vector observations."
        )
    if policy == "MultiInputPolicy" and not isinstance(observation_space, spaces.Dict):
        raise ConfigError(
            f"algo.policy=MultiInputPolicy needs Dict observations, but {env_id} observes {observation_space}. "
            "Use algo.policy=MlpPolicy."
        )
    if policy == "MlpPolicy" and isinstance(observation_space, spaces.Dict):
        raise ConfigError(f"{env_id} observes a Dict ({observation_space}); use algo.policy=MultiInputPolicy.")


def check_buffer_fits(cfg: DictConfig, env: Any) -> None:
    """A :class:`ConfigError` when the replay buffer alone would need more memory than the machine has."""
    def nbytes(space: Any) -> int:
        if isinstance(space, spaces.Dict):
            return sum(nbytes(sub) for sub in space.spaces.values())
        return int(np.prod(space.shape or (1,))) * np.dtype(space.dtype or np.float32).itemsize

    per_transition = nbytes(env.observation_space) * (1 if cfg.algo.optimize_memory_usage else 2)
    per_transition += nbytes(env.action_space) + 3 * 4  # rewards, dones, timeouts
    needed = int(cfg.algo.buffer_size) * per_transition
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not a POSIX system: nothing to compare with
        return
    if needed > memory:
        raise ConfigError(
            f"algo.buffer_size={cfg.algo.buffer_size} needs about {needed / 2**30:.1f} GiB for the replay buffer "
            f"({per_transition} bytes per transition of {cfg.env.id}), more than this machine's {memory / 2**30:.1f} GiB "
            "of memory. Lower algo.buffer_size (the paper's is 1000000)."
        )
