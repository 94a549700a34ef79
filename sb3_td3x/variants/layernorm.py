"""TD3 with LayerNorm critics: each hidden layer of each critic normalised before its activation."""

from __future__ import annotations

from stable_baselines3.common.torch_layers import create_mlp
from torch import nn

from sb3_td3x.td3x.td3x import TD3X


class TD3LayerNorm(TD3X):
    """TD3 whose critics (and their targets) are ``Linear, LayerNorm, ReLU, ..., Linear``: Ba et al. (2016)'s layer
    normalisation after each hidden layer, which keeps the critics' values bounded and their training stable with
    higher update ratios (Ball et al. 2023, RLPD; Nauman et al. 2024; SBX's ``TD3`` with ``layer_norm=True``).

    One hook changes, step 3's :meth:`~sb3_td3x.TD3X.q_network`: SB3's ``create_mlp`` with
    ``post_linear_modules=[nn.LayerNorm]``, which puts a LayerNorm after each hidden Linear and none after the output.
    The actor is TD3's. The update runs as the stock one does: the hooks as written, compiled on a long run.
    """

    def q_network(self, input_dim: int, net_arch: list[int], activation_fn: type[nn.Module]) -> nn.Module:
        return nn.Sequential(*create_mlp(input_dim, 1, net_arch, activation_fn, post_linear_modules=[nn.LayerNorm]))
