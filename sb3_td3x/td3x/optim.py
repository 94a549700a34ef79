"""Steps 12 and 13's optimizer step, written once for the eager update and the compiled one: :func:`minimize` (and
:func:`gradients` with :func:`apply_gradients`, for a step that changes the gradients in between).

Eagerly, ``minimize(optimizer, loss)`` is what SB3's TD3 does: ``zero_grad``, ``loss.backward()``, ``step()``, the
backward pass reaching the optimizer's own parameters only (so the actor's loss leaves the critics without gradient);
before a fused optimizer's ``step()``, the gradients and moments are laid out in memory as their parameters
(:func:`_step`: torch's fused CPU kernel computes wrong steps otherwise).

Inside ``torch.compile`` (:mod:`~sb3_td3x.td3x.update_paths.compiled`), the same call is written so that the forward
pass, the backward pass and the optimizer step trace into one graph: the gradients come from
``torch.autograd.grad`` and the parameters move by the optimizer's own update rule, torch's functional ``adam``
(what ``torch.optim.Adam.step()`` and ``AdamW.step()`` call), on the optimizer's own state tensors. torch 2.13 cannot
trace ``loss.backward()`` followed by ``optimizer.step()`` into one graph: the optimizer refuses a parameter whose
gradient the same graph writes. An optimizer that cannot be stepped this way (not torch's ``Adam`` or ``AdamW``, or
with step hooks, which ``step()`` would run: :func:`why_not_traceable`) stops the compilation with the reason, and
the update then runs eagerly. What the graph reads of an optimizer is made ready before each call (:func:`prepare`).
"""

from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass
from typing import Any

import torch as th
from torch.optim.adam import adam as functional_adam

from sb3_td3x.common.torch_internals import global_optimizer_hooks, optimizer_step_hooks

#: The optimizers :func:`minimize` steps inside a compiled graph: torch's own classes, not subclasses (whose ``step``
#: may do anything).
TRACEABLE = (th.optim.Adam, th.optim.AdamW)

#: Torch's own ``step`` of each of them (under the profiling wrapper ``Optimizer.__init__`` puts on the class): a
#: ``step`` replaced on the class or the instance is the user's, which the functional Adam would not run.
_TORCH_STEPS = {cls: inspect.unwrap(cls.step) for cls in TRACEABLE}

#: What :func:`why_not_traceable` says of an Adam that has not taken its first step: that step runs eagerly (it makes
#: the state), the next ones compiled. Every other reason steps the update aside for good.
NO_STATE = "the optimizer has not taken its first step (its state is made eagerly)"

#: Why a compiled step stops before it runs when a gradient reaches a parameter that has no Adam state yet (a
#: parameter group added, a layer unfrozen): the step runs eagerly, which makes the state, and the next one compiles.
FIRST_GRADIENT = "sb3_td3x.td3x.optim: a parameter's first gradient (Adam makes its state eagerly)"

#: The attribute where :func:`prepare` leaves, for a compiled step, an optimizer's learning rates as 0-d tensors (one
#: per parameter group: a schedule then changes a tensor's value, not a constant of the graph, and recompiles nothing),
#: or the reason it cannot be stepped inside a graph.
PREPARED = "_sb3_td3x_compiled_step"


def trainable(optimizer: th.optim.Optimizer) -> list[th.Tensor]:
    """The parameters ``optimizer`` steps that require a gradient, in its order (frozen ones get none)."""
    return [p for group in optimizer.param_groups for p in group["params"] if p.requires_grad]


def minimize(optimizer: th.optim.Optimizer, loss: th.Tensor) -> None:
    """One gradient step of ``optimizer`` on ``loss``: the gradient of ``loss`` with respect to the optimizer's
    parameters (and no other tensor), then the optimizer's update (see the module's docstring)."""
    if th.compiler.is_compiling():
        # A parameter the loss does not reach (a module replaced after the optimizer was made, an unused head) gets
        # no gradient, and the step leaves it and its state alone, as loss.backward(inputs=...) and step() do.
        apply_gradients(optimizer, gradients(optimizer, loss))
        return
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=trainable(optimizer))
    _step(optimizer)


def gradients(optimizer: th.optim.Optimizer, loss: th.Tensor) -> list[th.Tensor | None]:
    """The gradient of ``loss`` with respect to each of the optimizer's trainable parameters (:func:`trainable`'s
    order), with ``torch.autograd.grad``: to change them before :func:`apply_gradients` (clipping, say) in a way that
    compiles with the rest of the update. ``None`` for a parameter the loss does not reach (an unused head): as
    ``loss.backward()`` leaves its ``.grad`` unset, and :func:`apply_gradients` then leaves it and its state alone."""
    params = _prepared(optimizer).params if th.compiler.is_compiling() else trainable(optimizer)
    return list(th.autograd.grad(loss, params, allow_unused=True))


def apply_gradients(optimizer: th.optim.Optimizer, grads: list[th.Tensor | None]) -> None:
    """The optimizer's update with ``grads`` (one per trainable parameter, :func:`trainable`'s order): eagerly, the
    gradients set as ``.grad`` and ``optimizer.step()``; compiled, torch's functional Adam on the optimizer's state.
    A parameter whose gradient is ``None`` is left as it is, its state too (as ``step()`` leaves it)."""
    if not th.compiler.is_compiling():
        params = trainable(optimizer)
        if len(grads) != len(params):
            raise ValueError(f"apply_gradients: {len(grads)} gradients for the optimizer's {len(params)} trainable parameters")
        for p, g in zip(params, grads):
            p.grad = g
        _step(optimizer)
        return
    step = _prepared(optimizer)
    with th.no_grad():
        for group in step.groups:
            group_grads, grads = grads[: len(group.params)], grads[len(group.params) :]
            kept = [i for i, g in enumerate(group_grads) if g is not None]  # known when tracing: no guard, no branch
            if any(group.steps[i] is None for i in kept):
                th._dynamo.graph_break(msg=FIRST_GRADIENT)  # Adam makes its state eagerly: this step runs eagerly
            if not kept:
                continue
            functional_adam(
                [group.params[i] for i in kept],
                [group_grads[i] for i in kept],
                [group.exp_avgs[i] for i in kept],
                [group.exp_avg_sqs[i] for i in kept],
                [group.max_exp_avg_sqs[i] for i in kept] if group.max_exp_avg_sqs else [],
                [group.steps[i] for i in kept],
                # On a CPU one tensor at a time: two divisions an element where the foreach form's capturable branch
                # has three (Inductor fuses the tensors' loops into one C++ kernel either way); 3% of a Hopper-v5
                # gradient step, in the log. On a GPU the foreach form, whose tensors Inductor runs in combined
                # kernels (what the GPU tables measured).
                foreach=group.params[kept[0]].device.type != "cpu",
                capturable=True,  # the learning rate is a tensor
                lr=group.lr,
                **group.options,
            )


def _step(optimizer: th.optim.Optimizer) -> None:
    """``optimizer.step()``, eagerly, with each parameter's gradient and state first laid out in memory as the
    parameter is, where a parameter group uses torch's fused Adam (TD3X's default:
    :class:`~sb3_td3x.td3x.policies.TD3XPolicy`).

    torch 2.13's fused kernel on a CPU walks a parameter, its gradient and its two moments through memory side by side
    and silently computes wrong values where their layouts differ (on a GPU torch refuses them with an error, issue
    106951 of pytorch/pytorch): a network moved to ``channels_last`` after the first step (its moments keep the old
    layout; 0.03 off after one step), a gradient set by hand in another layout. Such a gradient or moment is copied
    into the parameter's layout, which changes no value. A parameter that is not one dense block of memory (a slice of
    a larger tensor) has no layout a copy can match: its group then steps with torch's for-loop implementation from
    then on, with a warning. Any fused optimizer (SGD's too) is treated so. The check costs 1 to 3 us a parameter
    (about 30 us for a critic's 12 tensors on a Zen 3 EPYC, where its fused Adam step takes 300 to 440 us and torch's
    for-loop one 1,400 to 2,100)."""
    for group in optimizer.param_groups:
        if group.get("fused"):
            _lay_out_as_params(optimizer, group)
    optimizer.step()


def _lay_out_as_params(optimizer: th.optim.Optimizer, group: dict[str, Any]) -> None:
    state = optimizer.state
    for p in group["params"]:
        grad = p.grad
        if grad is None:
            continue
        moments = state.get(p) or {}
        if p.is_contiguous() and grad.is_contiguous() and all(
            m.is_contiguous() for m in moments.values() if isinstance(m, th.Tensor)
        ):
            continue  # one layout, the kernel's: the common case
        stride = p.stride()
        if grad.stride() != stride:
            p.grad = grad = th.empty_like(p).copy_(grad)  # the same strides as p where p is dense
        moment_keys = [k for k, m in moments.items() if isinstance(m, th.Tensor) and m.shape == p.shape]  # not `step`
        for key in moment_keys:
            if moments[key].stride() != stride:
                moments[key] = th.empty_like(p).copy_(moments[key])
        if grad.stride() != stride or any(moments[key].stride() != stride for key in moment_keys):
            group["fused"] = False
            warnings.warn(
                f"sb3_td3x: a parameter of shape {tuple(p.shape)} is not one dense block of memory (strides {stride}), "
                f"which torch's fused {type(optimizer).__name__} steps wrongly; its parameter group steps with torch's "
                "for-loop implementation from now on (make the parameter contiguous to keep the fused one)",
                stacklevel=4,
            )
            return


@dataclass
class _Group:
    """What a compiled Adam step reads of one parameter group (:func:`prepare`): the graph reads this, never the
    optimizer's own dictionaries, whose learning rate changes with a schedule."""

    params: list[th.Tensor]
    # None for a parameter without state yet (no gradient so far: a head kept for later, a layer just added)
    exp_avgs: list[th.Tensor | None]
    exp_avg_sqs: list[th.Tensor | None]
    max_exp_avg_sqs: list[th.Tensor | None]
    steps: list[th.Tensor | None]
    lr: th.Tensor  # 0-d, refreshed before each call
    options: dict[str, Any]
    lr_value: float  # what lr holds


@dataclass
class _CompiledStep:
    params: list[th.Tensor]  # trainable(optimizer)
    groups: list[_Group]


def _prepared(optimizer: th.optim.Optimizer) -> _CompiledStep:
    prepared = getattr(optimizer, PREPARED, "the optimizer was not prepared for a compiled step (sb3_td3x.td3x.optim.prepare)")
    if isinstance(prepared, str):
        th._dynamo.graph_break(msg=f"sb3_td3x.td3x.optim: {prepared}")  # msg=: a positional one is lost (torch 2.13)
    return prepared


def why_not_traceable(optimizer: th.optim.Optimizer) -> str | None:
    """Why :func:`minimize` cannot step ``optimizer`` inside a compiled graph, or ``None`` where it can: torch's
    ``Adam`` or ``AdamW`` (not a subclass, its ``step`` torch's own), without step hooks, not differentiable, its
    state made by a first ``step()``, and no gradient hook on its parameters (``register_hook``,
    ``register_post_accumulate_grad_hook``: a graph differentiating with ``torch.autograd.grad`` would not run
    them)."""
    if type(optimizer) not in TRACEABLE:
        return f"the {type(optimizer).__name__} optimizer steps only eagerly (compiled: torch's Adam and AdamW)"
    if "step" in vars(optimizer) or inspect.unwrap(type(optimizer).step) is not _TORCH_STEPS[type(optimizer)]:
        return f"{type(optimizer).__name__}.step was replaced (compiled: torch's own step)"
    if optimizer_step_hooks(optimizer) is not False or global_optimizer_hooks() is not False:
        return "an optimizer step hook runs only with an eager step()"
    if any(group.get("differentiable") for group in optimizer.param_groups):
        return "a differentiable optimizer steps only eagerly"
    if not has_state(optimizer):
        return NO_STATE
    if hooked := [p for p in trainable(optimizer) if p._backward_hooks or getattr(p, "_post_accumulate_grad_hooks", None)]:
        return f"a gradient hook on a parameter (shape {tuple(hooked[0].shape)}) runs only in an eager backward pass"
    return None


def prepare(optimizer: th.optim.Optimizer) -> None:
    """Make ready, eagerly, what a compiled :func:`minimize` of ``optimizer`` reads (:data:`PREPARED`): its trainable
    parameters and state tensors, its options, its learning rates as 0-d tensors (refreshed at each call), or the
    reason it cannot be stepped inside a graph. Called before every compiled step: what it made is kept while the
    optimizer keeps the same parameters, state tensors and options (the graph's inputs stay the same objects)."""
    why = why_not_traceable(optimizer)
    if why is not None:
        optimizer.__dict__[PREPARED] = why
        return
    old = optimizer.__dict__.get(PREPARED)
    groups = [_group(optimizer, group, old.groups[k] if isinstance(old, _CompiledStep) and k < len(old.groups) else None)
              for k, group in enumerate(optimizer.param_groups)]  # fmt: skip
    if (not isinstance(old, _CompiledStep) or len(groups) != len(old.groups)  # add_param_group, say
            or any(new is not kept for new, kept in zip(groups, old.groups))):
        optimizer.__dict__[PREPARED] = _CompiledStep([p for g in groups for p in g.params], groups)


def _group(optimizer: th.optim.Optimizer, group: dict[str, Any], old: _Group | None) -> _Group:
    """What a compiled step reads of ``group``: ``old`` itself (its learning rate refreshed) where nothing else
    changed, else made anew."""
    params = [p for p in group["params"] if p.requires_grad]
    states = [optimizer.state.get(p) or {} for p in params]
    beta1, beta2 = group["betas"]
    options = {
        "beta1": beta1, "beta2": beta2, "eps": group["eps"], "weight_decay": group["weight_decay"],
        "amsgrad": group["amsgrad"], "maximize": group["maximize"],
        "decoupled_weight_decay": bool(group.get("decoupled_weight_decay", isinstance(optimizer, th.optim.AdamW))),
    }  # fmt: skip
    lr = float(group["lr"])
    # Every tensor the graph reads of the group, compared by identity with what ``old`` holds: a state tensor given
    # anew (Adam's second moments replaced, say) makes a new group, as a new parameter does.
    tensors = (
        params, [st.get("exp_avg") for st in states], [st.get("exp_avg_sq") for st in states],
        [st.get("max_exp_avg_sq") for st in states] if group["amsgrad"] else [], [st.get("step") for st in states],
    )  # fmt: skip
    if old is not None and options == old.options and all(
        len(new) == len(kept) and all(a is b for a, b in zip(new, kept))
        for new, kept in zip(tensors, (old.params, old.exp_avgs, old.exp_avg_sqs, old.max_exp_avg_sqs, old.steps))
    ):
        if lr != old.lr_value:
            old.lr.fill_(lr)
            old.lr_value = lr
        return old
    return _Group(*tensors, th.full((), lr, device=params[0].device), options, lr)


def has_state(optimizer: th.optim.Optimizer) -> bool:
    """Whether ``optimizer`` has taken its first step: its state made, for the parameters that had a gradient (one
    that never has one, an unused head, never gets state; one whose first gradient comes in a compiled step makes
    that step run eagerly, :data:`FIRST_GRADIENT`)."""
    return any(optimizer.state.get(p) for p in trainable(optimizer))
