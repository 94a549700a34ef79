"""What ``run.py`` does around :func:`~sb3_td3x.experiment.runner.run_experiment`: check the command line before Hydra
writes anything, rebuild the config of a resumed run, give each job of a multirun its share of the cores, mask the
secrets in Hydra's own records, and turn user errors into a one-paragraph message and an exit status. Which folder a
run trains in, and what may continue it, is :mod:`sb3_td3x.experiment.run_folder`'s."""

from __future__ import annotations

import contextlib
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
from sb3_td3x.experiment import jobs
from sb3_td3x.experiment.checkpoints import seed_folders
from sb3_td3x.experiment.errors import (
    ConfigError,
    RunFilesNotWritten,
    SeedProcessLost,
    TrainingDiverged,
    TrainingInterrupted,
)
from sb3_td3x.experiment.run_folder import check_new, check_resumable, config_for_resume
from sb3_td3x.experiment.runner import run_experiment
from sb3_td3x.experiment.schemas import CONFIG_GROUPS, whole_float_problems

EXIT_CONFIG_ERROR = 2
EXIT_DIVERGED = 3
EXIT_NOT_WRITTEN = 4  # a full disk, a quota: the run's files could not be written
EXIT_SEED_PROCESS_LOST = 5  # seeds=[...]: a process training some seeds was killed (the others finished)


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
                        check_resumable(Path(str(value)))
                        if len(values) == 1:
                            resume = OmegaConf.create({"resume": str(value)})
                            config_for_resume(resume, [a for a in args if re.match(r"^[+~]?[A-Za-z_][\w.]*=", a)])
            elif key == "run_dir" and not override.is_sweep_override() and values[0] is not None:
                check_new(Path(str(values[0])))
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


def _check_group_choice(conf_dir: Path, group: str, choice: object) -> None:
    options = sorted(path.stem for path in (conf_dir / group).glob("*.yaml"))
    if choice is None or str(choice) in options:
        return
    close = difflib.get_close_matches(str(choice), options, n=1)
    hint = f" Did you mean {group}={close[0]}?" if close else ""
    raise ConfigError(
        f"{group}={choice}: there is no config '{choice}' in {conf_dir / group}.{hint} The choices are: {', '.join(options)}."
    )


def shared_gpu(args: list[str], conf_dir: Path) -> contextlib.AbstractContextManager:
    """CUDA MPS around a multirun whose jobs run side by side on this machine's GPU (the joblib and submitit_local
    launchers; on SLURM the cluster decides: docs/cluster.md), as :mod:`sb3_td3x.experiment.mps` decides. One line
    says what it did where the jobs use a GPU; nothing happens elsewhere."""
    from sb3_td3x.experiment import mps
    from sb3_td3x.experiment.schemas import compose_config

    if not {"-m", "--multirun"} & set(args):
        return contextlib.nullcontext()
    launcher, n_jobs, combinations, plain = "joblib_cores", None, 1, []
    for arg in args:
        if re.match(r"^[+~]?[A-Za-z_][\w./]*=", arg) is None:
            continue
        try:
            override = OverridesParser.create().parse_override(arg)
        except Exception:  # check_command_line has let Hydra explain it
            return contextlib.nullcontext()
        values = list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]
        combinations *= max(1, len(values))
        key = override.key_or_group
        if key == "hydra/launcher":
            launcher = str(values[0])
        elif key == "hydra.launcher.n_jobs":
            n_jobs = int(values[0])
        elif not key.startswith("hydra"):
            plain.append(f"{arg.split('=', 1)[0]}={values[0]}")
    if launcher not in ("joblib_cores", "joblib", "submitit_local"):
        return contextlib.nullcontext()
    parallel = combinations
    if launcher != "submitit_local":
        n_jobs = n_jobs if n_jobs is not None else (-1 if launcher == "joblib_cores" else 10)  # the plugin's default: 10
        parallel = min(combinations, jobs_at_once(n_jobs, jobs.available_cores()))
    try:
        cfg = compose_config(plain, conf_dir)
    except Exception:  # noqa: BLE001  (a composition error is reported by Hydra itself)
        return contextlib.nullcontext()
    return mps.around_launch(parallel, str(cfg.device), bool(cfg.mps), say=lambda line: print(line, file=sys.stderr))


def default_threads(multirun: bool, launcher: DictConfig | dict) -> int | None:
    """Torch threads for a run that leaves ``torch_threads`` unset (docs/experiments.md).

    In a SLURM job, the cores it was given (``--cpus-per-task``: ``cpus_per_task`` of Hydra's submitit launcher);
    in a multirun of a launcher that says its cores per job (``cpus_per_task`` of submitit's local launcher), those;
    in a joblib multirun, the machine's cores shared among the jobs that run at once; else None: torch's default,
    every core, for a single run.
    """
    cores = jobs.job_cores()
    if cores is not None:
        return cores
    if not multirun:
        return None
    if launcher.get("cpus_per_task") is not None:
        return int(launcher["cpus_per_task"])
    if "n_jobs" in launcher:
        return threads_per_job(launcher.get("n_jobs"), jobs.available_cores())
    return None


def threads_per_job(n_jobs: int | None, cores: int) -> int | None:
    """Torch threads for one job of a multirun: the cores shared among the jobs that run at once.

    :param n_jobs: the launcher's ``n_jobs`` (joblib's meaning: -1 one job per core, -2 all cores but one, ...), or
        None for a launcher that runs one job at a time (Hydra's basic launcher)
    :return: the thread count, or None to leave torch's default (all cores) when jobs do not run side by side
    """
    if n_jobs is None:
        return None
    return max(1, cores // jobs_at_once(n_jobs, cores))


def jobs_at_once(n_jobs: int, cores: int) -> int:
    """How many jobs joblib runs side by side with ``n_jobs`` (-1 one per core, -2 all cores but one, ...)."""
    return n_jobs if n_jobs > 0 else max(1, cores + 1 + n_jobs)


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
        if cfg.torch_threads is None:
            cfg.torch_threads = default_threads(hydra_cfg.mode == RunMode.MULTIRUN, hydra_cfg.launcher)
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
        jobs.after_stop(error.exit_code, str(error))  # in a job submitit runs: submitit requeues it
        _exit(str(error), error.exit_code)
    except RunFilesNotWritten as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_NOT_WRITTEN)
    except SeedProcessLost as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_SEED_PROCESS_LOST)


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


def _one_paragraph(error: Exception) -> str:
    return " ".join(str(error).split())


def _exit(message: str, code: int) -> None:
    print(redact(message), file=sys.stderr)
    sys.exit(code)
