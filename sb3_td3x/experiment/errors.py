"""Errors the experiment framework raises on purpose.

``run.py`` turns each of them into a one-paragraph message and a non-zero exit status (2 for a bad config, 3 for a
diverged run, 4 for files that could not be written, 5 for a killed seed process, 128 + the signal for a stop);
everything else is a bug and keeps its traceback.
"""


class ConfigError(ValueError):
    """The composed configuration cannot be run: a value out of range, a missing checkpoint, an unknown id.

    The message says what was wrong and how to fix it.
    """


class TrainingDiverged(RuntimeError):
    """A training loss or an evaluation return became NaN or infinite.

    :param what: the quantity that diverged, e.g. ``"train/critic_loss"`` or ``"evaluation mean return"``
    :param value: its value
    :param num_timesteps: the environment step at which it was seen
    """

    def __init__(self, what: str, value: float, num_timesteps: int) -> None:
        self.what = what
        self.value = value
        self.num_timesteps = num_timesteps
        super().__init__(
            f"Training diverged: {what} became {value} at step {num_timesteps}. "
            "Start a new run with lower learning rates (algo.learning_rate, algo.critic_learning_rate), or check the "
            "environment's rewards for NaN/inf. Resuming would repeat the same steps: a resumed run continues exactly."
        )


class RunFilesNotWritten(RuntimeError):
    """A file of the run (a checkpoint, the evaluations) could not be written: a full disk, a quota, permissions.

    The message says what failed; the runner adds which checkpoint is intact and the command that continues.
    """


class SeedProcessLost(RuntimeError):
    """A process training some of ``seeds=[...]`` ended without a result (killed: out of memory, SIGKILL). Its seeds'
    folders keep their last checkpoints; the message says how to continue."""


class TrainingInterrupted(Exception):
    """Training stopped because of SIGINT or SIGTERM; a checkpoint was written first.

    :param signal_name: ``"SIGINT"`` or ``"SIGTERM"``
    :param exit_code: the shell convention, 128 + signal number
    :param num_timesteps: the step count stored in the checkpoint
    :param run_dir: the run folder, to pass as ``resume=``
    """

    def __init__(self, signal_name: str, exit_code: int, num_timesteps: int, run_dir: str) -> None:
        self.signal_name = signal_name
        self.exit_code = exit_code
        self.num_timesteps = num_timesteps
        self.run_dir = run_dir
        super().__init__(
            f"Stopped by {signal_name} at step {num_timesteps}; a checkpoint was saved in {run_dir}/checkpoints/last. "
            f"Continue this run with: python run.py resume={run_dir}"
        )
