"""Build the algorithm named by ``cfg.algo._target_`` from the config.

``sb3_td3x.TD3X`` and its subclasses (``sb3_td3x.DDPG``) take every field. SB3's own ``stable_baselines3.TD3``
(``algo=sb3_td3``, the baseline of the results pages) takes the fields both share; a TD3X-only field set away from
its default is an error rather than silently ignored.
"""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
from gymnasium import spaces
from hydra.utils import get_class
from omegaconf import DictConfig
from stable_baselines3 import TD3
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.vec_env import VecEnv

from sb3_td3x import TD3X
from sb3_td3x.experiment.configs.schemas import constructor_fields
from sb3_td3x.experiment.errors import ConfigError

# TD3X arguments that SB3's TD3 lacks, with TD3X's defaults, at which TD3X computes what SB3's TD3 does.
_TD3X_ONLY = {
    name: default
    for name, (_, default) in constructor_fields(TD3X).items()
    if name not in inspect.signature(TD3.__init__).parameters
}


def algorithm_class(algo_cfg: DictConfig) -> type[TD3X | TD3]:
    """The class named by ``algo._target_``: :class:`sb3_td3x.TD3X`, SB3's ``TD3``, or a subclass of either."""
    try:
        cls = get_class(algo_cfg._target_)
    except Exception as error:  # hydra wraps the ImportError/AttributeError in its own exception types
        raise ConfigError(f"algo._target_={algo_cfg._target_!r} cannot be imported ({error}).") from None
    if not (isinstance(cls, type) and issubclass(cls, (TD3X, TD3))):
        raise ConfigError(
            f"algo._target_={algo_cfg._target_!r} is not sb3_td3x.TD3X, stable_baselines3.TD3 or a subclass of either."
        )
    return cls


def algorithm_kwargs(algo_cfg: DictConfig, n_actions: int) -> dict[str, Any]:
    """Constructor keyword arguments of :class:`sb3_td3x.TD3X` for ``algo_cfg`` (without policy, env, seed, device).

    ``exploration_noise`` becomes ``NormalActionNoise(0, sigma)`` (no noise object when sigma is 0), ``net_arch``
    and ``n_critics`` go into ``policy_kwargs``, ``train_freq`` and ``train_freq_unit`` make SB3's tuple.
    """
    kwargs = {key: algo_cfg[key] for key in constructor_fields(TD3X)}
    if issubclass(algorithm_class(algo_cfg), TD3):
        changed = [f"algo.{key}={kwargs[key]}" for key, default in _TD3X_ONLY.items() if kwargs[key] != default]
        if changed:
            raise ConfigError(
                f"{', '.join(changed)}: SB3's TD3 (algo._target_={algo_cfg._target_}) has no such option; "
                "use algo=td3 (sb3_td3x.TD3X) or drop the override."
            )
        kwargs = {key: value for key, value in kwargs.items() if key not in _TD3X_ONLY}
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
