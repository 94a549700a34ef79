"""What ``run.py`` does around :func:`~sb3_td3x.experiment.runner.run_experiment`: pick the run folder, rebuild
the config of a resumed run, and turn user errors into a one-paragraph message and an exit status."""

from __future__ import annotations

import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sb3_td3x.experiment.errors import ConfigError, TrainingDiverged, TrainingInterrupted
from sb3_td3x.experiment.runner import CONFIG_FILE, run_experiment
from sb3_td3x.experiment.schemas import ExperimentConfig

# Config groups of conf/config.yaml; a resumed run keeps the choices it was started with.
CONFIG_GROUPS = ("algo", "env", "eval", "logger", "video", "debug")

EXIT_CONFIG_ERROR = 2
EXIT_DIVERGED = 3


def main(cfg: DictConfig) -> float:
    """Run the experiment of a config composed by ``@hydra.main``; exit with a message on a user error."""
    try:
        if cfg.resume is not None:
            cfg = config_for_resume(cfg, list(HydraConfig.get().overrides.task))
        else:
            cfg.run_dir = HydraConfig.get().runtime.output_dir
        return run_experiment(cfg)
    except (ConfigError, OmegaConfBaseException) as error:
        _exit(f"Error: {_one_paragraph(error)}", EXIT_CONFIG_ERROR)
    except TrainingDiverged as error:
        _exit(f"Error: {error}", EXIT_DIVERGED)
    except TrainingInterrupted as error:
        _exit(str(error), error.exit_code)


def config_for_resume(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """The config saved in the run folder ``cfg.resume``, with the command line's plain overrides applied.

    ``python run.py resume=DIR total_timesteps=2000000`` continues DIR to 2M steps with everything else as saved;
    changing a config group (``env=...``) is refused, since the checkpoint belongs to the saved choices.
    """
    run_dir = Path(cfg.resume)
    saved_file = run_dir / CONFIG_FILE
    if not saved_file.is_file():
        raise ConfigError(
            f"resume={run_dir}: {saved_file} does not exist. Pass the folder of an earlier run "
            "(runs/<env>/<algo>/seed<N>/<date>), which holds config.yaml and checkpoints/."
        )
    resumed = OmegaConf.merge(OmegaConf.structured(ExperimentConfig), OmegaConf.load(saved_file))
    for override in OverridesParser.create().parse_overrides(overrides):
        key = override.key_or_group
        if key == "resume" or key.startswith("hydra"):
            continue
        if key.split(".")[0] in CONFIG_GROUPS and "." not in key:
            raise ConfigError(
                f"resume={run_dir} continues the run with its saved config, so '{override.input_line}' cannot change the "
                f"config group '{key}'. Drop it, or start a new run without resume=."
            )
        OmegaConf.update(resumed, key, override.value(), merge=False)
    resumed.resume = str(run_dir)
    resumed.run_dir = str(run_dir)
    return resumed


def _one_paragraph(error: Exception) -> str:
    return " ".join(str(error).split())


def _exit(message: str, code: int) -> None:
    print(message, file=sys.stderr)
    sys.exit(code)
