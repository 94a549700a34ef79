"""The experiment framework around TD3X: ``run.py``, the Python API and the sweeps train through it.

Laid out by concern, imports flowing down this list:

- :mod:`~sb3_td3x.experiment.cli`: ``run.py``'s command line (read once, checked before Hydra writes anything, the
  run folder named) and its task function;
- :mod:`~sb3_td3x.experiment.runner`: :func:`~sb3_td3x.experiment.runner.run_experiment`, the one entry of a config;
- :mod:`~sb3_td3x.experiment.launch`: the ways processes that train are started, behind one interface;
- :mod:`~sb3_td3x.experiment.run`: one run: its folder and records, checkpoints, callbacks, envs, loggers;
- :mod:`~sb3_td3x.experiment.configs`: the configuration tree's schemas, its composition and checks, the algorithm;
- :mod:`~sb3_td3x.experiment.analysis`: aggregation and statistics over runs, and their plots;
- shared by all: :mod:`~sb3_td3x.experiment.stops` (stop signals), :mod:`~sb3_td3x.experiment.jobs` (the SLURM job),
  :mod:`~sb3_td3x.experiment.layout` (a run folder's file names), :mod:`~sb3_td3x.experiment.errors`.
"""
