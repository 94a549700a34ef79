"""What ``run.py`` does around :func:`~sb3_td3x.experiment.runner.run_experiment`.

Before Hydra starts, :func:`check_command_line` reads the command line once, with Hydra's own parsers:

- a command line that cannot run is refused with a one-paragraph message (exit status 2) before Hydra writes
  anything: a wrong group choice (``env=antt``), a key the config does not have, a value out of range, a ``resume=``
  that cannot be resumed or whose folder another process holds, a ``run_dir=`` that is a file or holds a run;
- the config is composed once (a multirun's sweep standing for its first values) and checked
  (:func:`~sb3_td3x.experiment.configs.compose.check_config`);
- the folder a single run trains in is named (:func:`~sb3_td3x.experiment.run.folder.folder_to_train_in`:
  ``resume=``'s, or the one a requeued SLURM job trained in, else ``run_dir``) and handed to Hydra as
  ``hydra.run.dir``, so that Hydra writes its records and ``run.log`` there;
- the launch is described (:class:`~sb3_td3x.experiment.launch.hydra_jobs.HydraJobs`): a multirun's jobs side by side
  on this machine's GPU share it through CUDA MPS.

In each job, :func:`main` (under ``@hydra.main``) rebuilds the config of a resumed run, gives the job its share of
the cores, masks the secrets in Hydra's own records, and turns user errors into a one-paragraph message and an exit
status.
"""

from __future__ import annotations

import difflib
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sb3_td3x.common.redaction import redact, redact_log_records
from sb3_td3x.experiment import jobs, stops
from sb3_td3x.experiment.configs.compose import check_config, compose_config, whole_float_problems
from sb3_td3x.experiment.configs.schemas import CONFIG_GROUPS
from sb3_td3x.experiment.errors import (
    ConfigError,
    RunFilesNotWritten,
    SeedProcessLost,
    TrainingDiverged,
    TrainingInterrupted,
)
from sb3_td3x.experiment.launch.hydra_jobs import HydraJobs
from sb3_td3x.experiment.run.folder import check_new, check_resumable, config_for_resume, folder_to_train_in, seed_folders
from sb3_td3x.experiment.runner import run_experiment

EXIT_CONFIG_ERROR = 2
EXIT_DIVERGED = 3
EXIT_NOT_WRITTEN = 4  # a full disk, a quota: the run's files could not be written
EXIT_SEED_PROCESS_LOST = 5  # seeds=[...]: a process training some seeds was killed (the others finished)

#: Hydra's flags that only print something: nothing is launched, so nothing is checked or named.
_INFORMATION = ("help", "hydra_help", "version", "shell_completion", "info", "experimental_rerun")


@dataclass
class CommandLine:
    """``run.py``'s command line, read once by :func:`check_command_line`."""

    hydra_args: list[str]  #: what Hydra parses: the command line, plus ``hydra.run.dir`` where it was named here
    launch: HydraJobs  #: the jobs this command line launches
    device: str = "cpu"  #: the config's device and ``mps``: whether the jobs share a GPU through CUDA MPS
    mps: bool = False

    def run(self, main: Callable[[], Any]) -> Any:
        """Hydra's ``main`` (which reads ``hydra_args`` from ``sys.argv``), inside the launch's CUDA MPS."""
        self.launch.main = main
        return self.launch.run(self.device, self.mps)


def check_command_line(args: list[str], conf_dir: Path) -> CommandLine:
    """Read ``run.py``'s command line (see the module's docstring); exit with a one-paragraph message (status 2) when
    it cannot run. Runs before ``@hydra.main``: Hydra would report these errors as a page of its own (with exit status
    1), and would write its records into the run folder before the task could refuse it."""
    from hydra._internal.utils import get_args_parser  # the parser of @hydra.main itself

    parsed = get_args_parser().parse_args(args)  # a wrong flag: argparse's message and exit status 2, as Hydra's
    as_given = CommandLine(list(args), HydraJobs({}, multirun=False))
    if any(getattr(parsed, flag, None) for flag in _INFORMATION):
        return as_given
    try:
        overrides = OverridesParser.create().parse_overrides(parsed.overrides)
    except Exception:  # noqa: BLE001  (Hydra's parser reports its own syntax errors well, when Hydra starts)
        return as_given
    try:
        return _read(args, parsed, overrides, conf_dir)
    except ConfigError as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_CONFIG_ERROR)
        raise  # not reached: _exit exits


def _read(args: list[str], parsed: Any, overrides: list[Override], conf_dir: Path) -> CommandLine:
    problems = whole_float_problems(overrides)
    if problems:
        raise ConfigError("; ".join(problems) + ".")
    first: list[str] = []  # the overrides of the first run: a sweep's first value stands for the sweep
    n_runs, resume, named = 1, None, False
    for override in overrides:
        key = override.key_or_group
        values = list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]
        n_runs *= max(1, len(values))
        if key in CONFIG_GROUPS:
            for value in values:
                _check_group_choice(conf_dir, key, value)
        elif key == "resume":
            for value in values:
                if value is not None:
                    check_resumable(Path(str(value)))
            resume = str(values[0]) if len(values) == 1 and values[0] is not None else None
        elif key == "run_dir" and not override.is_sweep_override() and values[0] is not None:
            check_new(Path(str(values[0])))
        named = named or key == "hydra.run.dir"
        text = override.input_line
        first.append(text if not override.is_sweep_override() else f"{text.split('=', 1)[0]}={values[0]}")
    conf, config_name, first = _config_source(parsed, conf_dir, first)
    multirun = bool(parsed.multirun)
    if resume is not None:  # a resume's overrides apply to its saved config, which config_for_resume checks
        cfg = config_for_resume(OmegaConf.create({"resume": resume}), [o.input_line for o in overrides])
        hydra = _compose([o for o in first if o.lstrip("+~").startswith("hydra")], conf, config_name).hydra
    else:
        composed = _compose(first, conf, config_name)
        hydra, cfg = composed.hydra, composed
    launch = HydraJobs(hydra.launcher, multirun, n_runs)
    if resume is None:
        check_config(cfg, on_this_machine=launch.side_by_side > 0)
    hydra_args = list(args)
    if not multirun and not named:
        folder = folder_to_train_in(resume, str(cfg.run_dir))
        hydra_args.append(f"hydra.run.dir={_quoted(str(folder))}")
    return CommandLine(hydra_args, launch, str(cfg.device), bool(cfg.mps))


def _config_source(parsed: Any, conf_dir: Path, overrides: list[str]) -> tuple[Path, str, list[str]]:
    """The config folder and name Hydra composes from (``-cp``, ``-cn``), and the overrides with ``-cd``'s folder added
    to the search path, as Hydra adds it."""
    conf = conf_dir
    if parsed.config_path is not None:
        conf = Path(parsed.config_path) if Path(parsed.config_path).is_absolute() else conf_dir.parent / parsed.config_path
    if parsed.config_dir is not None:
        overrides = [*overrides, f"hydra.searchpath=[{_quoted('file://' + str(Path(parsed.config_dir).resolve()))}]"]
    return conf, parsed.config_name or "config", overrides


def _compose(overrides: list[str], conf: Path, config_name: str) -> DictConfig:
    """The config of ``overrides``, as Hydra will compose it, with its ``hydra`` node: a key it does not have, a
    value of the wrong type, become a :class:`ConfigError` naming the override."""
    from hydra.errors import HydraException

    try:
        return compose_config(overrides, conf, config_name=config_name, with_hydra=True)
    except (HydraException, OmegaConfBaseException) as error:
        causes = [error] + ([error.__cause__] if error.__cause__ is not None else [])
        message = " ".join(" ".join(str(cause).split()).rstrip(".") + "." for cause in causes)
        raise ConfigError(f"{message} (python run.py --cfg job prints the whole config.)") from None


def _quoted(text: str) -> str:
    """``text`` as a quoted value of Hydra's override grammar."""
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _check_group_choice(conf_dir: Path, group: str, choice: object) -> None:
    options = sorted(path.stem for path in (conf_dir / group).glob("*.yaml"))
    if choice is None or str(choice) in options:
        return
    close = difflib.get_close_matches(str(choice), options, n=1)
    hint = f" Did you mean {group}={close[0]}?" if close else ""
    raise ConfigError(
        f"{group}={choice}: there is no config '{choice}' in {_as_typed(conf_dir / group)}.{hint} The choices are: "
        f"{', '.join(options)}."
    )


def _as_typed(path: Path) -> str:
    """``path`` relative to the folder run.py was started in, where it lies below it (``conf/env``), else whole."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


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
            launch = HydraJobs(hydra_cfg.launcher, multirun=hydra_cfg.mode == RunMode.MULTIRUN)
            cfg.torch_threads = launch.threads_per_process(jobs.available_cores())
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
        stops.after_stop(error.exit_code, str(error))  # in a job submitit runs: submitit requeues it
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
