"""What a fast path requires of a model, checked conservatively: everything it assumes about the user's code.

A fast path replaces some of the user's code with its own (a hook, a network's ``forward``, autograd's backward
pass). It may only run where that code is provably TD3X's and SB3's stock code. Each function here returns the list
of reasons it is not (empty when it is), worded for the update line in the logs, e.g.
``"critic.forward overridden by ScaledCritic"``. Anything not recognised counts as a change: when in doubt, the
user's code runs.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, ClassVar

import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.td3.policies import Actor
from torch import nn

from sb3_td3x.common.torch_internals import global_module_hooks
from sb3_td3x.td3x.hooks import defining_class, reference_class
from sb3_td3x.td3x.policies import TD3XCritic, TD3XPolicy

# The methods of SB3's ``Actor`` and of ``TD3XCritic`` that the fast paths stand in for.
ACTOR_METHODS = ("forward", "extract_features", "_predict")
CRITIC_METHODS = ("forward", "q1_forward", "q_values", "extract_features")

# What SB3's ``predict`` runs between the observation and the actor: the exploration shortcut skips these.
PREDICT_METHODS = ("predict", "_predict", "forward", "obs_to_tensor", "scale_action", "unscale_action")

class FastPath:
    """A way of running TD3X's math that replaces some of the user's code with its own. It declares which hooks it
    replaces (:attr:`replaces`) and what else it assumes (:meth:`requirements`); it may run only where
    :meth:`why_not` is ``None``."""

    #: The hooks (:data:`sb3_td3x.td3x.hooks.HOOK_NAMES`) whose code this path does not call.
    replaces: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def requirements(cls, model: Any) -> list[str]:
        """Every assumption of this path that ``model`` breaks (empty: it computes what the model's code computes)."""
        raise NotImplementedError

    @classmethod
    def why_not(cls, model: Any) -> str | None:
        """Why this path may not run for ``model`` (every reason, joined), or ``None`` when it may."""
        reasons = cls.requirements(model)
        return "; ".join(reasons) if reasons else None


def flat_box(space: Any) -> bool:
    """A 1-D Box: what SB3 preprocesses with ``.float()`` alone (Discrete and MultiDiscrete are one-hot encoded)."""
    return isinstance(space, spaces.Box) and len(space.shape) == 1 and not is_image_space(space)


def _overridden_methods(obj: Any, stock: type, methods: Iterable[str]) -> list[str]:
    """The ``methods`` of ``obj`` that are not ``stock``'s: overridden by a subclass, or set on the instance."""
    found = []
    for name in methods:
        if name in vars(obj):
            found.append(f"{name} set on the instance")
        elif getattr(type(obj), name, None) is not getattr(stock, name, None):
            owner = defining_class(type(obj), name)
            found.append(f"{name} overridden by {owner.__name__ if owner else '?'}")
    return found


def _instance_methods(module: nn.Module, role: str) -> list[str]:
    """Methods of ``module``'s class shadowed on the instance (``critic.forward = fn``)."""
    return [
        f"{role}.{name} set on the instance"
        for name, value in vars(module).items()
        if callable(value) and not isinstance(value, nn.Module) and callable(getattr(type(module), name, None))
    ]


def stock_module(module: nn.Module, role: str, stock: type, methods: Iterable[str]) -> list[str]:
    """``module`` is exactly ``stock`` (not a subclass), with no method replaced on the instance."""
    if type(module) is not stock:
        overridden = [m for m in _overridden_methods(module, stock, methods) if "instance" not in m]
        what = f" ({', '.join(f'{role}.{m}' for m in overridden)})" if overridden else ""
        return [f"the {role} is a {type(module).__name__}, not SB3's {stock.__name__}{what}"]
    return _instance_methods(module, role)


def relu_mlp_layers(mlp: Any, final: type[nn.Module] | None) -> list[nn.Linear] | None:
    """The Linear layers of an ``nn.Sequential`` of ``Linear, ReLU, ..., Linear[, final]``, or None for any other
    network (a subclass of any of these modules, another activation, dropout, normalisation...)."""
    if type(mlp) is not nn.Sequential:
        return None
    modules = list(mlp)
    if final is not None:
        if not modules or type(modules[-1]) is not final:
            return None
        modules = modules[:-1]
    if len(modules) % 2 != 1:
        return None
    linears = modules[0::2]
    if not all(type(m) is nn.Linear and m.bias is not None for m in linears):
        return None
    if not all(type(m) is nn.ReLU for m in modules[1::2]):
        return None
    return linears  # type: ignore[return-value]


def module_hooks(module: nn.Module, role: str) -> list[str]:
    """Forward and backward hooks registered on ``module`` or any of its submodules, or on every module (global)."""
    found = []
    for name, sub in module.named_modules():
        for kind in ("_forward_hooks", "_forward_pre_hooks", "_backward_hooks", "_backward_pre_hooks"):
            if getattr(sub, kind, None):
                where = f"{role}.{name}" if name else role
                found.append(f"a {kind.strip('_').replace('_', ' ')[:-1]} on {where}")
    global_kinds = global_module_hooks()
    if global_kinds is None:
        found.append(f"global module hooks cannot be checked with torch {th.__version__}")
    found += [f"a global module {kind.replace('_', ' ')} hook" for kind in global_kinds or []]
    return sorted(set(found))


def plain_parameters(module: nn.Module, role: str, dtype: th.dtype = th.float32) -> list[str]:
    """Every parameter is trainable, of ``dtype``, and without gradient hooks: what writing ``.grad`` by hand and
    stepping every parameter assumes."""
    found = []
    for name, p in module.named_parameters():
        where = f"{role}.{name}"
        if p.dtype != dtype:
            found.append(f"{where} is {p.dtype}, not {dtype}")
        if not p.requires_grad and not role.endswith("_target"):
            found.append(f"{where} is frozen (requires_grad=False)")
        if getattr(p, "_backward_hooks", None) or getattr(p, "_post_accumulate_grad_hooks", None):
            found.append(f"a gradient hook on {where}")
    return found[:3] + ([f"and {len(found) - 3} more"] if len(found) > 3 else [])


def _flatten_extractor(module: nn.Module, role: str) -> list[str]:
    """``module``'s features extractor is SB3's ``FlattenExtractor`` as written."""
    extractor = getattr(module, "features_extractor", None)
    if type(extractor) is not FlattenExtractor:
        return [f"the {role}'s features extractor is a {type(extractor).__name__}, not FlattenExtractor"]
    return stock_module(extractor, f"{role}.features_extractor", FlattenExtractor, ("forward",))


def stock_mlp_actor(actor: nn.Module, observation_space: Any, role: str = "actor") -> list[str]:
    """An SB3 ``Actor`` as TD3 builds it: flat observations, ``FlattenExtractor``, a ReLU MLP with a tanh output."""
    reasons = stock_module(actor, role, Actor, ACTOR_METHODS)
    if not flat_box(observation_space):
        reasons.append(f"the observations are not a flat Box (got {observation_space})")
    reasons += _flatten_extractor(actor, role)
    if relu_mlp_layers(getattr(actor, "mu", None), nn.Tanh) is None:
        reasons.append(f"the {role} is not a ReLU MLP with a tanh output (Linear, ReLU, ..., Linear, Tanh)")
    return reasons


def stock_mlp_critic(critic: nn.Module, role: str = "critic") -> list[str]:
    """A ``TD3XCritic`` as TD3 builds it: ``FlattenExtractor``, ReLU MLP critics of one architecture."""
    reasons = stock_module(critic, role, TD3XCritic, CRITIC_METHODS)
    reasons += _flatten_extractor(critic, role)
    shapes = None
    for q in getattr(critic, "q_networks", []):
        linears = relu_mlp_layers(q, None)
        if linears is None:
            reasons.append(f"a {role} network is not a ReLU MLP (Linear, ReLU, ..., Linear)")
            break
        layer_shapes = [tuple(lin.weight.shape) for lin in linears]
        if shapes is not None and layer_shapes != shapes:
            reasons.append(f"the {role} networks have different architectures")
            break
        shapes = layer_shapes
    return reasons


def stock_predict(model: Any) -> list[str]:
    """SB3's ``predict`` path (model and policy) as written: what the exploration shortcut skips."""
    reasons = [f"policy.{m}" for m in _overridden_methods(model.policy, TD3XPolicy, PREDICT_METHODS)]
    reasons += [f"model.{m}" for m in _overridden_methods(model, reference_class(model), ("predict",))]
    return reasons


def no_buffers(module: nn.Module) -> list[str]:
    """No buffers (batch-norm running statistics): the hand-written and functional updates do not update them."""
    names = [name for name, _ in module.named_buffers()]
    if not names:
        return []
    return [f"the policy has buffers ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''}: batch norm?)"]
