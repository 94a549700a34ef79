"""One function picks how a model's update runs, and gives its reason (see the package docstring)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch as th

from sb3_td3x.td3x.hooks import changed_hooks
from sb3_td3x.td3x.update_paths.compiled import FunctionalCompiledUpdate, compiled_step, decide_compile
from sb3_td3x.td3x.update_paths.cuda_graph import GraphedGradientStep, why_not_cuda_graph
from sb3_td3x.td3x.update_paths.mlp import MlpUpdate

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]
StepFn = Callable[[int, bool], Infos]

#: ``cuda_graph_reason`` and ``update_reason`` where auto runs the update in CUDA graphs.
AUTO_GRAPHS = (
    "cuda_graph=None (auto): a CUDA device, the tensor replay buffer, Adam, and the hooks as written with SB3's ReLU "
    "MLP actor and critics, captured in CUDA graphs"
)


@dataclass
class UpdateChoice:
    """The update a model runs: ``step(batch_size, update_actor)`` does one gradient step (steps 4 to 15)."""

    path: str
    reason: str
    step: StepFn


def _sampled(model: TD3X, update: Callable[[object, bool], Infos]) -> StepFn:
    """A step that samples with the model's own ``sample_batch`` (step 4), then runs ``update`` (steps 5 to 15)."""
    return lambda batch_size, update_actor: update(model.sample_batch(batch_size), update_actor)


def choose_update(model: TD3X) -> UpdateChoice:
    """The way ``model``'s gradient steps run, and why: the fastest one that computes what its code computes.

    In order: ``cuda_graph=True`` captures the hooks as written; ``cuda_graph=None`` (auto) set up for graphs when
    the model was built captures them where :func:`why_not_cuda_graph` still finds the update stock, and otherwise
    steps aside (the model is set up for eager steps again) to what follows, saying why; ``compile_update=True``
    compiles ``MlpUpdate`` where it applies, else the hooks (functional, else as they are), and
    ``compile_update=None`` (auto) compiles ``MlpUpdate`` where
    :func:`~sb3_td3x.td3x.update_paths.compiled.why_not_compile` finds nothing against it; otherwise ``MlpUpdate``
    where it applies, else the hooks with autograd. ``mlp_update=False`` rules ``MlpUpdate`` out.
    """
    decide_compile(model)
    if model.cuda_graph:
        if model.cuda_graph_request:
            return UpdateChoice(
                "cuda_graph", "cuda_graph=True: the hooks as written, captured in CUDA graphs", GraphedGradientStep(model)
            )
        why = why_not_cuda_graph(model)
        if why is None:
            model._use_cuda_graph(True, AUTO_GRAPHS)  # again: an optimizer or the buffer may have been replaced
            return UpdateChoice("cuda_graph", AUTO_GRAPHS, GraphedGradientStep(model))
        model._use_cuda_graph(False, f"cuda_graph=None (auto) stepped aside from CUDA graphs: {why}")
        eager = _eager_choice(model)
        said = model.cuda_graph_reason if eager.reason == why else f"{model.cuda_graph_reason}; {eager.reason}"
        return UpdateChoice(eager.path, said, eager.step)
    return _eager_choice(model)


def _eager_choice(model: TD3X) -> UpdateChoice:
    """:func:`choose_update` without CUDA graphs."""
    if not getattr(model, "mlp_update", True):
        mlp_reason: str | None = "mlp_update=False"
    else:
        mlp_reason = MlpUpdate.why_not(model)
    if model.update_compiled:
        if mlp_reason is None:
            return UpdateChoice(
                "compiled_mlp",
                f"{model.compile_reason}; MlpUpdate applies (SB3's ReLU MLP actor and critics, the hooks as written)",
                _sampled(model, MlpUpdate(model, compile=True)),
            )
        if changed := changed_hooks(model, ("gradient_step",)):
            message = (
                f"compile_update=True, but {changed[0]}: compiling the update would bypass it, so the update runs "
                "as written, with autograd, uncompiled"
            )
            warnings.warn(message + ".")
            return UpdateChoice("autograd", message, model.gradient_step)
        functional_reason = FunctionalCompiledUpdate.why_not(model)
        if functional_reason is None:
            return UpdateChoice(
                "compiled",
                f"compile_update=True; the hooks compiled as written with torch.func gradients (MlpUpdate does not "
                f"apply: {mlp_reason})",
                _sampled(model, FunctionalCompiledUpdate(model)),
            )
        warnings.warn(
            f"compile_update=True: {functional_reason}, so the update is compiled as it is, with eager backward "
            "passes (slower than the functional compiled update, and often slower than no compilation)."
        )
        return UpdateChoice(
            "compiled_eager_backward",
            f"compile_update=True; update_from_batch compiled as it is ({functional_reason})",
            _sampled(model, compiled_step(model.update_from_batch)),
        )
    if mlp_reason is None:
        return UpdateChoice(
            "mlp",
            "MlpUpdate: SB3's ReLU MLP actor and critics on flat observations, the hooks as written",
            _sampled(model, MlpUpdate(model)),
        )
    return UpdateChoice("autograd", mlp_reason, model.gradient_step)


__all__ = ["AUTO_GRAPHS", "UpdateChoice", "choose_update", "why_not_cuda_graph"]
