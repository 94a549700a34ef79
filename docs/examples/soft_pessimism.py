"""TD3 with a softer pessimism: override step 8, ``clipped_double_q_value``."""

from typing import Any

import torch as th

from sb3_td3x import TD3X


class SoftPessimismTD3X(TD3X):
    """TD3 whose target mixes the minimum and the mean of the critic targets.

    y = r + gamma (1 - d) [beta min_i Q'_i(s', a') + (1 - beta) mean_i Q'_i(s', a')]

    ``pessimism=1`` is TD3's clipped double-Q; ``pessimism=0`` averages the critic targets.

    :param pessimism: beta, the weight of the minimum, in [0, 1]
    """

    def __init__(self, *args: Any, pessimism: float = 0.75, **kwargs: Any):
        if not 0.0 <= pessimism <= 1.0:
            raise ValueError(f"pessimism={pessimism!r} must be in [0, 1]")
        self.pessimism = pessimism
        super().__init__(*args, **kwargs)

    def clipped_double_q_value(self, next_q: th.Tensor) -> th.Tensor:
        # next_q: (n_critics, batch_size, 1) -> (batch_size, 1)
        return self.pessimism * next_q.min(dim=0).values + (1.0 - self.pessimism) * next_q.mean(dim=0)


if __name__ == "__main__":
    model = SoftPessimismTD3X("MlpPolicy", "Pendulum-v1", pessimism=0.5, verbose=1)
    model.learn(total_timesteps=10_000)
