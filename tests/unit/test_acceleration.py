"""The accelerations: bf16 autocast, the compiled update (by default on a long CPU run), and the CUDA-graph path's
logic (run on the CPU)."""

import os
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import eager_capture, feed, random_batches
from stable_baselines3.common.logger import configure
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_td3x import TD3X
from sb3_td3x.common.buffers import TensorReplayBuffer
from sb3_td3x.td3x.optim import apply_gradients, gradients, minimize
from sb3_td3x.td3x.update_paths import precision
from sb3_td3x.td3x.update_paths.compiled import CompiledUpdate
from sb3_td3x.td3x.update_paths.cuda_graph import GraphedGradientStep

def batches(n: int, seed: int = 0) -> list[ReplayBufferSamples]:
    return random_batches(n, seed=seed)


def small(policy_kwargs: dict | None = None, cls: type[TD3X] = TD3X, **kwargs) -> TD3X:
    policy_kwargs = {"net_arch": [32, 32], **(policy_kwargs or {})}
    model = cls("MlpPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs, learning_starts=0, seed=0, **kwargs)
    model.set_logger(configure(None, []))
    return model


def assert_same_weights(reference: TD3X, model: TD3X, **tolerance) -> None:
    for (name, a), b in zip(reference.policy.state_dict().items(), model.policy.state_dict().values()):
        th.testing.assert_close(b, a, msg=lambda m, name=name: f"{name}: {m}", **tolerance)


def test_bf16_keeps_fp32_weights_and_follows_fp32_closely():
    fp32, bf16 = small(), small(bf16=True)
    bf16.policy.load_state_dict(fp32.policy.state_dict())
    data = batches(4)
    for model in (fp32, bf16):
        feed(model, data, seed=0)
        model.train(gradient_steps=4, batch_size=32)
    assert all(p.dtype == th.float32 for p in bf16.policy.parameters())
    assert_same_weights(fp32, bf16, rtol=0.05, atol=2e-3)
    assert np.isfinite(bf16.logger.name_to_value["train/critic_loss"])


def flat_weights(model: TD3X) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()])


def test_bf16_updates_follow_the_fp32_updates_closer_than_another_update():
    """In place of a bf16 learning run: 20 bf16 updates move the weights as the fp32 updates do, to within 8% of how
    far they moved (5.4% on a 2-core AMD EPYC, 2026-11), while the same updates with another gamma end 13% away; and
    bf16 products are really used (not fp32's weights to the bit). The compiled bf16 update is held to the eager one in
    tests/equivalence/test_user_changes.py."""
    fp32, bf16, other = small(), small(bf16=True), small(gamma=0.9)
    for model in (bf16, other):
        model.policy.load_state_dict(fp32.policy.state_dict())
    start = flat_weights(fp32)
    data = batches(20)
    for model in (fp32, bf16, other):
        feed(model, data, seed=0)
        model.train(gradient_steps=20, batch_size=32)
    fp32_moved = flat_weights(fp32) - start

    def apart(model: TD3X) -> float:
        """How far the model's updates end from fp32's, relative to how far fp32's moved the weights."""
        return float((flat_weights(model) - start - fp32_moved).norm() / fp32_moved.norm())

    assert 1e-3 < apart(bf16) < 0.08 < apart(other), (apart(bf16), apart(other))
    assert all(p.dtype == th.float32 for p in bf16.policy.parameters())


def train_fed(model: TD3X, data: list[ReplayBufferSamples], progresses=(1.0, 0.5, 0.25)) -> None:
    feed(model, data, seed=0)
    for progress in progresses:  # the learning rate changes between train() calls
        model._current_progress_remaining = progress
        model.train(gradient_steps=2, batch_size=32)


class HuberTD3X(TD3X):
    """A loss hook overridden, as in the docs' extending page: the compiled update must use it too."""

    def critic_loss(self, current_q, target_q):
        target = target_q.unsqueeze(0).expand_as(current_q)
        loss = th.nn.functional.smooth_l1_loss(current_q, target, reduction="none").mean(dim=(1, 2)).sum()
        return loss, {"critic_loss": loss.detach()}


@pytest.mark.parametrize("variant", ["adam", "adamw_weight_decay", "huber_critic_loss"])
def test_compiled_update_matches_eager_steps(variant, monkeypatch):
    """compile_update=True computes the same updates as the eager hooks (to float rounding), overridden loss hooks and
    AdamW's decoupled weight decay included, follows a learning-rate schedule without recompiling (one graph with the
    actor update, one without), and has no graph break. Inductor compiles Adam's graphs; the variants' graphs, which
    only add pointwise operations to them, run with ``aot_eager`` (Dynamo's graphs, as the catalogue of
    tests/equivalence/test_user_changes.py: each graph Inductor compiles costs about 34 s on a cold cache)."""
    if variant != "adam":
        monkeypatch.setattr(CompiledUpdate, "backend", "aot_eager")
    kwargs = {"learning_rate": lambda progress: 1e-3 * progress}
    if variant == "huber_critic_loss":
        kwargs["cls"] = HuberTD3X
    if variant == "adamw_weight_decay":
        kwargs["policy_kwargs"] = dict(optimizer_class=th.optim.AdamW, optimizer_kwargs=dict(weight_decay=0.05))
    eager = small(**kwargs)
    compiled = small(compile_update=True, **kwargs)
    compiled.policy.load_state_dict(eager.policy.state_dict())
    data = batches(6)
    train_fed(eager, data)
    counters = th._dynamo.utils.counters
    graphs_before, breaks_before = counters["stats"]["unique_graphs"], sum(counters["graph_break"].values())
    train_fed(compiled, data)
    # One graph with the actor update and one without: the schedule's learning rates are tensors the graphs read.
    assert counters["stats"]["unique_graphs"] - graphs_before == 2
    assert sum(counters["graph_break"].values()) == breaks_before
    assert compiled.update_path == "compiled"
    assert_same_weights(eager, compiled, rtol=1e-4, atol=1e-5)
    assert compiled.logger.name_to_value["train/critic_loss"] == pytest.approx(
        eager.logger.name_to_value["train/critic_loss"], rel=1e-4)


def test_compiled_update_stays_finite_in_a_run():
    """A short real run of the compiled update, on the small models and batches of the tests above (32-32, batch 32:
    Inductor's cache finds their graph). The compiled bf16 update is held to the eager bf16 one in
    tests/equivalence/test_user_changes.py (test_the_compiled_bf16_update_follows_the_eager_bf16_update)."""
    model = small(compile_update=True, batch_size=32)
    model.learn(60)
    assert model.update_path == "compiled"
    assert all(p.isfinite().all() for p in model.policy.parameters())
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])


def test_compiled_update_keeps_the_optimizer_state_usable_eagerly(dynamo_graphs_only):
    """The compiled update steps the optimizers' own states: switching compile_update off mid-run goes on exactly
    as an eager run would (and so do saving and loading them). Which state tensors the graph steps is Dynamo's and
    AOTAutograd's doing: run with ``aot_eager`` (a graph of its own, without smoothing noise, which Inductor would
    compile for about 25 s per graph on a cold cache; Inductor steps the same states in the Adam test above)."""
    # No smoothing noise: each train_fed call reseeds the RNG, which the eager run only does once.
    eager, switched = small(target_policy_smoothing=False), small(target_policy_smoothing=False, compile_update=True)
    switched.policy.load_state_dict(eager.policy.state_dict())
    data = batches(8)
    train_fed(eager, data, progresses=(1.0, 1.0, 1.0, 1.0))
    train_fed(switched, data[:4], progresses=(1.0, 1.0))
    assert switched.critic.optimizer.state_dict()["state"][0]["step"].item() == 4
    switched.compile_update, switched._step_fn = False, None
    switched.critic.optimizer.load_state_dict(switched.critic.optimizer.state_dict())
    train_fed(switched, data[4:], progresses=(1.0, 1.0))
    assert_same_weights(eager, switched, rtol=1e-4, atol=1e-5)


class ClippedTD3X(TD3X):
    """Step 12 with the gradients clipped, written with :func:`~sb3_td3x.td3x.optim.gradients` and
    :func:`~sb3_td3x.td3x.optim.apply_gradients`: compiled in one graph with the rest."""

    def optimize_critic(self, loss):
        grads = gradients(self.critic.optimizer, loss)  # None for a parameter the loss does not reach
        norm = th.linalg.vector_norm(th.stack([th.linalg.vector_norm(g) for g in grads if g is not None]))
        scale = (0.05 / (norm + 1e-6)).clamp(max=1.0)
        apply_gradients(self.critic.optimizer, [None if g is None else g * scale for g in grads])


class ZeroGradClippedTD3X(TD3X):
    """The same, written as in eager PyTorch: optimizer.zero_grad() cannot be compiled, so the update runs eagerly."""

    def optimize_critic(self, loss):
        self.critic.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        th.nn.utils.clip_grad_norm_(self.critic.parameters(), 0.05)
        self.critic.optimizer.step()


def test_a_clipped_critic_step_is_compiled_when_written_with_gradients_and_apply_gradients(dynamo_graphs_only):
    """gradients() and apply_gradients() trace into one graph with the rest (Dynamo's capture: ``aot_eager``, as the
    catalogue of tests/equivalence/test_user_changes.py), and compute clip_grad_norm_'s step."""
    eager, compiled = small(cls=ClippedTD3X), small(cls=ClippedTD3X, compile_update=True)
    compiled.policy.load_state_dict(eager.policy.state_dict())
    reference = small(cls=ZeroGradClippedTD3X)
    reference.policy.load_state_dict(eager.policy.state_dict())
    data = batches(6)
    for model in (eager, compiled, reference):
        train_fed(model, data)
    assert compiled.update_path == "compiled" and eager.update_path == "eager"
    assert_same_weights(eager, compiled, rtol=1e-4, atol=1e-5)
    assert_same_weights(reference, eager, rtol=1e-5, atol=1e-6)  # gradients/apply_gradients is clip_grad_norm_'s step
    unclipped = small()
    unclipped.policy.load_state_dict(reference.policy.state_dict())
    train_fed(unclipped, data)  # (from the trained weights: only to show the clipping moves the update)
    zero_grad = small(cls=ZeroGradClippedTD3X, compile_update=True)
    train_fed(zero_grad, data)
    assert zero_grad.update_path == "eager" and "Optimizer.zero_grad" in zero_grad.update_reason


def test_a_clipped_step_leaves_a_parameter_the_loss_does_not_reach_as_backward_and_step_do(dynamo_graphs_only):
    """An optimizer holding a parameter its loss never reaches (an unused head): gradients() gives it ``None`` (as
    ``loss.backward()`` leaves its ``.grad`` unset) instead of torch's "appears to not have been used in the graph",
    apply_gradients() leaves it and its Adam state alone, and the step is clip_grad_norm_'s, eager and compiled."""
    models = [small(cls=ClippedTD3X), small(cls=ClippedTD3X, compile_update=True), small(cls=ZeroGradClippedTD3X)]
    heads = []
    for model in models[1:]:
        model.policy.load_state_dict(models[0].policy.state_dict())
    for model in models:
        heads.append(th.nn.Parameter(th.ones(3)))
        model.critic.optimizer.add_param_group({"params": [heads[-1]]})
    data = batches(6)
    for model in models:
        train_fed(model, data)
    eager, compiled, reference = models
    assert compiled.update_path == "compiled", compiled.update_reason
    assert_same_weights(eager, compiled, rtol=1e-4, atol=1e-5)
    assert_same_weights(reference, eager, rtol=1e-5, atol=1e-6)
    for model, head in zip(models, heads):
        assert th.equal(head, th.ones(3)) and head not in model.critic.optimizer.state


@pytest.mark.parametrize("change", ["channels_last", "channels_last_sgd", "gradient_transposed", "sliced_parameter"])
def test_the_eager_fused_adam_step_is_torch_s_for_loop_step_whatever_the_memory_layouts(change):
    """TD3X's eager optimizer step (torch's fused Adam, the default) against torch's for-loop Adam, where a parameter,
    its gradient and its moments are laid out differently in memory: a network moved to ``channels_last`` after the
    first step (also with SGD's fused momentum step), a gradient given to apply_gradients() transposed in memory, a
    parameter that is a slice of a larger tensor. torch 2.13's fused CPU kernels alone are 0.02 to 0.03 off in each
    (with a plain optimizer.step() in place of the hooks' step, all four fail here); the slice warns that its group
    left the fused kernel."""

    def run(fused: bool) -> list[th.Tensor]:
        th.manual_seed(0)
        net = th.nn.Sequential(th.nn.Conv2d(3, 8, 3), th.nn.ReLU(), th.nn.Flatten(), th.nn.Linear(8 * 6 * 6, 4))
        params = list(net.parameters())
        if change == "sliced_parameter":
            whole = th.randn(4, 2 * 8 * 6 * 6)
            net[3].weight = th.nn.Parameter(whole[:, : 8 * 6 * 6])  # a view: not one dense block of memory
            params = list(net.parameters())
        if change.endswith("_sgd"):
            optimizer = th.optim.SGD(params, lr=1e-1, momentum=0.9, **({"fused": True} if fused else {"foreach": False}))
        else:
            optimizer = th.optim.Adam(params, lr=1e-2, **({"fused": True} if fused else {"foreach": False}))
        x = th.randn(5, 3, 8, 8)
        for k in range(3):
            moved = k >= 1 and change.startswith("channels_last")
            if k == 1 and moved:
                net.to(memory_format=th.channels_last)
            loss = net(x.contiguous(memory_format=th.channels_last) if moved else x).square().mean()
            if change == "gradient_transposed":
                grads = [g.mT.contiguous().mT if g.dim() == 2 else g for g in gradients(optimizer, loss)]
                apply_gradients(optimizer, grads)
            else:
                minimize(optimizer, loss)
        return [p.detach().contiguous() for p in params]

    reference = run(fused=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fused = run(fused=True)
    for a, b in zip(reference, fused):
        th.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    left = [w for w in caught if "for-loop implementation" in str(w.message)]
    assert len(left) == (change == "sliced_parameter"), [str(w.message) for w in caught]


def test_cuda_graph_needs_cuda():
    with pytest.raises(ValueError, match="CUDA device"):
        small(cuda_graph=True, device="cpu")


def test_graphed_step_logic_matches_eager_steps():
    """Warm-up and capture leave no trace (weights, optimizer states, the random generator: the smoothing noise of
    each replay is the eager step's), each (batch size, actor update) gets its graph, outputs are copied."""
    eager, graphed = small(policy_delay=2), small(policy_delay=2)
    graphed.policy.load_state_dict(eager.policy.state_dict())
    data = batches(6)
    junk = batches(1, seed=99)[0]

    eager_it = iter(data)
    eager.sample_batch = lambda batch_size: next(eager_it)
    graphed_it = iter(data)
    graphed.in_capture = False
    graphed.sample_batch = lambda batch_size: junk if graphed.in_capture else next(graphed_it)

    class Probe(GraphedGradientStep):
        def _capture(self, batch_size, update_actor):
            graphed.in_capture = True
            try:
                return super()._capture(batch_size, update_actor)
            finally:
                graphed.in_capture = False

    # The CPU buffer takes the static-bounds sampling the CUDA path uses, and the learning rates live in tensors
    # (updated in place by _update_learning_rate), as with cuda_graph=True.
    graphed.replay_buffer.enable_static_sampling()
    for optimizer in (graphed.actor.optimizer, graphed.critic.optimizer):
        for group in optimizer.param_groups:
            group["lr"] = th.tensor(float(group["lr"]))
    probe = Probe(graphed, capture=eager_capture)
    graphed._step_fn = probe
    th.manual_seed(0)
    eager.train(gradient_steps=6, batch_size=32)
    eager_logged = dict(eager.logger.name_to_value)
    th.manual_seed(0)
    graphed.train(gradient_steps=6, batch_size=32)
    assert sorted(probe._graphs) == [(32, False), (32, True)]
    assert isinstance(graphed.critic.optimizer.param_groups[0]["lr"], th.Tensor)
    assert_same_weights(eager, graphed, rtol=1e-5, atol=1e-6)
    for key in ("train/critic_loss", "train/actor_loss", "train/q1_mean", "train/target_q_mean"):
        assert graphed.logger.name_to_value[key] == pytest.approx(eager_logged[key], rel=1e-5), key


def test_static_sampling_respects_buffer_bounds():
    space = gym.spaces.Box(-1, 1, (2,))
    buffer = TensorReplayBuffer(20, space, space, optimize_memory_usage=True, handle_timeout_termination=False)
    buffer.enable_static_sampling()
    obs = np.zeros((1, 2), dtype=np.float32)
    for t in range(5):
        buffer.add(obs + t, obs + t + 1, obs, np.zeros(1), np.zeros(1), [{}])
    buffer.refresh_static_bounds()
    seen = th.cat([buffer.sample(256).observations[:, 0] for _ in range(20)])
    assert set(seen.tolist()) == {0.0, 1.0, 2.0, 3.0, 4.0}  # only the 5 valid transitions, all of them
    for t in range(5, 33):  # wraps around: full
        buffer.add(obs + t, obs + t + 1, obs, np.zeros(1), np.zeros(1), [{}])
    buffer.refresh_static_bounds()
    samples = buffer.sample(4096)
    # The slot at pos holds only a next-observation: never sampled; every other slot is.
    valid_obs = {float(t) for t in range(13, 33)} - {float(32 - 0)}
    got = set(samples.observations[:, 0].tolist())
    assert got <= {float(t) for t in range(14, 33)} and len(got) == 19
    th.testing.assert_close(samples.next_observations, samples.observations + 1)
    del valid_obs


@pytest.mark.parametrize(
    ("kind", "expected"),
    [
        ("amx", None),
        (None, None),  # torch cannot say
        ("avx512_bf16", "bf16=True on a CPU with AVX512-BF16 but no AMX"),
        ("emulated", "bf16=True on a CPU without bf16 matrix instructions"),
    ],
)
def test_bf16_on_a_cpu_without_amx_warns(monkeypatch, tmp_path, kind, expected):
    """bf16=True where the CPU has no AMX warns, at construction and when such a model is loaded: without AVX512-BF16
    either, its bf16 products are emulated (tens of times slower than fp32); with AVX512-BF16 alone they were measured
    slower than fp32. Not with AMX, nor where torch cannot say."""
    monkeypatch.setattr(precision, "cpu_bf16_matmul", lambda: kind)
    expected_list = [] if expected is None else [expected]

    def slow_bf16_warnings(record) -> list[str]:
        return [str(w.message)[: len(expected or "")] for w in record if str(w.message).startswith("bf16=True on a CPU")]

    with pytest.warns() as record:
        model = small(bf16=True)
        small()  # fp32: never
        warnings.warn("sentinel")  # pytest.warns needs one warning
    assert slow_bf16_warnings(record) == expected_list
    model.save(tmp_path / "model.zip")
    with pytest.warns() as record:
        TD3X.load(tmp_path / "model.zip")
        warnings.warn("sentinel")
    assert slow_bf16_warnings(record) == expected_list
    message = precision.bf16_on_cpu_warning(th.device("cpu"))
    assert (message is None) == (expected is None) and (expected is None or message.startswith(expected))
    assert precision.bf16_on_cpu_warning(th.device("meta")) is None  # not a CPU


def test_gpu_trained_model_loads_on_cpu_without_graphs(tmp_path):
    """A model saved with cuda_graph=True (a GPU run) loads on a CPU machine and trains eagerly, with a warning: the
    optimizer state it brings (capturable, learning rates in tensors) is set back for eager steps."""
    model = small()
    model.cuda_graph_request = True  # as saved by a GPU run with cuda_graph=True, whose optimizers were set up for graphs
    model._use_cuda_graph(True, "cuda_graph=True")
    model._step_fn = GraphedGradientStep(model, capture=eager_capture)
    model.learn(20)
    model.save(tmp_path / "gpu_model")
    with pytest.warns(UserWarning, match="cuda_graph=True needs a CUDA device"):
        loaded = TD3X.load(tmp_path / "gpu_model", env=gym.make("Pendulum-v1"), device="cpu")
    assert loaded.cuda_graph is False and loaded.cuda_graph_request is True
    assert "capturable" not in loaded.policy_kwargs.get("optimizer_kwargs", {})
    for group in (*loaded.actor.optimizer.param_groups, *loaded.critic.optimizer.param_groups):
        assert group["capturable"] is False and isinstance(group["lr"], float)
    loaded.learn(150)
    assert loaded.update_path == "eager"


def test_a_changed_setting_captures_the_graphs_again():
    """gamma, tau and the smoothing noise are Python numbers baked into a captured graph: a change between two
    train() calls captures anew (a callback annealing the noise is followed, not frozen)."""
    model = small(policy_delay=1)
    model.replay_buffer.enable_static_sampling()
    feed(model, batches(40))
    captures = []

    class Counting(GraphedGradientStep):
        def _capture(self, batch_size, update_actor):
            captures.append(batch_size)
            return super()._capture(batch_size, update_actor)

    model._step_fn = Counting(model, capture=eager_capture)
    model.train(gradient_steps=2, batch_size=32)
    model.train(gradient_steps=2, batch_size=32)
    assert len(captures) == 1  # nothing changed: the graph is replayed
    for name, value in (("target_policy_noise", 0.1), ("gamma", 0.9), ("tau", 0.01)):
        setattr(model, name, value)
        model.train(gradient_steps=2, batch_size=32)
    assert len(captures) == 4


@pytest.mark.parametrize("cuda", [False, True], ids=["cpu", "cuda"])
def test_the_test_processes_share_inductor_s_cache_on_a_cpu_and_not_where_cuda_is(cuda, monkeypatch):
    """On a CPU the pytest-xdist processes share one Inductor cache folder, so that a graph one compiled is found by
    the others; where CUDA is, each has its own (tests/conftest.py); a folder the caller set is kept."""
    from conftest import _inductor_cache_for_test_processes
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    monkeypatch.setattr(th.cuda, "is_available", lambda: cuda)
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw5")
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    _inductor_cache_for_test_processes()
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == os.path.join(default_cache_dir(), "pytest_gw5" if cuda else "pytest")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", "/somewhere/else")
    _inductor_cache_for_test_processes()
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == "/somewhere/else"
