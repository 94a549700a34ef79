"""Policies for TD3X: SB3's TD3 actor and policy, with a critic that returns all Q-values as one tensor."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, NatureCNN
from stable_baselines3.td3.policies import Actor, TD3Policy

#: The network builders of the algorithm that is building a policy now, by role (``"actor"``: TD3X's
#: ``actor_network`` hook, ``"critic"``: its ``q_network``), where a subclass overrides them (:func:`networks_built_by`).
_network_builders: ContextVar[dict[str, Callable[..., th.nn.Module]] | None] = ContextVar(
    "td3x_network_builders", default=None
)


@contextlib.contextmanager
def networks_built_by(builders: dict[str, Callable[..., th.nn.Module]]) -> Iterator[None]:
    """Policies built inside take their actor's network (``builders["actor"]``) and critics' networks
    (``builders["critic"]``) from these functions, with the signatures of TD3X's ``actor_network`` and ``q_network``;
    SB3's own networks for a role without one. Set by TD3X around its policy's construction; a policy loaded alone
    (``TD3XPolicy.load``) has SB3's networks: load the model instead."""
    token = _network_builders.set(builders)
    try:
        yield
    finally:
        _network_builders.reset(token)


class TD3XCritic(ContinuousCritic):
    """SB3's ``ContinuousCritic`` (same modules, same state dict) with :meth:`q_values`, the critics' outputs stacked.

    The state dict is SB3's, so weights move between ``TD3`` and ``TD3X`` with ``load_state_dict``.
    """

    def q_values(self, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Q_i(s, a) for every critic i. Returns shape (n_critics, batch_size, 1)."""
        return th.stack(self(obs, actions))


#: What ``n_critics`` must be (:func:`valid_n_critics`), said by the policy and by the experiment configs' check.
N_CRITICS = "an integer >= 1 (TD3's clipped double Q takes the minimum over 2, the default)"


def _positive_integer(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool) and x >= 1


def valid_n_critics(n_critics: Any) -> bool:
    """Whether ``n_critics`` (``policy_kwargs``, or an algo config's ``n_critics``) is :data:`N_CRITICS`."""
    return _positive_integer(n_critics)


#: What ``net_arch`` must be (:func:`valid_net_arch`): a width of 0 would silently make a network that outputs its bias.
NET_ARCH = (
    "a list of layer widths, each an integer >= 1 (an empty list: no hidden layer), a dict with such lists under 'pi'"
    " and 'qf', or None (the default, [400, 300])"
)


def valid_net_arch(net_arch: Any) -> bool:
    """Whether ``net_arch`` (``policy_kwargs``, or an algo config's ``net_arch``) is :data:`NET_ARCH`."""

    def widths(layers: Any) -> bool:
        return isinstance(layers, (list, tuple)) and all(_positive_integer(width) for width in layers)

    if isinstance(net_arch, dict):  # other keys are the user's (a subclass may read them), as SB3 leaves them
        return {"pi", "qf"} <= set(net_arch) and widths(net_arch["pi"]) and widths(net_arch["qf"])
    return net_arch is None or (isinstance(net_arch, list) and widths(net_arch))  # SB3 takes a tuple as a dict


class TD3XPolicy(TD3Policy):
    """SB3's ``TD3Policy`` (actor, critics and their targets: steps 2 and 3) with :class:`TD3XCritic` critics.

    Takes exactly the arguments of SB3's ``TD3Policy``: ``net_arch`` (default [400, 300]), ``activation_fn``,
    ``features_extractor_class``, ``n_critics`` (default 2), ``share_features_extractor``, ``optimizer_class``...
    """

    critic: TD3XCritic
    critic_target: TD3XCritic

    def __init__(self, *args: Any, **kwargs: Any):
        n_critics = kwargs.get("n_critics", 2)
        if not valid_n_critics(n_critics):
            raise ValueError(f"TD3X: invalid policy_kwargs n_critics={n_critics!r}; n_critics must be {N_CRITICS}.")
        net_arch = kwargs.get("net_arch", args[3] if len(args) > 3 else None)  # TD3Policy's fourth argument
        if not valid_net_arch(net_arch):
            raise ValueError(f"TD3X: invalid policy_kwargs net_arch={net_arch!r}; net_arch must be {NET_ARCH}.")
        optimizer_class = kwargs.get("optimizer_class", th.optim.Adam)
        optimizer_kwargs = dict(kwargs.get("optimizer_kwargs") or {})
        if optimizer_class in (th.optim.Adam, th.optim.AdamW) and not {"fused", "foreach"} & optimizer_kwargs.keys():
            # One fused kernel for the whole update instead of a loop over tensors (CPU and CUDA).
            optimizer_kwargs["fused"] = True
        kwargs["optimizer_kwargs"] = optimizer_kwargs
        super().__init__(*args, **kwargs)

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> Actor:
        """SB3's actor, its network ``mu`` built by the algorithm's ``actor_network`` hook where one is set
        (:func:`networks_built_by`)."""
        actor = super().make_actor(features_extractor)
        build = (_network_builders.get() or {}).get("actor")
        if build is not None:
            action_dim = get_action_dim(self.action_space)
            actor.mu = build(actor.features_dim, action_dim, actor.net_arch, actor.activation_fn).to(self.device)
        return actor

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> TD3XCritic:
        """A :class:`TD3XCritic`, its networks ``qf0``, ``qf1``... built by the algorithm's ``q_network`` hook where
        one is set (:func:`networks_built_by`)."""
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        critic = TD3XCritic(**critic_kwargs).to(self.device)
        build = (_network_builders.get() or {}).get("critic")
        if build is not None:
            input_dim = critic_kwargs["features_dim"] + get_action_dim(self.action_space)
            for i in range(len(critic.q_networks)):
                q_net = build(input_dim, critic_kwargs["net_arch"], critic_kwargs["activation_fn"]).to(self.device)
                critic.add_module(f"qf{i}", q_net)
                critic.q_networks[i] = q_net
        return critic

    def set_training_mode(self, mode: bool) -> None:
        """Put the actor and critics in training or evaluation mode (batch norm, dropout); a no-op when already there.

        SB3 calls this twice per environment step once training runs (collection, then training). Instead of
        ``Module.train``'s recursive walk, the flag is set on a list of the actor's and critics' modules made once,
        when every one of them uses ``Module.train`` as it is (otherwise the walk runs, as in SB3).
        """
        if self.actor.training == mode and self.critic.training == mode and self.training == mode:
            return
        cache = self.__dict__.get("_mode_modules")
        if cache is None or cache[0] is not self.actor or cache[1] is not self.critic:
            modules = [m for part in (self.actor, self.critic) for m in part.modules()]
            plain = all(type(m).train is th.nn.Module.train for m in modules)
            cache = (self.actor, self.critic, modules if plain else None)
            self.__dict__["_mode_modules"] = cache
        if cache[2] is None:
            super().set_training_mode(mode)
            return
        for module in cache[2]:
            module.__dict__["training"] = mode  # what Module.train sets, without Module.__setattr__
        self.training = mode

    def sb3_state_dict(self) -> dict[str, th.Tensor]:
        """The state dict in the layout of SB3's ``TD3Policy``."""
        return self.state_dict()

    def load_sb3_state_dict(self, state_dict: dict[str, th.Tensor]) -> None:
        """Load a state dict in the layout of SB3's ``TD3Policy``."""
        self.load_state_dict(state_dict)


MlpPolicy = TD3XPolicy


class CnnPolicy(TD3XPolicy):
    """TD3XPolicy for image observations (NatureCNN features extractor), as SB3's ``td3.CnnPolicy``."""

    def __init__(self, *args: Any, features_extractor_class: type[BaseFeaturesExtractor] = NatureCNN, **kwargs: Any):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class MultiInputPolicy(TD3XPolicy):
    """TD3XPolicy for Dict observations (CombinedExtractor), as SB3's ``td3.MultiInputPolicy``."""

    def __init__(
        self, *args: Any, features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor, **kwargs: Any
    ):
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


def copy_sb3_policy_weights(source: th.nn.Module, target: TD3XPolicy) -> None:
    """Copy the weights of an SB3 ``TD3Policy`` (or another ``TD3XPolicy``) into ``target``.

    Used to start TD3X from a model trained with SB3's TD3, and by the equivalence tests.
    """
    target.load_sb3_state_dict(source.state_dict())
