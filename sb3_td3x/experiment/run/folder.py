"""The run folder: which folder a run trains in, who owns it, what may continue it, and the records it keeps.

Every way of starting a run goes through this module: ``run.py`` (:mod:`~sb3_td3x.experiment.cli` names the folder
with :func:`folder_to_train_in` before Hydra composes the config, and refuses a folder in use or already used before
Hydra writes anything into it), the Python API (:func:`~sb3_td3x.experiment.runner.run_experiment`), the sweeps (a
trial's folder) and a scheduler job that starts again after a requeue. The rules:

1. A new run takes a folder that holds no run (:func:`refuse_existing_run`).
2. ``resume=DIR`` continues DIR with the config its checkpoint trained with; a resume may change only what does not
   enter the computation: its length, the evaluation and checkpoint frequencies, logging, the device and the thread
   count (:data:`RESUMABLE`, :func:`config_for_resume`, :func:`check_resume`). Everything else (the algorithm's
   hyperparameters, the environment, the seed, the evaluation episodes) is refused with the list of fields that
   differ, so that ``config.yaml`` always says what trained.
3. A SLURM job that starts again (``scontrol requeue``, a preemption with requeue, submitit's requeue at the time
   limit) continues the folder its earlier start trained in, found by the job's identity
   (:mod:`sb3_td3x.experiment.jobs`), never by the clock: the folder its ``run_dir`` names when that folder's last
   session was this job (a multirun job's folder, a fixed ``run_dir``), else the sibling folder whose last session
   was this job (``run_dir``'s default names a new dated folder at each launch). It resumes from the checkpoint, or,
   stopped before its first checkpoint, starts afresh in the same folder.
4. One process owns a folder at a time: an OS lock on ``.lock`` (:mod:`sb3_td3x.experiment.run.lock`); a second live
   owner is refused with the holder's name, a requeued job included.

Records: ``config.yaml`` (what trains, rewritten at each session), ``provenance.jsonl`` (one line per session: its
start, its step, the job, what it resumed from, what changed), ``summary.json`` (at the end).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sb3_td3x.common.redaction import redact
from sb3_td3x.experiment import jobs
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.experiment.layout import CONFIG_FILE, EVALUATIONS_CSV, PROVENANCE_FILE, SUMMARY_FILE
from sb3_td3x.experiment.run.checkpoints import checkpoint_config, last_step, resume_checkpoint
from sb3_td3x.experiment.run.lock import RunFolderLock

#: How a session started in its folder (``provenance.jsonl``'s ``start``).
NEW, RESUMED, REQUEUED, RESTARTED = "new", "resume", "requeue", "restart after requeue"

#: Fields (and whole sections) a resume may change; they take effect at the checkpoint's step.
RESUMABLE = ("total_timesteps", "eval.freq", "checkpoint", "logger", "video", "device", "torch_threads", "progress_bar", "mps", "seed_processes")
#: Fields that name where the run is, not what it computes (a run folder may be moved).
LOCATION = ("run_dir", "resume", "seed_run_dirs")


# Naming: the folder a launch of run.py trains in ----------------------------------------------------------------------
def folder_to_train_in(resume: str | None, run_dir: str) -> Path:
    """The folder a ``run.py`` launch trains in (rules 2 and 3), named before Hydra composes the config: ``resume``'s,
    else the folder this requeued job trained in, else ``run_dir``."""
    if resume is not None:
        return Path(resume)
    found = requeued_folder(Path(run_dir))
    return found if found is not None else Path(run_dir)


# What a folder holds ---------------------------------------------------------------------------------------------------
def last_session(run_dir: Path) -> dict[str, Any] | None:
    """The last line of the folder's ``provenance.jsonl`` (None when there is none, or it cannot be read)."""
    try:
        lines = (run_dir / PROVENANCE_FILE).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return None
    for line in reversed(lines):
        try:
            record = json.loads(line)
        except ValueError:
            continue  # a line cut by a full disk: the one before it tells
        if isinstance(record, dict):
            return record
    return None


def trained_by_this_job_before(run_dir: Path) -> bool:
    """Whether the folder's last session was this scheduler job, before it started again (rule 3)."""
    job = jobs.current_job()
    if job is None or job.restarts == 0 or not run_dir.is_dir():
        return False
    session = last_session(run_dir)
    return session is not None and job.is_earlier_run_of_this_job(session.get("job"))


def requeued_folder(run_dir: Path) -> Path | None:
    """The folder this requeued job trained in: ``run_dir`` itself, or a sibling (the same name but for its date);
    None outside a job that started again, or when its earlier start made no folder."""
    job = jobs.current_job()
    if job is None or job.restarts == 0:
        return None
    if trained_by_this_job_before(run_dir):
        return run_dir
    parent = run_dir.parent
    if not parent.is_dir():
        return None
    mine = [sibling for sibling in sorted(parent.iterdir()) if sibling.is_dir() and trained_by_this_job_before(sibling)]
    return mine[-1] if mine else None


def refuse_existing_run(run_dir: Path) -> None:
    """A :class:`ConfigError` when ``run_dir`` already holds a run's records: a new run never reuses a folder."""
    if not run_dir.is_dir():
        return
    checkpoints = run_dir / "checkpoints"
    held = [name for name in (CONFIG_FILE, EVALUATIONS_CSV, SUMMARY_FILE) if (run_dir / name).exists()]
    if checkpoints.is_dir() and any(checkpoints.iterdir()):
        step = last_step(run_dir)
        held.append(f"a checkpoint at step {step}" if step is not None else "checkpoints/")
    if held:
        raise ConfigError(
            f"run_dir={run_dir} already holds a run ({', '.join(held)}). Continue that run with: python run.py "
            f"resume={run_dir}, or start this one in a new folder (a new run_dir, or none: the default names a new "
            "folder for each launch)."
        )


# Checks before anything is written (run.py's command line) ------------------------------------------------------------
def check_new(run_dir: Path) -> None:
    """``run_dir=`` of a new run: a folder (or nothing yet), not in use, holding no run unless this requeued job's."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"run_dir={run_dir} is a file, not a folder. Pass a folder for the run's records.")
    RunFolderLock.check_free(run_dir)
    if not trained_by_this_job_before(run_dir):
        refuse_existing_run(run_dir)


def check_resumable(run_dir: Path) -> Path:
    """``resume=``: a run folder not in use, with a checkpoint; returns the checkpoint."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"resume={run_dir} is a file. Pass the folder of an earlier run (it holds checkpoints/).")
    RunFolderLock.check_free(run_dir)
    if run_dir.is_dir() and not (run_dir / CONFIG_FILE).is_file() and not (run_dir / "checkpoints").is_dir():
        raise ConfigError(
            f"resume={run_dir}: {run_dir / CONFIG_FILE} does not exist. Pass the folder of an earlier run "
            "(runs/<env>/<algo>/seed<N>/<date>), which holds config.yaml and checkpoints/."
        )
    return resume_checkpoint(run_dir)


def config_for_resume(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """The config the run ``cfg.resume`` trained with (kept in its checkpoint), with the command line's overrides.

    ``python run.py resume=DIR total_timesteps=2000000`` continues DIR to 2M steps with everything else as saved.
    Every change is checked against the checkpoint (:func:`check_resume`): a resume may
    change the length, the evaluation and checkpoint frequencies, logging and the device, nothing that enters the
    computation. A config group may change where it is one of those (``logger=wandb``, ``video=final``).
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from sb3_td3x.experiment.configs.compose import compose_config
    from sb3_td3x.experiment.configs.schemas import CONFIG_GROUPS, ExperimentConfig

    run_dir = Path(cfg.resume)
    checkpoint = check_resumable(run_dir)
    saved = saved_config(run_dir, checkpoint)
    resumed = OmegaConf.merge(OmegaConf.structured(ExperimentConfig), OmegaConf.create(saved))
    for override in OverridesParser.create().parse_overrides(overrides):
        key = override.key_or_group
        if key == "resume" or key.startswith("hydra"):
            continue
        if key in CONFIG_GROUPS:
            if key not in ("logger", "video"):
                raise ConfigError(
                    f"resume={run_dir} continues the run with its saved config, so '{override.input_line}' cannot change "
                    f"the config group '{key}'. Drop it, or start a new run without resume=."
                )
            resumed[key] = compose_config([override.input_line])[key]
            continue
        OmegaConf.update(resumed, key, override.value(), merge=False)
    resumed.resume = str(run_dir)
    resumed.run_dir = str(run_dir)
    check_resume(saved, public_config(resumed), run_dir)
    return resumed


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


def saved_config(run_dir: Path, checkpoint: Path | None) -> dict[str, Any]:
    """The config a run trained with: the one its checkpoint stores, else (a checkpoint written before it kept one)
    the run's ``config.yaml``. A :class:`ConfigError` when neither can be read."""
    config = checkpoint_config(checkpoint) if checkpoint is not None else None
    if config is not None:
        return config
    path = run_dir / CONFIG_FILE
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


def seed_folders(run_dir: Path | str, seeds: Sequence[int], seed: int | None = None) -> list[Path]:
    """The run folder of each of ``seeds`` trained together from ``run_dir``; the one function that names them.

    Where ``run_dir`` has a part ``seed<seed>`` (the folder Hydra made for ``run.py seeds=[...]``, from its first
    seed), that part names each seed instead: ``runs/hopper/td3/seed3/<date>`` for seed 3, as ``seed=3`` names it.
    Otherwise (a ``run_dir=`` of the user's, a multirun job, a sweep trial) ``<run_dir>/seed<s>``.
    """
    parts = list(Path(run_dir).parts)
    if seed is None or f"seed{seed}" not in parts:
        return [Path(run_dir) / f"seed{s}" for s in seeds]
    at = len(parts) - 1 - parts[::-1].index(f"seed{seed}")
    return [Path(*parts[:at], f"seed{s}", *parts[at + 1 :]) for s in seeds]


def seed_run_dirs(cfg: DictConfig) -> list[Path]:
    """The run folder of each of ``cfg.seeds``: ``cfg.seed_run_dirs`` when set (``run.py``, or the saved config of
    the seed folder ``cfg.resume``), else ``<run_dir>/seed<s>``."""
    if cfg.seed_run_dirs is not None:
        return [Path(d) for d in cfg.seed_run_dirs]
    saved = None if cfg.resume is None else saved_seed_run_dirs(Path(cfg.resume), len(cfg.seeds))
    return saved if saved is not None else seed_folders(cfg.run_dir, cfg.seeds)


def saved_seed_run_dirs(seed_folder: Path, n_seeds: int) -> list[Path] | None:
    """Every seed's folder, as listed in the ``config.yaml`` of one of them (each lists all); None where it has none."""
    if not (seed_folder / CONFIG_FILE).is_file():
        return None
    saved = OmegaConf.load(seed_folder / CONFIG_FILE).get("seed_run_dirs")
    return [Path(d) for d in saved] if saved is not None and len(saved) == n_seeds else None


# The owner ------------------------------------------------------------------------------------------------------------
@dataclass
class Start:
    """Where and how a run starts: in ``run_dir``, resuming ``resume`` (or not), and why (:data:`NEW`, ...); for
    ``seeds=[...]``, each seed's folder."""

    run_dir: Path
    resume: Path | None
    how: str
    seed_run_dirs: list[Path] | None = None


def where_to_start(cfg: DictConfig) -> Start:
    """Rules 1 to 3 for a composed config (``cfg.resume``, ``cfg.run_dir``), whoever calls: ``run.py``, the API, a
    sweep trial, a requeued job."""
    if cfg.seeds is not None:
        return _where_a_batch_starts(cfg)
    if cfg.resume is not None:
        return Start(Path(cfg.resume), Path(cfg.resume), RESUMED)
    run_dir = Path(cfg.run_dir)
    found = requeued_folder(run_dir)
    if found is None:
        return Start(run_dir, None, NEW)
    has_checkpoint = last_step(found) is not None
    return Start(found, found if has_checkpoint else None, REQUEUED if has_checkpoint else RESTARTED)


def _where_a_batch_starts(cfg: DictConfig) -> Start:
    """A batch trains in its seeds' folders, not in ``run_dir`` (which is the first seed's folder, or, with a
    ``run_dir=`` of the user's, their parent). A resumed batch needs a checkpoint in one of its seeds' folders at least
    (a seed without one starts afresh). A requeued job finds the first seed's folder it trained in (the one named now,
    or its dated sibling), whose ``config.yaml`` lists every seed's folder; any checkpoint resumes the batch."""
    named = seed_run_dirs(cfg)
    if cfg.resume is not None:
        if named and not any(last_step(d) is not None for d in named):
            raise ConfigError(
                f"resume={cfg.resume}: none of the batch's seed folders ({', '.join(map(str, named))}) has a "
                "checkpoint, so there is nothing to resume; start the batch again without resume=."
            )
        return Start(Path(cfg.resume), Path(cfg.resume), RESUMED, named)
    run_dir = Path(cfg.run_dir)
    found = requeued_folder(named[0]) if named else None  # seeds=[]: check_config refuses it, with a message
    if found is None:
        return Start(run_dir, None, NEW, named)
    dirs = saved_seed_run_dirs(found, len(named)) or named
    has_checkpoint = any(last_step(d) is not None for d in dirs)
    return Start(
        found if run_dir == named[0] else run_dir,  # where Hydra's folder is the first seed's: the one found
        found if has_checkpoint else None,
        REQUEUED if has_checkpoint else RESTARTED,
        dirs,
    )


class RunFolder:
    """One run folder, owned by this process from :meth:`claim` to :meth:`release` (or the end of the process)."""

    def __init__(self, path: Path, lock: RunFolderLock, how: str) -> None:
        self.path = path
        self.how = how
        self._lock: RunFolderLock | None = lock

    @classmethod
    def claim(cls, run_dir: Path | str, how: str) -> RunFolder:
        """Take the folder's lock; a new run (:data:`NEW`) also refuses a folder that holds a run."""
        path = Path(run_dir)
        lock = RunFolderLock.acquire(path)
        try:
            if how == NEW:
                refuse_existing_run(path)
        except BaseException:
            lock.release()
            raise
        return cls(path, lock, how)

    def start_session(self, config: dict[str, Any], at_step: int, session: dict[str, Any], provenance: dict[str, Any]) -> None:
        """``config.yaml`` as this session trains, and its line in ``provenance.jsonl`` (with the scheduler job)."""
        write_atomically(self.path / CONFIG_FILE, OmegaConf.to_yaml(OmegaConf.create(config)))
        job = jobs.current_job()
        record: dict[str, Any] = {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "at_step": int(at_step), "start": self.how}
        if job is not None:
            record["job"] = job.record()
        with open(self.path / PROVENANCE_FILE, "a") as file:  # one line per session: a run may span several
            file.write(json.dumps(redact({**record, **session, **provenance})) + "\n")

    def write_summary(self, summary: dict[str, Any]) -> None:
        (self.path / SUMMARY_FILE).write_text(json.dumps(redact(summary), indent=2))

    def release(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None


def public_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as plain containers, with its secrets masked (``***``) by
    :func:`sb3_td3x.common.redaction.redact`: the value under a credential-like key, the password of a URL.

    This is what the run folder records (``config.yaml``, each checkpoint's ``meta.json``) and W&B receives. The
    schemas have no credential field (W&B reads its key from ``WANDB_API_KEY`` or ``wandb login``), but free-form
    dicts such as ``env.kwargs`` could receive one.
    """
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    return redact(container)  # type: ignore[return-value]


def write_atomically(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` whole: a reader (or a crash) sees the old file or the new one, never a part."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise
