"""TD3 with LAP: prioritised replay with the loss that makes it unbiased, as TD7 uses them (sfujim/TD7)."""

from __future__ import annotations

from typing import Any

import torch as th

from sb3_td3x.td3x.td3x import TD3X


def lap_huber(td_errors: th.Tensor, min_priority: float = 1.0) -> th.Tensor:
    """TD7's ``LAP_huber`` (sfujim/TD7, TD7.py lines 60-61): the Huber loss with threshold ``min_priority`` of each
    |TD error|, summed over the critics and averaged over the batch.

    :param td_errors: |Q_i(s, a) - y|, shape (n_critics, batch_size, 1)
    """
    return th.where(td_errors < min_priority, 0.5 * td_errors.pow(2), min_priority * td_errors).sum(0).mean()


class TD3LAP(TD3X):
    """TD3 with Loss-Adjusted Prioritized experience replay (LAP; Fujimoto, Meger and Precup 2020, "An Equivalence
    between Loss Functions and Non-Uniform Sampling in Experience Replay", NeurIPS), with TD7's settings (Fujimoto et
    al. 2023, "For SALE: State-Action Representation Learning for Deep Reinforcement Learning", NeurIPS; code:
    https://github.com/sfujim/TD7).

    - Step 4 draws transition i with probability proportional to max(|delta_i|, 1) ** 0.4, delta_i its latest TD
      error: TD3X's :class:`~sb3_td3x.common.buffers.TensorReplayBuffer` with ``alpha=0.4``, ``min_priority=1`` and
      the priority of new transitions reset to the buffer's largest every 250 updates (TD7's buffer.py lines 35-77;
      TD7.py lines 28-29 and 284-290).
    - Step 11, :meth:`critic_loss`, is TD7's ``LAP_huber`` of |delta| (TD7.py lines 60-61 and 252-253): quadratic
      below ``min_priority``, linear above, which with the sampling above is in expectation the MSE under uniform
      sampling (the paper's Theorem 3).
    - After step 12 the stock :meth:`~sb3_td3x.TD3X.update_priorities` writes max_i |Q_i(s, a) - y| for the batch
      (TD7.py line 262).

    Departures from TD7, whose other parts (SALE, policy checkpoints, value clipping, hard target updates every 250
    steps) are not LAP: TD3's networks and Polyak targets, and a transition drawn twice in one batch keeps its larger
    new priority (TD7's indexed write keeps one of them).

    :param alpha: the priority exponent (TD7: 0.4)
    :param min_priority: the priority floor and the Huber threshold (TD7: 1)
    :param max_priority_reset_interval: updates between resets of the new transitions' priority (TD7: 250)
    """

    def __init__(
        self, *args: Any, alpha: float = 0.4, min_priority: float = 1.0, max_priority_reset_interval: int = 250, **kwargs: Any
    ):
        self.alpha, self.min_priority, self.max_priority_reset_interval = alpha, min_priority, max_priority_reset_interval
        lap = {"alpha": alpha, "min_priority": min_priority, "max_priority_reset_interval": max_priority_reset_interval}
        kwargs["replay_buffer_kwargs"] = {**lap, **(kwargs.get("replay_buffer_kwargs") or {})}
        super().__init__(*args, **kwargs)

    def critic_loss(self, current_q: th.Tensor, target_q: th.Tensor) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        """Step 11: TD7's LAP loss, :func:`lap_huber` of |Q_i(s, a) - y| with threshold ``min_priority``."""
        td_errors = (current_q.float() - target_q.float().unsqueeze(0)).abs()  # (n_critics, batch_size, 1)
        loss = lap_huber(td_errors, self.min_priority)
        info = {"critic_loss": loss.detach(), "target_q": target_q.float().mean()}
        q_means = current_q.detach().float().mean(dim=(1, 2))
        return loss, {**info, **{f"q{i + 1}": q_means[i] for i in range(current_q.shape[0])}}
