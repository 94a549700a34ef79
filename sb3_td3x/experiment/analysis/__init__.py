"""Analysis of finished runs: aggregation over seeds with bootstrap intervals (:mod:`~sb3_td3x.experiment.analysis.aggregate`),
the statistics (:mod:`~sb3_td3x.experiment.analysis.statistics`), and plots."""
