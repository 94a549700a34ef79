"""pi(s) for collection: the actor module called directly.

SB3 collects an action through ``model.predict`` -> ``policy.predict`` -> ``obs_to_tensor`` -> ``_predict`` ->
``actor.forward``, then ``scale_action``. TD3X calls the actor module itself on the observation (its ``forward``,
whatever it is) and skips the rest, where the rest is SB3's as written (:func:`why_not_direct`): the same actions,
without the Python around them. Otherwise collection is SB3's own ``_sample_action``.

A :class:`~sb3_td3x.seeds.SeedBatch` on a GPU computes pi(s) of all its seeds in one call instead
(:mod:`sb3_td3x.seeds.actions`).
"""

from __future__ import annotations

from typing import Any

from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space

#: The methods of SB3's predict path that direct collection skips: each must be SB3's own.
PREDICT_METHODS = ("predict", "_predict", "obs_to_tensor", "scale_action", "unscale_action")


def _owner(cls: type, name: str) -> type | None:
    return next((c for c in cls.__mro__ if name in vars(c)), None)


def _from_sb3_or_here(cls: type | None) -> bool:
    return cls is None or cls.__module__.split(".")[0] in ("stable_baselines3", "sb3_td3x")


def why_not_direct(model: Any) -> str | None:
    """Why collection's pi(s) goes through SB3's ``predict`` instead of the actor module called directly, or None:
    observations that are not one Box, or a predict path of the user's (a policy or model method of
    :data:`PREDICT_METHODS` defined outside SB3 and this package, or set on the instance)."""
    if not isinstance(model.observation_space, spaces.Box):
        return f"{type(model.observation_space).__name__} observations (SB3's predict prepares them)"
    if is_image_space(model.observation_space):
        return "image observations (SB3's predict transposes them)"
    for obj, role in ((model.policy, "policy"), (model, "model")):
        for name in PREDICT_METHODS if role == "policy" else ("predict",):
            if name in vars(obj):
                return f"{role}.{name} set on the instance"
            if not _from_sb3_or_here(owner := _owner(type(obj), name)):
                return f"{role}.{name} overridden by {owner.__name__}"  # type: ignore[union-attr]
    return None
