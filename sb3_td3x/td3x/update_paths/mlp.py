"""Steps 5 to 15 for MLP policies with the gradients written out by hand: TD3X's default update.

For the networks TD3 is run with (ReLU MLPs, a tanh actor, flat observations) the backward passes are a few matrix
products, so :class:`MlpUpdate` computes them itself instead of recording an autograd graph:

- the critics are evaluated as one ensemble: their weights live in stacked tensors (``[n_critics, out, in]``, views
  of one flat tensor) that the critics' own parameters are views of, so both critics (and both critic targets) go
  through each layer in one batched product (``baddbmm``, the shared input broadcast), forward and backward;
- the actor loss back-propagates through the first critic to the action only, with no gradient for the critic's
  weights and none for the observation columns of its first layer;
- ReLU and tanh backwards are ``threshold_backward`` and ``tanh_backward``, the kernels autograd runs; on a CPU the
  2-D hidden layers are oneDNN's linear with the ReLU fused into it;
- the optimizers are the model's own: gradients are written into ``.grad`` and ``optimizer.step()`` is called, so any
  optimizer, schedule, save and load behave as with autograd.

It computes what :meth:`TD3X.update_from_batch` computes (the tests compare both to float rounding), from the same
batch and the same random numbers, so it replaces it only where that holds: :meth:`MlpUpdate.why_not` checks every
assumption (the hooks of :data:`MlpUpdate.replaces` as written, SB3's own actor and critic classes with their
``forward`` as written, ReLU MLPs with a flatten features extractor, no module or gradient hooks, trainable fp32
parameters, no batch norm). With ``bf16=True``
the products run in bf16 with fp32 weights, gradients and optimizer, as under autocast. Anything else runs the hooks
with autograd, as before. Steps 14 and 15 are the model's own hooks, overridden or not. :func:`critic_gradients` and
:func:`actor_gradients` are pure functions of their inputs, which ``compile_update=True`` compiles.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch as th
import torch.optim.optimizer as _optim_module
from torch import nn

from sb3_td3x.td3x.hooks import changed_hooks
from sb3_td3x.td3x.update_paths import requirements
from sb3_td3x.td3x.update_paths.requirements import relu_mlp_layers

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]

_relu_backward = th.ops.aten.threshold_backward
_tanh_backward = th.ops.aten.tanh_backward


def _matmul(a: th.Tensor, b: th.Tensor) -> th.Tensor:
    """``a @ b``; an outer product (inner dimension 1, as back through a critic's output layer) as a broadcast
    multiply, which is what the product computes, without a matrix-product call for it."""
    if a.shape[-1] == 1:
        return a * b
    return a @ b


def _mkldnn_linear_relu() -> tuple[Any, frozenset[th.dtype]]:
    """oneDNN's linear with a fused ReLU, and the dtypes it runs in on this CPU (bf16 only with AVX-512 or AMX:
    on an AVX2 CPU it fails with "could not create a primitive descriptor")."""
    op = getattr(getattr(th.ops, "mkldnn", None), "_linear_pointwise", None)
    dtypes = set()
    for dtype in (th.float32, th.bfloat16):
        try:
            x = th.ones(2, 3, dtype=dtype)
            op(x, th.ones(4, 3, dtype=dtype), th.zeros(4, dtype=dtype), "relu", [], "")  # type: ignore[misc]
            dtypes.add(dtype)
        except (TypeError, RuntimeError):
            pass
    return (op if dtypes else None), frozenset(dtypes)


_LINEAR_POINTWISE, _LINEAR_POINTWISE_DTYPES = (
    _mkldnn_linear_relu() if th.backends.mkldnn.is_available() else (None, frozenset())
)


def addmm_relu(x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
    """relu(x W^T + b) with the kernels of ``nn.Linear`` and ``nn.ReLU``."""
    return th.addmm(bias, x, weight.t()).relu_()


def _linear_relu(x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
    """relu(x W^T + b). On a CPU, oneDNN's linear with the ReLU fused into it (what torch.compile's CPU backend
    calls): one pass over the output instead of two, and faster than MKL's addmm at these sizes (0.24 against 0.29 ms
    for 256 x 400 x 300 in fp32 on the 2-core benchmark machine). Under torch.compile, addmm and relu (Inductor
    lowers them itself)."""
    if (
        _LINEAR_POINTWISE is not None
        and x.device.type == "cpu"
        and x.dtype in _LINEAR_POINTWISE_DTYPES
        and not th.compiler.is_compiling()
    ):
        return _LINEAR_POINTWISE(x, weight, bias, "relu", [], "")
    return addmm_relu(x, weight, bias)


def optimizer_step(optimizer: th.optim.Optimizer) -> None:
    """``optimizer.step()``; for a fused Adam or AdamW, the kernel ``step()`` ends in, called straight away.

    ``Adam.step`` spends about as long in Python (grouping the tensors by device, checking its options) as its fused
    kernel takes on a critic. When nothing can differ (one parameter group, fused, no AMSGrad, maximize,
    differentiable or capturable, a float learning rate, no step hooks, every state already created by a first
    ``step()``), this makes the same two calls ``torch.optim.adam._fused_adam`` makes; otherwise it calls ``step()``.
    """
    call = fused_adam_call(optimizer)
    if call is None:
        optimizer.step()
    else:
        run_fused_adam([call])


def fused_adam_call(optimizer: th.optim.Optimizer) -> tuple[Any, dict[str, Any], list[list[th.Tensor]]] | None:
    """The kernel a fused Adam or AdamW's ``step()`` ends in, its options, and its tensors (parameters, gradients,
    ``exp_avg``, ``exp_avg_sq``, ``step``) when nothing else can differ (see :func:`optimizer_step`); else None."""
    if not isinstance(optimizer, th.optim.Adam) or len(optimizer.param_groups) != 1:
        return None
    if optimizer._optimizer_step_pre_hooks or optimizer._optimizer_step_post_hooks:
        return None
    if _optim_module._global_optimizer_pre_hooks or _optim_module._global_optimizer_post_hooks:
        return None
    group = optimizer.param_groups[0]
    if not group.get("fused") or isinstance(group["lr"], th.Tensor):
        return None
    if group["amsgrad"] or group["maximize"] or group["differentiable"] or group["capturable"]:
        return None
    params = [p for p in group["params"] if p.grad is not None]
    states = [optimizer.state.get(p) for p in params]
    if not params or not all(states):
        return None
    kernel = th._fused_adamw_ if group.get("decoupled_weight_decay") else th._fused_adam_
    beta1, beta2 = group["betas"]
    options = {"lr": group["lr"], "beta1": beta1, "beta2": beta2, "weight_decay": group["weight_decay"], "eps": group["eps"]}
    tensors = [
        params,
        [p.grad for p in params],
        [state["exp_avg"] for state in states],  # type: ignore[index]
        [state["exp_avg_sq"] for state in states],  # type: ignore[index]
        [state["step"] for state in states],  # type: ignore[index]
    ]
    return kernel, options, tensors


def run_fused_adam(calls: list[tuple[Any, dict[str, Any], list[list[th.Tensor]]]]) -> None:
    """The calls of :func:`fused_adam_call`, all of one kernel and options, as one step counter increment and one
    kernel call over all their tensors (the update is elementwise: each tensor's is what its own call computes)."""
    kernel, options, _ = calls[0]
    params, grads, exp_avgs, exp_avg_sqs, steps = ([t for call in calls for t in call[2][k]] for k in range(5))
    th._foreach_add_(steps, 1)
    kernel(
        params,
        grads,
        exp_avgs,
        exp_avg_sqs,
        [],
        steps,
        amsgrad=False,
        maximize=False,
        grad_scale=None,
        found_inf=None,
        **options,
    )


class FlatTensors:
    """Tensors of the given shapes, views of one flat tensor: copying or casting all of them is one operation."""

    def __init__(self, shapes: list[tuple[int, ...]], dtype: th.dtype, device: th.device):
        sizes = [math.prod(shape) for shape in shapes]
        self.flat = th.empty(sum(sizes), dtype=dtype, device=device)
        self.views: list[th.Tensor] = []
        offset = 0
        for shape, size in zip(shapes, sizes):
            self.views.append(self.flat[offset : offset + size].view(shape))
            offset += size


class MlpStack:
    """``n`` ReLU MLPs of one architecture (the critics, the critic targets, or one actor), stacked.

    ``weights[l]`` has shape ``(n, out, in)`` and ``biases[l]`` ``(n, out)``, all views of one flat tensor, and network
    ``i``'s layer ``l`` parameters are views of ``weights[l][i]`` and ``biases[l][i]``: the same memory. So the
    critics go through a layer in one batched product, and casting or copying every weight is one operation.
    Rebinds itself when a parameter's memory is replaced behind its back (``Module.to(device)``).
    """

    def __init__(self, networks: list[list[nn.Linear]]):
        self.layers = networks
        self._low_precision: dict[th.dtype, FlatTensors] = {}
        self._bind()

    def _shapes(self) -> list[tuple[int, ...]]:
        n = len(self.layers)
        return [
            shape
            for lin in self.layers[0]
            for shape in ((n, *lin.weight.shape), (n, *lin.bias.shape))  # type: ignore[union-attr]
        ]

    def _bind(self) -> None:
        first = self.layers[0][0].weight
        self.store = FlatTensors(self._shapes(), first.dtype, first.device)
        self.weights, self.biases = self.store.views[0::2], self.store.views[1::2]
        for depth in range(len(self.weights)):
            for i, net in enumerate(self.layers):
                lin = net[depth]
                self.weights[depth][i].copy_(lin.weight.detach())
                self.biases[depth][i].copy_(lin.bias.detach())
                lin.weight.data = self.weights[depth][i]
                lin.bias.data = self.biases[depth][i]
        self._pointers = self._current_pointers()
        self._low_precision.clear()

    def _current_pointers(self) -> list[int]:
        return [p.data_ptr() for p in self.parameters()]

    def parameters(self) -> list[nn.Parameter]:
        """Every parameter, network by network, layer by layer, weight then bias."""
        return [p for net in self.layers for lin in net for p in (lin.weight, lin.bias)]  # type: ignore[misc]

    def ensure_bound(self) -> None:
        if self._current_pointers() != self._pointers:
            self._bind()

    def cast(self, dtype: th.dtype) -> tuple[list[th.Tensor], list[th.Tensor]]:
        """The stacked weights and biases in ``dtype``: themselves, or a copy refreshed in place (one operation)."""
        if dtype == self.store.flat.dtype:
            return self.weights, self.biases
        copy = self._low_precision.get(dtype)
        if copy is None:
            copy = self._low_precision[dtype] = FlatTensors(self._shapes(), dtype, self.store.flat.device)
        copy.flat.copy_(self.store.flat)
        return copy.views[0::2], copy.views[1::2]

    def assign_grads(self, weight_grads: list[th.Tensor], bias_grads: list[th.Tensor]) -> None:
        """``param.grad`` of every parameter: its view of the stacked gradients (shaped like the weights)."""
        for i, net in enumerate(self.layers):
            for depth, lin in enumerate(net):
                lin.weight.grad = weight_grads[depth][i]
                lin.bias.grad = bias_grads[depth][i]

    @staticmethod
    def forward(
        x: th.Tensor, all_weights: list[th.Tensor], all_biases: list[th.Tensor]
    ) -> tuple[th.Tensor, list[th.Tensor]]:
        """Every network's output, shape (n, batch, out), and each layer's input (for backward).

        ``x`` is one input for every network, (batch, in), or one per network, (n, batch, in).
        """
        inputs = [x]
        # One batched product, a shared input broadcast: (n, batch, out).
        h = th.baddbmm(
            all_biases[0].unsqueeze(1), x if x.dim() == 3 else x.expand(all_weights[0].shape[0], *x.shape), all_weights[0].mT
        )
        for weights, biases in zip(all_weights[1:], all_biases[1:]):
            h = h.relu_()
            inputs.append(h)
            h = th.baddbmm(biases.unsqueeze(1), h, weights.mT)
        return h, inputs

    @staticmethod
    def backward(
        grad_out: th.Tensor, inputs: list[th.Tensor], all_weights: list[th.Tensor]
    ) -> tuple[list[th.Tensor], list[th.Tensor]]:
        """Weight and bias gradients, stacked like the weights, in fp32, from d loss / d output (n, batch, out)."""
        weight_grads: list[th.Tensor] = []
        bias_grads: list[th.Tensor] = []
        grad = grad_out
        for depth in range(len(all_weights) - 1, -1, -1):
            h = inputs[depth] if depth > 0 or inputs[0].dim() == 3 else inputs[0].expand(grad.shape[0], *inputs[0].shape)
            weight_grads.append(th.bmm(grad.mT, h).float())
            bias_grads.append(grad.sum(dim=1).float())
            if depth > 0:
                grad = _relu_backward(_matmul(grad, all_weights[depth]), h, 0)
        return weight_grads[::-1], bias_grads[::-1]


Weights = tuple[list[th.Tensor], list[th.Tensor]]


def relu_mlp(
    weights: list[th.Tensor], biases: list[th.Tensor], x: th.Tensor, linear_relu: Any = _linear_relu
) -> tuple[th.Tensor, list[th.Tensor]]:
    """A ReLU MLP's output before any final activation, and each layer's input (for the backward pass)."""
    inputs = [x]
    for w, b in zip(weights[:-1], biases[:-1]):
        x = linear_relu(x, w, b)
        inputs.append(x)
    return th.addmm(biases[-1], x, weights[-1].t()), inputs


def _actor_forward(weights: Weights, obs: th.Tensor) -> tuple[th.Tensor, list[th.Tensor]]:
    """pi(s) in [-1, 1] and each layer's input, from the actor's stacked (1, out, in) weights."""
    out, inputs = relu_mlp([w[0] for w in weights[0]], [b[0] for b in weights[1]], obs)
    return out.tanh_(), inputs


def compute_dtype_batch(batch: Any, dtype: th.dtype) -> tuple[th.Tensor, ...]:
    """(observations, actions, next_observations, rewards, dones) of a replay batch, the first three in ``dtype``.

    Cast before, not inside, the compiled functions: in bf16 on a CPU with AMX (torch 2.13), a matrix product whose
    left operand is a row-strided view (a row stride larger than its width) reads the columns past the view's width:
    finite values there leave the result right, NaN ones make it NaN. Compiled, an observation cast inside the graph
    is written straight into the concatenation ``[s, a]`` as such a view and read by the actor's first product while
    the action columns are still uninitialised memory: a NaN target now and then, from the first step on (the
    regression test is in ``tests/unit/test_mlp_update.py``, the reproduction in docs/performance.md). An input of the
    graph is copied into the concatenation instead.
    """
    return (
        batch.observations.to(dtype),
        batch.actions.to(dtype),
        batch.next_observations.to(dtype),
        batch.rewards,
        batch.dones,
    )


def critic_gradients(
    batch: tuple[th.Tensor, ...],
    discounts: th.Tensor | float,
    noise: th.Tensor | None,
    noise_clip: float,
    clipped_double_q: bool,
    actor_target: Weights,
    critic_target: Weights,
    critic: Weights,
) -> tuple[list[th.Tensor], list[th.Tensor], dict[str, th.Tensor]]:
    """Steps 5 to 11 and the critics' gradients: a pure function of its inputs (so it can be compiled).

    The products run in the weights' dtype (bf16 with ``bf16=True``): pass the weights, the observations and the
    actions already in it (see :func:`compute_dtype_batch`); rewards and dones stay fp32.

    :param batch: (observations, actions, next_observations, rewards, dones)
    :param noise: the target policy smoothing noise before clipping, sigma N(0, 1), or None without smoothing
    :return: the critics' weight and bias gradients (fp32, stacked like the weights) and the logged statistics
    """
    obs, actions, next_obs, rewards, dones = batch
    dtype = critic[0][0].dtype
    next_actions, _ = _actor_forward(actor_target, next_obs)  # step 5
    if noise is not None:  # step 6
        next_actions = next_actions + noise.clamp(-noise_clip, noise_clip)
    next_actions = next_actions.clamp(-1.0, 1.0)
    next_q, _ = MlpStack.forward(th.cat([next_obs, next_actions], dim=1), *critic_target)  # step 7
    next_q = next_q.min(dim=0).values if clipped_double_q else next_q[0]  # step 8
    target_q = rewards + (1.0 - dones) * discounts * next_q.float()  # step 9
    obs_actions = th.cat([obs, actions], dim=1)
    current_q, inputs = MlpStack.forward(obs_actions, *critic)  # step 10
    td_errors = current_q.float() - target_q.unsqueeze(0)  # (n_critics, batch, 1)
    loss = td_errors.square().mean(dim=(1, 2)).sum()  # step 11: sum_i MSE(Q_i, y)
    # d loss / d Q_i = 2 (Q_i - y) / batch
    grads = MlpStack.backward((td_errors * (2.0 / td_errors.shape[1])).to(dtype), inputs, critic[0])
    info = {"critic_loss": loss, "target_q": target_q.mean()}
    q_means = current_q.float().mean(dim=(1, 2))
    for i in range(current_q.shape[0]):
        info[f"q{i + 1}"] = q_means[i]
    return grads[0], grads[1], info


def actor_gradients(obs: th.Tensor, actor: Weights, critic: Weights) -> tuple[list[th.Tensor], list[th.Tensor], th.Tensor]:
    """Step 13's gradient: J = -mean Q_1(s, pi(s)), back through the first critic to the action only.

    The products run in the weights' dtype: pass the weights and the observations already in it.

    :return: the actor's weight and bias gradients (fp32, stacked like the weights) and the loss
    """
    dtype = critic[0][0].dtype
    actions, actor_inputs = _actor_forward(actor, obs)
    weights = [w[0] for w in critic[0]]
    q, critic_inputs = relu_mlp(weights, [b[0] for b in critic[1]], th.cat([obs, actions], dim=1))
    q = q.float()  # (batch, 1)
    loss = -q.mean()
    # d J / d Q_1 = -1 / batch, back through the critic's layers to its input
    grad = th.full_like(q, -1.0 / q.shape[0]).to(dtype)
    for depth in range(len(weights) - 1, 0, -1):
        grad = _relu_backward(_matmul(grad, weights[depth]), critic_inputs[depth], 0)
    grad = grad @ weights[0][:, obs.shape[1] :]  # d J / d a: the action columns of the first layer only
    grad = _tanh_backward(grad, actions)
    weight_grads: list[th.Tensor] = []
    bias_grads: list[th.Tensor] = []
    for depth in range(len(actor[0]) - 1, -1, -1):
        h = actor_inputs[depth]
        weight_grads.append((grad.t() @ h).float().unsqueeze(0))
        bias_grads.append(grad.sum(dim=0).float().unsqueeze(0))
        if depth > 0:
            grad = _relu_backward(grad @ actor[0][depth][0], h, 0)
    return weight_grads[::-1], bias_grads[::-1], loss


class MlpUpdate(requirements.FastPath):
    """Steps 5 to 15 of TD3 for MLP policies, gradients by hand (see the module's docstring).

    It replaces the hooks in :attr:`replaces` (their arithmetic is written out here) and calls the model's own
    ``sample_batch``, ``should_update_actor``, ``update_actor_target`` and ``update_critic_target``.

    Called as ``update(batch, update_actor)``, like :meth:`TD3X.update_from_batch`, and returns the same statistics.
    With ``compile=True`` (``compile_update=True``), :func:`critic_gradients` and :func:`actor_gradients` are compiled
    with ``torch.compile`` (one graph each); sampling, the random numbers, the optimizers and the target updates stay
    eager.
    """

    replaces = (
        "gradient_step",
        "update_from_batch",
        "compute_target_q",
        "target_actions",
        "target_policy_smoothing_noise",
        "next_q_values",
        "clipped_double_q_value",
        "td_target",
        "current_q_values",
        "critic_loss",
        "optimize_critic",
        "actor_loss",
        "optimize_actor",
    )

    def __init__(self, model: TD3X, compile: bool = False):
        self.model = model
        self._critic_gradients = th.compile(critic_gradients, dynamic=False) if compile else critic_gradients
        self._actor_gradients = th.compile(actor_gradients, dynamic=False) if compile else actor_gradients
        self.actor = MlpStack([relu_mlp_layers(model.actor.mu, nn.Tanh)])  # type: ignore[list-item]
        self.actor_target = MlpStack([relu_mlp_layers(model.actor_target.mu, nn.Tanh)])  # type: ignore[list-item]
        self.critic = MlpStack([relu_mlp_layers(q, None) for q in model.critic.q_networks])  # type: ignore[misc]
        self.critic_target = MlpStack([relu_mlp_layers(q, None) for q in model.critic_target.q_networks])  # type: ignore[misc]
        self.dtype = th.float32

    @classmethod
    def requirements(cls, model: TD3X) -> list[str]:
        """Every assumption of this update that ``model`` breaks (empty: it computes what the hooks compute)."""
        reasons = changed_hooks(model, cls.replaces)
        reasons += requirements.stock_mlp_actor(model.actor, model.observation_space, "actor")
        reasons += requirements.stock_mlp_actor(model.actor_target, model.observation_space, "actor_target")
        reasons += requirements.stock_mlp_critic(model.critic, "critic")
        reasons += requirements.stock_mlp_critic(model.critic_target, "critic_target")
        reasons += requirements.module_hooks(model.policy, "policy")
        for role in ("actor", "critic", "actor_target", "critic_target"):
            reasons += requirements.plain_parameters(getattr(model, role), role)
        reasons += requirements.no_buffers(model.policy)
        return list(dict.fromkeys(reasons))  # in order, without repeats

    # ------------------------------------------------------------------------------------------------------------
    def __call__(self, batch: Any, update_actor: bool) -> Infos:
        for stack in (self.actor, self.actor_target, self.critic, self.critic_target):
            stack.ensure_bound()
        # bf16=True: the products and activations in bf16 (as under autocast), the weights, their gradients, the
        # optimizers and the losses in fp32.
        self.dtype = th.bfloat16 if self.model.bf16 else th.float32
        with th.no_grad():
            critic_info = self._update_critics(batch)  # steps 5-12
            if not update_actor:
                return critic_info, {}
            actor_info = self._update_actor(batch.observations)  # step 13
        self.model.update_critic_target()  # step 15
        self.model.update_actor_target()  # step 14
        return critic_info, actor_info

    def _weights(self, stack: MlpStack) -> Weights:
        # Cast here, one operation per stack, also when compiled (the graph's inputs are then already in the
        # compute dtype; see compute_dtype_batch for what a cast inside the graph can do in bf16).
        return stack.cast(self.dtype)

    def _update_critics(self, batch: Any) -> dict[str, th.Tensor]:
        """Steps 5 to 12."""
        model = self.model
        noise = None
        if model.target_policy_smoothing:  # step 6's noise, drawn as randn_like(pi'(s')) draws it
            shape = (batch.next_observations.shape[0], self.actor_target.weights[-1].shape[1])  # (batch, action_dim)
            noise = th.randn(shape, dtype=self.dtype, device=batch.rewards.device) * model.target_policy_noise
        discounts = batch.discounts if getattr(batch, "discounts", None) is not None else model.gamma
        weight_grads, bias_grads, info = self._critic_gradients(
            compute_dtype_batch(batch, self.dtype),
            discounts,
            noise,
            float(model.target_noise_clip),
            bool(model.clipped_double_q),
            self._weights(self.actor_target),
            self._weights(self.critic_target),
            self._weights(self.critic),
        )
        self.critic.assign_grads(weight_grads, bias_grads)
        optimizer_step(model.critic.optimizer)  # step 12
        return info

    def _update_actor(self, obs: th.Tensor) -> dict[str, th.Tensor]:
        """Step 13 (with the critics as updated by step 12)."""
        weight_grads, bias_grads, loss = self._actor_gradients(
            obs.to(self.dtype), self._weights(self.actor), self._weights(self.critic)
        )
        self.actor.assign_grads(weight_grads, bias_grads)
        optimizer_step(self.model.actor.optimizer)
        return {"actor_loss": loss}
