"""TD3 with gradient clipping on the critics: override step 12, ``optimize_critic``."""

from typing import Any

import torch as th

from sb3_td3x import TD3X
from sb3_td3x.td3x.optim import apply_gradients, gradients


class GradClipTD3X(TD3X):
    """TD3 whose critic gradients are clipped to a maximum global norm before each optimizer step.

    :param max_grad_norm: the largest L2 norm of the critics' gradient, all parameters together
    """

    def __init__(self, *args: Any, max_grad_norm: float = 10.0, **kwargs: Any):
        self.max_grad_norm = max_grad_norm
        super().__init__(*args, **kwargs)

    def optimize_critic(self, loss: th.Tensor) -> None:
        optimizer = self.critic.optimizer
        # d loss / d p for each parameter the optimizer steps (None for one the loss does not reach: it is not stepped)
        grads = gradients(optimizer, loss)
        # clip_grad_norm_'s rule: scale every gradient by max_norm / norm where the norm is larger. All tensor
        # operations (no .item()): no host-device synchronisation, and the step compiles with the rest of the update.
        norm = th.linalg.vector_norm(th.stack([th.linalg.vector_norm(g) for g in grads if g is not None]))
        scale = (self.max_grad_norm / (norm + 1e-6)).clamp(max=1.0)
        apply_gradients(optimizer, [None if g is None else g * scale for g in grads])


if __name__ == "__main__":
    model = GradClipTD3X("MlpPolicy", "Pendulum-v1", max_grad_norm=1.0, verbose=1)
    model.learn(total_timesteps=10_000)
