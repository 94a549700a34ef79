"""One function picks how a model's update runs, and gives its reason (see the package docstring)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch as th

from sb3_td3x.td3x.update_paths.compiled import CompiledUpdate, decide_compile
from sb3_td3x.td3x.update_paths.cuda_graph import GraphedGradientStep

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]
StepFn = Callable[[int, bool], Infos]


@dataclass
class UpdateChoice:
    """The update a model runs: ``step(batch_size, update_actor)`` does one gradient step (steps 4 to 15)."""

    path: str
    reason: str
    step: StepFn


def choose_update(model: Any) -> UpdateChoice:
    """The way ``model``'s gradient steps run, and why: ``cuda_graph=True``'s capture, the compiled update
    (:func:`~sb3_td3x.td3x.update_paths.compiled.decide_compile`; on a GPU inside CUDA graphs) or ``gradient_step``
    itself, eagerly (the table of :mod:`sb3_td3x.td3x.update_paths`). Every way runs the model's hooks as written."""
    if model.cuda_graph:
        choice = UpdateChoice("cuda_graph", model.cuda_graph_reason, GraphedGradientStep(model))
    elif decide_compile(model):
        graphs = model.device.type == "cuda" and model.cuda_graph_request is None
        how = "the hooks as written, one graph" + (" in CUDA graphs (torch.compile's reduce-overhead)" if graphs else "")
        choice = UpdateChoice("compiled", f"{model.compile_reason}; {how}", CompiledUpdate(model, "reduce-overhead" if graphs else None))
    else:
        choice = UpdateChoice("eager", f"{model.compile_reason}; the hooks as written, eagerly", model.gradient_step)
    if (tree := getattr(model.replay_buffer, "priorities", None)) is not None:
        # A prioritised buffer's draws and new transitions' writes, outside the update's graph: compiled with it on a
        # CPU (a third of the eager time; measured in docs/variants.md). The tree's code, not the user's.
        on_cpu = choice.path == "compiled" and model.device.type == "cpu"
        tree.backend = CompiledUpdate.backend if on_cpu else None
    return choice


__all__ = ["UpdateChoice", "choose_update"]
