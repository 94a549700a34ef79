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
parameters, no batch norm). With ``bf16=True`` the products run in bf16 with fp32 weights, gradients and optimizer,
as under autocast. Anything else runs the hooks with autograd, as before. Steps 14 and 15 are the model's own hooks,
overridden or not. :func:`critic_gradients` and :func:`actor_gradients` are pure functions of their inputs, with a
leading seed axis, which ``compile_update=True`` compiles.

One implementation for one model and for many: a lone TD3X runs it with one model, a
:class:`~sb3_td3x.SeedBatch` with its N models (see :class:`MlpUpdate`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch as th
from torch import nn

from sb3_td3x.common.torch_internals import fused_adam_kernel, global_optimizer_hooks, linear_relu_kernel, optimizer_step_hooks
from sb3_td3x.td3x.hooks import changed_hooks
from sb3_td3x.td3x.update_paths import requirements
from sb3_td3x.td3x.update_paths.requirements import relu_mlp_layers

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]

_relu_backward = th.ops.aten.threshold_backward
_tanh_backward = th.ops.aten.tanh_backward


def _mm(a: th.Tensor, b: th.Tensor) -> th.Tensor:
    """``a @ b`` over a leading axis of networks, (n, i, k) @ (n, k, j): one batched product, for one network too (on
    a CPU as fast as the 2-D product at these sizes, without the views around it); an inner dimension of 1 (back
    through an output layer) as the broadcast multiply it is."""
    if a.shape[-1] == 1:
        return a * b
    return th.bmm(a, b)


def addmm_relu(x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
    """relu(x W^T + b) with the kernels of ``nn.Linear`` and ``nn.ReLU``."""
    return th.addmm(bias, x, weight.t()).relu_()


def _linear_relu(x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
    """relu(x W^T + b). On a CPU, oneDNN's linear with the ReLU fused into it (what torch.compile's CPU backend
    calls): one pass over the output instead of two, and faster than MKL's addmm at these sizes
    (docs/performance.md). Under torch.compile, addmm and relu (Inductor lowers them itself)."""
    if x.device.type != "cpu" or th.compiler.is_compiling():
        return addmm_relu(x, weight, bias)
    kernel, dtypes = linear_relu_kernel()
    if kernel is not None and x.dtype in dtypes:
        return kernel(x, weight, bias, "relu", [], "")
    return addmm_relu(x, weight, bias)


def step_optimizers(optimizers: list[th.optim.Optimizer]) -> None:
    """``optimizer.step()`` of each; the fused Adams (or AdamWs) of equal options as one call of the kernel their
    ``step()`` ends in.

    ``Adam.step`` spends about as long in Python (grouping the tensors by device, checking its options) as its fused
    kernel takes on a critic. When nothing can differ (see :func:`fused_adam_call`) the kernel is called straight
    away, once for the optimizers of all seeds: it is elementwise, so each tensor gets what its own ``step()`` gives.
    """
    groups: dict[tuple[Any, ...], list[Any]] = {}
    for optimizer in optimizers:
        call = fused_adam_call(optimizer)
        if call is None:
            optimizer.step()
        else:
            groups.setdefault((call[0], *call[1].values()), []).append(call)
    for calls in groups.values():
        run_fused_adam(calls)


class _AdamTensors:
    """The state tensors of a fused Adam's parameters, looked up once: still valid while the optimizer keeps the same
    state dictionary, parameter list and state tensors (``load_state_dict`` replaces them: looked up again).

    Each parameter's ``step`` counter becomes a view of one tensor of all of them, with the same values, so that the
    step that precedes the kernel is one addition instead of one per parameter (a ``step()`` through the optimizer
    increments the views in place, as it increments its own tensors)."""

    __slots__ = ("counters", "entries", "exp_avg_sqs", "exp_avgs", "params", "state", "steps")

    def __init__(self, optimizer: th.optim.Optimizer, params: list[th.Tensor], states: list[dict[str, Any]]):
        self.state, self.params = optimizer.state, params
        self.counters = th.stack([state["step"] for state in states])
        for k, state in enumerate(states):
            state["step"] = self.counters[k]
        self.entries = states
        self.exp_avgs = [state["exp_avg"] for state in states]
        self.exp_avg_sqs = [state["exp_avg_sq"] for state in states]
        self.steps = [state["step"] for state in states]

    def valid(self, optimizer: th.optim.Optimizer, params: list[th.Tensor]) -> bool:
        return (
            optimizer.state is self.state
            and params is self.params
            and len(params) == len(self.entries)  # a list grown in place
            and all(
                s["exp_avg"] is m and s["exp_avg_sq"] is v and s["step"] is c
                for s, m, v, c in zip(self.entries, self.exp_avgs, self.exp_avg_sqs, self.steps)
            )
        )


_ADAM_TENSORS = "_sb3_td3x_adam_tensors"


def fused_adam_call(optimizer: th.optim.Optimizer) -> tuple[Any, dict[str, Any], _AdamTensors, list[th.Tensor]] | None:
    """The kernel a fused Adam or AdamW's ``step()`` ends in, its options, its state tensors and the gradients, when
    nothing can differ (one parameter group, fused, no AMSGrad, maximize, differentiable or capturable, a float
    learning rate, no step hooks, every parameter with a gradient and a state made by a first ``step()``); else
    None."""
    if not isinstance(optimizer, th.optim.Adam) or len(optimizer.param_groups) != 1:
        return None
    if optimizer_step_hooks(optimizer) is not False or global_optimizer_hooks() is not False:
        return None
    group = optimizer.param_groups[0]
    if not group.get("fused") or isinstance(group["lr"], th.Tensor):
        return None
    if group["amsgrad"] or group["maximize"] or group["differentiable"] or group["capturable"]:
        return None
    params = group["params"]
    grads = [p.grad for p in params]
    if not params or any(g is None for g in grads):
        return None
    tensors = optimizer.__dict__.get(_ADAM_TENSORS)
    if tensors is None or not tensors.valid(optimizer, params):
        states = [optimizer.state.get(p) for p in params]
        if not all(states) or any(state["step"].shape != () for state in states):  # type: ignore[union-attr]
            return None
        tensors = optimizer.__dict__[_ADAM_TENSORS] = _AdamTensors(optimizer, params, states)  # type: ignore[arg-type]
    kernel = fused_adam_kernel(bool(group.get("decoupled_weight_decay")))
    if kernel is None:
        return None
    beta1, beta2 = group["betas"]
    options = {"lr": group["lr"], "beta1": beta1, "beta2": beta2, "weight_decay": group["weight_decay"], "eps": group["eps"]}
    return kernel, options, tensors, grads  # type: ignore[return-value]


def run_fused_adam(calls: list[tuple[Any, dict[str, Any], _AdamTensors, list[th.Tensor]]]) -> None:
    """The calls of :func:`fused_adam_call`, all of one kernel and options: each optimizer's step counters
    incremented (one addition each), then one kernel call over all their tensors (the update is elementwise: each
    tensor's is what its own call computes)."""
    kernel, options = calls[0][0], calls[0][1]
    for call in calls:
        call[2].counters.add_(1)
    params = [p for call in calls for p in call[2].params]
    grads = [g for call in calls for g in call[3]]
    exp_avgs = [t for call in calls for t in call[2].exp_avgs]
    exp_avg_sqs = [t for call in calls for t in call[2].exp_avg_sqs]
    steps = [t for call in calls for t in call[2].steps]
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
        self._params = self.parameters()
        self._pointers = self._current_pointers()
        self._low_precision.clear()

    def _current_pointers(self) -> list[int]:
        return [p.data_ptr() for p in self._params]

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
        for depth, (weight_grad, bias_grad) in enumerate(zip(weight_grads, bias_grads)):
            for net, w, b in zip(self.layers, weight_grad.unbind(0), bias_grad.unbind(0)):
                net[depth].weight.grad = w
                net[depth].bias.grad = b

    @staticmethod
    def forward(
        x: th.Tensor, all_weights: list[th.Tensor], all_biases: list[th.Tensor]
    ) -> tuple[th.Tensor, list[th.Tensor]]:
        """Every network's output, shape (n, batch, out), and each layer's input (for backward), from ``x``, one
        input per network, (n, batch, in) (an expanded view for an input they share).

        One network runs as 2-D products (on a CPU oneDNN's linear with the ReLU fused into it), more as one batched
        product per layer.
        """
        if all_weights[0].shape[0] == 1:
            out, inputs = relu_mlp([w[0] for w in all_weights], [b[0] for b in all_biases], x[0])
            return out.unsqueeze(0), [h.unsqueeze(0) for h in inputs]
        inputs = [x]
        h = th.baddbmm(all_biases[0].unsqueeze(1), x, all_weights[0].mT)
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
            h = inputs[depth]
            weight_grads.append(_mm(grad.mT, h).float())
            bias_grads.append(grad.sum(dim=1).float())
            if depth > 0:
                grad = _relu_backward(_mm(grad, all_weights[depth]), h, 0)
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


def _per_critic(x: th.Tensor, n_critics: int) -> th.Tensor:
    """(G, batch, in) -> (G * n_critics, batch, in): each seed's input for each of its critics, seed-major (one seed's
    as an expanded view, as a lone model's critics share their input)."""
    return x.expand(n_critics, *x.shape[1:]) if x.shape[0] == 1 else x.repeat_interleave(n_critics, dim=0)


def _first_critic(weights: Weights, n_critics: int) -> Weights:
    """Each seed's first critic, (G, out, in), from all critics' stacked (G * n_critics, out, in) weights (views)."""
    return (
        [w.unflatten(0, (-1, n_critics))[:, 0] for w in weights[0]],
        [b.unflatten(0, (-1, n_critics))[:, 0] for b in weights[1]],
    )


def critic_gradients(
    batch: tuple[th.Tensor, ...],
    discounts: th.Tensor | float,
    noise: th.Tensor | None,
    noise_clip: float,
    clipped_double_q: bool,
    n_critics: int,
    actor_target: Weights,
    critic_target: Weights,
    critic: Weights,
) -> tuple[list[th.Tensor], list[th.Tensor], dict[str, th.Tensor]]:
    """Steps 5 to 11 and the critics' gradients of G seeds: a pure function of its inputs (so it can be compiled).

    The products run in the weights' dtype (bf16 with ``bf16=True``): pass the weights, the observations and the
    actions already in it (see :func:`compute_dtype_batch`); rewards and dones stay fp32.

    :param batch: (observations, actions, next_observations, rewards, dones), each (G, batch, dim)
    :param discounts: gamma, or the n-step discounts (G, batch, 1)
    :param noise: the target policy smoothing noise before clipping, sigma N(0, 1), (G, batch, action_dim), or None
    :return: the critics' weight and bias gradients (fp32, stacked like the weights, (G * n_critics, ...)) and the
        statistics per seed: ``critic_loss`` and ``target_q`` (G,), ``q`` (G, n_critics)
    """
    obs, actions, next_obs, rewards, dones = batch
    n_seeds, batch_size = obs.shape[:2]
    dtype = critic[0][0].dtype
    next_actions, _ = MlpStack.forward(next_obs, *actor_target)  # step 5: (G, batch, action_dim)
    next_actions = next_actions.tanh_()
    if noise is not None:  # step 6
        next_actions = next_actions + noise.clamp(-noise_clip, noise_clip)
    next_actions = next_actions.clamp(-1.0, 1.0)
    next_q, _ = MlpStack.forward(_per_critic(th.cat([next_obs, next_actions], dim=2), n_critics), *critic_target)
    next_q = next_q.unflatten(0, (n_seeds, n_critics))  # step 7: (G, n_critics, batch, 1)
    next_q = next_q.min(dim=1).values if clipped_double_q else next_q[:, 0]  # step 8: (G, batch, 1)
    target_q = rewards + (1.0 - dones) * discounts * next_q.float()  # step 9
    current_q, inputs = MlpStack.forward(_per_critic(th.cat([obs, actions], dim=2), n_critics), *critic)  # step 10
    current_q = current_q.float().unflatten(0, (n_seeds, n_critics))
    td_errors = current_q - target_q.unsqueeze(1)  # (G, n_critics, batch, 1)
    loss = td_errors.square().mean(dim=(2, 3)).sum(dim=1)  # step 11, per seed: sum_i MSE(Q_i, y)
    # d loss / d Q_i = 2 (Q_i - y) / batch
    grads = MlpStack.backward((td_errors * (2.0 / batch_size)).to(dtype).flatten(0, 1), inputs, critic[0])
    info = {"critic_loss": loss, "target_q": target_q.mean(dim=(1, 2)), "q": current_q.mean(dim=(2, 3))}
    return grads[0], grads[1], info


def actor_gradients(
    obs: th.Tensor, n_critics: int, actor: Weights, critic: Weights
) -> tuple[list[th.Tensor], list[th.Tensor], th.Tensor]:
    """Step 13's gradient of G seeds: J = -mean Q_1(s, pi(s)), back through the first critic to the action only.

    The products run in the weights' dtype: pass the weights and the observations already in it.

    :param obs: (G, batch, obs_dim)
    :return: the actors' weight and bias gradients (fp32, stacked like the weights, (G, ...)) and the losses (G,)
    """
    dtype = critic[0][0].dtype
    actions, actor_inputs = MlpStack.forward(obs, *actor)  # (G, batch, action_dim)
    actions = actions.tanh_()
    weights, biases = _first_critic(critic, n_critics)
    q, critic_inputs = MlpStack.forward(th.cat([obs, actions], dim=2), weights, biases)
    q = q.float()  # (G, batch, 1)
    loss = -q.mean(dim=(1, 2))
    # d J / d Q_1 = -1 / batch, back through each seed's first critic to its input
    grad = th.full_like(q, -1.0 / q.shape[1]).to(dtype)
    for depth in range(len(weights) - 1, 0, -1):
        grad = _relu_backward(_mm(grad, weights[depth]), critic_inputs[depth], 0)
    grad = _mm(grad, weights[0][:, :, obs.shape[2] :])  # d J / d a: the action columns of the first layer only
    grad = _tanh_backward(grad, actions)
    weight_grads, bias_grads = MlpStack.backward(grad, actor_inputs, actor[0])
    return weight_grads, bias_grads, loss


# What enters the shared arithmetic of many models: it must be the same in all of them.
SHARED_SETTINGS = (
    "gamma",
    "n_steps",
    "target_policy_smoothing",
    "target_policy_noise",
    "target_noise_clip",
    "clipped_double_q",
    "bf16",
    "update_compiled",
    "flush_denormals",
)


class MlpUpdate(requirements.FastPath):
    """Steps 5 to 15 of TD3 for MLP policies, gradients by hand (see the module's docstring), for one model or many.

    It replaces the hooks in :attr:`replaces` (their arithmetic is written out here) and calls the model's own
    ``sample_batch``, ``should_update_actor``, ``update_actor_target`` and ``update_critic_target``.

    Called as ``update(batch, update_actor)``, like :meth:`TD3X.update_from_batch`, and returns the same statistics.
    With ``compile=True`` (``update_compiled``: ``compile_update=True``, or auto on a long run), :func:`critic_gradients` and :func:`actor_gradients` are compiled
    with ``torch.compile`` (one graph each); sampling, the random numbers, the optimizers and the target updates stay
    eager.

    **Many models** (one per seed, :class:`~sb3_td3x.SeedBatch`): :meth:`step` does one gradient step of each, from
    one batch each. Each role's weights of all models live in one :class:`MlpStack` (a leading seed axis; each
    model's parameters are views of it, so its optimizers, ``save`` and ``load`` see its own). The products of
    ``seeds_per_product`` seeds run as one call: by default one on a CPU, so each seed runs the kernels, shapes and
    order of operations of its lone run and computes its numbers bit for bit; all of them on a GPU, where a seed
    then equals its lone run to float rounding. The fused Adam steps and stock target updates of all seeds run as
    one call each (elementwise: bit for bit either way). Each seed's noise comes from its own model's streams.

    :param models: a model, or the models of a batch (see :meth:`why_not_together`)
    :param around: ``around(i)``, a context entered around model ``i``'s target-update hooks when they are its own
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

    def __init__(
        self,
        models: TD3X | Sequence[TD3X],
        compile: bool = False,
        seeds_per_product: int | None = None,
        around: Callable[[int], contextlib.AbstractContextManager] | None = None,
    ):
        self.models = list(models) if isinstance(models, (list, tuple)) else [models]
        self.model = self.models[0]
        self.around = around or (lambda i: contextlib.nullcontext())
        self._critic_gradients = th.compile(critic_gradients, dynamic=False) if compile else critic_gradients
        self._actor_gradients = th.compile(actor_gradients, dynamic=False) if compile else actor_gradients
        self.n_critics = len(self.model.critic.q_networks)
        if seeds_per_product is None:
            # On a CPU a product over many seeds outgrows the caches (and would round as no lone run does).
            seeds_per_product = len(self.models) if self.model.device.type == "cuda" else 1
        self.seeds_per_product = seeds_per_product
        ms = self.models
        self.actor = MlpStack([relu_mlp_layers(m.actor.mu, nn.Tanh) for m in ms])  # type: ignore[misc]
        self.actor_target = MlpStack([relu_mlp_layers(m.actor_target.mu, nn.Tanh) for m in ms])  # type: ignore[misc]
        # Seed-major: network s * n_critics + k is seed s's critic k.
        self.critic = MlpStack([relu_mlp_layers(q, None) for m in ms for q in m.critic.q_networks])  # type: ignore[misc]
        self.critic_target = MlpStack([relu_mlp_layers(q, None) for m in ms for q in m.critic_target.q_networks])  # type: ignore[misc]
        self._stock_targets = [not changed_hooks(m, ("update_critic_target", "update_actor_target")) for m in ms]
        if len(ms) > 1:
            for lin in {id(lin): lin for stack in self._stacks() for net in stack.layers for lin in net}.values():
                if _compact_state_dict not in lin._state_dict_hooks.values():
                    lin.register_state_dict_post_hook(_compact_state_dict)
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

    @classmethod
    def why_not_together(cls, models: Sequence[TD3X]) -> str | None:
        """Why these models cannot share one update (every reason, joined), or ``None``: each must be one this
        update trains (``mlp_update=True``, not in CUDA graphs), distinct, with the architecture, the device and
        :data:`SHARED_SETTINGS` of the first."""
        reasons = [f"model {i}: {r}" for i, m in enumerate(models) if (r := cls.why_not(m)) is not None]
        reasons += [f"model {i}: mlp_update=False" for i, m in enumerate(models) if not m.mlp_update]
        reasons += [
            f"model {i}: CUDA graphs (cuda_graph={m.cuda_graph_request})" for i, m in enumerate(models) if m.cuda_graph
        ]
        params = [p.data_ptr() for m in models for p in m.policy.parameters()]
        if len({id(m) for m in models}) != len(models) or len(set(params)) != len(params):
            reasons.append("a model is given twice, or models share parameters")
        first = models[0]
        for i, m in enumerate(models[1:], start=1):
            if _architecture(m) != _architecture(first) or m.device != first.device:
                reasons.append(f"model {i}'s networks or device differ from model 0's")
            reasons += [
                f"model {i}'s {name} is {getattr(m, name)!r}, model 0's {getattr(first, name)!r}"
                for name in SHARED_SETTINGS
                if getattr(m, name) != getattr(first, name)
            ]
        return "; ".join(reasons) if reasons else None

    def _stacks(self) -> tuple[MlpStack, ...]:
        return (self.actor, self.actor_target, self.critic, self.critic_target)

    # ------------------------------------------------------------------------------------------------------------
    def __call__(self, batch: Any, update_actor: bool) -> Infos:
        return self.step([batch], [update_actor])[0]

    def step(self, batches: Sequence[Any], update_actor: Sequence[bool]) -> list[Infos]:
        """Steps 5 to 15 of every model, model ``i`` on ``batches[i]``, its actor and targets when ``update_actor[i]``.
        Returns each model's statistics."""
        for stack in self._stacks():
            stack.ensure_bound()
        # bf16=True: the products and activations in bf16 (as under autocast), the weights, their gradients, the
        # optimizers and the losses in fp32.
        self.dtype = th.bfloat16 if self.model.bf16 else th.float32
        updating = [i for i, update in enumerate(update_actor) if update]
        with th.no_grad():
            critic_infos = self._update_critics(batches)  # steps 5-12
            actor_infos = self._update_actors(batches, updating)  # step 13
        self._update_targets(updating)  # steps 15 and 14
        return list(zip(critic_infos, actor_infos))

    def _groups(self) -> list[tuple[int, int]]:
        """The seeds whose products run as one call: ``a`` to ``b - 1`` for each ``(a, b)``."""
        n, size = len(self.models), self.seeds_per_product
        return [(a, min(a + size, n)) for a in range(0, n, size)]

    def _seeds(self, stack: MlpStack, a: int, b: int, per_seed: int = 1) -> Weights:
        """Seeds ``a`` to ``b - 1``'s weights and biases (views), ``per_seed`` networks each, in the compute dtype
        (cast here, one operation per stack, so that a compiled graph's inputs are already in it)."""
        weights, biases = stack.cast(self.dtype)
        if a == 0 and b == len(self.models):
            return weights, biases
        return [w[a * per_seed : b * per_seed] for w in weights], [x[a * per_seed : b * per_seed] for x in biases]

    def _noise(self, model: TD3X, batch: Any) -> th.Tensor:
        """Step 6's noise, drawn as ``randn_like(pi'(s'))`` draws it, from the model's own torch stream."""
        shape = (batch.next_observations.shape[0], self.actor_target.weights[-1].shape[1])  # (batch, action_dim)
        device = batch.rewards.device
        generator = model.random_streams.torch(device)
        return th.randn(shape, dtype=self.dtype, device=device, generator=generator) * model.target_policy_noise

    def _update_critics(self, batches: Sequence[Any]) -> list[dict[str, th.Tensor]]:
        """Steps 5 to 12 of every model."""
        first = self.model
        inputs = [compute_dtype_batch(batch, self.dtype) for batch in batches]
        noises = [self._noise(m, b) for m, b in zip(self.models, batches)] if first.target_policy_smoothing else None
        with_discounts = getattr(batches[0], "discounts", None) is not None
        parts = []
        for a, b in self._groups():
            parts.append(
                self._critic_gradients(
                    tuple(_seed_axis([x[k] for x in inputs[a:b]]) for k in range(5)),
                    _seed_axis([batch.discounts for batch in batches[a:b]]) if with_discounts else first.gamma,
                    None if noises is None else _seed_axis(noises[a:b]),
                    float(first.target_noise_clip),
                    bool(first.clipped_double_q),
                    self.n_critics,
                    self._seeds(self.actor_target, a, b),
                    self._seeds(self.critic_target, a, b, self.n_critics),
                    self._seeds(self.critic, a, b, self.n_critics),
                )
            )
        weight_grads, bias_grads, info = _joined(parts)
        self.critic.assign_grads(weight_grads, bias_grads)
        step_optimizers([m.critic.optimizer for m in self.models])  # step 12
        infos = []
        for i in range(len(self.models)):
            seed_info = {"critic_loss": info["critic_loss"][i], "target_q": info["target_q"][i]}
            for k in range(self.n_critics):
                seed_info[f"q{k + 1}"] = info["q"][i, k]
            infos.append(seed_info)
        return infos

    def _update_actors(self, batches: Sequence[Any], updating: list[int]) -> list[dict[str, th.Tensor]]:
        """Step 13 of the models in ``updating`` (with the critics as updated by step 12)."""
        infos: list[dict[str, th.Tensor]] = [{} for _ in self.models]
        for a, b in self._groups():
            if not any(a <= i < b for i in updating):
                continue
            weight_grads, bias_grads, loss = self._actor_gradients(
                _seed_axis([batch.observations.to(self.dtype) for batch in batches[a:b]]),
                self.n_critics,
                self._seeds(self.actor, a, b),
                self._seeds(self.critic, a, b, self.n_critics),
            )
            for i in (i for i in updating if a <= i < b):
                for depth, lin in enumerate(self.actor.layers[i]):
                    lin.weight.grad = weight_grads[depth][i - a]
                    lin.bias.grad = bias_grads[depth][i - a]
                infos[i] = {"actor_loss": loss[i - a]}
        step_optimizers([self.models[i].actor.optimizer for i in updating])
        return infos

    def _update_targets(self, updating: list[int]) -> None:
        """Steps 15 and 14: the stock ones of equal ``tau`` as one ``_foreach_lerp_`` (what each model's ``_polyak``
        calls; no batch norm here, so nothing else to copy), overridden ones as written. When every model updates
        its stock targets with one ``tau``, that is one ``lerp_`` per stack over its flat tensor: the same
        elementwise arithmetic, on every target parameter of every model, in two calls."""
        taus = {float(self.models[i].tau) for i in updating}
        if len(updating) == len(self.models) and len(taus) == 1 and all(self._stock_targets):
            tau = taus.pop()
            with th.no_grad():
                for target, online in ((self.critic_target, self.critic), (self.actor_target, self.actor)):
                    target.store.flat.lerp_(online.store.flat, tau)
            return
        groups: dict[float, tuple[list[th.Tensor], list[th.Tensor]]] = {}
        for i in updating:
            model = self.models[i]
            if self._stock_targets[i]:
                targets, params = groups.setdefault(float(model.tau), ([], []))
                targets += [*model._critic_target_params, *model._actor_target_params]
                params += [*model._critic_params, *model._actor_params]
            else:
                with self.around(i):
                    model.update_critic_target()  # step 15
                    model.update_actor_target()  # step 14
        with th.no_grad():
            for tau, (targets, params) in groups.items():
                th._foreach_lerp_(targets, params, tau)


def _seed_axis(tensors: Sequence[th.Tensor]) -> th.Tensor:
    """The tensors of consecutive seeds along a new leading axis (one seed's as a view)."""
    return tensors[0].unsqueeze(0) if len(tensors) == 1 else th.stack(list(tensors))


def _joined(parts: list[tuple[Any, ...]]) -> tuple[Any, ...]:
    """The gradients and statistics of consecutive groups of seeds as one group's: concatenated on the seed axis."""
    if len(parts) == 1:
        return parts[0]

    def join(values: list[Any]) -> Any:
        if isinstance(values[0], dict):
            return {key: th.cat([v[key] for v in values]) for key in values[0]}
        return [th.cat([v[i] for v in values]) for i in range(len(values[0]))]

    return tuple(join([part[k] for part in parts]) for k in range(len(parts[0])))


def _architecture(model: TD3X) -> list[list[tuple[int, ...]] | None]:
    """The weight shapes of the actor and of each critic; None for a network that is not a ReLU MLP (``why_not``
    names it)."""
    nets = [relu_mlp_layers(model.actor.mu, nn.Tanh), *(relu_mlp_layers(q, None) for q in model.critic.q_networks)]
    return [None if net is None else [tuple(lin.weight.shape) for lin in net] for net in nets]


def _compact_state_dict(module: nn.Module, state_dict: dict[str, Any], prefix: str, local_metadata: Any) -> None:
    """A state-dict post-hook: a tensor that is a view of a larger storage (every seed's weights) is replaced by a
    copy of itself, so that ``torch.save`` (``model.save``) writes this model's weights only."""
    for name in ("weight", "bias"):
        value = state_dict.get(prefix + name)
        if (
            isinstance(value, th.Tensor)
            and not isinstance(value, nn.Parameter)  # state_dict(keep_vars=True): the Parameters themselves
            and value.untyped_storage().nbytes() > value.numel() * value.element_size()
        ):
            state_dict[prefix + name] = value.clone()
