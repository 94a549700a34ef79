"""torch's private parts behind one module: used where they compute what the public API computes, set aside where
they are missing or changed (the fast paths then run the public API, or step aside and say why)."""

import importlib

import pytest
import torch as th

from sb3_td3x.common import torch_internals
from sb3_td3x.td3x.update_paths.mlp import step_optimizers
from sb3_td3x.td3x.update_paths.requirements import module_hooks


@pytest.fixture(autouse=True)
def fresh_probes():
    torch_internals.fused_adam_kernel.cache_clear()
    torch_internals.linear_relu_kernel.cache_clear()
    yield
    torch_internals.fused_adam_kernel.cache_clear()
    torch_internals.linear_relu_kernel.cache_clear()


def _two_steps(fast: bool) -> th.Tensor:
    """Two steps of a fused Adam: through the fast call of MlpUpdate's optimizer step, or through ``step()``."""
    p = th.nn.Parameter(th.linspace(-1.0, 1.0, 11))
    optimizer = th.optim.Adam([p], lr=1e-2, fused=True)
    for step in range(2):
        p.grad = th.linspace(0.3, -0.7, 11) * (step + 1)
        step_optimizers([optimizer]) if fast else optimizer.step()
    return p.detach()


def test_this_torch_has_every_private_part():
    assert torch_internals.fused_adam_kernel(False) is th._fused_adam_
    assert torch_internals.fused_adam_kernel(True) is th._fused_adamw_
    assert torch_internals.global_optimizer_hooks() is False and torch_internals.global_module_hooks() == []
    kernel, dtypes = torch_internals.linear_relu_kernel()
    assert kernel is None or th.float32 in dtypes


def test_a_changed_adam_kernel_is_set_aside_and_step_runs(monkeypatch):
    exact = _two_steps(fast=False)
    assert th.equal(_two_steps(fast=True), exact)
    kernel = th._fused_adam_

    def changed(*args, **kwargs):  # a release where the kernel's meaning moved: the learning rate doubled
        kwargs["lr"] *= 2
        return kernel(*args, **kwargs)

    monkeypatch.setattr(th, "_fused_adam_", changed)
    torch_internals.fused_adam_kernel.cache_clear()
    assert torch_internals.fused_adam_kernel(False) is None
    monkeypatch.setattr(th, "_fused_adam_", kernel)  # step() itself still runs torch's own kernel
    assert th.equal(_two_steps(fast=True), exact)


def test_a_missing_adam_kernel_is_set_aside(monkeypatch):
    monkeypatch.delattr(th, "_fused_adam_")
    assert torch_internals.fused_adam_kernel(False) is None


def test_hooks_are_seen_and_unknown_registries_make_the_fast_path_step_aside(monkeypatch):
    handle = th.nn.modules.module.register_module_forward_hook(lambda *args: None)
    try:
        assert torch_internals.global_module_hooks() == ["forward"]
        assert "a global module forward hook" in module_hooks(th.nn.Linear(2, 2), "actor")
    finally:
        handle.remove()
    module = importlib.import_module("torch.nn.modules.module")
    monkeypatch.delattr(module, "_global_backward_hooks")
    assert torch_internals.global_module_hooks() is None
    assert any("cannot be checked" in reason for reason in module_hooks(th.nn.Linear(2, 2), "actor"))
    optimizer = th.optim.Adam([th.nn.Parameter(th.zeros(2))])
    assert torch_internals.optimizer_step_hooks(optimizer) is False
    optimizer.register_step_pre_hook(lambda *args: None)
    assert torch_internals.optimizer_step_hooks(optimizer) is True
