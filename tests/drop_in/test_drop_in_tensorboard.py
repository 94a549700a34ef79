"""Drop-in: TensorBoard logging through SB3's logger (run folders, hyperparameters, TD3X's training metrics).

Mirrors SB3's ``tests/test_tensorboard.py::test_tensorboard`` (SB3 runs it with ``TD3``) with ``TD3X`` and ``DDPG``.
"""

import pytest
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import HParam

from sb3_td3x import DDPG, TD3X

N_STEPS = 100


class HParamCallback(BaseCallback):
    """Logs the hyperparameters and a metric to TensorBoard's HPARAMS tab at the start of training."""

    def _on_training_start(self) -> None:
        hparams = {"algorithm": type(self.model).__name__, "gamma": self.model.gamma}
        self.logger.record("hparams", HParam(hparams, {"rollout/ep_len_mean": 0}), exclude=("stdout", "log", "json", "csv"))

    def _on_step(self) -> bool:
        return True


# mirrors SB3 tests/test_tensorboard.py::test_tensorboard
@pytest.mark.parametrize(
    "model_class,log_name",
    [
        (TD3X, "TD3X"),
        (DDPG, "DDPG"),
    ],
)
def test_tensorboard(tmp_path, model_class, log_name):
    pytest.importorskip("tensorboard")
    kwargs = dict(train_freq=2, learning_starts=50, batch_size=32, buffer_size=1_000)
    model = model_class("MlpPolicy", "Pendulum-v1", tensorboard_log=tmp_path, **kwargs)
    model.learn(N_STEPS, callback=HParamCallback())
    # TD3X's own training metrics reach the logger.
    for key in ("train/critic_loss", "train/actor_loss", "train/n_updates"):
        assert key in model.logger.name_to_value or key in model.logger.name_to_excluded, key
    model.learn(N_STEPS, reset_num_timesteps=False)

    # Going on with the same run writes to the same folder...
    assert (tmp_path / f"{log_name}_1").is_dir()
    assert not (tmp_path / f"{log_name}_2").is_dir()

    # ... and each new run gets a new one.
    log_name = "tb_multiple_runs"
    model.learn(N_STEPS, tb_log_name=log_name)
    model.learn(N_STEPS, tb_log_name=log_name)
    assert (tmp_path / f"{log_name}_1").is_dir()
    assert (tmp_path / f"{log_name}_2").is_dir()
