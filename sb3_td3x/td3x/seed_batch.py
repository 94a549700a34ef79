"""Many seeds in one process: N independent runs trained together, each computing what it computes alone (issue 17).

.. code-block:: python

    from sb3_td3x import TD3X, SeedBatch

    batch = SeedBatch(lambda seed: TD3X("MlpPolicy", "Hopper-v5", seed=seed), seeds=[0, 1, 2, 3, 4])
    batch.learn(200_000)
    batch[2].save("hopper_seed2")             # seed 2 is a full TD3X: predict, save, evaluate_policy, TD3X.load
    batch.update_path, batch.update_reason     # how the gradient steps ran, and why

**The contract.** Seed ``i`` of a batch computes what ``make_model(seeds[i]).learn(...)`` computes alone: the same
actions, transitions, sampled indices, noises, and the same weights to float rounding. Each seed keeps its own
global random state (Python's, numpy's and torch's generators, :class:`~.update_paths.seeds.GlobalRandomState`),
captured right after its model is built, where its lone run would stand, and everything of that seed runs with its
state swapped in: its environment steps and exploration noise, its callbacks (evaluations, checkpoints), its
sampling and its target smoothing noise. So whatever the user's code draws, and from whichever global generator, it
draws what the lone run draws.

**What runs together.** The loop is SB3's ``OffPolicyAlgorithm.learn``, one round per rollout: every seed collects
its rollout (``model.collect_rollouts``, the model's own), then the seeds that train do their gradient steps. When
all N train the same number of steps with the same batch size, and
:class:`~.update_paths.seeds.SeedStackedMlpUpdate` applies to them (their lone update would be ``MlpUpdate``: SB3's
ReLU MLPs, the hooks of steps 5 to 13 as written, fp32, shared ``gamma``, smoothing and clipped double-Q settings),
those steps run as one batched update over a seed axis (``update_path == "seed_stacked_mlp"``). Otherwise each seed
runs its own ``train()``, one after the other, with its random state (``"per_seed"``): an overridden loss, a custom
network, ``compile_update``, ``cuda_graph``, another algorithm (SB3's ``TD3``), one seed alone, or a round in which
the seeds want different numbers of gradient steps (``train_freq`` in episodes). ``update_reason`` says why, and
each model's logger gets the line at its first gradient step.

Where it would not run the user's code, it refuses: a model whose class overrides ``learn`` (the batch runs SB3's
loop itself, calling each model's ``collect_rollouts``, callbacks and ``train``); an overridden ``train`` makes each
seed train alone.

**Limits.** The environments step one seed after the other (a batch saves per-step overhead in the update, not in
the simulator). Each seed's callbacks must be its own objects (one list per seed). A seed whose model raises stops
the batch (``keep_going=False``, the default), or only itself (``keep_going=True``: the others go on and
:attr:`SeedBatch.errors` holds what it raised).
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback

from sb3_td3x.td3x.td3x import TD3X
from sb3_td3x.td3x.update_paths.seeds import GlobalRandomState, SeedRandomStreams, SeedStackedMlpUpdate

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


SEED_STACKED = "seed_stacked_mlp"
PER_SEED = "per_seed"


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
        environment). It is called once per seed, in order, and the global random state it leaves is that seed's
        random stream from then on
    :param seeds: the seeds, distinct
    :param fuse: passed to :class:`~.update_paths.seeds.SeedStackedMlpUpdate`
    """

    def __init__(self, make_model: Callable[[int], OffPolicyAlgorithm], seeds: Sequence[int], fuse: bool = True):
        seeds = self._check_seeds(seeds)
        models, states = [], []
        caller = GlobalRandomState.capture()
        try:
            for seed in seeds:
                model = make_model(seed)
                if not isinstance(model, OffPolicyAlgorithm):
                    raise TypeError(
                        f"SeedBatch: make_model({seed}) returned {type(model).__name__}, not a model; it must build and "
                        "return one off-policy model (e.g. lambda seed: TD3X('MlpPolicy', env_id, seed=seed))."
                    )
                models.append(model)
                states.append(GlobalRandomState.capture(model.device))
        finally:
            caller.restore()
        self._setup(models, states, seeds, fuse)

    @classmethod
    def from_models(
        cls,
        models: Sequence[OffPolicyAlgorithm],
        random_states: Sequence[GlobalRandomState],
        seeds: Sequence[int] | None = None,
        fuse: bool = True,
    ) -> SeedBatch:
        """A batch of models built elsewhere (loaded from checkpoints, ...).

        :param random_states: each model's global random state where its lone run stands
            (:meth:`GlobalRandomState.capture` right after building or loading it, before anything else draws)
        :param seeds: their seeds (default: each model's ``seed``)
        """
        batch = cls.__new__(cls)
        if seeds is None:
            seeds = [int(m.seed) if m.seed is not None else i for i, m in enumerate(models)]
        batch._setup(list(models), list(random_states), cls._check_seeds(seeds), fuse)
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

    def _setup(self, models: list[OffPolicyAlgorithm], states: list[GlobalRandomState], seeds: list[int], fuse: bool) -> None:
        if len(models) != len(seeds) or len(states) != len(seeds):
            raise ValueError(f"SeedBatch: {len(models)} models, {len(states)} random states and {len(seeds)} seeds.")
        if len({id(m) for m in models}) != len(models):
            raise ValueError("SeedBatch: a model is given twice; each seed needs its own model.")
        envs = [m.get_env() for m in models]
        if len({id(e) for e in envs if e is not None}) != len([e for e in envs if e is not None]):
            raise ValueError("SeedBatch: two seeds share one environment; each seed needs its own (build it in make_model).")
        self.models = models
        self.seeds = seeds
        self.fuse = fuse
        self.streams = SeedRandomStreams(states, models[0].device)
        #: How the last ``learn()`` ran the gradient steps ("seed_stacked_mlp" or "per_seed") and why.
        self.update_path: str | None = None
        self.update_reason: str | None = None
        #: Seed index -> the exception that stopped it (``learn(keep_going=True)``).
        self.errors: dict[int, BaseException] = {}
        self._stacked: SeedStackedMlpUpdate | None = None
        self._announced: set[int] = set()
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
        return f"SeedBatch({type(self.models[0]).__name__}, seeds={self.seeds}, update_path={self.update_path!r})"

    @contextlib.contextmanager
    def seed_context(self, index: int) -> Iterator[OffPolicyAlgorithm]:
        """Seed ``index``'s random state as the global one inside (and :data:`current_seed` set); the caller's
        state is put back at the end. For code that must draw as seed ``index``'s lone run would."""
        with self.streams.kept_apart(), self._seed(index):
            yield self.models[index]

    @contextlib.contextmanager
    def _seed(self, index: int) -> Iterator[None]:
        with acting_as(index), self.streams.seed(index):
            yield

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
    def why_not_stacked(self) -> str | None:
        """Why the gradient steps cannot run as one batched update (then each seed trains alone), or None."""
        if len(self.models) == 1:
            return "one seed: its own learn()"
        not_td3x = [f"model {i} is a {type(m).__name__}" for i, m in enumerate(self.models) if not isinstance(m, TD3X)]
        if not_td3x:
            return "the batched update is TD3X's: " + "; ".join(not_td3x)
        batch_sizes = {m.batch_size for m in self.models}
        if len(batch_sizes) > 1:
            return f"the seeds' batch sizes differ ({sorted(batch_sizes)})"
        return SeedStackedMlpUpdate.why_not_together(self.models)  # type: ignore[arg-type]

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
        if len(self.models) > 1 and (changed := [r for i, m in enumerate(self.models) if (r := _learn_changed(i, m))]):
            raise ValueError(
                f"SeedBatch.learn runs SB3's learn loop for every seed, so it would not run {'; '.join(changed)}. "
                "Move that code into a callback (or an override of collect_rollouts or train, which the batch calls), "
                "or train those seeds alone."
            )
        totals = self._per_seed_values("total_timesteps", total_timesteps)
        resets = self._per_seed_values("reset_num_timesteps", reset_num_timesteps)
        self.errors = {}
        self._on_error = on_error
        if len(self.models) == 1:  # one seed: its own learn(), today's TD3X to the line
            self._choose_update()
            try:
                with self.seed_context(0) as model:
                    name = tb_log_name or type(model).__name__
                    model.learn(totals[0], callbacks[0], log_interval, name, resets[0], progress_bar)
            except Exception as error:
                self._fail(0, error, keep_going)
            return self
        runs: list[_SeedRun] = []
        with self.streams.kept_apart():
            for i, model in enumerate(self.models):
                with self._seed(i):
                    name = tb_log_name or type(model).__name__
                    total, cb = model._setup_learn(totals[i], callbacks[i], resets[i], name, progress_bar)
                    cb.on_training_start({"self": model, "total_timesteps": total, "log_interval": log_interval}, globals())
                runs.append(_SeedRun(i, model, total, cb, finished=model.num_timesteps >= total))
            self._choose_update()
            active = [run for run in runs if not run.finished]
            while active:
                wants: list[tuple[_SeedRun, int]] = []
                for run in active:
                    model = run.model
                    try:
                        with self._seed(run.index):
                            rollout = model.collect_rollouts(
                                model.env,  # type: ignore[arg-type]
                                train_freq=model.train_freq,  # type: ignore[arg-type]
                                action_noise=model.action_noise,
                                callback=run.callback,
                                learning_starts=model.learning_starts,
                                replay_buffer=model.replay_buffer,  # type: ignore[arg-type]
                                log_interval=log_interval,
                            )
                    except Exception as error:
                        self._fail(run.index, error, keep_going)
                        run.failed = True
                        continue
                    if not rollout.continue_training:
                        run.finished = True
                        continue
                    if model.num_timesteps > 0 and model.num_timesteps > model.learning_starts:
                        steps = model.gradient_steps if model.gradient_steps >= 0 else rollout.episode_timesteps
                        if steps > 0:
                            wants.append((run, steps))
                self._train(wants, keep_going)
                for run in active:
                    run.finished = run.finished or run.model.num_timesteps >= run.total_timesteps
                active = [run for run in active if not (run.finished or run.failed)]
            for run in runs:
                if not run.failed:
                    with self._seed(run.index):
                        run.callback.on_training_end()
        return self

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

    def _choose_update(self) -> None:
        """The update of this ``learn()`` call: batched where :meth:`why_not_stacked` allows it."""
        reason = self.why_not_stacked()
        self._stacked = None
        if reason is None:
            self._stacked = SeedStackedMlpUpdate(self.models, self.streams, fuse=self.fuse)  # type: ignore[arg-type]
            self.update_path = SEED_STACKED
            self.update_reason = (
                f"SeedStackedMlpUpdate: the {len(self.models)} seeds' gradient steps as one batched update (each "
                "seed's lone update is MlpUpdate)"
            )
        else:
            self.update_path, self.update_reason = PER_SEED, f"each seed trains alone: {reason}"
        self._announced = set()

    def _announce(self, index: int, path: str, reason: str) -> None:
        """The update line in seed ``index``'s log, once per ``learn()`` call."""
        if index in self._announced:
            return
        self._announced.add(index)
        model = self.models[index]
        if path == SEED_STACKED and isinstance(model, TD3X):
            model.update_path, model.update_reason = path, reason
        model.logger.info(f"seed batch: {path} ({reason})")

    def _train(self, wants: list[tuple[_SeedRun, int]], keep_going: bool) -> None:
        if not wants:
            return
        steps = {n for _, n in wants}
        if self._stacked is not None and len(wants) == len(self.models) and len(steps) == 1:
            for run, _ in wants:
                self._announce(run.index, SEED_STACKED, self.update_reason or "")
            self._stacked.train(gradient_steps=steps.pop(), batch_size=self.models[0].batch_size)
            return
        if self._stacked is not None:  # this round only: the seeds want different steps
            reason = (
                f"this round {len(wants)} of {len(self.models)} seeds train, "
                f"{'/'.join(str(n) for _, n in wants)} gradient steps: each alone"
            )
            log.debug("SeedBatch: %s", reason)
        for run, n in wants:
            self._announce(run.index, PER_SEED, self.update_reason or "")
            try:
                with self._seed(run.index):
                    run.model.train(batch_size=run.model.batch_size, gradient_steps=n)
            except Exception as error:
                self._fail(run.index, error, keep_going)
                run.failed = True


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


__all__ = ["PER_SEED", "SEED_STACKED", "SeedBatch", "acting_as", "current_seed"]
