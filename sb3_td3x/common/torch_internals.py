"""The registries of torch's optimizer step hooks, read where torch keeps them (a private place), in one module.

A compiled or captured optimizer step would not run step hooks: the compiled update and ``cuda_graph=True`` check
for them here. Where this torch keeps them elsewhere, the answer is ``None`` ("cannot tell"), and the callers treat it
as a hook: they step aside to ``optimizer.step()``.
"""

from __future__ import annotations

import importlib

import torch as th

_OPTIMIZER_HOOKS = ("_global_optimizer_pre_hooks", "_global_optimizer_post_hooks")
_OPTIMIZER_MODULE = importlib.import_module("torch.optim.optimizer")


def global_optimizer_hooks() -> bool | None:
    """Whether a global optimizer step hook is registered (``register_optimizer_step_pre_hook``...), None when this
    torch keeps them where this function cannot see."""
    registries = [getattr(_OPTIMIZER_MODULE, name, None) for name in _OPTIMIZER_HOOKS]
    if not all(isinstance(registry, dict) for registry in registries):
        return None
    return any(registries)


def optimizer_step_hooks(optimizer: th.optim.Optimizer) -> bool | None:
    """Whether ``optimizer`` has step hooks of its own (``register_step_pre_hook``...), None when this torch keeps
    them where this function cannot see."""
    registries = [getattr(optimizer, name, None) for name in ("_optimizer_step_pre_hooks", "_optimizer_step_post_hooks")]
    if not all(isinstance(registry, dict) for registry in registries):
        return None
    return any(registries)
