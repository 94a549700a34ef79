"""Steps 5 to 15 for MLP policies with the gradients written out by hand: TD3X's default update.

For the networks TD3 is run with (ReLU MLPs, a tanh actor, flat observations) the backward passes are a few matrix
products, so :class:`MlpUpdate` computes them itself instead of recording an autograd graph:

- the critics are evaluated as one ensemble: their weights live in stacked tensors (``[n_critics, out, in]``) that
  the critics' own parameters are views of, so both critics (and both critic targets) go through each layer in one
  batched product (``baddbmm``), forward and backward, and the first layer's products are one ``addmm``;
- the actor loss back-propagates through the first critic to the action only, with no gradient for the critic's
  weights and none for the observation columns of its first layer;
- ReLU and tanh backwards are ``threshold_backward`` and ``tanh_backward``, the kernels autograd runs;
- the optimizers are the model's own: gradients are written into ``.grad`` and ``optimizer.step()`` is called, so any
  optimizer, schedule, save and load behave as with autograd.

It computes what :meth:`TD3X.update_from_batch` computes (the tests compare both to float rounding), from the same
batch and the same random numbers, so it replaces it only where that holds: :meth:`MlpUpdate.why_not` lists the
conditions (no hook of steps 5 to 13 overridden, ReLU MLPs with a flatten features extractor). With ``bf16=True``
the products run in bf16 with fp32 weights, gradients and optimizer, as under autocast. Anything
else runs the hooks with autograd, as before. Steps 14 and 15 are the model's own hooks, overridden or not.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch as th
import torch.optim.optimizer as _optim_module
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch import nn

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]

# The hooks whose arithmetic MlpUpdate writes out; overriding any of them switches it off.
REPLACED_HOOKS = (
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

_relu_backward = th.ops.aten.threshold_backward
_tanh_backward = th.ops.aten.tanh_backward


def _mlp_linears(mlp: nn.Module, final: type[nn.Module] | None) -> list[nn.Linear] | None:
    """The Linear layers of ``Linear, ReLU, ..., Linear[, final]``, or None for any other network."""
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


def _flat_box(space: Any) -> bool:
    """A 1-D Box: what SB3 preprocesses with ``.float()`` alone (Discrete and MultiDiscrete are one-hot encoded)."""
    return isinstance(space, spaces.Box) and len(space.shape) == 1 and not is_image_space(space)


def mlp_actor_layers(actor: nn.Module, observation_space: Any) -> list[nn.Linear] | None:
    """The Linear layers of an SB3 ``Actor`` that is a ReLU MLP with a tanh output on flat, non-image observations."""
    if not _flat_box(observation_space):
        return None
    if type(getattr(actor, "features_extractor", None)) is not FlattenExtractor:
        return None
    return _mlp_linears(actor.mu, nn.Tanh)


def optimizer_step(optimizer: th.optim.Optimizer) -> None:
    """``optimizer.step()``; for a fused Adam or AdamW, the kernel ``step()`` ends in, called straight away.

    ``Adam.step`` spends about as long in Python (grouping the tensors by device, checking its options) as its fused
    kernel takes on a critic. When nothing can differ (one parameter group, fused, no AMSGrad, maximize,
    differentiable or capturable, a float learning rate, no step hooks, every state already created by a first
    ``step()``), this makes the same two calls ``torch.optim.adam._fused_adam`` makes; otherwise it calls ``step()``.
    """
    if not _direct_fused_adam(optimizer):
        optimizer.step()


def _direct_fused_adam(optimizer: th.optim.Optimizer) -> bool:
    if not isinstance(optimizer, th.optim.Adam) or len(optimizer.param_groups) != 1:
        return False
    if optimizer._optimizer_step_pre_hooks or optimizer._optimizer_step_post_hooks:
        return False
    if _optim_module._global_optimizer_pre_hooks or _optim_module._global_optimizer_post_hooks:
        return False
    group = optimizer.param_groups[0]
    if not group.get("fused") or isinstance(group["lr"], th.Tensor):
        return False
    if group["amsgrad"] or group["maximize"] or group["differentiable"] or group["capturable"]:
        return False
    params = [p for p in group["params"] if p.grad is not None]
    states = [optimizer.state.get(p) for p in params]
    if not params or not all(states):
        return False
    steps = [state["step"] for state in states]  # type: ignore[index]
    th._foreach_add_(steps, 1)
    kernel = th._fused_adamw_ if group.get("decoupled_weight_decay") else th._fused_adam_
    beta1, beta2 = group["betas"]
    kernel(
        params,
        [p.grad for p in params],
        [state["exp_avg"] for state in states],  # type: ignore[index]
        [state["exp_avg_sq"] for state in states],  # type: ignore[index]
        [],
        steps,
        amsgrad=False,
        lr=group["lr"],
        beta1=beta1,
        beta2=beta2,
        weight_decay=group["weight_decay"],
        eps=group["eps"],
        maximize=False,
        grad_scale=None,
        found_inf=None,
    )
    return True


class CriticEnsemble:
    """The critics (or critic targets) of a policy as stacked tensors, which their parameters are views of.

    ``weights[l]`` has shape ``(n_critics, out, in)`` and ``biases[l]`` ``(n_critics, out)``; critic ``i``'s layer
    ``l`` weight is ``weights[l][i]``, the same memory. Rebinds itself when a parameter's memory is replaced (a load
    with ``assign=True``, a move to another device).
    """

    def __init__(self, q_networks: nn.ModuleList):
        self.layers = [_mlp_linears(q, None) for q in q_networks]
        self.weights: list[th.Tensor] = []
        self.biases: list[th.Tensor] = []
        self._bind()

    def _bind(self) -> None:
        self.weights, self.biases = [], []
        for depth in range(len(self.layers[0])):
            layer = [net[depth] for net in self.layers]  # type: ignore[index]
            weights = th.stack([lin.weight.detach() for lin in layer])
            biases = th.stack([lin.bias.detach() for lin in layer])
            for i, lin in enumerate(layer):
                lin.weight.data = weights[i]
                lin.bias.data = biases[i]
            self.weights.append(weights)
            self.biases.append(biases)
        self._pointers = self._current_pointers()

    def _current_pointers(self) -> list[int]:
        return [p.data_ptr() for net in self.layers for lin in net for p in (lin.weight, lin.bias)]  # type: ignore[union-attr]

    def ensure_bound(self) -> None:
        if self._current_pointers() != self._pointers:
            self._bind()

    def parameters_in_order(self) -> list[tuple[nn.Parameter, int, int, str]]:
        """(parameter, layer, critic, "weight" or "bias") for every parameter."""
        return [
            (getattr(lin, kind), depth, i, kind)
            for i, net in enumerate(self.layers)
            for depth, lin in enumerate(net)  # type: ignore[arg-type]
            for kind in ("weight", "bias")
        ]

    def cast(self, dtype: th.dtype) -> tuple[list[th.Tensor], list[th.Tensor]]:
        """The stacked weights and biases in ``dtype`` (the tensors themselves in their own dtype)."""
        return [w.to(dtype) for w in self.weights], [b.to(dtype) for b in self.biases]

    @staticmethod
    def forward(
        x: th.Tensor, all_weights: list[th.Tensor], all_biases: list[th.Tensor]
    ) -> tuple[th.Tensor, list[th.Tensor]]:
        """Q_i(x) for every critic, shape (n_critics, batch, 1), and each layer's input (for the backward pass)."""
        inputs = [x]
        # The critics share their input: one batched product with the input broadcast, (n_critics, batch, out).
        h = th.baddbmm(all_biases[0].unsqueeze(1), x.expand(all_weights[0].shape[0], *x.shape), all_weights[0].mT)
        for weights, biases in zip(all_weights[1:], all_biases[1:]):
            h = h.relu_()
            inputs.append(h)
            h = th.baddbmm(biases.unsqueeze(1), h, weights.mT)
        return h, inputs

    @staticmethod
    def backward(
        grad_out: th.Tensor, inputs: list[th.Tensor], all_weights: list[th.Tensor]
    ) -> tuple[list[th.Tensor], list[th.Tensor]]:
        """Weight and bias gradients, per layer and stacked like the weights, from d loss / d Q (n, batch, 1)."""
        grad = grad_out
        weight_grads: list[th.Tensor] = [None] * len(all_weights)  # type: ignore[list-item]
        bias_grads: list[th.Tensor] = [None] * len(all_weights)  # type: ignore[list-item]
        for depth in range(len(all_weights) - 1, 0, -1):
            h = inputs[depth]
            weight_grads[depth] = th.bmm(grad.transpose(1, 2), h)
            bias_grads[depth] = grad.sum(dim=1)
            grad = _relu_backward(th.bmm(grad, all_weights[depth]), h, 0)
        x = inputs[0]
        weight_grads[0] = th.bmm(grad.transpose(1, 2), x.expand(grad.shape[0], *x.shape))
        bias_grads[0] = grad.sum(dim=1)
        return weight_grads, bias_grads


class MlpUpdate:
    """Steps 5 to 15 of TD3 for MLP policies, gradients by hand (see the module's docstring).

    Called as ``update(batch, update_actor)``, like :meth:`TD3X.update_from_batch`, and returns the same statistics.
    """

    def __init__(self, model: TD3X):
        self.model = model
        self.actor = _mlp_linears(model.actor.mu, nn.Tanh)
        self.actor_target = _mlp_linears(model.actor_target.mu, nn.Tanh)
        self.critic = CriticEnsemble(model.critic.q_networks)
        self.critic_target = CriticEnsemble(model.critic_target.q_networks)
        self._critic_params = self.critic.parameters_in_order()

    @staticmethod
    def why_not(model: TD3X) -> str | None:
        """Why ``model``'s update needs autograd (the hooks as written), or ``None`` when this update computes it."""
        from sb3_td3x.td3x.td3x import TD3X

        for hook in REPLACED_HOOKS:
            if getattr(type(model), hook) is not getattr(TD3X, hook):
                return f"{hook} is overridden"
        policy = model.policy
        space = model.observation_space
        if not _flat_box(space):
            return f"the observations are not a flat Box (got {space})"
        for name in ("actor", "actor_target", "critic", "critic_target"):
            module = getattr(model, name)
            if type(module.features_extractor) is not FlattenExtractor:
                return f"the {name}'s features extractor is {type(module.features_extractor).__name__}"
        if _mlp_linears(model.actor.mu, nn.Tanh) is None or _mlp_linears(model.actor_target.mu, nn.Tanh) is None:
            return "the actor is not a ReLU MLP with a tanh output"
        for critic in (model.critic, model.critic_target):
            shapes = None
            for q in critic.q_networks:
                linears = _mlp_linears(q, None)
                if linears is None:
                    return "a critic is not a ReLU MLP"
                layer_shapes = [tuple(lin.weight.shape) for lin in linears]
                if shapes is not None and layer_shapes != shapes:
                    return "the critics have different architectures"
                shapes = layer_shapes
        if any(True for _ in policy.buffers()):
            return "the policy has buffers (batch norm)"
        return None

    # ------------------------------------------------------------------------------------------------------------
    def __call__(self, batch: Any, update_actor: bool) -> Infos:
        self.critic.ensure_bound()
        self.critic_target.ensure_bound()
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

    def _cast_actor(self, linears: list[nn.Linear]) -> tuple[list[th.Tensor], list[th.Tensor]]:
        return [lin.weight.to(self.dtype) for lin in linears], [lin.bias.to(self.dtype) for lin in linears]

    @staticmethod
    def _actor_forward(
        weights: list[th.Tensor], biases: list[th.Tensor], obs: th.Tensor
    ) -> tuple[th.Tensor, list[th.Tensor]]:
        """pi(s) in [-1, 1] and each layer's input."""
        inputs = [obs]
        h = obs
        for w, b in zip(weights[:-1], biases[:-1]):
            h = th.addmm(b, h, w.t()).relu_()
            inputs.append(h)
        return th.addmm(biases[-1], h, weights[-1].t()).tanh_(), inputs

    def _target_q(self, batch: Any) -> th.Tensor:
        """Steps 5 to 9: y = r + gamma (1 - d) min_i Q'_i(s', clip(pi'(s') + eps, -1, 1))."""
        model = self.model
        next_obs = batch.next_observations.to(self.dtype)
        next_actions, _ = self._actor_forward(*self._cast_actor(self.actor_target), next_obs)  # step 5
        if model.target_policy_smoothing:  # step 6
            noise = th.randn_like(next_actions) * model.target_policy_noise
            next_actions = next_actions + noise.clamp(-model.target_noise_clip, model.target_noise_clip)
        next_actions = next_actions.clamp(-1.0, 1.0)
        obs_actions = th.cat([next_obs, next_actions], dim=1)
        next_q, _ = self.critic_target.forward(obs_actions, *self.critic_target.cast(self.dtype))  # step 7
        next_q = next_q.min(dim=0).values if model.clipped_double_q else next_q[0]  # step 8
        discounts = batch.discounts if getattr(batch, "discounts", None) is not None else model.gamma
        return batch.rewards + (1.0 - batch.dones) * discounts * next_q.float()  # step 9

    def _update_critics(self, batch: Any) -> dict[str, th.Tensor]:
        target_q = self._target_q(batch)  # steps 5-9
        obs_actions = th.cat([batch.observations, batch.actions], dim=1).to(self.dtype)
        weights, biases = self.critic.cast(self.dtype)
        current_q, inputs = self.critic.forward(obs_actions, weights, biases)  # step 10
        td_errors = current_q.float() - target_q.unsqueeze(0)  # (n_critics, batch, 1)
        loss = td_errors.square().mean(dim=(1, 2)).sum()  # step 11: sum_i MSE(Q_i, y)
        # d loss / d Q_i = 2 (Q_i - y) / batch
        grad = (td_errors * (2.0 / td_errors.shape[1])).to(self.dtype)
        weight_grads, bias_grads = self.critic.backward(grad, inputs, weights)
        for param, depth, i, kind in self._critic_params:
            param.grad = (weight_grads if kind == "weight" else bias_grads)[depth][i].float()
        optimizer_step(self.model.critic.optimizer)  # step 12
        info = {"critic_loss": loss, "target_q": target_q.mean()}
        q_means = current_q.float().mean(dim=(1, 2))
        for i in range(current_q.shape[0]):
            info[f"q{i + 1}"] = q_means[i]
        return info

    def _update_actor(self, obs: th.Tensor) -> dict[str, th.Tensor]:
        """Step 13: J = -mean Q_1(s, pi(s)); the gradient reaches the actor through the action only."""
        obs = obs.to(self.dtype)
        actor_weights, actor_biases = self._cast_actor(self.actor)
        actions, actor_inputs = self._actor_forward(actor_weights, actor_biases, obs)
        weights = [w[0].to(self.dtype) for w in self.critic.weights]
        biases = [b[0].to(self.dtype) for b in self.critic.biases]
        h = th.cat([obs, actions], dim=1)
        critic_inputs = []
        for w, b in zip(weights[:-1], biases[:-1]):
            h = th.addmm(b, h, w.t()).relu_()
            critic_inputs.append(h)
        q = th.addmm(biases[-1], h, weights[-1].t()).float()  # (batch, 1)
        loss = -q.mean()
        # d J / d Q_1 = -1 / batch, back through the critic's layers to its input
        grad = th.full_like(q, -1.0 / q.shape[0]).to(self.dtype)
        for depth in range(len(weights) - 1, 0, -1):
            grad = _relu_backward(grad @ weights[depth], critic_inputs[depth - 1], 0)
        obs_dim = obs.shape[1]
        grad = grad @ weights[0][:, obs_dim:]  # d J / d a: the action columns of the first layer only
        grad = _tanh_backward(grad, actions)
        for depth in range(len(self.actor) - 1, -1, -1):
            lin, h = self.actor[depth], actor_inputs[depth]
            lin.weight.grad = (grad.t() @ h).float()
            lin.bias.grad = grad.sum(dim=0).float()
            if depth > 0:
                grad = _relu_backward(grad @ actor_weights[depth], h, 0)
        optimizer_step(self.model.actor.optimizer)
        return {"actor_loss": loss}
