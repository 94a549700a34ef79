"""What ``run.py`` does around :func:`~sb3_td3x.experiment.runner.run_experiment`: pick the run folder, rebuild
the config of a resumed run, mask the secrets in Hydra's own records, and turn user errors into a one-paragraph
message and an exit status."""

from __future__ import annotations

import difflib
import math
import os
import re
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sb3_td3x.common.redaction import redact, redact_log_records
from sb3_td3x.experiment.checkpoints import resume_checkpoint, seed_folders
from sb3_td3x.experiment.errors import ConfigError, RunFilesNotWritten, TrainingDiverged, TrainingInterrupted
from sb3_td3x.experiment.lock import RunFolderLock
from sb3_td3x.experiment.resume import check_resume, saved_config
from sb3_td3x.experiment.runner import CONFIG_FILE, run_experiment
from sb3_td3x.experiment.schemas import ExperimentConfig, public_config, whole_float_problems

# Config groups of conf/config.yaml; a resumed run keeps the choices it was started with.
CONFIG_GROUPS = ("algo", "env", "eval", "logger", "video", "debug")

EXIT_CONFIG_ERROR = 2
EXIT_DIVERGED = 3
EXIT_NOT_WRITTEN = 4  # a full disk, a quota: the run's files could not be written


def check_command_line(args: list[str], conf_dir: Path) -> None:
    """Exit with a one-paragraph message (status 2) when the command line cannot run: a wrong group choice
    (``env=antt``), a key the config does not have (``algo.taau=0.1``), a ``resume=`` that cannot be resumed or whose
    folder another process holds, a ``run_dir=`` that is a file or already holds a run.

    Runs before ``@hydra.main``: Hydra would report these as a page of its own (with exit status 1), and would
    write its records into the run folder before the task could refuse it.
    """
    try:
        problems = whole_float_problems(args)
        if problems:
            raise ConfigError("; ".join(problems) + ".")
        plain = []  # the overrides to compose, a sweep's first value standing for the sweep
        for arg in args:
            if re.match(r"^[+~]?[A-Za-z_][\w.]*=", arg) is None:
                continue  # a flag such as -m, or something Hydra will explain itself
            try:
                override = OverridesParser.create().parse_override(arg)
            except Exception:  # Hydra's parser reports its own syntax errors well
                continue
            key = override.key_or_group
            values = list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]
            if key in CONFIG_GROUPS:
                for value in values:
                    _check_group_choice(conf_dir, key, value)
            elif key == "resume":
                for value in values:
                    if value is not None:
                        _check_resume_dir(Path(str(value)))
                        if len(values) == 1:
                            resume = OmegaConf.create({"resume": str(value)})
                            config_for_resume(resume, [a for a in args if re.match(r"^[+~]?[A-Za-z_][\w.]*=", a)])
            elif key == "run_dir" and not override.is_sweep_override() and values[0] is not None:
                _check_new_run_dir(Path(str(values[0])))
            if not key.startswith("hydra"):
                plain.append(arg if not override.is_sweep_override() else f"{arg.split('=', 1)[0]}={values[0]}")
        _check_composes(plain, conf_dir)
    except ConfigError as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_CONFIG_ERROR)


def _check_composes(overrides: list[str], conf_dir: Path) -> None:
    """Compose the config as Hydra will (with a sweep's first values): a key it does not have, a value of the
    wrong type, become a :class:`ConfigError` naming the override."""
    from hydra.errors import HydraException

    from sb3_td3x.experiment.schemas import compose_config

    if any(arg.split("=", 1)[0].lstrip("+~") == "resume" for arg in overrides):
        return  # a resume's overrides apply to the saved config (config_for_resume checks them)
    try:
        compose_config(overrides, conf_dir)
    except (HydraException, OmegaConfBaseException) as error:
        causes = [error] + ([error.__cause__] if error.__cause__ is not None else [])
        message = " ".join(" ".join(str(cause).split()).rstrip(".") + "." for cause in causes)
        raise ConfigError(f"{message} (python run.py --cfg job prints the whole config.)") from None


def _check_new_run_dir(run_dir: Path) -> None:
    from sb3_td3x.experiment.runner import refuse_existing_run

    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"run_dir={run_dir} is a file, not a folder. Pass a folder for the run's records.")
    RunFolderLock.check_free(run_dir)
    refuse_existing_run(run_dir)


def _check_group_choice(conf_dir: Path, group: str, choice: object) -> None:
    options = sorted(path.stem for path in (conf_dir / group).glob("*.yaml"))
    if choice is None or str(choice) in options:
        return
    close = difflib.get_close_matches(str(choice), options, n=1)
    hint = f" Did you mean {group}={close[0]}?" if close else ""
    raise ConfigError(
        f"{group}={choice}: there is no config '{choice}' in {conf_dir / group}.{hint} The choices are: {', '.join(options)}."
    )


def _check_resume_dir(run_dir: Path) -> None:
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"resume={run_dir} is a file. Pass the folder of an earlier run (it holds checkpoints/).")
    RunFolderLock.check_free(run_dir)
    if run_dir.is_dir() and not (run_dir / CONFIG_FILE).is_file() and not (run_dir / "checkpoints").is_dir():
        raise ConfigError(
            f"resume={run_dir}: {run_dir / CONFIG_FILE} does not exist. Pass the folder of an earlier run "
            "(runs/<env>/<algo>/seed<N>/<date>), which holds config.yaml and checkpoints/."
        )
    resume_checkpoint(run_dir)


def available_cores() -> int:
    """The CPUs this process may run on (its affinity mask where the OS has one, as joblib counts them)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def threads_per_job(n_jobs: int | None, cores: int) -> int | None:
    """Torch threads for one job of a multirun: the cores shared among the jobs that run at once.

    :param n_jobs: the launcher's ``n_jobs`` (joblib's meaning: -1 one job per core, -2 all cores but one, ...), or
        None for a launcher that runs one job at a time (Hydra's basic launcher)
    :return: the thread count, or None to leave torch's default (all cores) when jobs do not run side by side
    """
    if n_jobs is None:
        return None
    parallel = n_jobs if n_jobs > 0 else max(1, cores + 1 + n_jobs)
    return max(1, cores // parallel)


def main(cfg: DictConfig) -> float:
    """Run the experiment of a config composed by ``@hydra.main``; exit with a message on a user error.

    In a multirun, a diverged job prints its message and returns NaN, so the other jobs of the sweep go on.
    """
    hydra_cfg = HydraConfig.get()
    redact_log_records()  # run.py did it in its own process; a multirun job may run in another (joblib)
    redact_hydra_records(hydra_cfg)
    try:
        if cfg.resume is not None:
            cfg = config_for_resume(cfg, list(hydra_cfg.overrides.task))
        else:
            if cfg.seeds is not None and cfg.seed_run_dirs is None:
                cfg.seed_run_dirs = [str(d) for d in seed_folders(hydra_cfg.runtime.output_dir, cfg.seeds, cfg.seed)]
            cfg.run_dir = hydra_cfg.runtime.output_dir
        if cfg.torch_threads is None and hydra_cfg.mode == RunMode.MULTIRUN:
            # Jobs side by side share the cores; a single run keeps them all (docs/experiments.md).
            cfg.torch_threads = threads_per_job(hydra_cfg.launcher.get("n_jobs"), available_cores())
        return run_experiment(cfg)
    except (ConfigError, OmegaConfBaseException) as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_CONFIG_ERROR)
    except TrainingDiverged as error:
        if hydra_cfg.mode == RunMode.MULTIRUN:
            # One diverged job must not abort the sweep and lose the jobs running beside it.
            print(redact(f"Error: {error}"), file=sys.stderr)
            return math.nan
        _exit(f"Error: {error}", EXIT_DIVERGED)
    except TrainingInterrupted as error:
        _exit(str(error), error.exit_code)
    except RunFilesNotWritten as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_NOT_WRITTEN)


def redact_hydra_records(hydra_cfg: DictConfig) -> None:
    """Mask the secrets in the files Hydra wrote before the job started: ``.hydra/{config,hydra,overrides}.yaml``
    of the run folder (they hold the command line's overrides, ``hydra.job.env_set``, ...) and, in a multirun,
    the sweep folder's ``multirun.yaml``. Files without a secret are left as they are."""
    files: list[Path] = []
    if hydra_cfg.output_subdir is not None:
        files += sorted((Path(hydra_cfg.runtime.output_dir) / str(hydra_cfg.output_subdir)).glob("*.yaml"))
    if hydra_cfg.mode == RunMode.MULTIRUN:
        files.append(Path(hydra_cfg.sweep.dir) / "multirun.yaml")
    for path in files:
        try:
            text = path.read_text()
            tree = OmegaConf.to_container(OmegaConf.create(text), resolve=False)
        except (OSError, OmegaConfBaseException, ValueError):
            continue  # not written (yet), or not YAML OmegaConf reads: nothing of ours
        redacted = redact(tree)
        if redacted == tree:
            continue
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # jobs of a multirun may rewrite multirun.yaml together
        tmp.write_text(OmegaConf.to_yaml(OmegaConf.create(redacted)))
        os.replace(tmp, path)


def config_for_resume(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """The config the run ``cfg.resume`` trained with (kept in its checkpoint), with the command line's overrides.

    ``python run.py resume=DIR total_timesteps=2000000`` continues DIR to 2M steps with everything else as saved.
    Every change is checked against the checkpoint (:func:`~sb3_td3x.experiment.resume.check_resume`): a resume may
    change the length, the evaluation and checkpoint frequencies, logging and the device, nothing that enters the
    computation. A config group may change where it is one of those (``logger=wandb``, ``video=final``).
    """
    run_dir = Path(cfg.resume)
    _check_resume_dir(run_dir)
    saved = saved_config(run_dir, resume_checkpoint(run_dir), CONFIG_FILE)
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
            from sb3_td3x.experiment.schemas import compose_config

            resumed[key] = compose_config([override.input_line])[key]
            continue
        OmegaConf.update(resumed, key, override.value(), merge=False)
    resumed.resume = str(run_dir)
    resumed.run_dir = str(run_dir)
    check_resume(saved, public_config(resumed), run_dir)
    return resumed


def _one_paragraph(error: Exception) -> str:
    return " ".join(str(error).split())


def _exit(message: str, code: int) -> None:
    print(redact(message), file=sys.stderr)
    sys.exit(code)
