"""The critic's value estimate against the true discounted return (sb3_td3x/experiment/run/value_bias.py), on hand-made
episodes: known rewards, a critic that returns known values, exact expected numbers."""

from __future__ import annotations

import csv
import json
import logging
import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from gymnasium.envs.registration import EnvSpec
from stable_baselines3 import TD3
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize
from stable_baselines3.td3.policies import TD3Policy

from sb3_td3x import TD3X
from sb3_td3x.experiment.layout import VALUE_FIELDS
from sb3_td3x.experiment.run import callbacks
from sb3_td3x.experiment.run.callbacks import PeriodicEvaluation
from sb3_td3x.experiment.run.value_bias import (
    Episode,
    cut_at_time_limit,
    discounted_returns,
    kept_states,
    measure_value_bias,
    summarize,
)
from sb3_td3x.td3x.policies import TD3XCritic, TD3XPolicy

GAMMA, TOLERANCE = 0.5, 0.25  # a truncated episode's state counts when 0.5^k <= 0.25: k >= 2 rewards collected

# Two episodes. Observations are (q, t): the known critic below returns q, so Q_1(s_t, a_t) = q_t.
# Terminated after 3 steps: G = (1 + 0.5 * 4, 2 + 0.5 * 4, 4) = (3, 4, 4), all kept.
# Truncated after 4 steps: G = (8.75, 1.5, 3, 2); the last state (k = 1, 0.5 > 0.25) is dropped.
TERMINATED = {"q": [4.0, 4.0, 5.0], "rewards": [1.0, 2.0, 4.0], "final_q": 70.0}
TRUNCATED = {"q": [9.0, 2.0, 3.0, 100.0], "rewards": [8.0, 0.0, 2.0, 2.0], "final_q": 80.0}
ESTIMATES = [4.0, 4.0, 5.0, 9.0, 2.0, 3.0]
TRUE_VALUES = [3.0, 4.0, 4.0, 8.75, 1.5, 3.0]
EXPECTED = {
    "value_estimate": 27.0 / 6,
    "true_value": 24.25 / 6,
    "overestimation": 2.75 / 6,
    "normalized_bias": 2.75 / 24.25,
    "value_states": 6,
}


class KnownCritic(TD3XCritic):
    """Q_i(s, a) = s[0] + 100 (i - 1): the first critic returns the first observation component. Only ``forward`` is
    overridden, so SB3's ``q1_forward`` (its untrained network) would give other values."""

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(obs[:, :1].float() + 100.0 * i + 0.0 * actions[:, :1] for i in range(self.n_critics))


class KnownPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None) -> KnownCritic:
        return KnownCritic(**self._update_features_extractor(self.critic_kwargs, features_extractor)).to(self.device)


class SB3KnownCritic(ContinuousCritic):
    forward = KnownCritic.forward


class SB3KnownPolicy(TD3Policy):
    def make_critic(self, features_extractor=None) -> SB3KnownCritic:
        return SB3KnownCritic(**self._update_features_extractor(self.critic_kwargs, features_extractor)).to(self.device)


class DoubledQ(TD3X):
    """An overridden ``current_q_values`` hook: the measurement must read the critic through it."""

    batches: list = []

    def current_q_values(self, batch):
        self.batches.append(batch)
        return 2.0 * super().current_q_values(batch)


class TwoEpisodes(gym.Env):
    """Plays TERMINATED then TRUNCATED (cut by a TimeLimit of 4 steps), again and again; observations (q, t)."""

    observation_space = spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = spaces.Box(-2.0, 2.0, (1,), np.float32)

    def __init__(self, first: int = 0) -> None:
        self.first = first
        self.episode, self.t = first - 1, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self.episode = self.first - 1
        self.episode, self.t = self.episode + 1, 0
        return self._obs(), {}

    def _plan(self) -> dict:
        return TERMINATED if self.episode % 2 == 0 else TRUNCATED

    def _obs(self) -> np.ndarray:
        plan = self._plan()
        q = plan["q"][self.t] if self.t < len(plan["q"]) else plan["final_q"]
        return np.array([q, self.t], dtype=np.float32)

    def step(self, action):
        plan = self._plan()
        reward = plan["rewards"][self.t]
        self.t += 1
        terminated = plan is TERMINATED and self.t == len(plan["rewards"])
        return self._obs(), reward, terminated, False, {}


def make_env(first: int = 0) -> gym.Env:
    env = TwoEpisodes(first)
    env.spec = EnvSpec("TwoEpisodes-v0")  # TimeLimit's spec then says max_episode_steps=4, as gym.make's do
    return Monitor(gym.wrappers.TimeLimit(env, max_episode_steps=4))


def hand_made_episodes() -> list[Episode]:
    def episode(plan: dict, terminated: bool) -> Episode:
        obs = [np.array([q, t], dtype=np.float32) for t, q in enumerate(plan["q"])]
        final = np.array([plan["final_q"], len(obs)], dtype=np.float32)
        actions = [np.array([1.0], dtype=np.float32)] * len(obs)  # env scale: 0.5 in the policy's [-1, 1]
        return Episode(obs, actions, list(plan["rewards"]), final, terminated)

    return [episode(TERMINATED, True), episode(TRUNCATED, False)]


def make_model(cls=TD3X, policy=KnownPolicy, env=None, **kwargs):
    env = env if env is not None else DummyVecEnv([make_env])
    model = cls(policy, env, gamma=GAMMA, policy_kwargs={"net_arch": [8]}, learning_starts=0, seed=0, **kwargs)
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def test_discounted_returns_and_the_truncation_rule():
    assert discounted_returns(np.array([1.0, 2.0, 4.0]), GAMMA).tolist() == [3.0, 4.0, 4.0]
    assert discounted_returns(np.array([8.0, 0.0, 2.0, 2.0]), GAMMA).tolist() == [8.75, 1.5, 3.0, 2.0]
    assert discounted_returns(np.array([]), GAMMA).tolist() == []
    assert kept_states(4, True, GAMMA, TOLERANCE) == 4  # terminated: every return is exact
    assert kept_states(4, False, GAMMA, TOLERANCE) == 3  # 0.5^4, 0.5^3, 0.5^2 <= 0.25 < 0.5^1
    assert kept_states(1, False, GAMMA, TOLERANCE) == 0
    assert kept_states(1000, False, 0.99, 0.01) == 542  # the default on a 1000-step MuJoCo episode
    assert kept_states(200, False, 0.99, 0.01) == 0  # Pendulum-v1: NaN with the default tolerance
    assert kept_states(5, False, 1.0, 0.5) == 0 and kept_states(5, False, 0.0, 0.0) == 5


def test_summary_of_no_state_and_of_returns_that_cancel():
    empty, reason = summarize(np.zeros(0), np.zeros(0))
    assert empty["value_states"] == 0 and all(math.isnan(empty[key]) for key in VALUE_FIELDS[:4]) and reason
    cancel, reason = summarize(np.array([1.0, 3.0]), np.array([-5.0, 5.0]))
    assert cancel["overestimation"] == 2.0 and math.isnan(cancel["normalized_bias"]) and "about 0" in reason
    negative, reason = summarize(np.array([-1.0, -3.0]), np.array([-4.0, -4.0]))
    assert negative["normalized_bias"] == 0.5 and reason is None  # (-2 - -4) / |-4|: above the true value is positive


@pytest.mark.parametrize("n_steps", [1, 3])  # n-step replay changes the critic's target, not what is measured
def test_hand_made_episodes_give_the_exact_numbers_through_a_subclassed_critic(n_steps):
    values, reason = measure_value_bias(make_model(n_steps=n_steps), hand_made_episodes(), TOLERANCE)
    assert values == pytest.approx(EXPECTED, rel=1e-12) and reason is None


def test_sb3_td3_reads_its_critic_the_same_way():
    values, _ = measure_value_bias(make_model(TD3, SB3KnownPolicy), hand_made_episodes(), TOLERANCE)
    assert values == pytest.approx(EXPECTED, rel=1e-12)


def test_an_overridden_current_q_values_hook_is_measured_with_the_evaluation_transitions():
    DoubledQ.batches = []
    values, _ = measure_value_bias(make_model(DoubledQ), hand_made_episodes(), TOLERANCE)
    assert values["value_estimate"] == pytest.approx(2 * EXPECTED["value_estimate"], rel=1e-12)
    assert values["true_value"] == pytest.approx(EXPECTED["true_value"], rel=1e-12)
    (batch,) = DoubledQ.batches  # one batched forward pass over the kept states
    assert batch.observations[:, 0].tolist() == [4.0, 4.0, 5.0, 9.0, 2.0, 3.0]
    assert batch.next_observations[:, 0].tolist() == [4.0, 5.0, 70.0, 2.0, 3.0, 100.0]
    assert batch.actions.flatten().tolist() == [0.5] * 6  # env action 1.0 in [-2, 2], as the replay buffer stores it
    assert batch.rewards.flatten().tolist() == [1.0, 2.0, 4.0, 8.0, 0.0, 2.0]
    assert batch.dones.flatten().tolist() == [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]  # only a termination ends the return


def test_normalised_rewards_are_the_ones_the_critic_learned():
    env = VecNormalize(DummyVecEnv([make_env]), norm_obs=False, norm_reward=True)
    env.ret_rms.var = np.array(4.0 - env.epsilon)  # rewards divided by 2
    values, _ = measure_value_bias(make_model(env=env), hand_made_episodes(), TOLERANCE)
    assert values["true_value"] == pytest.approx(EXPECTED["true_value"] / 2, rel=1e-6)
    assert values["value_estimate"] == pytest.approx(EXPECTED["value_estimate"], rel=1e-12)


def evaluation(tmp_path, model, **kwargs) -> PeriodicEvaluation:
    callback = PeriodicEvaluation(DummyVecEnv([make_env]), tmp_path, freq=1, n_episodes=2, eval_seed=0, **kwargs)
    callback.init_callback(model)
    return callback


def read_csv(path) -> list[dict[str, str]]:
    with open(path) as file:
        return list(csv.DictReader(file))


def test_the_evaluation_episodes_are_recorded_and_the_columns_written(tmp_path):
    model = make_model()
    logged: dict[str, float] = {}
    model.logger.record = lambda key, value, exclude=None: logged.__setitem__(key, value)  # type: ignore[method-assign]
    callback = evaluation(tmp_path, model, value_horizon_tolerance=TOLERANCE)
    result = callback.evaluate()
    assert result["mean_return"] == (7.0 + 12.0) / 2  # the same episodes measure both
    assert {key: result[key] for key in VALUE_FIELDS} == pytest.approx(EXPECTED, rel=1e-12)
    assert {key: logged[f"eval/{key}"] for key in VALUE_FIELDS} == pytest.approx(EXPECTED, rel=1e-12)
    (row,) = read_csv(tmp_path / "evaluations.csv")
    assert {key: float(row[key]) for key in VALUE_FIELDS} == pytest.approx(EXPECTED, rel=1e-12)
    assert callback.timing["value_bias_s"] >= 0 and callback.timing["episodes_s"] > 0


def test_switched_off_there_are_no_columns(tmp_path):
    model = make_model()
    logged: list[str] = []
    model.logger.record = lambda key, value, exclude=None: logged.append(key)  # type: ignore[method-assign]
    result = evaluation(tmp_path, model, value_bias=False).evaluate()
    assert not set(VALUE_FIELDS) & set(result) and not [key for key in logged if key.startswith("eval/value")]
    assert list(read_csv(tmp_path / "evaluations.csv")[0]) == ["timesteps", "mean_return", "std_return", "mean_length",
                                                              "wall_time"]


def test_no_state_to_measure_is_nan_not_zero(tmp_path):
    callback = evaluation(tmp_path, make_model(), value_horizon_tolerance=0.0)
    callback.eval_env = DummyVecEnv([lambda: make_env(first=1)])  # the truncated episode only
    callback.n_episodes = 1
    result = callback.evaluate()  # tolerance 0: no state of a truncated episode counts
    assert result["value_states"] == 0 and all(math.isnan(result[key]) for key in VALUE_FIELDS[:4])
    (row,) = read_csv(tmp_path / "evaluations.csv")
    assert row["value_estimate"] == "nan" and row["value_states"] == "0"
    assert json.loads((tmp_path / "evaluations.json").read_text())[0]["value_estimate"] is None  # strict JSON


@pytest.mark.parametrize("time_limit, level", [(4, logging.INFO), (5, logging.WARNING), (None, logging.WARNING)])
def test_no_state_is_info_only_when_every_episode_ran_to_its_time_limit(tmp_path, caplog, time_limit, level):
    """Episodes that all ran to the env's time limit (4 steps here, 200 on Pendulum-v1, the README's first run) leave
    no state by the configuration: said once at INFO. Cut before it, or with no known limit: a WARNING."""
    callback = evaluation(tmp_path, make_model(), value_horizon_tolerance=0.0)
    callback.eval_env = DummyVecEnv([lambda: make_env(first=1)])  # the truncated episode only, cut at 4 steps
    callback.n_episodes = 1
    assert callback._time_limit() == 4  # read from the env
    callback._time_limit = lambda: time_limit  # type: ignore[method-assign]
    with caplog.at_level(logging.INFO, logger="sb3_td3x"):
        callback.evaluate()
        callback.evaluate()
    said = [record for record in caplog.records if "Value measurement" in record.getMessage()]
    assert [record.levelno for record in said] == [level] and "time limit" in said[0].getMessage()


def test_a_nan_with_states_kept_is_a_warning(tmp_path, caplog, monkeypatch):
    """A NaN that the configuration does not explain (the normalised bias of returns that cancel) stays a WARNING,
    also after the INFO line of an evaluation without states."""
    nan, reasons = math.nan, iter(["no state", "the mean true value 0 is about 0"])
    outcomes = iter([{key: nan for key in VALUE_FIELDS[:4]} | {"value_states": 0},
                     {key: 1.0 for key in VALUE_FIELDS[:3]} | {"normalized_bias": nan, "value_states": 6}])
    monkeypatch.setattr(callbacks, "measure_value_bias", lambda model, episodes, tolerance: (next(outcomes), next(reasons)))
    callback = evaluation(tmp_path, make_model(), value_horizon_tolerance=TOLERANCE)
    callback.eval_env = DummyVecEnv([lambda: make_env(first=1)])  # episodes cut at their time limit
    callback.n_episodes = 1
    with caplog.at_level(logging.INFO, logger="sb3_td3x"):
        callback.evaluate()
        callback.evaluate()
    said = [record for record in caplog.records if "Value measurement" in record.getMessage()]
    assert [record.levelno for record in said] == [logging.INFO, logging.WARNING]
    assert "about 0" in said[1].getMessage()


def test_cut_at_time_limit():
    terminated, truncated = hand_made_episodes()  # 3 steps, terminated; 4 steps, cut
    assert cut_at_time_limit([truncated, truncated], 4)
    assert not cut_at_time_limit([truncated], 5) and not cut_at_time_limit([truncated], None)
    assert not cut_at_time_limit([truncated, terminated], 4) and not cut_at_time_limit([], 4)


def test_no_state_says_which_tolerance_would_keep_one():
    """Every episode truncated before a state's tail is small enough (Pendulum-v1 with the defaults): the reason
    names the tolerance that keeps a state, and that tolerance does keep one."""
    model = make_model()
    truncated = hand_made_episodes()[1]  # 4 steps, gamma 0.5: the first state's missing tail weighs 0.5^4 = 0.0625
    values, reason = measure_value_bias(model, [truncated], 0.01)
    assert values["value_states"] == 0 and "the longest after 4 steps" in reason and "needs 7 steps" in reason
    suggested = float(reason.split("eval.value_horizon_tolerance=")[2].split()[0])
    assert suggested == 0.0625 and "eval.value_bias=false" in reason
    assert measure_value_bias(model, [truncated], suggested)[0]["value_states"] == 1
    # 5 steps: 0.5^5 = 0.03125, said with 3 digits rounded up (0.0313), which keeps the state (0.0312 would not)
    longer = Episode([*truncated.observations, truncated.final_observation], [*truncated.actions, truncated.actions[0]],
                     [*truncated.rewards, 1.0], truncated.final_observation, False)  # fmt: skip
    _, reason = measure_value_bias(model, [longer], 0.01)
    suggested = float(reason.split("eval.value_horizon_tolerance=")[2].split()[0])
    assert suggested == 0.0313 and measure_value_bias(model, [longer], suggested)[0]["value_states"] == 1
    # A terminated episode among them: its states count, no such advice
    terminated = hand_made_episodes()[0]
    values, reason = measure_value_bias(model, [terminated, truncated], 0.01)
    assert values["value_states"] == len(terminated) and (reason is None or "time limit" not in reason)


def test_a_resumed_history_without_the_columns_is_written_with_empty_cells(tmp_path):
    callback = evaluation(tmp_path, make_model(), value_horizon_tolerance=TOLERANCE)
    old = {"timesteps": 1, "mean_return": 3.0, "std_return": 0.0, "mean_length": 4.0, "wall_time": 0.0}
    callback.load_state_dict({"history": [old]})
    assert list(read_csv(tmp_path / "evaluations.csv")[0]) == list(old)  # as the old run wrote it
    callback.num_timesteps = 2
    callback.evaluate()
    rows = read_csv(tmp_path / "evaluations.csv")
    assert list(rows[0]) == list(old) + list(VALUE_FIELDS)
    assert [rows[0][key] for key in VALUE_FIELDS] == [""] * 5 and float(rows[1]["value_states"]) == 6
