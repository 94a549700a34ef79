"""DDPG and the paper's ablations (Fujimoto et al. 2018, Table 2) as TD3X presets: explicit switches, no magic values.

Each preset is a dict of ``TD3X`` keyword arguments; ``TD3X("MlpPolicy", env, **PRESETS["td3_no_cdq"])``. The
experiment configs ``conf/algo/<name>.yaml`` take their switches from here.
"""

from __future__ import annotations

from typing import Any, TypeVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_td3x.td3x.td3x import TD3X

SelfDDPG = TypeVar("SelfDDPG", bound="DDPG")

PRESETS: dict[str, dict[str, Any]] = {
    # The full algorithm (SB3's TD3 defaults).
    "td3": {},
    # DDPG (Lillicrap et al. 2016) as in SB3 and the paper's "our DDPG": one critic, no target smoothing,
    # no clipped double-Q, actor and targets updated at every gradient step.
    "ddpg": {
        "policy_delay": 1,
        "target_policy_smoothing": False,
        "clipped_double_q": False,
        "policy_kwargs": {"n_critics": 1},
    },
    # TD3 - TPS: without target policy smoothing.
    "td3_no_smoothing": {"target_policy_smoothing": False},
    # TD3 - CDQ: without clipped double-Q learning (a single critic).
    "td3_no_cdq": {"clipped_double_q": False, "policy_kwargs": {"n_critics": 1}},
    # TD3 - DP: without delayed policy updates.
    "td3_no_delay": {"policy_delay": 1},
}


def preset_kwargs(name: str, **overrides: Any) -> dict[str, Any]:
    """The keyword arguments of preset ``name`` merged with ``overrides`` (``policy_kwargs`` merged key by key)."""
    if name not in PRESETS:
        raise ValueError(f"Unknown TD3X preset {name!r}; choose one of {sorted(PRESETS)}.")
    kwargs = {k: (dict(v) if isinstance(v, dict) else v) for k, v in PRESETS[name].items()}
    policy_kwargs = {**kwargs.pop("policy_kwargs", {}), **(overrides.pop("policy_kwargs", None) or {})}
    kwargs.update(overrides)
    if policy_kwargs:
        kwargs["policy_kwargs"] = policy_kwargs
    return kwargs


class DDPG(TD3X):
    """
    Deep Deterministic Policy Gradient (DDPG) as a TD3X preset: TD3 with its three tricks switched off.

    Lillicrap et al. (2016), "Continuous control with deep reinforcement learning", https://arxiv.org/abs/1509.02971,
    in the form of SB3's DDPG and of the TD3 paper's "our DDPG": a single critic (``n_critics=1``), no target policy
    smoothing, no clipped double-Q, and the actor and targets updated at every gradient step (``policy_delay=1``).
    Every argument of :class:`~sb3_td3x.TD3X` is accepted; the preset's switches can be overridden explicitly.
    """

    def __init__(
        self,
        policy: Any,
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        **td3x_kwargs: Any,
    ):
        """SB3's ``DDPG`` arguments, in SB3's order; any other ``TD3X`` argument by keyword."""
        super().__init__(
            policy,
            env,
            **preset_kwargs(
                "ddpg",
                learning_rate=learning_rate,
                buffer_size=buffer_size,
                learning_starts=learning_starts,
                batch_size=batch_size,
                tau=tau,
                gamma=gamma,
                train_freq=train_freq,
                gradient_steps=gradient_steps,
                action_noise=action_noise,
                replay_buffer_class=replay_buffer_class,
                replay_buffer_kwargs=replay_buffer_kwargs,
                optimize_memory_usage=optimize_memory_usage,
                n_steps=n_steps,
                tensorboard_log=tensorboard_log,
                policy_kwargs=policy_kwargs,
                verbose=verbose,
                seed=seed,
                device=device,
                _init_setup_model=_init_setup_model,
                **td3x_kwargs,
            ),
        )

    def learn(
        self: SelfDDPG,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DDPG",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDDPG:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
