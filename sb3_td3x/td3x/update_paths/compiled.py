"""The update compiled with ``torch.compile``: whether (``compile_update``: ``None``, auto, by default) and how.

:func:`why_not_compile` is auto's rule: compile where it wins and computes what the code says (``MlpUpdate``'s
gradient functions, on a CPU, for a run long enough to pay for the compilation), never a user's change.

Two ways of compiling the hooks themselves (``compile_update=True`` where ``MlpUpdate`` does not apply), chosen by
:func:`~sb3_td3x.td3x.update_paths.choose_update`:

- :class:`FunctionalCompiledUpdate`: steps 5 to 15 as one graph, the model's own loss hooks evaluated with
  ``torch.func`` (so overridden losses, targets and networks are compiled as written), Adam's rule on the
  optimizers' own states. It replaces ``gradient_step``, ``update_from_batch``, ``optimize_critic`` and
  ``optimize_actor``, so it requires them as written.
- :func:`compiled_step`: ``update_from_batch`` compiled as it is (eager backward passes), when the functional form
  does not apply (an overridden optimizer step, another optimizer...).

(``MlpUpdate`` compiled, the third form, is in :mod:`~sb3_td3x.td3x.update_paths.mlp`.)
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch as th

from sb3_td3x.common.torch_internals import global_optimizer_hooks, optimizer_step_hooks
from sb3_td3x.td3x.hooks import changed_hooks
from sb3_td3x.td3x.update_paths import requirements
from sb3_td3x.td3x.update_paths.mlp import MlpUpdate

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]

#: What compiling costs at the first gradient steps (Hopper-v5, 400-300 networks, 2 cores of an Intel Xeon with
#: AVX-512, torch 2.13): said in auto's reason for a short run.
COMPILE_COST = "about 3 s with Inductor's cache warm, 16 s cold"


def training_steps(model: TD3X) -> int:
    """The environment steps after ``learning_starts`` of the run ``learn()`` was last asked for: its target
    (``_total_timesteps``, counted from the run's start, so the same for a resumed run as for the uninterrupted
    one) less ``learning_starts``. With ``train_freq=1`` and ``gradient_steps=1``, its gradient steps."""
    return max(0, int(getattr(model, "_total_timesteps", 0)) - max(0, int(model.learning_starts)))


@functools.cache
def why_no_cpu_compiler() -> str | None:
    """Why ``torch.compile`` cannot compile for a CPU here (no C++ compiler for Inductor), or ``None``."""
    try:
        from torch._inductor.cpp_builder import get_cpp_compiler

        get_cpp_compiler()
    except Exception as error:  # noqa: BLE001  (torch raises its own error types, which differ between versions)
        return f"no C++ compiler for torch.compile's CPU backend ({type(error).__name__}: {str(error).strip()[:200]})"
    return None


def why_not_compile(model: TD3X) -> str | None:
    """Why ``compile_update=None`` (auto) runs ``model``'s update uncompiled, or ``None`` where it compiles it: the
    first condition that fails, in one line.

    Auto compiles only where it was measured to win and computes what the code says (docs/performance.md): on a CPU
    (on a GPU, CUDA graphs are auto's fast path), in fp32, ``MlpUpdate``'s gradient functions (SB3's ReLU MLP actor
    and critics, every hook of steps 5 to 13 as written: a user's change always runs uncompiled, as written), with a
    C++ compiler for Inductor, and for a run of at least ``model.compile_auto_min_steps`` training steps
    (:func:`training_steps`), which pays back the compilation's start-up cost (:data:`COMPILE_COST`).
    """
    if model.device.type != "cpu":
        return f"auto compiles on a CPU only (device {model.device})"
    if model.bf16:
        return "bf16=True (compiled bf16 products are not measured to win)"
    if not model.mlp_update:
        return "mlp_update=False"
    if (why := MlpUpdate.why_not(model)) is not None:
        return f"the hooks run as written ({why})"
    if not long_enough(model):
        return (
            f"a run of {training_steps(model):,} training steps: compiling ({COMPILE_COST}) pays for itself from "
            f"{int(model.compile_auto_min_steps):,} (compile_update=True compiles any run)"
        )
    return why_no_cpu_compiler()


def long_enough(model: TD3X) -> bool:
    """Whether the run is long enough for auto to compile: ``model.compile_auto_min_steps`` training steps or more."""
    return training_steps(model) >= model.compile_auto_min_steps


def decide_compile(model: TD3X) -> bool:
    """Whether ``model``'s update is compiled, from ``compile_update`` (``None``: :func:`why_not_compile`); sets
    ``model.update_compiled`` and ``model.compile_reason`` (logged with the update at the first ``train()``)."""
    request = model.compile_update
    if request is None:
        why = why_not_compile(model)
        on = why is None
        reason = (
            f"compile_update=None (auto): a run of {training_steps(model):,} training steps on a CPU, MlpUpdate's "
            "gradient functions compiled"
            if on
            else f"compile_update=None (auto), not compiled: {why}"
        )
    else:
        on, reason = bool(request), f"compile_update={bool(request)}"
    model.update_compiled, model.compile_reason = on, reason
    return on


def compile_watch(model: TD3X) -> tuple[Any, bool]:
    """What :func:`decide_compile` decides from, in short (read at every ``train()`` call, so cheap): the request,
    and for auto whether the run is long enough. When it changes, the update is chosen again."""
    request = model.compile_update
    return request, request is None and long_enough(model)


def compiled_step(update: Callable[[Any, bool], Infos]) -> Callable[[Any, bool], Infos]:
    """``torch.compile`` of the update from a batch as it is (forward, backward, optimizer steps, Polyak updates).

    Dynamo breaks the graph at every ``loss.backward()`` and around the optimizer, so the backward passes stay eager:
    the fallback of :class:`FunctionalCompiledUpdate` when a model's update cannot be made functional.
    """
    return th.compile(update, dynamic=False)


class _Call(th.nn.Module):
    """Runs a closure with the policy's parameters swapped, through ``torch.func.functional_call``."""

    def __init__(self, policy: th.nn.Module):
        super().__init__()
        self.policy = policy

    def forward(self, fn: Callable[[], Any]) -> Any:
        return fn()


class FunctionalCompiledUpdate(requirements.FastPath):
    """
    ``compile_update=True``: steps 5 to 15 as one compiled graph per value of ``update_actor``.

    ``loss.backward()`` splits a compiled update into many graphs with eager backward passes between them, which on a
    CPU is slower than no compilation at all. Here the gradients come from ``torch.func.grad_and_value`` instead, so
    Dynamo traces forward, backward, optimizer and Polyak updates into one graph:

    - the losses are the model's own hooks (``compute_target_q``, ``current_q_values``, ``critic_loss``,
      ``actor_loss``...), evaluated with the parameters swapped in by ``torch.func.functional_call``, so overriding
      them works as in eager mode;
    - steps 12 and 13's optimizer steps are Adam's (or AdamW's) update rule, written with ``torch._foreach`` ops on
      the optimizer's own state (``exp_avg``, ``exp_avg_sq``, ``step``), so saving, loading and switching
      ``compile_update`` off keep working;
    - the learning rates are 0-d tensors refreshed before each call: a schedule does not recompile.

    :meth:`requirements` lists what a model must keep for this to compute what its hooks compute.
    """

    def __init__(self, model: TD3X):
        self.model = model
        self._call = _Call(model.policy)
        names = {id(p): name for name, p in self._call.named_parameters(remove_duplicate=False)}
        self._optimizers = (model.critic.optimizer, model.actor.optimizer)
        self._params = [list(opt.param_groups[0]["params"]) for opt in self._optimizers]
        self._names = [[names[id(p)] for p in params] for params in self._params]
        self._lrs = [th.tensor(0.0, device=model.device) for _ in self._optimizers]
        self._all_params = list(self._call.parameters())
        self._hyperparameters: list[tuple[float, float, float, float, bool]] = []
        self._states: list[tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor]]] = []
        # One compiled function per value of update_actor: each has one graph, so no failed guard check per call.
        self._critic_update = th.compile(lambda batch: self._update(batch, False), dynamic=False)
        self._full_update = th.compile(lambda batch: self._update(batch, True), dynamic=False)

    replaces = ("gradient_step", "update_from_batch", "optimize_critic", "optimize_actor")

    @classmethod
    def requirements(cls, model: TD3X) -> list[str]:
        """Every assumption of the functional update that ``model`` breaks: the hooks it replaces as written, Adam or
        AdamW with one parameter group and no step hooks, every parameter trainable and without gradient hooks
        (``torch.func`` neither skips frozen parameters nor runs tensor hooks), no backward hooks on modules, no
        batch norm."""
        reasons = changed_hooks(model, cls.replaces)
        for optimizer in (model.critic.optimizer, model.actor.optimizer):
            if type(optimizer) not in (th.optim.Adam, th.optim.AdamW):
                reasons.append(f"the optimizer is {type(optimizer).__name__}, not Adam or AdamW")
            elif len(optimizer.param_groups) != 1:
                reasons.append("an optimizer has several parameter groups")
            elif any(optimizer.param_groups[0].get(k) for k in ("amsgrad", "maximize", "differentiable")):
                reasons.append("the optimizer uses amsgrad, maximize or differentiable")
            if optimizer_step_hooks(optimizer) is not False:
                reasons.append("an optimizer has step hooks (or this torch keeps them where TD3X cannot see)")
        global_hooks = global_optimizer_hooks()
        if global_hooks is not False:
            reasons.append("a global optimizer step hook is registered" if global_hooks else
                           f"global optimizer step hooks cannot be checked with torch {th.__version__}")
        for role in ("actor", "critic"):
            reasons += requirements.plain_parameters(getattr(model, role), role)
        reasons += [r for r in requirements.module_hooks(model.policy, "policy") if "backward" in r]
        reasons += requirements.no_buffers(model.policy)
        return list(dict.fromkeys(reasons))

    def __call__(self, batch: Any, update_actor: bool) -> Infos:
        # Everything the graph reads from the optimizers is gathered here, outside it: Dynamo then guards on these
        # lists and numbers, not on the optimizers' dicts (whose learning rates change with a schedule).
        self._hyperparameters, self._states = [], []
        for optimizer, params, lr in zip(self._optimizers, self._params, self._lrs):
            group = optimizer.param_groups[0]
            lr.fill_(group["lr"])
            beta1, beta2 = group["betas"]
            self._hyperparameters.append(
                (float(beta1), float(beta2), float(group["eps"]), float(group["weight_decay"]),
                 isinstance(optimizer, th.optim.AdamW))
            )
            states = []
            for p in params:
                if not optimizer.state[p]:  # as Adam's first step would create them
                    optimizer.state[p] = {
                        "step": th.zeros((), dtype=th.float32, device=p.device),
                        "exp_avg": th.zeros_like(p, memory_format=th.preserve_format),
                        "exp_avg_sq": th.zeros_like(p, memory_format=th.preserve_format),
                    }
                states.append(optimizer.state[p])
            self._states.append(tuple([state[key] for state in states] for key in ("step", "exp_avg", "exp_avg_sq")))
        # torch.func differentiates without requires_grad; switched off, it also makes the hooks' ``frozen()`` a no-op
        # (requires_grad_ cannot be called inside a torch.func transform).
        trainable = [p for p in self._all_params if p.requires_grad]
        for p in trainable:
            p.requires_grad_(False)
        try:
            return self._full_update(batch) if update_actor else self._critic_update(batch)
        finally:
            for p in trainable:
                p.requires_grad_(True)

    def _grads(self, which: int, loss_fn: Callable[[], tuple[th.Tensor, dict[str, th.Tensor]]]) -> Any:
        names = self._names[which]

        def loss_of(values: tuple[th.Tensor, ...]) -> tuple[th.Tensor, dict[str, th.Tensor]]:
            return th.func.functional_call(self._call, dict(zip(names, values)), (loss_fn,), strict=False)

        grads, (_, info) = th.func.grad_and_value(loss_of, has_aux=True)(tuple(self._params[which]))
        return list(grads), info

    @th.no_grad()
    def _adam_step(self, which: int, grads: list[th.Tensor]) -> None:
        """Adam's update rule (torch.optim.Adam, non-capturable), in place on the parameters and the states."""
        params, lr = self._params[which], self._lrs[which]
        beta1, beta2, eps, weight_decay, decoupled = self._hyperparameters[which]
        steps, exp_avgs, exp_avg_sqs = self._states[which]
        if weight_decay != 0:
            if decoupled:  # AdamW
                th._foreach_mul_(params, 1 - lr * weight_decay)
            else:
                grads = th._foreach_add(grads, params, alpha=weight_decay)
        th._foreach_add_(steps, 1)
        # The parameters of one optimizer always step together: their counters are equal.
        bias_correction1 = 1 - beta1 ** steps[0]
        bias_correction2 = 1 - beta2 ** steps[0]
        th._foreach_lerp_(exp_avgs, grads, 1 - beta1)
        th._foreach_mul_(exp_avg_sqs, beta2)
        th._foreach_addcmul_(exp_avg_sqs, grads, grads, 1 - beta2)
        denominators = th._foreach_sqrt(exp_avg_sqs)
        th._foreach_div_(denominators, bias_correction2.sqrt())
        th._foreach_add_(denominators, eps)
        updates = th._foreach_div(exp_avgs, denominators)
        th._foreach_mul_(updates, -lr / bias_correction1)
        th._foreach_add_(params, updates)

    def _update(self, batch: Any, update_actor: bool) -> Infos:
        """``TD3X.update_from_batch`` with the backward passes and optimizer steps made functional."""
        model = self.model
        with model._autocast():
            target_q = model.compute_target_q(batch)  # steps 5-9

        def critic_loss() -> tuple[th.Tensor, dict[str, th.Tensor]]:
            with model._autocast():
                current_q = model.current_q_values(batch)  # step 10
            return model.critic_loss(current_q, target_q)  # step 11

        grads, critic_info = self._grads(0, critic_loss)
        self._adam_step(0, grads)  # step 12
        if not update_actor:
            return critic_info, {}

        def actor_loss() -> tuple[th.Tensor, dict[str, th.Tensor]]:
            with model._autocast():
                return model.actor_loss(batch.observations)  # step 13

        grads, actor_info = self._grads(1, actor_loss)
        self._adam_step(1, grads)
        model.update_critic_target()  # step 15
        model.update_actor_target()  # step 14
        return critic_info, actor_info
