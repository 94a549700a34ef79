"""The private parts of torch that TD3X's fast paths use, in one place, each checked before use.

Each is looked up once and probed on small tensors against torch's public API (same inputs, the same result to float
rounding) the first time it is asked for. Where it is missing, or its signature or result changed in the installed
torch, the accessor says so (``None``) and the caller runs the public API instead: slower, never different. The hook registries are read where torch keeps them; where they are
not there, the fast paths cannot prove that no hook runs and step aside.
"""

from __future__ import annotations

import functools
import importlib
import logging
from collections.abc import Callable
from typing import Any

import torch as th

log = logging.getLogger(__name__)

#: Where the names below live in the torch releases this package was written against (2.3 to 2.14).
_MODULE_HOOKS = ("_global_forward_hooks", "_global_forward_pre_hooks", "_global_backward_hooks", "_global_backward_pre_hooks")
_OPTIMIZER_HOOKS = ("_global_optimizer_pre_hooks", "_global_optimizer_post_hooks")


def _unavailable(what: str, error: BaseException | str) -> None:
    log.info("torch %s: %s is not used (%s); the public API runs instead", th.__version__, what, error)


@functools.cache
def fused_adam_kernel(decoupled_weight_decay: bool) -> Callable[..., None] | None:
    """``torch._fused_adamw_`` or ``torch._fused_adam_``: the kernel a fused Adam(W)'s ``step()`` ends in, taking
    ``(params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, state_steps, *, lr, beta1, beta2, weight_decay, eps,
    amsgrad, maximize, grad_scale, found_inf)`` with the steps already incremented; None where it is not that."""
    name = "_fused_adamw_" if decoupled_weight_decay else "_fused_adam_"
    kernel = getattr(th, name, None)
    if kernel is None:
        _unavailable(f"torch.{name}", "missing")
        return None
    optimizer_class = th.optim.AdamW if decoupled_weight_decay else th.optim.Adam
    options = {"lr": 1e-2, "betas": (0.9, 0.99), "eps": 1e-8, "weight_decay": 0.01}
    try:
        public = th.nn.Parameter(th.linspace(-1.0, 1.0, 7))
        public.grad = th.linspace(0.5, -0.3, 7)
        optimizer = optimizer_class([public], foreach=False, **options)  # the plain, unfused update
        optimizer.step()
        optimizer.step()
        private = th.linspace(-1.0, 1.0, 7)
        exp_avg, exp_avg_sq, step = th.zeros(7), th.zeros(7), th.zeros(())
        for _ in range(2):
            step += 1
            kernel([private], [public.grad], [exp_avg], [exp_avg_sq], [], [step], lr=options["lr"], beta1=0.9,
                   beta2=0.99, weight_decay=0.01, eps=1e-8, amsgrad=False, maximize=False, grad_scale=None,
                   found_inf=None)  # fmt: skip
        if not th.allclose(private, public.detach(), rtol=1e-5, atol=1e-7):
            raise ValueError("its result differs from the optimizer's plain step()")
    except (TypeError, RuntimeError, ValueError) as error:
        _unavailable(f"torch.{name}", error)
        return None
    return kernel


def global_optimizer_hooks() -> bool | None:
    """Whether a global optimizer step hook is registered (``register_optimizer_step_pre_hook``...), None when this
    torch keeps them where this function cannot see."""
    module = importlib.import_module("torch.optim.optimizer")
    registries = [getattr(module, name, None) for name in _OPTIMIZER_HOOKS]
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


def global_module_hooks() -> list[str] | None:
    """The kinds of global module hooks registered (``register_module_forward_hook``...: ``forward``,
    ``forward_pre``, ``backward``, ``backward_pre``), None when this torch keeps them where this function cannot
    see."""
    module = importlib.import_module("torch.nn.modules.module")
    registries = {name: getattr(module, name, None) for name in _MODULE_HOOKS}
    if not all(isinstance(registry, dict) for registry in registries.values()):
        return None
    return [name.removeprefix("_global_").removesuffix("_hooks") for name, registry in registries.items() if registry]


@functools.cache
def linear_relu_kernel() -> tuple[Callable[..., th.Tensor] | None, frozenset[th.dtype]]:
    """oneDNN's linear with a fused ReLU (``torch.ops.mkldnn._linear_pointwise``, what torch.compile's CPU backend
    calls), taking ``(x, weight, bias, "relu", [], "")``, and the dtypes it computes ``relu(addmm(bias, x, W^T))``
    in on this CPU, to float rounding (bf16 only with AVX-512 or AMX); ``(None, {})`` where there is no such
    kernel."""
    op: Any = getattr(getattr(th.ops, "mkldnn", None), "_linear_pointwise", None)
    if op is None or not th.backends.mkldnn.is_available():
        return None, frozenset()
    dtypes = set()
    for dtype in (th.float32, th.bfloat16):
        generator = th.Generator().manual_seed(0)
        x, weight, bias = (th.randn(shape, generator=generator).to(dtype) for shape in ((5, 3), (4, 3), (4,)))
        try:
            result, expected = op(x, weight, bias, "relu", [], ""), th.addmm(bias, x, weight.t()).relu_()
            if result.dtype == dtype and th.allclose(result.float(), expected.float(), rtol=1e-2, atol=1e-2):
                dtypes.add(dtype)
        except (TypeError, RuntimeError):  # bf16 on an AVX2 CPU: "could not create a primitive descriptor"
            pass
    return (op if dtypes else None), frozenset(dtypes)
