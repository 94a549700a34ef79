"""Opt-in accelerations of TD3X's gradient step: bf16 autocast, ``torch.compile``, CUDA graph capture.

Each wraps :meth:`TD3X.gradient_step` (or :meth:`TD3X.update_from_batch`) as it is, so overridden hooks are
accelerated too.
"""

from __future__ import annotations

import contextlib
import platform
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch as th

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]
StepFn = Callable[[int, bool], Infos]


def autocast_context(device: th.device, enabled: bool, cache: bool = True) -> contextlib.AbstractContextManager:
    """bf16 autocast for the forward passes (AMX on recent x86 CPUs, tensor cores on GPUs); weights stay fp32.

    ``cache=False`` under CUDA graph capture: cached casts must not outlive the captured region.
    """
    if not enabled:
        return contextlib.nullcontext()
    return th.autocast(device_type=device.type, dtype=th.bfloat16, cache_enabled=cache)


def cpu_bf16_matmul_is_native() -> bool | None:
    """Whether this CPU multiplies bf16 matrices in hardware (AVX512-BF16 or AMX), or ``None`` when torch cannot say.

    Without them (an AVX2-only x86 CPU), oneDNN converts bf16 in software: a 256 x 400 x 300 product took 19.8 ms in
    bf16 against 0.42 ms in fp32 on a 2-core AMD EPYC (AVX2), where AMX makes it 2 to 5 times *faster* than fp32.
    """
    if platform.machine().lower() not in ("x86_64", "amd64", "i386", "i686", "x86"):
        return None
    probes = [getattr(th.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    if any(probe is None for probe in probes):
        return None
    return any(probe() for probe in probes)  # type: ignore[misc]


def bf16_on_cpu_warning(device: th.device) -> str | None:
    """The warning for ``bf16=True`` on ``device``: set when it is a CPU without bf16 matrix instructions."""
    if device.type != "cpu" or cpu_bf16_matmul_is_native() is not False:
        return None
    capability = th.backends.cpu.get_cpu_capability()
    return (
        f"bf16=True on a CPU without bf16 matrix instructions (no AVX512-BF16 or AMX; torch reports {capability}): "
        "its bf16 matrix products run in software emulation, tens of times slower than fp32 (47x for 256 x 400 x "
        "300 on an AVX2 AMD EPYC). Use bf16=False on this machine; bf16 pays off on CPUs with AMX (Intel Xeon "
        "Sapphire Rapids and later) and on GPUs."
    )


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


class FunctionalCompiledUpdate:
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

    Use :meth:`why_not` to know whether a model qualifies (Adam or AdamW with one parameter group, no AMSGrad, no
    batch norm, ``optimize_critic``, ``optimize_actor`` and ``update_from_batch`` not overridden).
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

    @staticmethod
    def why_not(model: TD3X) -> str | None:
        """Why ``model``'s update cannot be made functional, or ``None`` when it can."""
        from sb3_td3x.td3x.td3x import TD3X

        for hook in ("update_from_batch", "optimize_critic", "optimize_actor"):
            if getattr(type(model), hook) is not getattr(TD3X, hook):
                return f"{hook} is overridden"
        for optimizer in (model.critic.optimizer, model.actor.optimizer):
            if type(optimizer) not in (th.optim.Adam, th.optim.AdamW):
                return f"the optimizer is {type(optimizer).__name__}, not Adam or AdamW"
            if len(optimizer.param_groups) != 1:
                return "an optimizer has several parameter groups"
            group = optimizer.param_groups[0]
            if group.get("amsgrad") or group.get("maximize") or group.get("differentiable"):
                return "the optimizer uses amsgrad, maximize or differentiable"
        if any(True for _ in model.policy.buffers()):
            return "the policy has buffers (batch norm)"
        return None

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


def cuda_graph_capture(fn: Callable[[], Infos], pool: Any | None) -> tuple[Callable[[], None], Infos, Any]:
    """Capture ``fn`` in a CUDA graph; returns (replay, the static outputs, the memory pool)."""
    graph = th.cuda.CUDAGraph()
    with th.cuda.graph(graph, pool=pool):
        outputs = fn()
    return graph.replay, outputs, graph.pool()


class GraphedGradientStep:
    """
    The whole gradient step (sampling included) captured once per (batch size, actor update or not) and replayed.

    Requirements, checked by ``TD3X``: a CUDA device, the tensor replay buffer (sampled on the device from bounds
    kept in device tensors), no ``VecNormalize`` (it normalises on the host), and Adam with ``capturable=True``.
    The warm-up steps that precede a capture are undone (parameters and optimizer states restored in place), so
    capturing does not change what is learned.

    :param model: the TD3X model
    :param capture: how to capture a step; ``cuda_graph_capture`` on a GPU. Tests on the CPU pass an eager stand-in,
        which checks everything but the capture itself: static bounds, cloned outputs, restored warm-up.
    :param warmup_steps: eager steps run before a capture (CUDA needs them on a side stream to set up its kernels)
    """

    def __init__(
        self,
        model: TD3X,
        capture: Callable[[Callable[[], Infos], Any | None], tuple[Callable[[], None], Infos, Any]] = cuda_graph_capture,
        warmup_steps: int = 3,
    ):
        self.model = model
        self.capture = capture
        self.warmup_steps = warmup_steps
        self._graphs: dict[tuple[int, bool], tuple[Callable[[], None], Infos]] = {}
        self._pool: Any | None = None

    def __call__(self, batch_size: int, update_actor: bool) -> Infos:
        key = (batch_size, update_actor)
        if key not in self._graphs:
            self._graphs[key] = self._capture(batch_size, update_actor)
        replay, (critic_info, actor_info) = self._graphs[key]
        self.model.replay_buffer.refresh_static_bounds()  # type: ignore[union-attr]
        replay()
        # The outputs are static tensors overwritten by the next replay: keep copies (device ops, no sync).
        return {k: v.clone() for k, v in critic_info.items()}, {k: v.clone() for k, v in actor_info.items()}

    def _capture(self, batch_size: int, update_actor: bool) -> tuple[Callable[[], None], Infos]:
        model = self.model
        model.replay_buffer.refresh_static_bounds()  # type: ignore[union-attr]
        saved = self._snapshot()
        on_cuda = model.device.type == "cuda"
        stream = th.cuda.Stream() if on_cuda else None
        context = th.cuda.stream(stream) if stream is not None else contextlib.nullcontext()
        if stream is not None:
            stream.wait_stream(th.cuda.current_stream())
        with context:
            for _ in range(self.warmup_steps):
                model.gradient_step(batch_size, update_actor)
        if stream is not None:
            th.cuda.current_stream().wait_stream(stream)
        replay, outputs, self._pool = self.capture(lambda: model.gradient_step(batch_size, update_actor), self._pool)
        self._restore(saved)
        return replay, outputs

    def _tensors(self) -> list[th.Tensor]:
        """Every tensor a gradient step writes: parameters (online and target), buffers, optimizer states."""
        model = self.model
        tensors = [*model.policy.parameters(), *model.policy.buffers()]
        for optimizer in (model.actor.optimizer, model.critic.optimizer):
            for state in optimizer.state.values():
                tensors.extend(v for v in state.values() if isinstance(v, th.Tensor))
        return tensors

    @th.no_grad()
    def _snapshot(self) -> list[tuple[th.Tensor, th.Tensor]]:
        # Optimizer states may not exist yet (no step taken): the warm-up creates them, and _restore zeroes them.
        return [(t, t.clone()) for t in self._tensors()]

    @th.no_grad()
    def _restore(self, saved: list[tuple[th.Tensor, th.Tensor]]) -> None:
        saved_ids = {id(t) for t, _ in saved}
        for tensor, value in saved:
            tensor.copy_(value)
        # States created during the warm-up start from zero, as a fresh optimizer's would.
        for t in self._tensors():
            if id(t) not in saved_ids:
                t.zero_()
