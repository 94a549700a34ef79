"""The configuration tree of ``conf/``: typed schemas (:mod:`~sb3_td3x.experiment.configs.schemas`), composition and
checks (:mod:`~sb3_td3x.experiment.configs.compose`), and the algorithm a config names (:mod:`~sb3_td3x.experiment.configs.algos`)."""
