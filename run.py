"""Train TD3X on a gymnasium environment: ``python run.py algo=td3 env=ant``.

With no overrides it trains TD3 on Pendulum-v1 for 10k steps (a couple of minutes on 2 CPU cores).
Several seeds trained together (on a CPU, one process per core): ``python run.py seeds=[0,1,2,3,4]``; as separate
jobs: ``python run.py -m seed=0,1,2,3,4``; continue a stopped run: ``python run.py resume=<run folder>``.
See docs/experiments.md.
"""

import os
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from sb3_td3x.common.redaction import redact_log_records
from sb3_td3x.experiment.cli import check_command_line
from sb3_td3x.experiment.cli import main as run_main
from sb3_td3x.experiment.launch import job_watch

CONF_DIR = Path(__file__).resolve().parent / "conf"


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    return run_main(cfg)


if __name__ == "__main__":
    sys.path.append(os.getcwd())  # algo._target_ may name a module of the folder run.py is started from, as python -m
    redact_log_records()  # every log line of the run, Hydra's included, with its secrets masked
    command = check_command_line(sys.argv[1:], CONF_DIR)  # refuses a bad one; names the run folder
    job_watch.install()  # hydra/launcher=submitit_slurm: follow the jobs with scontrol where sacct does not answer
    sys.argv[1:] = command.hydra_args  # what Hydra reads: the command line, and the run folder named above
    command.run(main)  # a multirun's jobs side by side on one GPU: CUDA MPS (sb3_td3x/experiment/launch/mps.py)
