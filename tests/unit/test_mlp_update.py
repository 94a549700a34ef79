"""MlpUpdate (TD3X's default update, gradients by hand) against the hooks run with autograd, and flush_denormals."""

import copy

import numpy as np
import pytest
import torch as th
from conftest import feed, random_batches
from stable_baselines3.common.logger import configure
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_td3x.common.torch_internals import linear_relu_kernel
from sb3_td3x import TD3X
from sb3_td3x.common.denormals import flush_denormals, flushes_all_threads
from sb3_td3x.td3x.update_paths import mlp as mlp_update_module
from sb3_td3x.td3x.update_paths.mlp import MlpUpdate


def batches(n: int, obs_dim: int = 3, action_dim: int = 1, seed: int = 0) -> list[ReplayBufferSamples]:
    return random_batches(n, 32, obs_dim, action_dim, seed=seed)


def pair(env: str = "Pendulum-v1", policy_kwargs: dict | None = None, **kwargs) -> tuple[TD3X, TD3X]:
    """Two models with the same weights: the default update (MlpUpdate) and the hooks with autograd."""
    policy_kwargs = {"net_arch": [32, 32], **(policy_kwargs or {})}
    models = [
        TD3X("MlpPolicy", env, policy_kwargs=policy_kwargs, learning_starts=0, seed=0, mlp_update=flag, **kwargs)
        for flag in (True, False)
    ]
    models[1].policy.load_state_dict(models[0].policy.state_dict())
    for model in models:
        model.set_logger(configure(None, []))
    return models[0], models[1]


def train_on(model: TD3X, data: list[ReplayBufferSamples], progresses=(1.0, 0.6, 0.3)) -> None:
    feed(model, data, seed=0)  # the same target policy smoothing noise in both models
    steps = len(data) // len(progresses)
    for progress in progresses:  # a learning-rate schedule changes between the calls
        model._current_progress_remaining = progress
        model.train(gradient_steps=steps, batch_size=32)


def assert_same_training(fast: TD3X, reference: TD3X) -> None:
    for (name, a), b in zip(reference.policy.state_dict().items(), fast.policy.state_dict().values()):
        th.testing.assert_close(b, a, rtol=1e-4, atol=1e-5, msg=lambda m, name=name: f"{name}: {m}")
    for optimizer in ("actor", "critic"):
        ref_state = getattr(reference, optimizer).optimizer.state_dict()["state"]
        fast_state = getattr(fast, optimizer).optimizer.state_dict()["state"]
        assert ref_state.keys() == fast_state.keys()
        for key in ref_state:
            for field in ref_state[key]:
                th.testing.assert_close(fast_state[key][field], ref_state[key][field], rtol=1e-4, atol=1e-6)
    for key, value in reference.logger.name_to_value.items():
        assert fast.logger.name_to_value[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"policy_kwargs": {"n_critics": 3, "net_arch": {"pi": [16], "qf": [24, 16, 8]}}},
        {"target_policy_smoothing": False, "clipped_double_q": False, "policy_delay": 1},
        {"learning_rate": lambda progress: 1e-3 * progress, "critic_learning_rate": 3e-4},
        {"policy_kwargs": {"optimizer_class": th.optim.AdamW, "optimizer_kwargs": {"weight_decay": 0.1}}},
        {"policy_kwargs": {"optimizer_kwargs": {"fused": False, "foreach": True}}},  # optimizer.step() itself
        {"policy_kwargs": {"optimizer_class": th.optim.SGD, "optimizer_kwargs": {"momentum": 0.9}}},
    ],
    ids=["defaults", "3-critics-deeper", "ddpg-like", "lr-schedules", "adamw", "foreach-adam", "sgd"],
)
def test_mlp_update_trains_as_autograd(kwargs):
    fast, reference = pair(**kwargs)
    data = batches(6)
    train_on(fast, data)
    train_on(reference, data)
    assert fast.update_path == "mlp" and reference.update_path == "autograd"
    assert_same_training(fast, reference)


def test_mlp_update_with_n_step_returns_on_a_mujoco_task():
    """NStepReplayBuffer's per-transition discounts, a MuJoCo observation, and the default sampling path."""
    fast, reference = pair("InvertedPendulum-v5", n_steps=3, buffer_size=1000)
    fast.learn(200)  # fills the buffer (no gradient step is compared here)
    reference.replay_buffer = fast.replay_buffer
    reference.policy.load_state_dict(fast.policy.state_dict())
    # Deep copies: Adam's load_state_dict keeps the "step" tensors it is given, which the other optimizer increments.
    reference.actor.optimizer.load_state_dict(copy.deepcopy(fast.actor.optimizer.state_dict()))
    reference.critic.optimizer.load_state_dict(copy.deepcopy(fast.critic.optimizer.state_dict()))
    reference._n_updates, reference._n_actor_updates = fast._n_updates, fast._n_actor_updates
    for model in (fast, reference):
        np.random.seed(1)
        th.manual_seed(1)
        model.train(gradient_steps=4, batch_size=64)
    assert getattr(fast.replay_buffer.sample(4), "discounts", None) is not None
    assert_same_training(fast, reference)


def test_mlp_update_stacks_the_critics_and_survives_save_load(tmp_path):
    fast, reference = pair()
    data = batches(6)
    train_on(fast, data[:3], progresses=(1.0,))
    train_on(reference, data[:3], progresses=(1.0,))
    critic = fast.critic.q_networks
    # The critics' parameters are views of one stacked tensor per layer.
    assert critic[0][0].weight.untyped_storage().data_ptr() == critic[1][0].weight.untyped_storage().data_ptr()
    fast.save(tmp_path / "model.zip")
    loaded = TD3X.load(tmp_path / "model.zip")
    loaded.set_logger(configure(None, []))
    # Parameter memory replaced behind the update's back (as Module.to(device) does) is bound again at the next step.
    loaded.train(gradient_steps=0, batch_size=32)
    for param in loaded.policy.parameters():
        param.data = param.data.clone()
    train_on(loaded, data[3:], progresses=(1.0,))
    train_on(reference, data[3:], progresses=(1.0,))
    assert loaded.update_path == "mlp"
    assert_same_training(loaded, reference)


def test_optimizer_state_replaced_between_steps_is_the_one_stepped():
    """MlpUpdate keeps a fused Adam's state tensors from one step to the next (and makes each ``step`` counter a view
    of one tensor): what ``load_state_dict`` or a user's code puts in the optimizer's state is what the next step
    updates, as ``optimizer.step()`` would."""
    fast, reference = pair()
    data = batches(9)
    train_on(fast, data[:3], progresses=(1.0,))
    train_on(reference, data[:3], progresses=(1.0,))
    for model in (fast, reference):
        for optimizer in (model.actor.optimizer, model.critic.optimizer):
            optimizer.load_state_dict(copy.deepcopy(optimizer.state_dict()))  # every state tensor replaced
        first = next(iter(model.critic.parameters()))
        model.critic.optimizer.state[first]["exp_avg"] = th.ones_like(first)  # one replaced by hand
    train_on(fast, data[3:6], progresses=(1.0,))
    train_on(reference, data[3:6], progresses=(1.0,))
    assert fast.update_path == "mlp"
    assert_same_training(fast, reference)
    steps = [state["step"] for state in fast.critic.optimizer.state.values()]
    assert len({s.untyped_storage().data_ptr() for s in steps}) == 1  # views of one tensor, moved by one addition
    fast.critic.optimizer.step()  # the optimizer's own step() moves each counter as its own tensor
    assert [float(s) for s in steps] == [float(steps[0])] * len(steps) and float(steps[0]) == 7.0


class HuberTD3X(TD3X):
    calls = 0

    def critic_loss(self, current_q, target_q):
        HuberTD3X.calls += 1
        loss = sum(th.nn.functional.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}


def test_an_overridden_hook_runs_with_autograd():
    model = HuberTD3X("MlpPolicy", "Pendulum-v1", learning_starts=0, seed=0, policy_kwargs={"net_arch": [16]})
    model.set_logger(configure(None, []))
    assert MlpUpdate.why_not(model) == "critic_loss overridden by HuberTD3X"
    HuberTD3X.calls = 0
    train_on(model, batches(3), progresses=(1.0,))
    assert HuberTD3X.calls == 3


def test_why_not_names_the_reason():
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=0, seed=0, policy_kwargs={"activation_fn": th.nn.Tanh})
    assert "the actor is not a ReLU MLP with a tanh output" in MlpUpdate.why_not(model)


def test_bf16_mlp_update_follows_bf16_autocast():
    """bf16=True: bf16 products with fp32 weights, as autograd under autocast computes them (to bf16 rounding)."""
    fast, reference = pair(bf16=True)
    data = batches(6)
    train_on(fast, data)
    train_on(reference, data)
    assert fast.update_path == "mlp" and reference.update_path == "autograd"
    assert all(p.dtype == th.float32 for p in fast.policy.parameters())
    for (name, a), b in zip(reference.policy.state_dict().items(), fast.policy.state_dict().values()):
        th.testing.assert_close(b, a, rtol=0.05, atol=2e-3, msg=lambda m, name=name: f"{name}: {m}")


@pytest.mark.parametrize("dtype", [th.float32, th.bfloat16])
def test_fused_linear_relu_runs_in_every_dtype_on_this_cpu(dtype):
    """The hidden layers' relu(x W^T + b): oneDNN's fused linear where it takes the dtype, addmm and relu otherwise.

    Regression: on an AVX2 CPU (no AVX-512), oneDNN's linear has no bf16 kernel and raised "could not create a
    primitive descriptor" at the first bf16 step.
    """
    g = th.Generator().manual_seed(0)
    x, w, b = th.randn(64, 40, generator=g), th.randn(30, 40, generator=g), th.randn(30, generator=g)
    x, w, b = x.to(dtype), w.to(dtype), b.to(dtype)
    kernel, dtypes = linear_relu_kernel()
    if kernel is not None:  # the op exists: it takes fp32 at least
        assert th.float32 in dtypes
    out = mlp_update_module._linear_relu(x, w, b)
    assert out.dtype == dtype
    tolerance = {} if dtype == th.float32 else {"rtol": 2e-2, "atol": 5e-2}
    th.testing.assert_close(out.float(), th.relu(x.float() @ w.float().t() + b.float()), **tolerance)


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

    model.critic.optimizer.step = step  # a step hook would also switch off the direct fused call
    model.mlp_update = False
    train_on(model, batches(2), progresses=(1.0,))
    assert seen == [True, True]
    tiny = th.full((8,), 1e-20)
    assert (tiny * tiny > 0).all()


@pytest.mark.parametrize("mlp_update", [True, False])
def test_compiled_bf16_update_stays_finite_over_uninitialised_memory(mlp_update):
    """compile_update=True, bf16=True (MlpUpdate compiled, or the hooks made functional) never reads uninitialised
    memory.

    Regression: with the observations cast inside the compiled graph, the actor's first bf16 product read the
    action columns of the concatenation [s', a'] before they were written (see ``compute_dtype_batch``), so NaN
    bytes left in freed memory came out as a NaN target. Freed memory is filled with NaN before every step here.
    """
    model = TD3X("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [64, 64]}, learning_starts=0, seed=0,
                 batch_size=256, compile_update=True, bf16=True, mlp_update=mlp_update)
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
    with th._inductor.config.patch(fallback_random=True):
        model.train(gradient_steps=24, batch_size=256)
    assert model.update_path == ("compiled_mlp" if mlp_update else "compiled")
    assert all(p.isfinite().all() for p in model.policy.parameters())
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])
