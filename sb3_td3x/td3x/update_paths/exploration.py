"""The exploration shortcut: pi(s) for one collection step, from the actor's Linear layers called directly.

SB3 collects an action through ``model.predict`` -> ``policy.predict`` -> ``obs_to_tensor`` -> ``_predict`` ->
``actor.forward``, then ``scale_action``. For the actor TD3 is run with (SB3's ``Actor``: flat observations, a ReLU
MLP with a tanh output) :class:`DirectMlpActor` computes the same products with the same kernels, without the module
calls (a third of the time of an actor forward on one observation). It stands in for ``actor.forward`` and for the
predict path above, so :meth:`DirectMlpActor.why_not` requires all of them as written; otherwise collection is
SB3's own ``_sample_action``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch as th
from torch import nn

from sb3_td3x.td3x.update_paths import requirements
from sb3_td3x.td3x.update_paths.mlp import addmm_relu, relu_mlp


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
