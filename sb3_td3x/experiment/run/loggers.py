"""Metric loggers: SB3's logger writing TensorBoard events, plus Weights & Biases when configured.

Every metric goes through SB3's ``Logger`` (``train/*`` and ``rollout/*`` from the algorithm, ``eval/*`` from
:class:`~sb3_td3x.experiment.run.callbacks.PeriodicEvaluation`); W&B is one more output format of it, so TensorBoard
and W&B always show the same numbers. The W&B API key is read by ``wandb`` itself (``WANDB_API_KEY`` or
``wandb login``) and never passes through the config. What reaches TensorBoard as text or hyper-parameters, and
W&B as config or command line, goes through :func:`~sb3_td3x.common.redaction.redact` first.
"""

from __future__ import annotations

import contextlib
import logging
import netrc
import os
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from stable_baselines3.common.logger import HParam, KVWriter, Logger, SeqWriter, TensorBoardOutputFormat

from sb3_td3x.common.redaction import redact

WANDB_ID_FILE = "wandb_run_id.txt"


class RedactedTensorBoardOutputFormat(TensorBoardOutputFormat):
    """SB3's TensorBoard output, with text values and hyper-parameters redacted (secrets masked) before they are
    written."""

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        redacted = {
            key: (
                redact(value)
                if isinstance(value, str)
                else HParam(redact(dict(value.hparam_dict)), value.metric_dict)
                if isinstance(value, HParam)
                else value
            )
            for key, value in key_values.items()
        }
        super().write(redacted, key_excluded, step)


class WandbOutputFormat(KVWriter):
    """SB3 output format that logs scalars to the active W&B run, against ``global_step`` (the env step)."""

    def __init__(self, run: Any) -> None:
        self.run = run
        # Steps go back when a run resumes from a checkpoint; a custom step metric accepts that.
        run.define_metric("global_step")
        run.define_metric("*", step_metric="global_step")

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        scalars = {
            key: value
            for key, value in key_values.items()
            if isinstance(value, (int, float)) and not (key_excluded.get(key) and "wandb" in key_excluded[key])
        }
        if scalars:
            self.run.log({**scalars, "global_step": step})

    def close(self) -> None:
        pass


def wandb_api_key_configured() -> bool:
    """True when wandb would find an API key: ``WANDB_API_KEY``, or an ``api.wandb.ai`` entry in ``$NETRC`` or ~/.netrc."""
    if os.environ.get("WANDB_API_KEY"):
        return True
    path = Path(os.environ.get("NETRC") or Path.home() / ".netrc")
    try:
        return netrc.netrc(str(path)).authenticators("api.wandb.ai") is not None
    except (OSError, netrc.NetrcParseError):
        return False


def wandb_mode(mode: str) -> str:
    """``auto`` means online with an API key and offline without; ``WANDB_MODE`` in the environment wins."""
    if os.environ.get("WANDB_MODE"):
        return os.environ["WANDB_MODE"]
    if mode == "auto":
        return "online" if wandb_api_key_configured() else "offline"
    return mode


def start_wandb(wandb_cfg: DictConfig, run_dir: Path, run_name: str, config: dict[str, Any]) -> Any:
    """Start (or, for a resumed run, continue) the W&B run of ``run_dir``; its files go to ``run_dir/wandb``."""
    import wandb  # imported here: it takes a second, and only W&B runs need it

    id_file = run_dir / WANDB_ID_FILE
    run_id = (
        id_file.read_text().strip() if id_file.is_file() else uuid.uuid4().hex[:8]
    )  # os.urandom: leaves the seeded generators alone
    id_file.write_text(run_id)
    with _redacted_argv():  # W&B records the command line in the run's metadata
        return wandb.init(
            project=wandb_cfg.project,
            entity=wandb_cfg.entity,
            group=wandb_cfg.group,
            tags=list(wandb_cfg.tags),
            name=run_name,
            id=run_id,
            resume="allow",
            config=redact(config),
            dir=str(run_dir),
            mode=wandb_mode(wandb_cfg.mode),
            settings=wandb.Settings(console="off", save_code=False, x_disable_stats=True, silent=True),
        )


@contextlib.contextmanager
def _redacted_argv() -> Iterator[None]:
    """``sys.argv`` with its secrets masked, for the time of the block."""
    saved = sys.argv
    sys.argv = redact(list(saved))
    try:
        yield
    finally:
        sys.argv = saved


class PythonLogOutput(SeqWriter):
    """SB3's text messages (``logger.info(...)``, e.g. TD3X's ``update: ...`` line) as log records of the run's
    Python logger: on the console and in Hydra's log file, with the run's other lines."""

    def __init__(self, name: str = "sb3_td3x") -> None:
        self.log = logging.getLogger(name)

    def write_sequence(self, sequence: list[str]) -> None:
        self.log.info("".join(sequence))

    def close(self) -> None:
        pass


def build_logger(logger_cfg: DictConfig, run_dir: Path, wandb_run: Any | None) -> Logger:
    """SB3 ``Logger`` writing TensorBoard events to ``run_dir/tb`` and/or to W&B, and its text messages to the
    Python log."""
    output_formats: list[KVWriter | SeqWriter] = [PythonLogOutput()]
    if logger_cfg.tensorboard:
        output_formats.append(RedactedTensorBoardOutputFormat(str(run_dir / "tb")))
    if wandb_run is not None:
        output_formats.append(WandbOutputFormat(wandb_run))
    return Logger(folder=str(run_dir), output_formats=output_formats)
