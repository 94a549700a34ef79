"""The exploration shortcut: pi(s) for one collection step, from the actor's Linear layers called directly.

SB3 collects an action through ``model.predict`` -> ``policy.predict`` -> ``obs_to_tensor`` -> ``_predict`` ->
``actor.forward``, then ``scale_action``. For the actor TD3 is run with (SB3's ``Actor``: flat observations, a ReLU
MLP with a tanh output) :class:`DirectMlpActor` computes the same products with the same kernels, without the module
calls (a third of the time of an actor forward on one observation). It stands in for ``actor.forward`` and for the
predict path above, so :meth:`DirectMlpActor.why_not` requires all of them as written; otherwise collection is
SB3's own ``_sample_action``.

Many seeds in one process (:class:`~sb3_td3x.SeedBatch`) on a GPU compute pi(s) of all their seeds at the start of a
round in one batched product per layer (:func:`prefetch_actions`), the weights stacked as the seed-stacked update
stacks them; each seed's collection step then takes its row (:class:`PrefetchedAction`) where nothing it depends on
has changed since, and computes pi(s) itself otherwise. The exploration noise, the clipping and the scaling stay the
seed's own. On a CPU each seed computes its own, with the 2-D products of its lone run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th
from torch import nn

from sb3_td3x.td3x.update_paths import requirements
from sb3_td3x.td3x.update_paths.mlp import MlpStack, addmm_relu, relu_mlp


class DirectMlpActor(requirements.FastPath):
    """pi(s) of a ReLU MLP actor from its Linear layers: what the module computes, with the same kernels."""

    def __init__(self, layers: list[nn.Linear]):
        self.layers = layers

    def __call__(self, obs: th.Tensor) -> th.Tensor:
        weights, biases = [layer.weight for layer in self.layers], [layer.bias for layer in self.layers]
        return relu_mlp(weights, biases, obs.float(), linear_relu=addmm_relu)[0].tanh_()

    @classmethod
    def requirements(cls, model: Any) -> list[str]:
        """Every assumption of the shortcut that ``model`` breaks (empty: it computes what ``actor.forward`` does)."""
        reasons = requirements.stock_mlp_actor(model.actor, model.observation_space, "actor")
        reasons += requirements.stock_predict(model)
        reasons += requirements.module_hooks(model.actor, "actor")
        reasons += requirements.plain_parameters(model.actor, "actor")
        return list(dict.fromkeys(reasons))


def choose_exploration_actor(model: Any) -> tuple[Callable[[th.Tensor], th.Tensor] | None, str, str]:
    """The shortcut collection calls for pi(s), its name, and why: a ``DirectMlpActor`` where it computes what
    ``actor.forward`` computes, or ``None`` (SB3's own ``_sample_action``, through ``predict``) with the reason."""
    reason = DirectMlpActor.why_not(model)
    if reason is None:
        layers = requirements.relu_mlp_layers(model.actor.mu, nn.Tanh)
        return DirectMlpActor(layers), "direct_mlp", "SB3's Actor, a ReLU MLP with a tanh output, predict as written"  # type: ignore[arg-type]
    return None, "sb3_predict", reason


@dataclass(frozen=True)
class PrefetchedAction:
    """pi(s) of a model's next collection step, computed ahead of it with other seeds' (:func:`prefetch_actions`).

    Valid while nothing it was computed from has changed: the same observation array (``_last_obs``, the same
    object), the same ``num_timesteps``, the same shortcut, no actor update since (``_n_actor_updates``: a CUDA graph's
    replay writes the weights without bumping their version counters), and the actor's parameters neither changed in
    place (their version counters) nor replaced (their memory) since."""

    obs: np.ndarray
    num_timesteps: int
    actor_updates: int
    actor: DirectMlpActor
    versions: tuple[int, ...]
    actions: np.ndarray  # (n_envs, *action_shape), in [-1, 1]

    def valid_for(self, model: Any, actor: Any) -> bool:
        return (
            self.obs is model._last_obs
            and self.num_timesteps == model.num_timesteps
            and self.actor_updates == model._n_actor_updates
            and self.actor is actor
            and self.versions == _versions(actor)
        )


def _versions(actor: DirectMlpActor) -> tuple[int, ...]:
    """The actor's parameters' version counters (bumped by every in-place change) and memory (``.data`` replaced)."""
    return tuple(n for layer in actor.layers for p in (layer.weight, layer.bias) for n in (p._version, p.data_ptr()))


def _prefetchable(model: Any) -> DirectMlpActor | None:
    """The shortcut ``model``'s next collection step takes, or None where it takes none: a random action (before
    ``learning_starts``), observations that are not one array, or SB3's predict (a user's actor or predict path)."""
    if model.num_timesteps < model.learning_starts or not isinstance(model._last_obs, np.ndarray):
        return None
    return model._exploration()[0]


def _kind(model: Any, actor: DirectMlpActor) -> tuple[Any, ...]:
    """What models must share for one batched product: layer shapes, observation batch, device, dtype."""
    first = actor.layers[0].weight
    shapes = tuple(tuple(p.shape) for layer in actor.layers for p in (layer.weight, layer.bias))
    return shapes, model._last_obs.shape, first.device, first.dtype


def prefetch_actions(models: Sequence[Any]) -> list[int]:
    """pi(s) of every model of ``models`` whose next collection step takes :class:`DirectMlpActor`, in one batched
    product per layer (the actors' weights stacked, the observations stacked), left on each model for that step
    (:class:`PrefetchedAction`, taken by ``TD3X._sample_action``). Returns the positions of the models served; none
    unless at least two can be, with one architecture, one number of environments and one device.

    The batched product is the stacked update's (:meth:`MlpStack.forward`): what each seed's own 2-D products
    compute, to float rounding.
    """
    prefetchable = [(i, actor) for i, m in enumerate(models) if (actor := _prefetchable(m)) is not None]
    ready, actors = [i for i, _ in prefetchable], [actor for _, actor in prefetchable]
    kinds = {_kind(models[i], actor) for i, actor in zip(ready, actors)}
    if len(ready) < 2 or len(kinds) != 1:
        return []
    first = models[ready[0]]
    n_envs, depth = first.n_envs, len(actors[0].layers)
    with th.no_grad():
        weights = [th.stack([a.layers[d].weight for a in actors]) for d in range(depth)]
        biases = [th.stack([a.layers[d].bias for a in actors]) for d in range(depth)]
        obs = np.stack([models[i]._last_obs for i in ready])
        x = th.as_tensor(obs, device=first.device).reshape(len(ready), n_envs, -1).float()
        actions = MlpStack.forward(x, weights, biases)[0].tanh_().cpu().numpy()
    for row, (i, actor) in enumerate(zip(ready, actors)):
        model = models[i]
        model._prefetched_action = PrefetchedAction(
            model._last_obs,
            model.num_timesteps,
            model._n_actor_updates,
            actor,
            _versions(actor),
            actions[row].reshape((n_envs, *model.action_space.shape)),
        )
    return ready
