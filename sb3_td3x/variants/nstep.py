"""TD3 with n-step returns (n = 3): SB3's ``n_steps``, on TD3X's tensor replay buffer."""

from __future__ import annotations

from typing import Any

from sb3_td3x.td3x.td3x import TD3X


class TD3NStep(TD3X):
    """TD3 with 3-step returns: the TD target of step 9 becomes

    y = sum_{k<m} gamma^k r_{t+k} + gamma^m (1 - d_{t+m-1}) min_i Q'_i(s_{t+m}, a'),

    with ``m`` the steps up to the first termination, truncation or the newest transition, at most ``n_steps``.
    Nothing is overridden: ``n_steps`` is SB3's own argument (SB3 2.7's ``NStepReplayBuffer``), whose returns TD3X's
    :class:`~sb3_td3x.common.buffers.TensorReplayBuffer` computes as that buffer does (the same batches from the same
    transitions). Step 4's batch carries ``discounts = gamma ** m``, which :meth:`~sb3_td3x.TD3X.compute_target_q`
    passes to :meth:`~sb3_td3x.TD3X.td_target`, compiled with the rest of the update on a long run. FastTD3 (Seo et al. 2025) trains with 3-step returns on its MuJoCo tasks
    (``fast_td3/hyperparams.py``: ``num_steps = 3``).

    :param n_steps: the steps of each return (3; 1 is TD3)
    """

    def __init__(self, *args: Any, n_steps: int = 3, **kwargs: Any):
        super().__init__(*args, n_steps=n_steps, **kwargs)
