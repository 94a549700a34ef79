"""What a finished (or paused) study leaves in its folder.

``<study folder>/``

* ``summary.txt``: trial counts by state, the best trial, the top trials, and why trials failed or were pruned;
  with ``seeds_per_trial`` above 1, the best trial's line and the top trials give each seed's final return;
* ``trials.csv``: every trial with its parameters, value, state, seed, run folder and reasons;
* ``best_overrides.txt``: the best trial's Hydra overrides, one a line: ``python run.py $(cat best_overrides.txt)``;
* ``tuned/best.yaml``: the same as a config: ``python run.py -cd <study folder> +tuned=best``;
* ``plots/``: Optuna's optimization history, parameter importances and intermediate values (matplotlib PNGs).

Files are written to a temporary name and moved into place, so a reader never sees half a file even when two
workers finish at once. ``summary.txt`` and ``trials.csv`` go through :func:`~sb3_td3x.common.redaction.redact`
(the workers also redact what they store on trials, but a study may hold older records).
"""

from __future__ import annotations

import logging
import os
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import optuna
from omegaconf import OmegaConf
from optuna.trial import FrozenTrial, TrialState

from sb3_td3x.common.redaction import redact
from sb3_td3x.sweeps.objective import SEED_VALUES, TRIAL_DEFAULTS
from sb3_td3x.sweeps.worker import LATE_RESULT_PREFIX

logger = logging.getLogger(__name__)

TUNED_GROUP = "tuned"

#: A worker records the reason of every trial it ends; a FAIL without one was ended by Optuna's heartbeat check.
STALE_REASON = "its worker stopped sending heartbeats (killed, preempted or cut off) and Optuna marked it FAIL"


@dataclass
class ResultFiles:
    summary: str  #: the text of summary.txt
    best_overrides: Path | None  #: None while no trial has completed
    plots: list[Path]


def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def best_overrides(trial: FrozenTrial) -> list[str]:
    """The overrides that retrain the best trial: its own, less its run folder (and resume) and display settings."""
    own = ("run_dir=", "resume=")  # a new run gets its own folder and starts from scratch
    return [o for o in trial.user_attrs["overrides"] if not o.startswith(own) and o not in TRIAL_DEFAULTS]


def tuned_config(overrides: list[str], config_dir: Path) -> str:
    """``overrides`` as a global config: group choices go into its defaults list, values into its body."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    groups = _config_groups(config_dir, overrides)
    parser = OverridesParser.create()
    defaults: list[dict[str, str]] = []
    body = OmegaConf.create({})
    for text in overrides:
        override = parser.parse_override(text)
        key = override.key_or_group
        if key in groups:
            defaults.append({f"override /{key}": str(override.value())})
        else:
            OmegaConf.update(body, key, override.value(), force_add=True)
    header = (
        "# @package _global_\n"
        "# The best trial of a sweep, as a config. Train with it:\n"
        f"#   python run.py -cd <this study folder> +{TUNED_GROUP}=best\n"
    )
    tree = OmegaConf.create({"defaults": defaults + ["_self_"]}) if defaults else OmegaConf.create({})
    tree = OmegaConf.merge(tree, body)
    return header + OmegaConf.to_yaml(tree)


def _config_groups(config_dir: Path, overrides: list[str]) -> set[str]:
    """The config groups of the composed config (``algo``, ``env``, ...): their overrides choose a file."""
    from hydra import compose, initialize_config_dir

    import sb3_td3x.experiment.configs.schemas  # noqa: F401

    with initialize_config_dir(config_dir=str(config_dir.resolve()), version_base="1.3", job_name="sweep"):
        cfg = compose("config", overrides=overrides, return_hydra_config=True)
    return {group for group in cfg.hydra.runtime.choices if not group.startswith("hydra/")}


def summary_text(study: optuna.Study, storage_display: str, dashboard_command: str, dashboard_hint: str | None = None) -> str:
    """The text of ``summary.txt``, secrets masked; ``dashboard_hint`` (a sentence on how to give the dashboard a
    masked password) goes under the dashboard command."""
    trials = study.get_trials(deepcopy=False)
    counts = Counter(t.state.name for t in trials)
    metric = study.user_attrs.get("metric", "value")
    lines = [
        f"study {study.study_name} in {storage_display}",
        f"{len(trials)} trials: " + ", ".join(f"{n} {state}" for state, n in sorted(counts.items())),
    ]
    complete = [t for t in trials if t.state == TrialState.COMPLETE]
    if complete:
        best = study.best_trial
        lines += [
            (
                f"best: trial {best.number}, {metric} = {best.value:.3f}, {_seeds_text(best)}, "
                f"run folder {best.user_attrs.get('run_dir')}"
            ),
            "",
            "top trials:",
            _table(sorted(complete, key=lambda t: t.value, reverse=study.direction.name == "MAXIMIZE")[:10]),
        ]
    else:
        lines.append("no trial has completed yet")
    stopped = [t for t in trials if t.state in (TrialState.PRUNED, TrialState.FAIL)]
    if stopped:
        lines += ["", "pruned and failed trials:"]
        for t in stopped:
            reason = t.user_attrs.get("fail_reason") or t.user_attrs.get("prune_reason") or STALE_REASON
            lines.append(f"  {t.number:4d} {t.state.name:7s} {reason}")
    lines += _late_results_lines(study)
    lines += ["", f"dashboard: {dashboard_command}"]
    if dashboard_hint:
        lines.append(f"  {dashboard_hint}")
    return redact("\n".join(lines) + "\n")


def _late_results_lines(study: optuna.Study) -> list[str]:
    """Results that cut-off workers measured after their trial had been failed as stale (``late_result_trial_<n>``)."""
    late = sorted(
        (int(key.removeprefix(LATE_RESULT_PREFIX)), value)
        for key, value in study.user_attrs.items()
        if key.startswith(LATE_RESULT_PREFIX)
    )
    if not late:
        return []
    lines = ["", "late results (a worker cut off past the grace period came back after its trial was failed):"]
    for number, result in late:
        value = "no value" if result.get("value") is None else f"{result['value']:.3f}"
        lines.append(
            f"  {number:4d} {value} at step {result.get('step')}, {result.get('outcome')} in worker {result.get('worker')}; "
            f"the trial stays {result.get('state_in_study')} (study attribute {LATE_RESULT_PREFIX}{number})"
        )
    return lines


def _seeds_text(trial: FrozenTrial) -> str:
    """``seed 3``; for a trial of several seeds ``mean of 2 seeds: 4 -1210.52, 5 -1302.10`` (each one's final return)."""
    seeds = trial.user_attrs.get("seeds")
    if seeds is None:
        return f"seed {trial.user_attrs.get('seed')}"
    aggregate = trial.user_attrs.get("seeds_aggregate", "mean")
    return f"{aggregate} of {len(seeds)} seeds: " + ", ".join(f"{seed} {value}" for seed, value in _seed_finals(trial))


def _seed_finals(trial: FrozenTrial) -> list[tuple[int, str]]:
    values = trial.user_attrs.get(SEED_VALUES) or {}
    return [(seed, f"{values[str(seed)]:.2f}" if str(seed) in values else "?") for seed in trial.user_attrs["seeds"]]


def _table(trials: list[FrozenTrial]) -> str:
    import pandas as pd

    rows = []
    for t in trials:
        row = {"trial": t.number, "value": round(t.value, 3), **t.params}
        if t.user_attrs.get("seeds") is None:
            row["seed"] = t.user_attrs.get("seed")
        else:  # several seeds: which, and each one's final return
            row["seeds"] = ",".join(str(seed) for seed in t.user_attrs["seeds"])
            row["per seed"] = " ".join(value for _, value in _seed_finals(t))
        rows.append(row)
    return pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.4g}")


def trials_csv(study: optuna.Study) -> str:
    frame = study.trials_dataframe(attrs=("number", "state", "value", "params", "user_attrs", "datetime_start", "duration"))
    return redact(frame.to_csv(index=False))


def save_plots(study: optuna.Study, plot_dir: Path) -> list[Path]:
    """Optuna's matplotlib plots; a plot that needs more trials than the study has is skipped with a log line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.visualization import matplotlib as vis

    plots = {
        "optimization_history": vis.plot_optimization_history,
        "param_importances": vis.plot_param_importances,
        "intermediate_values": vis.plot_intermediate_values,
    }
    saved = []
    plot_dir.mkdir(parents=True, exist_ok=True)
    for name, plot in plots.items():
        path = plot_dir / f"{name}.png"
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # experimental-feature and too-few-trials warnings
                axes = plot(study)
            figure = axes.figure if hasattr(axes, "figure") else axes.flat[0].figure
            figure.set_size_inches(9, 5)
            figure.tight_layout()
            tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.png")
            figure.savefig(tmp, dpi=100)
            os.replace(tmp, path)
            plt.close(figure)
            saved.append(path)
        except Exception as err:  # noqa: BLE001  (e.g. importances need two completed trials with varied parameters)
            logger.info("plot %s skipped: %s", name, err)
    return saved


def write_results(
    study: optuna.Study,
    study_dir: Path,
    config_dir: Path,
    storage_display: str,
    dashboard_command: str,
    dashboard_hint: str | None = None,
) -> ResultFiles:
    """Write the study's results into ``study_dir`` (see the module docstring)."""
    summary = summary_text(study, storage_display, dashboard_command, dashboard_hint)
    _atomic_write(study_dir / "summary.txt", summary)
    if study.get_trials(deepcopy=False):
        _atomic_write(study_dir / "trials.csv", trials_csv(study))
    best_path = None
    if any(t.state == TrialState.COMPLETE for t in study.get_trials(deepcopy=False)):
        overrides = redact(best_overrides(study.best_trial))
        best_path = study_dir / "best_overrides.txt"
        _atomic_write(best_path, "\n".join(overrides) + "\n")
        _atomic_write(study_dir / TUNED_GROUP / "best.yaml", tuned_config(overrides, config_dir))
    plots = save_plots(study, study_dir / "plots")
    return ResultFiles(summary, best_path, plots)
