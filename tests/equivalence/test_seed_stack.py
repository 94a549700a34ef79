"""SeedStackedMlpUpdate (issue 17's first block): N seeds trained together compute what N lone TD3X runs compute.

Each seed's model is built and its buffer filled by a short ``learn()`` that only collects; then the same hundreds of
gradient steps run batched over the seeds and, for comparison, in lone models (same seeds, same buffers, same random
states) with their own ``train()``. Weights, optimizer states, counters, logged statistics and each seed's random
state must agree; variants that share or mix the seeds' random streams must not.
"""

import contextlib
import zipfile

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure

from sb3_td3x import TD3X
from sb3_td3x.td3x.update_paths.seeds import GlobalRandomState, SeedRandomStreams, SeedStackedMlpUpdate

COLLECT = 200  # environment steps that fill each buffer (learning_starts: no gradient step)
BATCH = 64
SEEDS = (0, 1, 2)
CHUNKS = (110, 110, 110)  # train() calls of 330 gradient steps in all, the learning rate changing between them


def filled(seed: int, **kwargs) -> tuple[TD3X, GlobalRandomState]:
    """A model whose buffer holds COLLECT transitions, and the global random state its lone training starts from."""
    kwargs = {"policy_kwargs": {"net_arch": [32, 32]}, "learning_rate": lambda progress: 1e-3 * progress, **kwargs}
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=COLLECT, buffer_size=COLLECT, seed=seed, **kwargs)
    model.learn(COLLECT)  # collection only
    model.set_logger(configure(None, []))
    return model, GlobalRandomState.capture()


def train_in_chunks(train, models: list[TD3X], chunks=CHUNKS) -> None:
    for n, steps in enumerate(chunks):
        for model in models:
            model._current_progress_remaining = 1.0 - 0.25 * n
        train(steps, BATCH)


def lone_runs(chunks=CHUNKS, per_seed=None, **kwargs) -> tuple[list[TD3X], list[GlobalRandomState]]:
    """Each seed trained alone with its own train() (MlpUpdate), from the global state its construction left."""
    models, states = [], []
    for seed in SEEDS:
        model, _ = filled(seed, **kwargs, **(per_seed or {}).get(seed, {}))
        train_in_chunks(model.train, [model], chunks)
        assert model.update_path == "mlp"
        models.append(model)
        states.append(GlobalRandomState.capture())
    return models, states


def batched_models(per_seed=None, **kwargs) -> tuple[list[TD3X], list[GlobalRandomState]]:
    built = [filled(seed, **kwargs, **(per_seed or {}).get(seed, {})) for seed in SEEDS]
    return [model for model, _ in built], [state for _, state in built]


def assert_same_weights(batched: TD3X, lone: TD3X) -> None:
    for (name, a), b in zip(lone.policy.state_dict().items(), batched.policy.state_dict().values()):
        th.testing.assert_close(b, a, rtol=1e-4, atol=1e-5, msg=lambda m, name=name: f"{name}: {m}")


def assert_same_run(batched: TD3X, lone: TD3X, batched_state: GlobalRandomState, lone_state: GlobalRandomState) -> None:
    assert_same_weights(batched, lone)
    for optimizer in ("actor", "critic"):
        lone_state_dict = getattr(lone, optimizer).optimizer.state_dict()
        batched_state_dict = getattr(batched, optimizer).optimizer.state_dict()
        assert lone_state_dict["param_groups"] == batched_state_dict["param_groups"]
        assert lone_state_dict["state"].keys() == batched_state_dict["state"].keys()
        for key, fields in lone_state_dict["state"].items():
            for field, value in fields.items():
                th.testing.assert_close(batched_state_dict["state"][key][field], value, rtol=1e-4, atol=1e-6)
    assert (batched._n_updates, batched._n_actor_updates) == (lone._n_updates, lone._n_actor_updates)
    assert batched.logger.name_to_value.keys() == lone.logger.name_to_value.keys()
    for key, value in lone.logger.name_to_value.items():
        assert batched.logger.name_to_value[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    # The seed's random stream ends where the lone run's does: the same draws, no more, no fewer.
    assert batched_state.python == lone_state.python
    assert all(np.array_equal(a, b) for a, b in zip(batched_state.numpy, lone_state.numpy))
    assert th.equal(batched_state.torch, lone_state.torch)


@pytest.mark.parametrize("seeds_per_product", [None, 2, 3], ids=["default-1-on-cpu", "groups-of-2", "all-3-as-on-a-gpu"])
def test_seeds_trained_together_compute_what_lone_runs_compute(tmp_path, seeds_per_product):
    lone, lone_states = lone_runs()
    models, states = batched_models()
    caller = GlobalRandomState.capture()
    update = SeedStackedMlpUpdate(models, states, seeds_per_product=seeds_per_product)
    assert update.seeds_per_product == (seeds_per_product or 1)
    train_in_chunks(update.train, models)
    # Each role of every seed is one stacked tensor per layer; the models' Parameters are views of it.
    storage = {p.untyped_storage().data_ptr() for model in models for p in model.critic.parameters()}
    assert len(storage) == 1 and update.critic.weights[0].shape[0] == len(SEEDS) * 2
    for i in range(len(SEEDS)):
        assert_same_run(models[i], lone[i], update.streams.states[i], lone_states[i])
    # The caller's global random state is put back.
    assert all(np.array_equal(a, b) for a, b in zip(np.random.get_state(), caller.numpy))
    assert th.equal(th.get_rng_state(), caller.torch)

    # Each seed is still a full SB3 model: save writes its own weights only, and load gives them back.
    models[1].save(tmp_path / "batched.zip")
    lone[1].save(tmp_path / "lone.zip")
    # (A view of the stacked weights would otherwise bring every seed's weights into the file: 2.6 times the lone
    # model's policy.pth with 3 seeds, against 1.16 times here, where each tensor is a storage record of its own.)
    sizes = [zipfile.ZipFile(tmp_path / name).getinfo("policy.pth").file_size for name in ("batched.zip", "lone.zip")]
    assert sizes[0] < 1.3 * sizes[1]
    loaded = TD3X.load(tmp_path / "batched.zip")
    for a, b in zip(models[1].policy.state_dict().values(), loaded.policy.state_dict().values()):
        assert th.equal(a, b)


def test_a_seed_goes_on_alone_and_back():
    """After batched training, a model trains alone from its seed's stream (its own MlpUpdate takes the weights
    back), then batched again: still the lone run."""
    lone, lone_states = lone_runs(chunks=(40, 20, 20))
    models, states = batched_models()
    update = SeedStackedMlpUpdate(models, states)
    train_in_chunks(update.train, models, chunks=(40,))
    with update.streams.kept_apart():  # each seed alone, its random stream the global one
        for i, model in enumerate(models):
            with update.streams.seed(i):
                model._current_progress_remaining = 0.75
                model.train(20, BATCH)
    for model in models:
        model._current_progress_remaining = 0.5
    update.train(20, BATCH)  # together again
    for i in range(len(SEEDS)):
        assert_same_run(models[i], lone[i], update.streams.states[i], lone_states[i])


def test_per_model_settings_run_per_model():
    """Learning rates, tau and policy_delay are each model's own (its optimizers and hooks): seeds whose actors
    update on different steps still compute their lone runs."""
    per_seed = {
        0: {"policy_delay": 1},
        1: {"policy_delay": 3, "tau": 0.02},
        2: {"learning_rate": 3e-4, "critic_learning_rate": 1e-3},
    }
    lone, lone_states = lone_runs(chunks=(30, 30), per_seed=per_seed)
    models, states = batched_models(per_seed=per_seed)
    update = SeedStackedMlpUpdate(models, states)
    train_in_chunks(update.train, models, chunks=(30, 30))
    assert [m._n_actor_updates for m in models] == [60, 20, 30]
    for i in range(len(SEEDS)):
        assert_same_run(models[i], lone[i], update.streams.states[i], lone_states[i])


def test_fused_optimizer_steps_and_target_updates_are_the_per_seed_ones_to_the_bit():
    """fuse=True: one Adam kernel call per group of equal options and one lerp per tau, over all seeds; the same bits
    as each model's own optimizer steps and target-update hooks (fuse=False)."""
    per_seed = {1: {"learning_rate": 3e-4, "tau": 0.02}, 2: {"policy_delay": 3}}
    runs = []
    for fuse in (True, False):
        models, states = batched_models(per_seed=per_seed)
        train_in_chunks(SeedStackedMlpUpdate(models, states, fuse=fuse).train, models, chunks=(30, 30))
        runs.append(models)
    for fused, stepped in zip(*runs):
        for a, b in zip(fused.policy.state_dict().values(), stepped.policy.state_dict().values()):
            assert th.equal(a, b)
        for optimizer in ("actor", "critic"):
            fused_state = getattr(fused, optimizer).optimizer.state_dict()["state"]
            stepped_state = getattr(stepped, optimizer).optimizer.state_dict()["state"]
            for key, fields in stepped_state.items():
                for field, value in fields.items():
                    assert th.equal(fused_state[key][field], value), (optimizer, key, field)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_steps": 3},  # NStepReplayBuffer: per-transition discounts
        {"target_policy_smoothing": False, "clipped_double_q": False},
        {"policy_kwargs": {"n_critics": 3, "net_arch": {"pi": [16], "qf": [24, 16, 8]}}},
    ],
    ids=["n-step", "no-smoothing-no-clipped-double-q", "3-critics-other-widths"],
)
def test_other_settings_shared_by_the_seeds(kwargs):
    lone, lone_states = lone_runs(chunks=(30, 30), **kwargs)
    models, states = batched_models(**kwargs)
    if "n_steps" in kwargs:
        assert getattr(models[0].replay_buffer.sample(4), "discounts", None) is not None
    update = SeedStackedMlpUpdate(models, states)
    train_in_chunks(update.train, models, chunks=(30, 30))
    for i in range(len(SEEDS)):
        assert_same_run(models[i], lone[i], update.streams.states[i], lone_states[i])


@contextlib.contextmanager
def _no_swap(self, i):
    yield  # every seed draws from the one global stream, one after the other


def _restore_without_torch(self):
    np.random.set_state(self.numpy)  # the indices from each seed's own numpy stream, the noise from a shared one


@pytest.mark.parametrize("broken", ["one_shared_stream", "streams_swapped", "noise_stream_shared"])
def test_shared_or_mixed_random_streams_are_detected(broken, monkeypatch):
    lone, _ = lone_runs(chunks=(10,))
    models, states = batched_models()
    if broken == "one_shared_stream":
        monkeypatch.setattr(SeedRandomStreams, "seed", _no_swap)
    elif broken == "streams_swapped":
        states = [states[1], states[0], states[2]]
    else:
        monkeypatch.setattr(GlobalRandomState, "restore", _restore_without_torch)
    update = SeedStackedMlpUpdate(models, states)
    train_in_chunks(update.train, models, chunks=(10,))
    differ = []
    for i in range(len(SEEDS)):
        try:
            assert_same_weights(models[i], lone[i])
        except AssertionError:
            differ.append(i)
    assert differ, f"{broken}: the seeds' weights match their lone runs, so the test cannot see mixed streams"
    if broken == "streams_swapped":
        assert differ == [0, 1]


class HuberTD3X(TD3X):
    def critic_loss(self, current_q, target_q):
        loss = sum(th.nn.functional.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}


@pytest.mark.filterwarnings("ignore:bf16=True on a CPU")
def test_models_it_cannot_train_exactly_are_refused():
    def build(cls=TD3X, **kwargs):
        kwargs = {"policy_kwargs": {"net_arch": [16]}, **kwargs}
        return cls("MlpPolicy", "Pendulum-v1", learning_starts=0, seed=0, **kwargs)

    states = [GlobalRandomState.capture()] * 2
    with pytest.raises(ValueError, match=r"cannot train these models together: model 1: critic_loss overridden by HuberTD3X"):
        SeedStackedMlpUpdate([build(), build(HuberTD3X)], states)
    with pytest.raises(ValueError, match=r"model 1's networks differ from model 0's"):
        SeedStackedMlpUpdate([build(), build(policy_kwargs={"net_arch": [8]})], states)
    with pytest.raises(ValueError, match=r"model 1's gamma is 0.9, model 0's 0.99"):
        SeedStackedMlpUpdate([build(), build(gamma=0.9)], states)
    with pytest.raises(ValueError, match=r"model 0: bf16=True"):
        SeedStackedMlpUpdate([build(bf16=True), build()], states)
    model = build()
    with pytest.raises(ValueError, match="a model is given twice"):
        SeedStackedMlpUpdate([model, model], states)
    with pytest.raises(ValueError, match="2 models but 1 random states"):
        SeedStackedMlpUpdate([build(), build()], states[:1])
