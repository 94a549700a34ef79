"""Launching the processes that train, behind one interface (:mod:`~sb3_td3x.experiment.launch.launcher`): seed
processes, Hydra's jobs of ``run.py`` (joblib, submitit, SLURM), CUDA MPS around them, and how SLURM jobs are followed."""
