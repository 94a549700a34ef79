"""One run: the run folder (which, who owns it, its records), checkpoints, callbacks, envs, loggers, the value
measurement, and the training of one seed (:mod:`~sb3_td3x.experiment.run.train`) or of seeds together in one process
(:mod:`~sb3_td3x.experiment.run.seeds`)."""
