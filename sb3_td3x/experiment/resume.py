"""What a resumed run may change, and the check of a resume's config against the checkpoint it continues.

A resumed run continues the exact computation of its checkpoint, so only settings that do not enter that computation
may change on resume: how long it trains, how often it is evaluated and checkpointed, where it logs, the device and
the thread count. Everything else (the algorithm's hyperparameters, the environment, the seed, the evaluation
episodes) is refused with the list of fields that differ, so that ``config.yaml`` always says what trained.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sb3_td3x.experiment.errors import ConfigError

#: Fields (and whole sections) a resume may change; they take effect at the checkpoint's step.
RESUMABLE = ("total_timesteps", "eval.freq", "checkpoint", "logger", "video", "device", "torch_threads", "progress_bar", "mps", "seed_processes")
#: Fields that name where the run is, not what it computes (a run folder may be moved).
LOCATION = ("run_dir", "resume", "seed_run_dirs")


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """``{"algo": {"tau": 0.005}}`` as ``{"algo.tau": 0.005}``; lists stay values."""
    if isinstance(tree, dict):
        if not tree and prefix:
            return {prefix: {}}
        flat: dict[str, Any] = {}
        for key, value in tree.items():
            flat.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    return {prefix: tree}


def _under(key: str, sections: tuple[str, ...]) -> bool:
    return any(key == section or key.startswith(section + ".") for section in sections)


def config_changes(saved: dict[str, Any], new: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The fields whose value differs between two resolved configs, as ``{key: {"from": old, "to": new}}``."""
    before, after = flatten(saved), flatten(new)
    changes = {}
    for key in sorted(before.keys() | after.keys()):
        if _under(key, LOCATION):
            continue
        old, value = before.get(key, "<unset>"), after.get(key, "<unset>")
        if old != value:
            changes[key] = {"from": old, "to": value}
    return changes


def check_resume(saved: dict[str, Any], new: dict[str, Any], run_dir: Path) -> dict[str, dict[str, Any]]:
    """The changes of ``new`` against the checkpoint's config ``saved``, if a resume may make them all.

    :raises ConfigError: listing every field a resume cannot change, with both values
    """
    changes = config_changes(saved, new)
    refused = {key: change for key, change in changes.items() if not _under(key, RESUMABLE)}
    if refused:
        listed = "; ".join(f"{key}: {change['from']!r} in the checkpoint, {change['to']!r} asked" for key, change in refused.items())
        raise ConfigError(
            f"resume={run_dir} continues the run its checkpoint holds, which cannot change {listed}. A resume may "
            f"change only {', '.join(RESUMABLE)}. Drop those overrides, or start a new run (a new run_dir) with them."
        )
    return changes


def saved_config(run_dir: Path, checkpoint: Path | None, config_file: str) -> dict[str, Any]:
    """The config a run trained with: the one its checkpoint stores, else (a checkpoint written before it kept one)
    the run's ``config.yaml``. A :class:`ConfigError` when neither can be read."""
    from sb3_td3x.experiment.checkpoints import checkpoint_config

    config = checkpoint_config(checkpoint) if checkpoint is not None else None
    if config is not None:
        return config
    path = run_dir / config_file
    try:
        loaded = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except (OSError, OmegaConfBaseException, ValueError) as error:
        raise ConfigError(
            f"resume={run_dir}: the run's config cannot be read ({path}: {' '.join(str(error).split())}), and its "
            "checkpoint predates the copy of the config kept in meta.json. Restore config.yaml (e.g. from "
            f"{run_dir}/.hydra/config.yaml) and resume again."
        ) from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"resume={run_dir}: {path} does not hold a config (it is empty or damaged).")
    return loaded
