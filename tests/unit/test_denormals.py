"""flush_denormals around train(), and a compiled bf16 update that must never read uninitialised memory."""

import warnings

import numpy as np
import torch as th
from conftest import feed, random_batches
from stable_baselines3.common.logger import configure
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_td3x import TD3X
from sb3_td3x.common.denormals import flush_denormals, flushes_all_threads


def batches(n: int, obs_dim: int = 3, action_dim: int = 1, seed: int = 0) -> list[ReplayBufferSamples]:
    return random_batches(n, 32, obs_dim, action_dim, seed=seed)


def test_flush_denormals_reaches_the_worker_threads_and_restores():
    threads = th.get_num_threads()
    th.set_num_threads(2)
    try:
        tiny = th.full((4_000_000,), 1e-20)  # large enough to be split across both threads
        assert (tiny * tiny > 0).all()  # 1e-40: a denormal
        with flush_denormals():
            flushed = tiny * tiny
        assert (tiny * tiny > 0).all(), "the setting outlived the block"
        if flushes_all_threads():
            assert (flushed == 0).all()
        else:
            assert (flushed == 0).any()
        with flush_denormals(enabled=False):
            assert (tiny * tiny > 0).all()
    finally:
        th.set_num_threads(threads)


def test_train_flushes_denormals_only_inside_train():
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=0, seed=0, policy_kwargs={"net_arch": [16]})
    model.set_logger(configure(None, []))
    seen = []
    original = model.critic.optimizer.step

    def step(*args, **kwargs):
        tiny = th.full((8,), 1e-20)
        seen.append(bool((tiny * tiny == 0).all()))
        return original(*args, **kwargs)

    model.critic.optimizer.step = step
    feed(model, batches(2), seed=0)
    model.train(gradient_steps=2, batch_size=32)
    assert seen == [True, True]
    tiny = th.full((8,), 1e-20)
    assert (tiny * tiny > 0).all()


def test_compiled_bf16_update_stays_finite_over_uninitialised_memory():
    """compile_update=True, bf16=True never reads uninitialised memory.

    Regression (of the hand-written update this package had before): with the observations cast inside a compiled
    graph, the actor's first bf16 product read the action columns of the concatenation [s', a'] before they were
    written, so NaN bytes left in freed memory came out as a NaN target (torch 2.13, AMX). Freed memory is filled
    with NaN before every step here.
    """
    model = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [64, 64]}, learning_starts=0, seed=0,
                 batch_size=256, compile_update=True, bf16=True)
    model.set_logger(configure(None, []))
    data = [
        ReplayBufferSamples(*(th.cat([a] * 8) for a in batch[:5]))  # 256 rows: products large enough for AMX tiles
        for batch in batches(24)
    ]
    it = iter(data)

    def sample(batch_size):
        for size in (256 * 4, 256 * 8, 256 * 64, 256 * 300, 256 * 400):
            th.full((size,), float("nan"), dtype=th.bfloat16)  # freed at once, for the allocator to hand out again
        return next(it)

    model.sample_batch = sample
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bf16 on a CPU without AMX warns (test_acceleration.py)
        model.train(gradient_steps=24, batch_size=256)
    assert model.update_path == "compiled"
    assert all(p.isfinite().all() for p in model.policy.parameters())
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])
