"""pi(s) of many seeds in one call (:class:`~sb3_td3x.seeds.SeedBatch` on a GPU, or ``batched_actions=True``).

At the start of a round the seeds' actor parameters are stacked (``torch.func.stack_module_state``) and the first
seed's actor module runs over them with ``torch.func.vmap`` of ``torch.func.functional_call``, so the batched pi(s) is
the actor's own ``forward``. Each seed's collection step (``TD3X._sample_action``) then takes its row
(:class:`PrefetchedAction`) where nothing it depends on has changed since, and computes pi(s) itself otherwise. The
exploration noise, the clipping and the scaling stay the seed's own.
"""

from __future__ import annotations

import functools
import types
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th


@dataclass(frozen=True)
class PrefetchedAction:
    """pi(s) of a model's next collection step, computed ahead of it with other seeds' (:func:`prefetch_actions`).

    Valid while nothing it was computed from has changed: the same observation array (``_last_obs``, the same
    object), the same ``num_timesteps``, the same actor module, no actor update since (``_n_actor_updates``: a CUDA
    graph's replay writes the weights without bumping their version counters), and the actor's parameters neither
    changed in place (their version counters) nor replaced (their memory) since."""

    obs: np.ndarray
    num_timesteps: int
    actor_updates: int
    actor: th.nn.Module
    versions: tuple[int, ...]
    actions: np.ndarray  # (n_envs, *action_shape), in [-1, 1]

    def valid_for(self, model: Any) -> bool:
        return (
            self.obs is model._last_obs
            and self.num_timesteps == model.num_timesteps
            and self.actor_updates == model._n_actor_updates
            and self.actor is model.actor
            and self.versions == _versions(model.actor)
        )


def _versions(actor: th.nn.Module) -> tuple[int, ...]:
    """The actor's parameters' and buffers' version counters (bumped by every in-place change) and memory."""
    tensors = [*actor.parameters(), *actor.buffers()]
    return tuple(n for t in tensors for n in (t._version, t.data_ptr()))


def _prefetchable(model: Any) -> bool:
    """Whether ``model``'s next collection step calls its actor directly: past ``learning_starts``, observations in
    one array, SB3's predict path as written."""
    return (
        model.num_timesteps >= model.learning_starts
        and isinstance(model._last_obs, np.ndarray)
        and model._exploration()[0] is not None
    )


def _own_code(actor: th.nn.Module) -> bool:
    """Whether ``actor`` (or a module in it) has code of its own instance: a method set on the instance, or a module
    hook. Another seed's actor has other code there, so one call of the first actor cannot stand for it."""
    for module in actor.modules():
        if any(isinstance(v, (types.FunctionType, types.MethodType, functools.partial)) for v in vars(module).values()):
            return True
        if module._forward_hooks or module._forward_pre_hooks:
            return True
    return False


def _kind(model: Any) -> tuple[Any, ...]:
    """What models must share for one batched call: the actor's class and shapes, the observation batch, device."""
    shapes = tuple((name, tuple(t.shape), t.dtype) for name, t in [*model.actor.named_parameters(), *model.actor.named_buffers()])
    return type(model.actor), shapes, model._last_obs.shape, model.device


def prefetch_actions(models: Sequence[Any]) -> list[int]:
    """pi(s) of every model of ``models`` whose next collection step calls its actor directly, in one vmapped call
    of the first one's actor module over their stacked parameters, left on each model for that step
    (:class:`PrefetchedAction`, taken by ``TD3X._sample_action``). Returns the positions of the models served; none
    unless at least two can be, with one actor class and shapes, one number of environments and one device, and no
    code of an actor's own instance (a method set on it, a module hook: :func:`_own_code`).
    What each seed's own call computes, to float rounding (batched products round as no 2-D product does)."""
    ready = [i for i, m in enumerate(models) if _prefetchable(m) and not _own_code(m.actor)]
    if len(ready) < 2 or len({_kind(models[i]) for i in ready}) != 1:
        return []
    first = models[ready[0]]
    actors = [models[i].actor for i in ready]
    with th.no_grad():
        params, buffers = th.func.stack_module_state(actors)  # type: ignore[arg-type]
        obs = np.stack([models[i]._last_obs for i in ready])
        x = th.as_tensor(obs, device=first.device).reshape(len(ready), first.n_envs, *first.observation_space.shape)

        def pi(p: dict[str, th.Tensor], b: dict[str, th.Tensor], o: th.Tensor) -> th.Tensor:
            return th.func.functional_call(actors[0], (p, b), (o,))

        actions = th.func.vmap(pi)(params, buffers, x).cpu().numpy()
    for row, i in enumerate(ready):
        model = models[i]
        model._prefetched_action = PrefetchedAction(
            model._last_obs,
            model.num_timesteps,
            model._n_actor_updates,
            model.actor,
            _versions(model.actor),
            actions[row].reshape((model.n_envs, *model.action_space.shape)),
        )
    return ready
