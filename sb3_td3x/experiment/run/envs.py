"""Environment factory: the training env, the separately seeded evaluation env, and the env that renders the video of
the final policy (:func:`record_video`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
from omegaconf import DictConfig, OmegaConf
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize

from sb3_td3x.experiment.errors import ConfigError


def gym_make_kwargs(env_cfg: DictConfig) -> dict[str, Any]:
    """Keyword arguments of ``gymnasium.make`` for this env config (besides the id)."""
    kwargs: dict[str, Any] = OmegaConf.to_container(env_cfg.kwargs, resolve=True)  # type: ignore[assignment]
    if env_cfg.max_episode_steps is not None:
        kwargs["max_episode_steps"] = env_cfg.max_episode_steps
    return kwargs


def make_train_env(env_cfg: DictConfig, n_envs: int, seed: int) -> VecEnv:
    """``n_envs`` Monitor-wrapped copies in a DummyVecEnv (sub-env ``i`` seeded with ``seed + i``).

    Wrapped in ``VecNormalize`` when ``env.normalize_obs`` or ``env.normalize_reward`` is set.
    DummyVecEnv rather than subprocesses: TD3 is bound by its gradient steps, not by stepping the env.
    """
    kwargs = gym_make_kwargs(env_cfg)
    try:
        venv = make_vec_env(env_cfg.id, n_envs=n_envs, seed=seed, env_kwargs=kwargs, vec_env_cls=DummyVecEnv)
    except TypeError as error:  # an argument the environment does not take (env.kwargs)
        raise ConfigError(
            f"gymnasium.make({env_cfg.id!r}, **{kwargs}) failed: {error}. Check env.kwargs against the arguments of "
            f"{env_cfg.id} (gymnasium's documentation of the environment lists them)."
        ) from None
    if env_cfg.normalize_obs or env_cfg.normalize_reward:
        venv = VecNormalize(venv, norm_obs=env_cfg.normalize_obs, norm_reward=env_cfg.normalize_reward)
    return venv


def make_eval_env(env_cfg: DictConfig) -> VecEnv:
    """One Monitor-wrapped copy for evaluation; its seed is set before every evaluation by the caller.

    When the training env normalises observations, this one gets a frozen ``VecNormalize`` whose statistics
    are copied from the training env before each evaluation; rewards are never normalised here.
    """
    venv: VecEnv = DummyVecEnv([lambda: Monitor(gym.make(env_cfg.id, **gym_make_kwargs(env_cfg)))])
    if env_cfg.normalize_obs or env_cfg.normalize_reward:
        venv = VecNormalize(venv, training=False, norm_obs=env_cfg.normalize_obs, norm_reward=False)
    return venv


def make_render_env(env_cfg: DictConfig, width: int, height: int) -> gym.Env:
    """A single env that renders RGB frames (MuJoCo envs take the frame size; classic control ones do not)."""
    kwargs = gym_make_kwargs(env_cfg)
    try:
        return gym.make(env_cfg.id, render_mode="rgb_array", width=width, height=height, **kwargs)
    except TypeError:
        return gym.make(env_cfg.id, render_mode="rgb_array", **kwargs)


def record_video(model, env_cfg: DictConfig, video_cfg: DictConfig, path: Path, seed: int) -> Path:
    """Render ``video_cfg.n_episodes`` episodes of the deterministic policy to ``path`` (GIF or MP4).

    Observation normalisation, when the run used it, is applied with the training statistics. Off-screen
    MuJoCo rendering needs ``MUJOCO_GL=egl`` or ``MUJOCO_GL=osmesa``.
    """
    import imageio.v2 as imageio  # only video runs need it

    env = make_render_env(env_cfg, video_cfg.width, video_cfg.height)
    vec_normalize = model.get_vec_normalize_env()
    frames = []
    try:
        for episode in range(video_cfg.n_episodes):
            obs, _ = env.reset(seed=seed + episode)
            frames.append(env.render())
            done = False
            while not done:
                policy_obs = vec_normalize.normalize_obs(obs) if vec_normalize is not None else obs
                action, _ = model.predict(policy_obs, deterministic=True)
                obs, _, terminated, truncated, _ = env.step(action)
                frames.append(env.render())
                done = terminated or truncated
        fps = video_cfg.fps or env.metadata.get("render_fps", 30)
    finally:
        env.close()
    if video_cfg.format == "gif":
        imageio.mimsave(path, frames, duration=1000 / fps, loop=0)
    else:
        imageio.mimsave(path, frames, fps=fps)
    return path
