"""TD3 with FastTD3's categorical critic: C51 distributions on a fixed support, trained with a cross-entropy loss."""

from __future__ import annotations

from typing import Any

import torch as th
import torch.nn.functional as F
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn

from sb3_td3x.td3x.td3x import TD3X


def categorical_projection(
    probs: th.Tensor, rewards: th.Tensor, discounts: th.Tensor, v_min: float, v_max: float
) -> th.Tensor:
    """The distribution of r + discounts * Z, Z ~ ``probs`` on ``linspace(v_min, v_max, n_atoms)``, projected back onto
    that support (Bellemare et al. 2017, eq. 7): FastTD3's ``DistributionalQNetwork.projection`` (younggyoseo/FastTD3
    at 229ed59, fast_td3/fast_td3.py lines 119-154), its fix for atoms landing exactly on the support included.

    :param probs: shape (..., batch_size, n_atoms)
    :param rewards: shape (batch_size, 1)
    :param discounts: gamma ** n (1 - done), shape (batch_size, 1)
    :return: shape of ``probs``
    """
    n_atoms = probs.shape[-1]
    support = th.linspace(v_min, v_max, n_atoms, device=probs.device)
    target_z = (rewards + discounts * support).clamp(v_min, v_max)  # (batch_size, n_atoms)
    b = (target_z - v_min) / ((v_max - v_min) / (n_atoms - 1))
    lower, upper = b.floor().long(), b.ceil().long()
    on_atom = lower == upper  # all the mass to that atom: move one neighbour so that the weights below are 1 and 0
    lower, upper = th.where(on_atom & (lower > 0), lower - 1, lower), th.where(on_atom & (lower == 0), upper + 1, upper)
    projected = th.zeros_like(probs)
    projected.scatter_add_(-1, lower.expand_as(probs), probs * (upper.float() - b))
    projected.scatter_add_(-1, upper.expand_as(probs), probs * (b - lower.float()))
    return projected


class TD3C51(TD3X):
    """TD3 with FastTD3's distributional critic (Seo, Sferrazza, Geng, Nauman, Yin and Abbeel 2025, "FastTD3: Simple,
    Fast, and Capable Reinforcement Learning for Humanoid Control"; code: https://github.com/younggyoseo/FastTD3, read
    at 229ed59): each critic outputs logits over ``n_atoms`` atoms evenly spaced on [v_min, v_max] (C51, Bellemare,
    Dabney and Munos 2017). The hooks, composed:

    - step 3, :meth:`q_network`: one logit per atom;
    - step 7, :meth:`next_q_values`: each critic target's distribution, the softmax of its logits;
    - step 8, :meth:`clipped_double_q_value`: all of them go on, FastTD3 choosing after the projection;
    - step 9, :meth:`td_target`: each projected with :func:`categorical_projection`, and with ``clipped_double_q`` the
      one of lower mean per transition (fast_td3/train.py lines 438-456), else the first critic's;
    - step 11, :meth:`critic_loss`: the sum over critics of the cross-entropy to it (train.py lines 463-470);
    - step 13, :meth:`actor_loss`: the critics' expected values at pi(s), their minimum with ``clipped_double_q``, else
      their mean (train.py lines 502-509; TD3 uses the first critic's).

    Not taken from FastTD3: its networks, batch sizes and parallel environments (TD3's ``net_arch`` here).

    :param v_min: the lowest atom (FastTD3's default, -250); returns below it are clipped to it
    :param v_max: the highest atom (FastTD3's default, 250)
    :param n_atoms: the number of atoms (FastTD3: 101)
    """

    def __init__(self, *args: Any, v_min: float = -250.0, v_max: float = 250.0, n_atoms: int = 101, **kwargs: Any):
        if not (v_min < v_max and n_atoms >= 2):
            raise ValueError(f"TD3C51 needs v_min < v_max and n_atoms >= 2, got {v_min}, {v_max} and {n_atoms}.")
        self.v_min, self.v_max, self.n_atoms = float(v_min), float(v_max), int(n_atoms)
        super().__init__(*args, **kwargs)

    @property
    def support(self) -> th.Tensor:
        """The atoms, shape (n_atoms,)."""
        return th.linspace(self.v_min, self.v_max, self.n_atoms, device=self.device)

    def q_network(self, input_dim: int, net_arch: list[int], activation_fn: type[nn.Module]) -> nn.Module:
        return nn.Sequential(*create_mlp(input_dim, self.n_atoms, net_arch, activation_fn))

    def next_q_values(self, next_observations: Any, next_actions: th.Tensor) -> th.Tensor:
        return F.softmax(self.critic_target.q_values(next_observations, next_actions).float(), dim=-1)

    def clipped_double_q_value(self, next_q: th.Tensor) -> th.Tensor:
        return next_q

    def td_target(self, rewards: th.Tensor, dones: th.Tensor, discounts: Any, next_q: th.Tensor) -> th.Tensor:
        projected = categorical_projection(next_q, rewards, (1.0 - dones) * discounts, self.v_min, self.v_max)
        if not self.clipped_double_q:
            return projected[0]
        values = (projected * self.support).sum(-1)  # (n_critics, batch_size)
        target, lowest = projected[0], values[0]
        for i in range(1, len(projected)):  # FastTD3: where(Q_1 < Q_2, Z_1, Z_2), so a tie takes the later critic's
            lower = values[i] <= lowest
            target, lowest = th.where(lower.unsqueeze(-1), projected[i], target), th.where(lower, values[i], lowest)
        return target

    def critic_loss(self, current_q: th.Tensor, target_q: th.Tensor) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        log_probs = F.log_softmax(current_q.float(), dim=-1)  # (n_critics, batch_size, n_atoms)
        loss = -(target_q.float() * log_probs).sum(-1).mean(-1).sum()
        q_means = (log_probs.detach().exp() * self.support).sum(-1).mean(-1)
        info = {"critic_loss": loss.detach(), "target_q": (target_q.float() * self.support).sum(-1).mean()}
        return loss, {**info, **{f"q{i + 1}": q_means[i] for i in range(len(q_means))}}

    def actor_loss(self, observations: Any) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        logits = self.critic.q_values(observations, self.actor(observations)).float()  # (n_critics, batch, atoms)
        values = (F.softmax(logits, dim=-1) * self.support).sum(-1)  # (n_critics, batch_size)
        loss = -(values.min(dim=0).values if self.clipped_double_q else values.mean(dim=0)).mean()
        return loss, {"actor_loss": loss.detach()}

    def q_value_estimates(self, batch: Any) -> th.Tensor:
        return (F.softmax(self.current_q_values(batch).float(), dim=-1) * self.support).sum(-1, keepdim=True)
