"""torch's optimizer hook registries, read in one place: seen when set, and "cannot tell" (a step aside) where this
torch keeps them elsewhere."""

import importlib

import torch as th
from torch.optim.optimizer import register_optimizer_step_post_hook

from sb3_td3x.common import torch_internals
from sb3_td3x.td3x.optim import prepare, why_not_traceable


def test_optimizer_hooks_are_seen_and_an_unknown_registry_makes_the_compiled_step_step_aside(monkeypatch):
    assert torch_internals.global_optimizer_hooks() is False
    p = th.nn.Parameter(th.zeros(2))
    optimizer = th.optim.Adam([p])
    p.grad = th.ones(2)
    optimizer.step()  # its state made
    assert torch_internals.optimizer_step_hooks(optimizer) is False and why_not_traceable(optimizer) is None
    handle = optimizer.register_step_pre_hook(lambda *args: None)
    assert torch_internals.optimizer_step_hooks(optimizer) is True
    assert why_not_traceable(optimizer) == "an optimizer step hook runs only with an eager step()"
    handle.remove()
    handle = register_optimizer_step_post_hook(lambda *args: None)
    try:
        assert torch_internals.global_optimizer_hooks() is True and why_not_traceable(optimizer) is not None
    finally:
        handle.remove()
    module = importlib.import_module("torch.optim.optimizer")
    monkeypatch.delattr(module, "_global_optimizer_pre_hooks")
    assert torch_internals.global_optimizer_hooks() is None
    prepare(optimizer)
    assert why_not_traceable(optimizer) == "an optimizer step hook runs only with an eager step()"
