"""TD3 with a Huber critic loss: override step 11, ``critic_loss``."""

from typing import Any

import torch as th
import torch.nn.functional as F

from sb3_td3x import TD3X


class HuberTD3X(TD3X):
    """TD3 whose critics regress on the TD target with the Huber loss instead of the mean squared error.

    :param huber_delta: the TD error at which the loss turns from quadratic to linear
    """

    def __init__(self, *args: Any, huber_delta: float = 1.0, **kwargs: Any):
        self.huber_delta = huber_delta
        super().__init__(*args, **kwargs)

    def critic_loss(self, current_q: th.Tensor, target_q: th.Tensor) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        # current_q: (n_critics, batch_size, 1); target_q: (batch_size, 1), without gradient
        target_q = target_q.unsqueeze(0).expand_as(current_q)  # (n_critics, batch_size, 1)
        per_critic = F.huber_loss(current_q, target_q, reduction="none", delta=self.huber_delta).mean(dim=(1, 2))
        loss = per_critic.sum()  # the sum over critics, as TD3's loss sums their MSEs
        # Return the loss and detached statistics; never step an optimizer here.
        return loss, {"critic_loss": loss.detach(), "target_q": target_q.mean()}


if __name__ == "__main__":
    model = HuberTD3X("MlpPolicy", "Pendulum-v1", huber_delta=10.0, verbose=1)
    model.learn(total_timesteps=10_000)
