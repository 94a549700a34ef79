"""The learning checks' one measure: SB3's own EvalCallback evaluates the deterministic policy on Pendulum-v1 every
500 steps (10 episodes) and StopTrainingOnRewardThreshold ends the run at the first evaluation over the bar, as
rl-zoo's learning checks do. Why the first evaluation over the bar and not the policy at one fixed step: Pendulum's
policies swing between evaluations, and one seed follows another trajectory on another CPU (test_variants_learn.py
says what was measured)."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.callbacks import EvalCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

THRESHOLD = -250.0  # random actions score about -1200; a learnt swing-up about -150
EVAL_EVERY = 500


@pytest.fixture
def learn_until_the_bar(tmp_path):
    """learn_until_the_bar(name, model, max_steps, eval_seed) trains the model until its deterministic policy scores
    THRESHOLD or max_steps pass, prints its evaluations as (steps, mean return) pairs, and fails if none reached the
    bar."""

    def learn(name: str, model, max_steps: int, eval_seed: int = 10_000) -> list[tuple[int, float]]:
        eval_env = DummyVecEnv([lambda: Monitor(gym.make("Pendulum-v1"))])
        eval_env.seed(eval_seed)
        evaluation = EvalCallback(
            eval_env,
            callback_on_new_best=StopTrainingOnRewardThreshold(reward_threshold=THRESHOLD),
            eval_freq=EVAL_EVERY,
            n_eval_episodes=10,
            log_path=str(tmp_path),  # keeps each evaluation's returns in evaluation.evaluations_results
            deterministic=True,
            verbose=0,
        )
        model.learn(total_timesteps=max_steps, callback=evaluation)
        means = [round(float(np.mean(returns)), 1) for returns in evaluation.evaluations_results]
        evaluations = list(zip(evaluation.evaluations_timesteps, means))
        print(f"{name} ({model.update_path}): {evaluations}")
        best = max(means)
        assert best >= THRESHOLD, f"{name}: best {best} < {THRESHOLD} in {max_steps:,} steps; evaluations: {evaluations}"
        return evaluations

    return learn
