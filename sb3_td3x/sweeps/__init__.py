"""Optuna hyper-parameter search over the configs that ``run.py`` trains.

Built on current Optuna rather than ``hydra-optuna-sweeper`` (which pins ``optuna<3``, runs trials in synchronous
batches, cannot prune because the task never sees its trial, and crashes on a NaN objective): each trial composes
``conf/`` with the same overrides ``run.py`` takes, reports its periodic evaluations to its Optuna trial, and stops
when the pruner says so. See ``docs/sweeps.md``.

* :mod:`~sb3_td3x.sweeps.spec`: the search-space file (``sweeps/*.yaml``);
* :mod:`~sb3_td3x.sweeps.storage`: SQLite / SQLAlchemy / journal storages, heartbeat, the shared trial budget;
* :mod:`~sb3_td3x.sweeps.objective`: one trial;
* :mod:`~sb3_td3x.sweeps.worker`: the loop a worker runs, persistence and Ctrl-C;
* :mod:`~sb3_td3x.sweeps.results`: summary, best overrides, plots;
* :mod:`~sb3_td3x.sweeps.launch`: workers as SLURM jobs (submitit, configured like Hydra's submitit launcher);
* :mod:`~sb3_td3x.sweeps.cli`: ``python -m sb3_td3x.sweeps``.
"""

from sb3_td3x.sweeps.errors import StorageError, SweepError, SweepSpecError
from sb3_td3x.sweeps.spec import SweepSpec, load_sweep

__all__ = ["StorageError", "SweepError", "SweepSpec", "SweepSpecError", "load_sweep"]
