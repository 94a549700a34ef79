"""Overestimation made visible: the critic's value estimate against the true discounted return, at every evaluation.

TD3 (Fujimoto et al. 2018) exists to fix the overestimation of actor-critic values; its Figure 1 plots the critic's
estimate against the true discounted return of the current policy over training. This module measures the same two
numbers on the deterministic evaluation episodes that :class:`~sb3_td3x.experiment.run.callbacks.PeriodicEvaluation`
runs anyway (no extra episode):

- **Which states.** Every state s_t the evaluation episodes visit, except the last states of an episode cut by a
  time limit (below). Recorded as they run by :class:`EpisodeRecorder`, an ``evaluate_policy`` callback.
- **The estimate.** The first critic's Q_1(s_t, a_t), with a_t the action the policy took there (for the
  deterministic policy, pi(s_t)), rescaled to the policy's [-1, 1] action space with ``policy.scale_action`` as the
  replay buffer stores it. For :class:`~sb3_td3x.TD3X` (and subclasses) it is read through the model's own
  ``q_value_estimates(batch)[0]``: its ``current_q_values`` hook, the value that the critic loss regresses onto the TD
  target (so an overridden ``current_q_values`` or a subclassed critic network is what is measured), or a
  distributional critic's expected value. The batch is
  the evaluation's own transitions (s, a, s', r, terminated), built as the replay buffer would give them. SB3's
  ``TD3`` has no such hook: its ``critic(obs, actions)[0]``, which is what its ``train()`` regresses. (SB3's
  ``q1_forward``, used by the actor loss, is not used: a critic subclass that overrides ``forward`` alone would not be
  seen by it.) One batched forward pass (in chunks of :data:`CHUNK` states), under ``torch.no_grad()``, with the
  policy in evaluation mode; it draws no random numbers, so a run's curve and a resumed run are unchanged.
- **The true value.** The discounted return actually collected from s_t to the end of the episode,
  G_t = sum_{j >= t} gamma^(j - t) r_j, with the model's training ``gamma`` (one factor per step, also for n-step
  replay buffers: the critic estimates the same Q^pi either way). Rewards are those the critic was trained on:
  normalised by the training ``VecNormalize`` when the run normalises rewards (``env.normalize_reward``), raw
  otherwise. Observations are the evaluation env's, which are already normalised with the training statistics.
- **Truncated episodes.** A *terminated* episode's returns are exact. An episode cut by a time limit is missing the
  tail gamma^k V(s_T) of each return, k being the number of rewards collected from s_t (k = T - t). A state is kept
  only when that tail weighs ``gamma^k <= tolerance`` (``eval.value_horizon_tolerance``, default 0.01: with
  gamma = 0.99 the last 458 states of a truncated episode are dropped, and the first 542 of a 1000-step Hopper
  episode kept). Nothing is bootstrapped with the critic, which would bias the comparison towards the estimate.
  The estimate is compared with the true value on the same states.
- **The numbers** (means over the kept states of all the evaluation's episodes):
  ``value_estimate`` = mean Q_1, ``true_value`` = mean G, ``overestimation`` = value_estimate - true_value,
  ``normalized_bias`` = overestimation / |true_value| (the issue's REDQ-style normalisation, Chen et al. 2021; REDQ's
  released code divides each state's bias by max(|G_t|, 10) before averaging instead), ``value_states`` = how many
  states were kept. With no state kept (e.g. Pendulum-v1's 200-step episodes, always truncated, with the default
  tolerance), every value is NaN and ``value_states`` 0: when every episode ran to its time limit
  (:func:`cut_at_time_limit`), a consequence of the configuration, which
  :class:`~sb3_td3x.experiment.run.callbacks.PeriodicEvaluation` logs once at INFO with :func:`no_state_reason`. ``normalized_bias`` is NaN when |mean G| is below
  :data:`NORMALIZATION_FLOOR` times the mean |G|: returns of both signs cancel and the ratio would measure the
  cancellation, not the bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples

CHUNK = 16_384  # states per critic forward pass (bounds the memory for image observations)
NORMALIZATION_FLOOR = 1e-3


@dataclass
class Episode:
    """One recorded evaluation episode: s_0..s_{T-1}, the actions taken (env scale), r_0..r_{T-1}, s_T, how it ended."""

    observations: list[Any] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    final_observation: Any = None
    terminated: bool = False

    def __len__(self) -> int:
        return len(self.rewards)


class EpisodeRecorder:
    """An ``evaluate_policy`` callback that records every step of the episodes it runs (any number of envs).

    ``evaluate_policy`` calls it once per env and step with its ``locals()``: the observation the action was chosen
    from, the action, the reward, ``done`` and ``info`` (``terminal_observation``, ``TimeLimit.truncated``). An
    episode ends at ``done``; it is *terminated* unless the VecEnv marked it ``TimeLimit.truncated``.
    """

    def __init__(self) -> None:
        self.episodes: list[Episode] = []
        self._running: dict[int, Episode] = {}

    def __call__(self, local_vars: dict[str, Any], global_vars: dict[str, Any]) -> None:
        i = local_vars["i"]
        episode = self._running.setdefault(i, Episode())
        observations = local_vars["observations"]
        if isinstance(observations, dict):
            episode.observations.append({key: np.array(value[i]) for key, value in observations.items()})
        else:
            episode.observations.append(np.array(observations[i]))
        episode.actions.append(np.array(local_vars["actions"][i]))
        episode.rewards.append(float(local_vars["reward"]))
        if local_vars["done"]:
            info = local_vars["info"]
            final = info.get("terminal_observation")
            if final is None:  # not a VecEnv of SB3's: the next observation is all there is
                new_observations = local_vars["new_observations"]
                final = (
                    {key: value[i] for key, value in new_observations.items()}
                    if isinstance(new_observations, dict)
                    else new_observations[i]
                )
            episode.final_observation = final
            episode.terminated = not info.get("TimeLimit.truncated", False)
            self.episodes.append(self._running.pop(i))


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = r_t + gamma * G_{t+1}, with G_T = 0, for every t of one episode (float64)."""
    returns = np.zeros(len(rewards), dtype=np.float64)
    following = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        following = float(rewards[t]) + gamma * following
        returns[t] = following
    return returns


def kept_states(length: int, terminated: bool, gamma: float, tolerance: float) -> int:
    """How many leading states of an episode of ``length`` steps have a meaningful return.

    All of them when the episode terminated. When it was truncated, state t (k = length - t rewards collected) is
    kept when the missing tail weighs gamma^k <= ``tolerance``; these are the first states of the episode.
    """
    if terminated:
        return length
    remaining = np.arange(length, 0, -1, dtype=np.float64)  # k for t = 0 .. length - 1
    return int(np.count_nonzero(gamma**remaining <= tolerance))


def no_state_reason(episodes: list[Episode], gamma: float, tolerance: float) -> str | None:
    """Why no state was kept, with what to change, when every episode was truncated too short for the tolerance
    (Pendulum-v1's 200 steps with gamma 0.99 and the default 0.01); None otherwise."""
    if not episodes or any(episode.terminated for episode in episodes):
        return None
    longest = max(len(episode) for episode in episodes)
    if longest == 0:
        return None
    cut = f"every evaluation episode was cut by its time limit, the longest after {longest} steps"
    off = "eval.value_bias=false switches the measurement off"
    if gamma >= 1.0:
        return f"{cut}, and with gamma {gamma:g} the return missing beyond the cut never shrinks; {off}"
    weight = gamma**longest  # of the missing tail, for the first state of the longest episode
    digits = 2 - math.floor(math.log10(weight)) if weight > 0 else 0
    suggested = math.ceil(weight * 10**digits) / 10**digits  # rounded up: it does keep that state
    needed = (
        f"a state needs {math.ceil(math.log(tolerance) / math.log(gamma))} steps before the cut for the missing tail "
        f"to weigh gamma^k <= {tolerance:g}" if 0 < tolerance < 1 else f"a tolerance of {tolerance:g} keeps no such state"
    )  # fmt: skip
    return (
        f"{cut}, and {needed} (gamma {gamma:g}, eval.value_horizon_tolerance={tolerance:g}). To measure anyway, "
        f"eval.value_horizon_tolerance={suggested:g} keeps at least the first state of the longest one, whose true value then "
        f"leaves out up to {suggested:g} of the discounted return beyond the cut; or {off}"
    )


def cut_at_time_limit(episodes: list[Episode], time_limit: int | None) -> bool:
    """Whether every episode ran to ``time_limit`` steps and was cut there (Pendulum-v1's, always): then no state
    kept is a consequence of the configuration, not of the run."""
    return bool(episodes) and time_limit is not None and all(
        not episode.terminated and len(episode) == time_limit for episode in episodes
    )


def summarize(estimates: np.ndarray, true_values: np.ndarray) -> tuple[dict[str, float], str | None]:
    """The logged numbers from per-state estimates and true values; and why ``normalized_bias`` is NaN, if it is."""
    n = len(true_values)
    if n == 0:
        nan = math.nan
        result = {"value_estimate": nan, "true_value": nan, "overestimation": nan, "normalized_bias": nan}
        return {**result, "value_states": 0}, "no state of the evaluation episodes had a meaningful return"
    estimate, true = float(np.mean(estimates)), float(np.mean(true_values))
    overestimation = estimate - true
    reason = None
    if abs(true) > NORMALIZATION_FLOOR * float(np.mean(np.abs(true_values))):
        normalized = overestimation / abs(true)
    else:
        normalized = math.nan
        reason = (
            f"the mean true value {true:.3g} is about 0 against the mean |true value| "
            f"{float(np.mean(np.abs(true_values))):.3g}; the normalised bias is undefined"
        )
    result = {"value_estimate": estimate, "true_value": true, "overestimation": overestimation}
    return {**result, "normalized_bias": normalized, "value_states": n}, reason


def measure_value_bias(model: Any, episodes: list[Episode], tolerance: float) -> tuple[dict[str, float], str | None]:
    """The critic's value estimate against the true discounted return on the evaluation episodes (module docstring).

    :param model: a :class:`~sb3_td3x.TD3X` (or subclass) or SB3 ``TD3`` (anything with ``policy``, ``critic`` and
        ``gamma``)
    :param episodes: the episodes recorded by :class:`EpisodeRecorder`
    :param tolerance: a state of a truncated episode is kept when its missing tail weighs gamma^k <= tolerance
    :return: ``value_estimate``, ``true_value``, ``overestimation``, ``normalized_bias``, ``value_states``; and the
        reason ``normalized_bias`` is NaN, when it is
    """
    gamma = float(model.gamma)
    vec_normalize = model.get_vec_normalize_env()
    observations, next_observations, actions, rewards, dones, true_values = [], [], [], [], [], []
    for episode in episodes:
        n = kept_states(len(episode), episode.terminated, gamma, tolerance)
        if n == 0:
            continue
        episode_rewards = np.asarray(episode.rewards, dtype=np.float64)
        if vec_normalize is not None:  # the rewards the critic was trained on (a no-op unless norm_reward)
            episode_rewards = np.asarray(vec_normalize.normalize_reward(episode_rewards), dtype=np.float64)
        true_values.append(discounted_returns(episode_rewards, gamma)[:n])
        following = [*episode.observations[1:], episode.final_observation]
        observations += episode.observations[:n]
        next_observations += following[:n]
        actions += episode.actions[:n]
        rewards.append(episode_rewards[:n])
        done = np.zeros(n)
        if episode.terminated and n == len(episode):
            done[-1] = 1.0
        dones.append(done)
    if not true_values:
        values, reason = summarize(np.zeros(0), np.zeros(0))
        return values, no_state_reason(episodes, gamma, tolerance) or reason
    estimates = critic_estimates(
        model, observations, next_observations, np.stack(actions), np.concatenate(rewards), np.concatenate(dones)
    )
    return summarize(estimates, np.concatenate(true_values))


def critic_estimates(
    model: Any,
    observations: list[Any],
    next_observations: list[Any],
    actions: np.ndarray,
    rewards: np.ndarray,
    dones: np.ndarray,
) -> np.ndarray:
    """Q_1(s, a) for each transition, through the model's ``q_value_estimates`` when it has one (TD3X: its
    ``current_q_values`` hook, or a distributional critic's expected value), else ``critic(obs, actions)[0]`` (SB3's
    TD3). Actions are in the env's scale; they are rescaled as the replay buffer stores them."""
    policy = model.policy
    policy.set_training_mode(False)
    hook = getattr(model, "q_value_estimates", None)
    values = []
    with th.no_grad():
        for start in range(0, len(actions), CHUNK):
            stop = min(start + CHUNK, len(actions))
            obs, _ = policy.obs_to_tensor(_stack(observations[start:stop]))
            scaled = np.asarray(policy.scale_action(actions[start:stop]), dtype=np.float32)
            action_tensor = th.as_tensor(scaled, device=policy.device).reshape(stop - start, -1)
            if callable(hook):
                next_obs, _ = policy.obs_to_tensor(_stack(next_observations[start:stop]))
                samples = DictReplayBufferSamples if isinstance(obs, dict) else ReplayBufferSamples
                batch = samples(
                    observations=obs,
                    actions=action_tensor,
                    next_observations=next_obs,
                    dones=_column(dones[start:stop], policy.device),
                    rewards=_column(rewards[start:stop], policy.device),
                )
                q = hook(batch)[0]  # (batch_size, 1): the first critic
            else:
                q = model.critic(obs, action_tensor)[0]
            values.append(q.detach().float().reshape(-1).cpu().numpy())
    return np.concatenate(values).astype(np.float64)


def _stack(observations: list[Any]) -> np.ndarray | dict[str, np.ndarray]:
    if isinstance(observations[0], dict):
        return {key: np.stack([obs[key] for obs in observations]) for key in observations[0]}
    return np.stack(observations)


def _column(values: np.ndarray, device: th.device) -> th.Tensor:
    return th.as_tensor(np.asarray(values, dtype=np.float32), device=device).reshape(-1, 1)
