"""The hooks of TD3X: the one list of the methods that say what an update computes.

Each step of TD3 (numbered as in the course notes, ``shared/seeds``) is a method of :class:`~sb3_td3x.TD3X`. This
module names them once. Every way of running the update (``update_paths``) runs them as written. :func:`changed_hooks`
says which a model changed: where the policy must build a network with a hook of the user's (steps 2 and 3), and
where a ``gradient_step`` of the user's is compiled whole. The ``TD3X`` docstring table and ``docs/extending.md`` are
checked against this list by ``tests/unit/test_docs.py``.

Nothing here imports ``TD3X`` (the fast paths import this module, and ``td3x.py`` imports them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Hook:
    """A step of TD3 as a method of ``TD3X``: its name, its step number(s), and what it computes."""

    name: str
    step: str
    what: str


HOOKS: tuple[Hook, ...] = (
    Hook("actor_network", "2", "the actor's network pi_phi (and its target's)"),
    Hook("q_network", "3", "each critic's network Q_theta_i (and its target's)"),
    Hook("sample_batch", "4", "sample a batch (s, a, r, s', d)"),
    Hook("target_actions", "5-6", "a' = clip(pi_phi'(s') + eps, -1, 1)"),
    Hook("target_policy_smoothing_noise", "6", "eps = clip(N(0, sigma~), -c, c)"),
    Hook("next_q_values", "7", "Q'_i(s', a') for each critic target"),
    Hook("clipped_double_q_value", "8", "min_i Q'_i(s', a') (clipped double-Q)"),
    Hook("td_target", "9", "y = r + gamma (1 - d) min_i Q'_i(s', a')"),
    Hook("current_q_values", "10", "Q_i(s, a) for each critic"),
    Hook("critic_loss", "11", "L = sum_i MSE(Q_i(s, a), y)"),
    Hook("optimize_critic", "12", "gradient step on the critics"),
    Hook("update_priorities", "12", "then: the batch's new priorities (prioritised replay)"),
    Hook("should_update_actor", "13", "update the actor and the targets this step?"),
    Hook("actor_loss", "13", "J = -Q_1(s, pi(s))"),
    Hook("optimize_actor", "13", "gradient step on the actor"),
    Hook("update_actor_target", "14", "phi' <- tau phi + (1 - tau) phi'"),
    Hook("update_critic_target", "15", "theta'_i <- tau theta_i + (1 - tau) theta'_i"),
    Hook("compute_target_q", "5-9", "the TD target y, without gradient"),
    Hook("update_from_batch", "5-15", "the updates from a sampled batch"),
    Hook("gradient_step", "4-15", "one gradient step, the steps above in order"),
)

HOOK_NAMES: tuple[str, ...] = tuple(hook.name for hook in HOOKS)


def reference_class(model: Any) -> type:
    """The class whose hooks are the stock ones: the most basic class of ``model`` that defines every hook (``TD3X``).

    Found from the class hierarchy, so that the fast paths need not import ``TD3X``.
    """
    for cls in reversed(type(model).__mro__):
        if all(name in vars(cls) for name in HOOK_NAMES):
            return cls
    raise TypeError(f"{type(model).__name__} is not a TD3X: it does not define the hooks {HOOK_NAMES}")


def defining_class(cls: type, name: str) -> type | None:
    """The class in ``cls``'s hierarchy whose body defines ``name`` (the one ``getattr`` finds)."""
    return next((c for c in cls.__mro__ if name in vars(c)), None)


def changed_hooks(model: Any, names: tuple[str, ...] | list[str] = HOOK_NAMES) -> list[str]:
    """Each of ``names`` that would not run ``TD3X``'s own code on ``model``, with how it was changed.

    A hook is changed when a subclass overrides it (even to call ``super()``: what it adds is unknown) or when it is
    set on the instance (``model.td_target = fn``). Returns, e.g., ``["td_target overridden by MyTD3",
    "critic_loss set on the instance"]``; empty when every hook is the stock one.
    """
    reference = reference_class(model)
    changes = []
    for name in names:
        if name in vars(model):
            changes.append(f"{name} set on the instance")
            continue
        owner = defining_class(type(model), name)
        if owner is not None and owner is not reference and getattr(type(model), name) is not getattr(reference, name):
            changes.append(f"{name} overridden by {owner.__name__}")
    return changes
