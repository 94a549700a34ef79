"""SeedBatch: N seeds trained in one process compute, bit for bit on a CPU, what N lone ``learn()`` calls compute.

Each test builds the same models twice from one factory: once alone, ``make(seed).learn(...)`` one after the other,
and once as a batch. Collection (exploration noise, random actions before ``learning_starts``), sampling, the target
smoothing noise and the weights must be equal seed by seed, with the eager update and the compiled one (a long run's
default), with an overridden loss hook, and with an action noise of the user's that draws from numpy's global
generator; and they must differ when the seeds' random streams are shared or swapped. Collection in threads
(``collect_threads``) is bit for bit too; pi(s) batched across seeds (``batched_actions``, a GPU's default) to float
rounding, and the test sees a stale or misplaced batched row.
"""

import functools
import threading
import time

import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.noise import NormalActionNoise

from sb3_td3x import TD3X, SeedBatch
from sb3_td3x.common.random_streams import RandomStreams
from sb3_td3x.variants import TD3C51, TD3LAP, TD3LayerNorm, TD3NStep

SEEDS = (0, 1, 2)
STEPS = 300  # 200 gradient steps after learning_starts=100


class HuberTD3X(TD3X):
    """An overridden loss hook: the batch runs it per seed, as written."""

    def critic_loss(self, current_q, target_q):
        loss = sum(th.nn.functional.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}


class LongRunTD3X(TD3X):
    """Every run counts as long: compile_update=None (auto) compiles the update, as on a long run on a CPU."""

    compile_auto_min_steps = 0


class GlobalNoise(NormalActionNoise):
    """A user's action noise, drawing from numpy's global generator itself: the batch installs the seed's streams."""

    def __call__(self):
        return np.random.normal(self._mu, 2 * self._sigma).astype(self._dtype)


def factory(cls=TD3X, noise=NormalActionNoise, **kwargs):
    def make(seed):
        options = {
            "learning_starts": 100,
            "batch_size": 64,
            "policy_kwargs": {"net_arch": [32, 32]},
            "action_noise": noise(np.zeros(1), 0.1 * np.ones(1)),
            **kwargs,
        }
        return cls("MlpPolicy", "Pendulum-v1", seed=seed, **options)

    return make


def lone_runs(make, steps=STEPS, seeds=SEEDS):
    return [make(seed).learn(steps) for seed in seeds]


@functools.cache
def default_lone_runs(steps=STEPS):
    """The lone runs of ``factory()``'s model, trained once per length for every test that compares with them (the
    tests only read them)."""
    return lone_runs(factory(), steps)


def differences(batch, lone):
    """Per seed: the largest weight difference to its lone run."""
    return [
        max((a - b).abs().max().item() for a, b in zip(m.policy.state_dict().values(), l.policy.state_dict().values()))
        for m, l in zip(batch, lone)
    ]


def assert_same_runs(batch, lone, exact=True):
    """The same transitions (collection is the lone run's) and weights: bit for bit, or (``exact=False``, against
    another update) to float rounding."""
    tolerance = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-4, "atol": 1e-5}
    for i, (model, alone) in enumerate(zip(batch, lone)):
        assert (model.num_timesteps, model._n_updates) == (alone.num_timesteps, alone._n_updates)
        pos, start = alone.replay_buffer.pos, alone.learning_starts
        for field in ("observations", "actions", "rewards"):
            ours, theirs = (np.asarray(getattr(m.replay_buffer, field)[:pos]) for m in (model, alone))
            np.testing.assert_array_equal(ours[:start], theirs[:start])  # random actions before learning_starts
            np.testing.assert_allclose(ours, theirs, **tolerance, err_msg=f"seed {i} {field}")
        for (name, a), b in zip(alone.policy.state_dict().items(), model.policy.state_dict().values()):
            th.testing.assert_close(b, a, **tolerance, msg=lambda m, name=name, i=i: f"seed {i} {name}: {m}")


@pytest.mark.parametrize(
    ("cls", "noise", "swaps"),
    [
        (TD3X, NormalActionNoise, False),
        (HuberTD3X, NormalActionNoise, True),
        (TD3X, GlobalNoise, True),
        (LongRunTD3X, NormalActionNoise, True),
    ],
    ids=["default", "overridden-critic_loss", "noise-from-numpy-global", "compiled-long-run"],
)
def test_a_batch_computes_the_lone_runs_bit_for_bit(cls, noise, swaps):
    make = factory(cls, noise)
    compiled = cls is LongRunTD3X  # the long run's default: each lone run and each seed of the batch compile the update
    seeds = SEEDS[:2] if compiled else SEEDS  # two seeds show it: each compile costs seconds
    lone = default_lone_runs() if (cls, noise) == (TD3X, NormalActionNoise) else lone_runs(make, seeds=seeds)
    caller = np.random.get_state()
    batch = SeedBatch(make, seeds).learn(STEPS)
    assert batch.collection == "one seed after the other (collect_threads=1); pi(s) per seed"  # a CPU's default
    assert all(m.update_path == ("compiled" if compiled else "eager") for m in [*lone, *batch])
    assert all(("compile_update=None (auto): a run of 200 training steps" in m.update_reason) == compiled for m in batch)
    # The default model's rounds swap no global state; a user's class or noise runs with the seed's streams installed.
    assert batch._globals == [swaps] * len(seeds)
    assert all(m._n_updates == STEPS - 100 for m in batch)
    assert_same_runs(batch, lone)
    # The caller's global random state is as it was.
    assert all(np.array_equal(a, b) for a, b in zip(np.random.get_state(), caller))


@pytest.mark.parametrize(
    ("cls", "kwargs"),
    [(TD3LAP, {}), (TD3NStep, {}), (TD3LayerNorm, {}), (TD3C51, {"v_min": -1600.0, "v_max": 0.0})],
    ids=["td3_lap", "td3_nstep", "td3_layernorm", "td3_c51"],
)
def test_a_batch_of_each_variant_computes_its_lone_runs_bit_for_bit(cls, kwargs):
    """The variants of sb3_td3x.variants: seed i of a batch is its lone run, prioritised draws (from each seed's own
    torch stream) and priorities included."""
    make = factory(cls, **kwargs)
    lone = lone_runs(make)
    batch = SeedBatch(make, SEEDS).learn(STEPS)
    assert_same_runs(batch, lone)
    if cls is TD3LAP:
        for model, alone in zip(batch, lone):
            assert th.equal(model.replay_buffer.priorities.leaves, alone.replay_buffer.priorities.leaves)
            assert th.equal(model.replay_buffer.max_priority, alone.replay_buffer.max_priority)


def test_the_test_fails_when_the_math_differs():
    """A batch of a model whose loss differs from the lone runs' is seen."""
    lone = default_lone_runs()
    batch = SeedBatch(factory(HuberTD3X), SEEDS).learn(STEPS)
    with pytest.raises(AssertionError):
        assert_same_runs(batch, lone)


@pytest.mark.parametrize("broken", ["one_shared_stream", "streams_swapped"])
def test_shared_or_mixed_random_streams_are_detected(broken, monkeypatch):
    make = factory()
    lone = default_lone_runs(200)
    if broken == "one_shared_stream":  # every seed draws from the global generators, one after the other
        monkeypatch.setattr(RandomStreams, "detach", lambda self: self)
        batch = SeedBatch(make, SEEDS)
    else:
        batch = SeedBatch(make, SEEDS)
        first = batch.streams[0].state()
        batch.streams[0].set_state(batch.streams[1].state())
        batch.streams[1].set_state(first)
    batch.learn(200)
    differ = [i for i, d in enumerate(differences(batch, lone)) if d > 1e-4]
    assert differ, f"{broken}: the seeds match their lone runs, so the test cannot see mixed streams"
    if broken == "streams_swapped":
        assert differ == [0, 1]


def test_learn_goes_on_and_each_seed_is_a_full_model(tmp_path):
    """learn() twice (reset_num_timesteps=False), per-seed callbacks, save and TD3X.load."""
    make = factory()
    lone = []
    for seed in SEEDS:
        model = make(seed)
        model.learn(200)
        model.learn(100, reset_num_timesteps=False)
        lone.append(model)
    batch = SeedBatch(make, SEEDS)
    batch.learn(200)
    calls = [[] for _ in SEEDS]

    class Count(BaseCallback):
        def __init__(self, i):
            super().__init__()
            self.i = i

        def _on_step(self):
            calls[self.i].append(self.model.num_timesteps)
            return True

    batch.learn(100, callback=[Count(i) for i in range(len(SEEDS))], reset_num_timesteps=False)
    assert calls == [list(range(201, 301))] * len(SEEDS)
    assert_same_runs(batch, lone)
    paths = batch.save(tmp_path)
    loaded = TD3X.load(paths[1])
    for a, b in zip(batch[1].policy.state_dict().values(), loaded.policy.state_dict().values()):
        assert th.equal(a, b)


def _collecting_threads(monkeypatch):
    """The names of the threads each seed's transitions were stored from (TD3X's own method, patched on the class:
    the models stay TD3X's, so their rounds may run in threads)."""
    seen = {}
    store = TD3X._store_transition

    def recording(self, *args, **kwargs):
        seen.setdefault(self.seed, set()).add(threading.current_thread().name)
        return store(self, *args, **kwargs)

    monkeypatch.setattr(TD3X, "_store_transition", recording)
    return seen


@pytest.mark.parametrize("collect_threads", [1, 3])
def test_per_seed_evaluations_equal_the_lone_runs(collect_threads, monkeypatch):
    """An EvalCallback per seed (evaluation inside collection, on its own env) sees what the lone run sees: the seeds
    collecting in turn, and in threads (SB3's EvalCallback is SB3's code: its seed may collect in a thread)."""
    make = factory()

    def evaluation(seed):
        return EvalCallback(factory()(seed).get_env(), eval_freq=150, n_eval_episodes=1, verbose=0, warn=False)

    lone_evals = []
    for seed in SEEDS:
        model = make(seed)
        callback = evaluation(seed)
        model.learn(300, callback=callback)
        lone_evals.append(callback.evaluations_results)
    threads = _collecting_threads(monkeypatch)
    callbacks = [evaluation(seed) for seed in SEEDS]
    batch = SeedBatch(make, SEEDS, collect_threads=collect_threads).learn(300, callback=callbacks)
    assert [cb.evaluations_results for cb in callbacks] == lone_evals
    in_threads = {name.startswith("sb3_td3x_collect") for names in threads.values() for name in names}
    assert in_threads == {collect_threads > 1}
    assert batch.collection.startswith("3 seeds in 3 threads" if collect_threads > 1 else "one seed after the other")


def test_sb3_td3_runs_per_seed_and_matches():
    def make(seed):
        return TD3("MlpPolicy", "Pendulum-v1", learning_starts=100, batch_size=32, policy_kwargs={"net_arch": [16]}, seed=seed)

    lone = [make(seed).learn(200) for seed in SEEDS[:2]]
    batch = SeedBatch(make, SEEDS[:2]).learn(200)
    assert_same_runs(batch, lone)


def test_a_failing_seed_stops_alone_with_keep_going():
    class Fail(BaseCallback):
        def _on_step(self):
            if self.num_timesteps == 150:
                raise RuntimeError("seed 1 broke")
            return True

    make = factory()
    batch = SeedBatch(make, SEEDS)
    with pytest.raises(RuntimeError, match="seed 1 broke"):
        batch.learn(200, callback=[None, Fail(), None])
    batch = SeedBatch(make, SEEDS)
    batch.learn(200, callback=[None, Fail(), None], keep_going=True)
    assert list(batch.errors) == [1] and [m.num_timesteps for m in batch] == [200, 150, 200]
    # The other two go on per seed after seed 1 stops (2 of 3 seeds train each round) and still compute their lone runs.
    assert_same_runs([batch[0], batch[2]], [default_lone_runs(200)[0], default_lone_runs(200)[2]])


def test_bad_input_is_refused_with_a_clear_message():
    make = factory()
    with pytest.raises(ValueError, match="repeat a seed"):
        SeedBatch(make, [0, 0])
    with pytest.raises(ValueError, match="no seeds"):
        SeedBatch(make, [])
    with pytest.raises(TypeError, match="returned int, not a model"):
        SeedBatch(lambda seed: seed, [0])
    batch = SeedBatch(make, SEEDS[:2])
    with pytest.raises(TypeError, match="give one per seed"):
        batch.learn(10, callback=EvalCallback(make(0).get_env()))
    with pytest.raises(ValueError, match="3 callbacks for 2 seeds"):
        batch.learn(10, callback=[None, None, None])
    shared = EvalCallback(make(0).get_env())
    with pytest.raises(ValueError, match="given to two seeds"):
        batch.learn(10, callback=[shared, [shared]])
    model = make(0)
    with pytest.raises(ValueError, match="a model is given twice"):
        SeedBatch.from_models([model, model], seeds=[0, 1])


class CountingTrain(TD3X):
    """train() overridden (it calls super): the batch calls each seed's train()."""

    def train(self, gradient_steps, batch_size=100):
        self.train_calls = getattr(self, "train_calls", 0) + 1
        super().train(gradient_steps, batch_size)


class OwnLearn(TD3X):
    def learn(self, *args, **kwargs):
        self.my_learn_ran = True
        return super().learn(*args, **kwargs)


def test_an_overridden_train_runs_and_an_overridden_learn_is_refused():
    make = factory(CountingTrain)
    lone = lone_runs(make, steps=200)
    batch = SeedBatch(make, SEEDS).learn(200)
    assert [m.train_calls for m in batch] == [m.train_calls for m in lone] == [100] * len(SEEDS)
    assert_same_runs(batch, lone)
    with pytest.raises(ValueError, match=r"would not run model 0's learn \(overridden by OwnLearn\).*callback"):
        SeedBatch(factory(OwnLearn), SEEDS[:2]).learn(10)
    single = SeedBatch(factory(OwnLearn), SEEDS[:1]).learn(10)  # one seed: its own learn()
    assert single[0].my_learn_ran


# Collection: the seeds in threads, pi(s) batched ---------------------------------------------------------------------
def test_seeds_collecting_in_threads_compute_their_lone_runs_bit_for_bit(monkeypatch):
    """collect_threads: the seeds whose code draws only from their streams collect in threads (their environments
    step in parallel), a seed with a user's action noise in the caller's thread after them; each is its lone run."""

    def make(seed):  # seed 1 with a user's noise, which draws from numpy's global generator
        return factory(noise=GlobalNoise if seed == 1 else NormalActionNoise)(seed)

    lone = lone_runs(make, steps=300)
    threads = _collecting_threads(monkeypatch)
    batch = SeedBatch(make, SEEDS, collect_threads=2).learn(300)
    assert batch.collection == "2 seeds in 2 threads, 1 in turn after them; pi(s) per seed"
    assert batch._globals == [False, True, False]
    assert all(name.startswith("sb3_td3x_collect") for seed in (0, 2) for name in threads[seed])
    assert threads[1] == {threading.main_thread().name}
    assert_same_runs(batch, lone)


class PerturbActor(BaseCallback):
    """Zeroes the actor's output layer in place at the start of one rollout (after batched pi(s) was computed):
    pi(s) = tanh(0) = 0 from then on, until the next actor update."""

    def __init__(self, at_step):
        super().__init__()
        self.at_step = at_step

    def _on_rollout_start(self):
        if self.num_timesteps == self.at_step:
            with th.no_grad():
                self.model.actor.mu[-2].weight.zero_()
                self.model.actor.mu[-2].bias.zero_()

    def _on_step(self):
        return True


def _count_prefetched(monkeypatch):
    """How many collection steps took a prefetched pi(s), per seed."""
    from sb3_td3x.seeds import actions

    taken = {}
    valid = actions.PrefetchedAction.valid_for

    def counting(self, model):
        ok = valid(self, model)
        taken[model.seed] = taken.get(model.seed, 0) + ok
        return ok

    monkeypatch.setattr(actions.PrefetchedAction, "valid_for", counting)
    return taken


def test_batched_actions_compute_what_each_seed_computes(monkeypatch):
    """batched_actions=True (the GPU's default) on a CPU: pi(s) of the three seeds in one vmapped call of the actor,
    each seed's collection to float rounding its lone run's. A seed whose actor changed in place after the batched
    pi(s) (a callback at a rollout's start) computes its own: else it would act with the old weights."""
    lone = []
    for seed in SEEDS:
        lone.append(factory()(seed).learn(STEPS, callback=PerturbActor(250) if seed == 1 else None))
    taken = _count_prefetched(monkeypatch)
    callbacks = [PerturbActor(250) if seed == 1 else None for seed in SEEDS]
    batch = SeedBatch(factory(), SEEDS, batched_actions=True).learn(STEPS, callback=callbacks)
    assert batch.collection.endswith("pi(s) batched across seeds")
    # From learning_starts on, every step but seed 1's at step 250 took the batched pi(s).
    assert taken == {0: STEPS - 100, 1: STEPS - 100 - 1, 2: STEPS - 100}
    assert_same_runs(batch, lone, exact=False)


def _halved_actor(model):
    """A user's change on the instance: the actor's output halved (collection must call it as written)."""
    forward = model.actor.forward
    model.actor.forward = lambda obs: 0.5 * forward(obs)
    return model


def test_batched_actions_run_the_users_actor(monkeypatch):
    """A Tanh MLP actor: the batched pi(s) is the actor module's own forward, vmapped over the seeds' parameters, so
    it computes the user's network (to float rounding) and is taken."""

    def make(seed):
        return factory(policy_kwargs={"net_arch": [32, 32], "activation_fn": th.nn.Tanh})(seed)

    lone = lone_runs(make, steps=250)
    taken = _count_prefetched(monkeypatch)
    batch = SeedBatch(make, SEEDS, batched_actions=True).learn(250)
    assert batch.collection.endswith("pi(s) batched across seeds")
    assert taken == {seed: 150 for seed in SEEDS}
    assert_same_runs(batch, lone, exact=False)


def test_batched_actions_step_aside_for_an_actor_forward_set_on_the_instance(monkeypatch):
    """A forward set on each seed's actor instance may differ from seed to seed: one call cannot stand for all of
    them, so each seed computes its own pi(s), as written, bit for bit its lone run's."""
    make = lambda seed: _halved_actor(factory()(seed))  # noqa: E731
    lone = lone_runs(make, steps=250)
    taken = _count_prefetched(monkeypatch)
    batch = SeedBatch(make, SEEDS, batched_actions=True).learn(250)
    assert all(m.exploration_path == "actor" for m in batch)
    assert taken == {}  # no row was computed, so none was offered
    assert_same_runs(batch, lone)


def test_the_batched_actions_test_fails_when_the_rows_are_mixed_up(monkeypatch):
    """The seeds' rows of the batched pi(s) swapped: the collections differ from the lone runs, and it is seen."""
    from dataclasses import replace

    from sb3_td3x.seeds import batch as seed_batch

    prefetch = seed_batch.prefetch_actions

    def mixed_up(models):
        served = prefetch(models)
        if len(served) > 1:
            first, second = (models[i] for i in served[:2])
            first._prefetched_action, second._prefetched_action = (
                replace(first._prefetched_action, actions=second._prefetched_action.actions),
                replace(second._prefetched_action, actions=first._prefetched_action.actions),
            )
        return served

    monkeypatch.setattr(seed_batch, "prefetch_actions", mixed_up)
    lone = default_lone_runs(200)
    batch = SeedBatch(factory(), SEEDS, batched_actions=True).learn(200)
    with pytest.raises(AssertionError):
        assert_same_runs(batch, lone, exact=False)


def test_an_interrupted_wait_lets_every_collection_thread_finish(monkeypatch):
    """A signal's exception in the caller's wait (Ctrl-C) is raised only once every seed's rollout is done: no
    seed goes on collecting behind a checkpoint."""
    from concurrent.futures import ThreadPoolExecutor

    from sb3_td3x.seeds import batch as seed_batch

    calls = []
    real_wait = seed_batch.wait

    def interrupted_once(pending):
        calls.append(len(pending))
        if len(calls) == 1:
            raise KeyboardInterrupt
        return real_wait(pending)

    monkeypatch.setattr(seed_batch, "wait", interrupted_once)
    with ThreadPoolExecutor(2) as pool:
        futures = {i: pool.submit(time.sleep, 0.2) for i in range(2)}
        with pytest.raises(KeyboardInterrupt):
            seed_batch._all_done(futures)
        assert all(f.done() for f in futures.values()) and len(calls) == 2


def test_bad_collection_options_are_refused():
    for threads in (0, None, 1.5):
        with pytest.raises(ValueError, match=rf"collect_threads={threads}; give a number of threads >= 1"):
            SeedBatch(factory(), SEEDS[:2], collect_threads=threads)
    with pytest.raises(ValueError, match="batched_actions='yes'"):
        SeedBatch(factory(), SEEDS[:2], batched_actions="yes")
