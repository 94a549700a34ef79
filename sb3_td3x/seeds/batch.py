"""Many seeds in one process: N runs of one configuration trained together, seed ``i`` computing its lone run.

.. code-block:: python

    from sb3_td3x import TD3X, SeedBatch

    batch = SeedBatch(lambda seed: TD3X("MlpPolicy", "Hopper-v5", seed=seed), seeds=[0, 1, 2, 3, 4])
    batch.learn(200_000)
    batch[2].save("hopper_seed2")             # seed 2 is a full TD3X: predict, save, evaluate_policy, TD3X.load
    batch[2].update_path, batch[2].update_reason  # how its gradient steps ran, and why

Each round, every seed collects its rollout (its model's ``collect_rollouts``), then takes its gradient steps with
its model's own ``train()``: the update its lone run would run, so seed ``i`` computes its lone run's numbers bit for
bit. Each model draws from its own random streams (:class:`~sb3_td3x.common.random_streams.RandomStreams`), detached
where its lone run stands; code that may draw from the global generators runs with its seed's streams installed as
them (:func:`_may_draw_from_globals`). The seeds collect in turn, or in ``collect_threads`` threads, and on a GPU pi(s)
of all seeds is one vmapped call (:func:`~sb3_td3x.seeds.actions.prefetch_actions`): docs/seeds.md says how each
works, and what was measured.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutReturn

from sb3_td3x.common import denormals
from sb3_td3x.common.buffers import TensorReplayBuffer
from sb3_td3x.common.random_streams import RandomStreams, detached_streams
from sb3_td3x.seeds.actions import prefetch_actions
from sb3_td3x.td3x.td3x import TD3X

log = logging.getLogger(__name__)

#: The seed whose code runs now (its index in the batch), None outside a batch's per-seed work: what per-seed log
#: handlers filter on (``sb3_td3x.experiment``).
current_seed: contextvars.ContextVar[int | None] = contextvars.ContextVar("sb3_td3x_current_seed", default=None)


@contextlib.contextmanager
def acting_as(index: int) -> Iterator[None]:
    """:data:`current_seed` set to ``index`` inside: the code runs as that seed's (its log lines go to its log)."""
    token = current_seed.set(index)
    try:
        yield
    finally:
        current_seed.reset(token)


# Packages whose code draws only from the model's streams (or from generators of its own, as gymnasium's envs).
_OWN_STREAMS_CODE = ("stable_baselines3", "gymnasium", "sb3_td3x")


@dataclass
class _SeedRun:
    """One seed's place in a ``learn()`` call."""

    index: int
    model: OffPolicyAlgorithm
    total_timesteps: int
    callback: BaseCallback
    finished: bool = False  # its rollout asked to stop, or it reached total_timesteps
    failed: bool = False


class SeedBatch:
    """N runs of one configuration, one per seed, trained together in this process (see the module's docstring).

    :param make_model: builds seed ``seed``'s model, as its lone run would (``TD3X(..., seed=seed)`` on its own
        environment). It is called once per seed, in order; the caller's global random state is put back after
    :param seeds: the seeds, distinct
    :param collect_threads: threads the seeds collect in, at most one per seed (see the module's docstring); 1, the
        default: one after the other, in the caller's thread
    :param batched_actions: pi(s) of all seeds in one vmapped call of the actor: None (default) on a GPU, True also
        on a CPU (there to float rounding, not bit for bit: each seed's own 2-D products are its lone run's), False
        never
    """

    def __init__(
        self,
        make_model: Callable[[int], OffPolicyAlgorithm],
        seeds: Sequence[int],
        *,
        collect_threads: int = 1,
        batched_actions: bool | None = None,
    ):
        seeds = self._check_seeds(seeds)
        models, streams = [], []
        caller = RandomStreams().state()
        try:
            for seed in seeds:
                model = make_model(seed)
                if not isinstance(model, OffPolicyAlgorithm):
                    raise TypeError(
                        f"SeedBatch: make_model({seed}) returned {type(model).__name__}, not a model; it must build and "
                        "return one off-policy model (e.g. lambda seed: TD3X('MlpPolicy', env_id, seed=seed))."
                    )
                models.append(model)
                streams.append(detached_streams(model))
        finally:
            RandomStreams().set_state(caller)
        self._setup(models, streams, seeds, collect_threads, batched_actions)

    @classmethod
    def from_models(
        cls,
        models: Sequence[OffPolicyAlgorithm],
        random_streams: Sequence[RandomStreams] | None = None,
        seeds: Sequence[int] | None = None,
        *,
        collect_threads: int = 1,
        batched_actions: bool | None = None,
    ) -> SeedBatch:
        """A batch of models built elsewhere (loaded from checkpoints, ...).

        :param random_streams: each model's streams, detached where its lone run stands
            (:func:`~sb3_td3x.common.random_streams.detached_streams` right after building or loading it); default:
            detached now
        :param seeds: their seeds (default: each model's ``seed``)
        :param collect_threads: as the constructor's
        :param batched_actions: as the constructor's
        """
        batch = cls.__new__(cls)
        if seeds is None:
            seeds = [int(m.seed) if m.seed is not None else i for i, m in enumerate(models)]
        streams = list(random_streams) if random_streams is not None else [detached_streams(m) for m in models]
        batch._setup(list(models), streams, cls._check_seeds(seeds), collect_threads, batched_actions)
        return batch

    @staticmethod
    def _check_seeds(seeds: Sequence[int]) -> list[int]:
        seeds = list(seeds)
        if not seeds:
            raise ValueError("SeedBatch: no seeds; give at least one, e.g. seeds=[0, 1, 2].")
        if not all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 0 for s in seeds):
            raise ValueError(f"SeedBatch: seeds must be integers >= 0, got {seeds}.")
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"SeedBatch: seeds {seeds} repeat a seed; each seed is one run, give each once.")
        return [int(s) for s in seeds]

    def _setup(
        self,
        models: list[OffPolicyAlgorithm],
        streams: list[RandomStreams],
        seeds: list[int],
        collect_threads: int,
        batched_actions: bool | None,
    ) -> None:
        if not isinstance(collect_threads, (int, np.integer)) or isinstance(collect_threads, bool) or collect_threads < 1:
            raise ValueError(
                f"SeedBatch: collect_threads={collect_threads!r}; give a number of threads >= 1 (1, the default: the "
                "seeds collect one after the other in this thread)."
            )
        if batched_actions not in (None, True, False):
            raise ValueError(f"SeedBatch: batched_actions={batched_actions!r}; give None (on a GPU), True or False.")
        if len(models) != len(seeds) or len(streams) != len(seeds):
            raise ValueError(f"SeedBatch: {len(models)} models, {len(streams)} random streams and {len(seeds)} seeds.")
        if len({id(m) for m in models}) != len(models):
            raise ValueError("SeedBatch: a model is given twice; each seed needs its own model.")
        envs = [m.get_env() for m in models]
        if len({id(e) for e in envs if e is not None}) != len([e for e in envs if e is not None]):
            raise ValueError("SeedBatch: two seeds share one environment; each seed needs its own (build it in make_model).")
        self.models = models
        self.seeds = seeds
        #: Each seed's random streams (its model's own for a TD3X).
        self.streams = streams
        #: Seed index -> the exception that stopped it (``learn(keep_going=True)``).
        self.errors: dict[int, BaseException] = {}
        self.collect_threads = int(collect_threads)
        self.batched_actions = batched_actions
        self._batched_actions = False  # this learn() call's: decided with its collection threads
        #: How the last ``learn()`` collected: threads used and seeds in them, whether pi(s) was batched, and why.
        self.collection: str | None = None
        self._globals = [True] * len(models)  # whose rounds run with their streams installed (set by learn)
        self._on_error: Callable[[int, BaseException], None] | None = None

    # ------------------------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.models)

    def __getitem__(self, index: int) -> OffPolicyAlgorithm:
        """Seed ``index``'s model (its position in ``seeds``), a full SB3 model."""
        return self.models[index]

    def __iter__(self) -> Iterator[OffPolicyAlgorithm]:
        return iter(self.models)

    def __repr__(self) -> str:
        return f"SeedBatch({type(self.models[0]).__name__}, seeds={self.seeds})"

    @contextlib.contextmanager
    def seed_context(self, index: int, install: bool = True) -> Iterator[OffPolicyAlgorithm]:
        """Code run as seed ``index``'s (:data:`current_seed` set), with its streams as the global generators
        (``install``); the caller's global state is put back at the end."""
        with acting_as(index), (self.streams[index].installed() if install else contextlib.nullcontext()):
            yield self.models[index]

    def save(self, directory: str | Path) -> list[Path]:
        """Save each seed's model as ``<directory>/seed<seed>.zip`` (each loads with ``TD3X.load``)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        paths = []
        for seed, model in zip(self.seeds, self.models):
            path = directory / f"seed{seed}.zip"
            model.save(path)
            paths.append(path)
        return paths

    # ------------------------------------------------------------------------------------------------------------
    def _per_seed_callbacks(self, callback: Sequence[MaybeCallback] | None) -> list[MaybeCallback]:
        if callback is None:
            return [None] * len(self.models)
        if isinstance(callback, BaseCallback) or callable(callback) or not isinstance(callback, Sequence):
            raise TypeError(
                "SeedBatch.learn: a callback keeps the state of one run, so give one per seed: callback=[cb_0, cb_1, "
                f"...] ({len(self.models)} entries, each what SB3's learn() takes), e.g. "
                "[EvalCallback(make_eval_env(seed)) for seed in batch.seeds]."
            )
        if len(callback) != len(self.models):
            raise ValueError(
                f"SeedBatch.learn: {len(callback)} callbacks for {len(self.models)} seeds; give one entry per seed "
                "(a list of callbacks as one entry, or None)."
            )
        objects = [id(cb) for cb in _flat_callbacks(callback)]
        if len(set(objects)) != len(objects):
            raise ValueError("SeedBatch.learn: one callback object is given to two seeds; each seed needs its own.")
        return list(callback)

    def learn(
        self,
        total_timesteps: int | Sequence[int],
        callback: Sequence[MaybeCallback] | None = None,
        log_interval: int = 4,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool | Sequence[bool] = True,
        progress_bar: bool = False,
        keep_going: bool = False,
        on_error: Callable[[int, BaseException], None] | None = None,
    ) -> SeedBatch:
        """``model.learn(total_timesteps, ...)`` for every seed, in one loop (see the module's docstring).

        :param total_timesteps: as SB3's, for every seed, or one per seed (resumed runs that stopped at different
            steps)
        :param callback: None, or one entry per seed (what SB3's ``learn`` takes: a callback, a list of them, None)
        :param tb_log_name: TensorBoard run name (default: the model's class name, as SB3's and TD3X's ``learn``)
        :param reset_num_timesteps: as SB3's, for every seed, or one per seed
        :param keep_going: a seed that raises stops alone and the others go on; :attr:`errors` maps its index to the
            exception. ``False``: the exception propagates at once (every seed can go on with
            ``learn(..., reset_num_timesteps=False)``, as a lone run can)
        :param on_error: with ``keep_going``, called as ``on_error(index, exception)`` when a seed stops
        """
        callbacks = self._per_seed_callbacks(callback)
        self._refuse_own_learn()
        totals = self._per_seed_values("total_timesteps", total_timesteps)
        resets = self._per_seed_values("reset_num_timesteps", reset_num_timesteps)
        self.errors, self._on_error = {}, on_error
        if len(self.models) == 1:  # one seed: its own learn()
            self.collection = "one seed: its own learn()"
            try:
                with self.seed_context(0) as model:
                    model.learn(totals[0], callbacks[0], log_interval, tb_log_name or type(model).__name__, resets[0], progress_bar)
            except Exception as error:
                self._fail(0, error, keep_going)
            return self
        # SB3's learn() runs one model to its end, and a round's batched pi(s) or collection threads need every seed
        # at once: so the batch runs that loop's body (_setup_learn, collect_rollouts, train) round by round.
        runs = [
            self._start(i, totals[i], callbacks[i], resets[i], tb_log_name, progress_bar, log_interval)
            for i in range(len(self.models))
        ]
        active = [run for run in runs if not run.finished]
        with self._collection() as pool:
            while active:
                self._train(self._collect_round(active, log_interval, keep_going, pool), keep_going)
                active = [r for r in active if not (r.finished or r.failed) and r.model.num_timesteps < r.total_timesteps]
        for run in runs:
            if not run.failed:
                with self.seed_context(run.index, install=self._globals[run.index]):
                    run.callback.on_training_end()
        return self

    def _refuse_own_learn(self) -> None:
        if len(self.models) > 1 and (changed := [r for i, m in enumerate(self.models) if (r := _learn_changed(i, m))]):
            raise ValueError(
                f"SeedBatch.learn runs SB3's learn loop for every seed, so it would not run {'; '.join(changed)}. "
                "Move that code into a callback (or an override of collect_rollouts or train, which the batch calls), "
                "or train those seeds alone."
            )

    def _start(self, index: int, total: int, callback: MaybeCallback, reset: bool, name: str | None, progress_bar: bool, log_interval: int) -> _SeedRun:
        """SB3's ``learn()`` up to its loop, for seed ``index``."""
        model = self.models[index]
        with self.seed_context(index):
            total, cb = model._setup_learn(total, callback, reset, name or type(model).__name__, progress_bar)
            cb.on_training_start({"self": model, "total_timesteps": total, "log_interval": log_interval}, globals())
        self._globals[index] = _may_draw_from_globals(model, cb)
        return _SeedRun(index, model, total, cb, finished=model.num_timesteps >= total)

    @contextlib.contextmanager
    def _collection(self) -> Iterator[ThreadPoolExecutor | None]:
        """How this ``learn()`` call collects: its threads (None: the caller's alone) and whether pi(s) is batched;
        :attr:`collection` says so."""
        in_threads = [i for i in range(len(self.models)) if not self._globals[i]]
        threads = min(self.collect_threads, len(in_threads))
        on_gpu = self.models[0].device.type == "cuda"
        batched = on_gpu if self.batched_actions is None else self.batched_actions
        self._batched_actions = batched and all(isinstance(m, TD3X) for m in self.models)
        actions = "pi(s) batched across seeds" if self._batched_actions else "pi(s) per seed"
        if threads < 2:
            why = "collect_threads=1" if self.collect_threads < 2 else "fewer than two seeds whose code draws only from their streams"
            self.collection = f"one seed after the other ({why}); {actions}"
            yield None
            return
        alone = len(self.models) - len(in_threads)
        self.collection = f"{len(in_threads)} seeds in {threads} threads" + (f", {alone} in turn after them" if alone else "")
        self.collection += f"; {actions}"
        pool = ThreadPoolExecutor(threads, thread_name_prefix="sb3_td3x_collect", initializer=denormals.same_fp_environment())
        try:
            yield pool
        finally:
            pool.shutdown(wait=True)

    def _collect_round(
        self, active: list[_SeedRun], log_interval: int, keep_going: bool, pool: ThreadPoolExecutor | None
    ) -> list[tuple[_SeedRun, int]]:
        """One rollout of every active seed; the seeds that then want gradient steps, with their number."""
        try:
            if self._batched_actions:
                prefetch_actions([run.model for run in active])
            threaded = [run for run in active if not self._globals[run.index]] if pool is not None else []
            outcomes = {}
            if pool is not None and len(threaded) > 1:
                outcomes = _all_done({run.index: pool.submit(self._rollout, run, log_interval) for run in threaded})
            wants = []
            for run in active:  # in seed order: the threaded seeds' outcomes, then each other seed's rollout
                outcome = outcomes[run.index] if run.index in outcomes else self._rollout(run, log_interval)
                if steps := self._gradient_steps_wanted(run, *outcome, keep_going):
                    wants.append((run, steps))
            return wants
        finally:  # a row a seed did not take (it stopped, or took SB3's path) is not kept to a later round
            if self._batched_actions:
                for run in active:
                    run.model.__dict__.pop("_prefetched_action", None)

    def _rollout(self, run: _SeedRun, log_interval: int) -> tuple[RolloutReturn | None, Exception | None]:
        """One rollout of ``run``'s seed, as SB3's loop collects it, or what it raised."""
        model = run.model
        try:
            with self.seed_context(run.index, install=self._globals[run.index]):
                return model.collect_rollouts(
                    model.env,  # type: ignore[arg-type]
                    train_freq=model.train_freq,  # type: ignore[arg-type]
                    action_noise=model.action_noise,
                    callback=run.callback,
                    learning_starts=model.learning_starts,
                    replay_buffer=model.replay_buffer,  # type: ignore[arg-type]
                    log_interval=log_interval,
                ), None
        except Exception as error:
            return None, error

    def _gradient_steps_wanted(
        self, run: _SeedRun, rollout: RolloutReturn | None, error: Exception | None, keep_going: bool
    ) -> int:
        """The gradient steps ``run``'s seed wants after its rollout (0: none; it stopped, or is still warming up)."""
        if error is not None:
            self._fail(run.index, error, keep_going)
            run.failed = True
            return 0
        assert rollout is not None
        if not rollout.continue_training:
            run.finished = True
            return 0
        model = run.model
        if model.num_timesteps > 0 and model.num_timesteps > model.learning_starts:
            return model.gradient_steps if model.gradient_steps >= 0 else rollout.episode_timesteps
        return 0

    def _per_seed_values(self, name: str, value: Any) -> list[Any]:
        if not isinstance(value, (list, tuple)):
            return [value] * len(self.models)
        if len(value) != len(self.models):
            raise ValueError(
                f"SeedBatch.learn: {len(value)} values of {name} for {len(self.models)} seeds; give one, or one per seed."
            )
        return list(value)

    def _fail(self, index: int, error: Exception, keep_going: bool) -> None:
        """Seed ``index`` raised ``error``: raise it, or (``keep_going``) record it; the caller stops the seed."""
        if not keep_going:
            raise error
        self.errors[index] = error
        if self._on_error is not None:
            self._on_error(index, error)
        log.warning("SeedBatch: seed %d stopped: %s: %s", self.seeds[index], type(error).__name__, error)

    def _train(self, wants: list[tuple[_SeedRun, int]], keep_going: bool) -> None:
        """The gradient steps of the seeds that want them, each with its model's own ``train()``."""
        for run, n in wants:
            try:
                with self.seed_context(run.index):
                    run.model.train(batch_size=run.model.batch_size, gradient_steps=n)
            except Exception as error:
                self._fail(run.index, error, keep_going)
                run.failed = True


def _all_done(futures: dict[int, Future]) -> dict[int, Any]:
    """Each future's result, once all are done. A wait interrupted (a signal's exception) waits on until they are
    done, then raises: no seed goes on collecting behind the caller's back (a checkpoint of a seed in mid-step)."""
    interrupted: BaseException | None = None
    pending = set(futures.values())
    while pending:
        try:
            pending = wait(pending)[1]
        except BaseException as error:  # noqa: BLE001 (raised below, once the threads are done)
            interrupted = interrupted or error
    if interrupted is not None:
        raise interrupted
    return {index: future.result() for index, future in futures.items()}


def _may_draw_from_globals(model: OffPolicyAlgorithm, callback: BaseCallback) -> bool:
    """Whether code of ``model``'s rounds may draw from the global generators itself, not from its streams (see the
    module's docstring): then its streams are installed around them."""
    if not isinstance(model, TD3X) or not isinstance(model.replay_buffer, TensorReplayBuffer):
        return True
    if model.action_noise is not None and type(model.action_noise) is not NormalActionNoise:
        return True
    parts = _parts([model, model.policy, callback, model.get_env()])
    return any(type(part).__module__.split(".")[0] not in _OWN_STREAMS_CODE for part in parts)


def _parts(objects: list[Any]) -> list[Any]:
    """``objects`` and what they wrap or hold: callbacks in lists and events, evaluation envs, env wrappers."""
    seen: dict[int, Any] = {}
    todo = list(objects)
    while todo:
        obj = todo.pop()
        if obj is None or id(obj) in seen:
            continue
        seen[id(obj)] = obj
        for name in ("callbacks", "callback", "callback_on_new_best", "callback_after_eval", "eval_env", "venv", "envs", "env"):
            value = obj.__dict__.get(name) if hasattr(obj, "__dict__") else None
            todo += list(value) if isinstance(value, (list, tuple)) else [value]
    return list(seen.values())


def _learn_changed(index: int, model: OffPolicyAlgorithm) -> str | None:
    """Why model ``index``'s ``learn`` is not SB3's loop (an override outside SB3 and this package), or None."""
    if "learn" in vars(model):
        return f"model {index}'s learn (set on the instance)"
    owner = next(cls for cls in type(model).__mro__ if "learn" in vars(cls))
    if owner.__module__.split(".")[0] in ("stable_baselines3", "sb3_td3x"):
        return None  # OffPolicyAlgorithm's loop, or a subclass's that only passes its arguments on (TD3, TD3X, ...)
    return f"model {index}'s learn (overridden by {owner.__name__})"


def _flat_callbacks(callbacks: Sequence[MaybeCallback]) -> list[Any]:
    flat: list[Any] = []
    for cb in callbacks:
        if cb is None:
            continue
        if isinstance(cb, (list, tuple)):
            flat += _flat_callbacks(cb)
        else:
            flat.append(cb)
    return flat


__all__ = ["SeedBatch", "acting_as", "current_seed"]
