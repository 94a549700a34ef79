"""TD3 with gradient clipping on the critics: override step 12, ``optimize_critic``."""

from typing import Any

import torch as th

from sb3_td3x import TD3X


class GradClipTD3X(TD3X):
    """TD3 whose critic gradients are clipped to a maximum global norm before each optimizer step.

    :param max_grad_norm: the largest L2 norm of the critics' gradient, all parameters together
    """

    def __init__(self, *args: Any, max_grad_norm: float = 10.0, **kwargs: Any):
        self.max_grad_norm = max_grad_norm
        super().__init__(*args, **kwargs)

    def optimize_critic(self, loss: th.Tensor) -> None:
        self.critic.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # Returns the norm before clipping as a tensor: no host-device synchronisation.
        th.nn.utils.clip_grad_norm_(self.critic.parameters(), self.max_grad_norm)
        self.critic.optimizer.step()


if __name__ == "__main__":
    model = GradClipTD3X("MlpPolicy", "Pendulum-v1", max_grad_norm=1.0, verbose=1)
    model.learn(total_timesteps=10_000)
