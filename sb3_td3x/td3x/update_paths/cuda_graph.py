"""CUDA graphs: the whole gradient step, sampling included, captured in CUDA graphs and replayed.

:class:`GraphedGradientStep` runs :meth:`TD3X.gradient_step` as it is (every hook as written, overridden or not), so
it replaces no hook. A graph replays the kernels its capture launched, never the Python that launched them: what a
hook decides in Python at the capture is frozen into it, except :data:`GRAPH_SETTINGS`, whose change captures the
graphs again. ``cuda_graph=True`` captures the hooks as they are (the user vouches for them); what it requires (a CUDA
device, the tensor replay buffer, capturable Adam) is checked by :func:`why_not_capture`. ``cuda_graph=None``, the
default, runs the compiled update inside CUDA graphs instead (:mod:`~sb3_td3x.td3x.update_paths.compiled`), where
Dynamo's guards see every Python value the hooks read.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable
from typing import Any

import torch as th

from sb3_td3x.common.buffers import TensorReplayBuffer
from sb3_td3x.common.torch_internals import global_optimizer_hooks, optimizer_step_hooks

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]

#: The optimizers whose step can be captured (``capturable=True``): torch's own classes, not subclasses (whose
#: ``step`` may do anything).
CAPTURABLE_OPTIMIZERS = (th.optim.Adam, th.optim.AdamW)

#: The model's settings that the stock hooks read as Python numbers: a capture bakes them into its graph, so a
#: change (a callback annealing ``target_policy_noise``, say) captures the graphs again.
GRAPH_SETTINGS = (
    "gamma", "tau", "target_policy_noise", "target_noise_clip", "target_policy_smoothing", "clipped_double_q",
)  # fmt: skip


def why_not_capture(model: Any) -> str | None:
    """Why ``cuda_graph=True`` cannot capture ``model``'s gradient step, or ``None`` where it can: a CUDA device,
    TD3X's ``TensorReplayBuffer`` (sampled inside the graph), no ``VecNormalize`` (it normalises the samples on the
    host), torch's Adam or AdamW for both optimizers (``capturable=True``), without step hooks (they would run once,
    at the capture)."""
    if model.device.type != "cuda":
        return f"no CUDA device ({model.device})"
    if type(model.replay_buffer) is not TensorReplayBuffer:
        return (
            f"the replay buffer is a {type(model.replay_buffer).__name__}, not TD3X's TensorReplayBuffer "
            "(Box observations, replay_buffer_class=None)"
        )
    if model.get_vec_normalize_env() is not None:
        return "VecNormalize normalises the samples on the host"
    for role in ("actor", "critic"):
        optimizer = getattr(model, role).optimizer
        if type(optimizer) not in CAPTURABLE_OPTIMIZERS:
            return f"the {role}'s optimizer is {type(optimizer).__name__}, not torch's Adam or AdamW"
        if optimizer_step_hooks(optimizer) is not False:
            return f"step hooks on the {role}'s optimizer (or this torch hides them)"
    if global_optimizer_hooks() is not False:
        return "global optimizer step hooks (or this torch hides them)"
    return None


def cuda_graph_capture(fn: Callable[[], Infos], pool: Any | None) -> tuple[Callable[[], None], Infos, Any]:
    """Capture ``fn`` in a CUDA graph; returns (replay, the static outputs, the memory pool)."""
    graph = th.cuda.CUDAGraph()
    with th.cuda.graph(graph, pool=pool):
        outputs = fn()
    return graph.replay, outputs, graph.pool()


def _device_random_state(device: th.device) -> th.Tensor:
    return th.cuda.get_rng_state(device) if device.type == "cuda" else th.get_rng_state()


def _set_device_random_state(device: th.device, state: th.Tensor) -> None:
    if device.type == "cuda":
        th.cuda.set_rng_state(state, device)
    else:
        th.set_rng_state(state)


class GraphedGradientStep:
    """
    The whole gradient step (sampling included) captured once per (batch size, actor update or not) and replayed
    (see the module's docstring; :func:`why_not_capture` checks what it requires). The warm-up steps before a capture
    are undone (parameters, optimizer states and the device's random generator restored), so each replay computes
    the eager step that would have run in its place, with the same random draws (``tests/gpu/test_cuda.py``).

    :param model: the TD3X model
    :param capture: how to capture a step; ``cuda_graph_capture`` on a GPU. Tests on the CPU pass an eager stand-in,
        which checks everything but the capture itself: static bounds, cloned outputs, restored warm-up.
    :param warmup_steps: eager steps run before a capture (CUDA needs them on a side stream to set up its kernels)
    """

    def __init__(
        self,
        model: Any,
        capture: Callable[[Callable[[], Infos], Any | None], tuple[Callable[[], None], Infos, Any]] = cuda_graph_capture,
        warmup_steps: int = 3,
    ):
        self.model = model
        self.capture = capture
        self.warmup_steps = warmup_steps
        self._graphs: dict[tuple[int, bool], tuple[Callable[[], None], Infos]] = {}
        self._pool: Any | None = None
        self._settings: tuple[Any, ...] | None = None  # GRAPH_SETTINGS's values when the graphs were captured

    def __call__(self, batch_size: int, update_actor: bool) -> Infos:
        settings = tuple(getattr(self.model, name) for name in GRAPH_SETTINGS)
        if settings != self._settings:
            self._graphs.clear()  # captured with other values baked in
            self._settings = settings
        key = (batch_size, update_actor)
        if key not in self._graphs:
            self._graphs[key] = self._capture(batch_size, update_actor)
        replay, (critic_info, actor_info) = self._graphs[key]
        self.model.replay_buffer.refresh_static_bounds()  # type: ignore[union-attr]
        replay()
        # The outputs are static tensors overwritten by the next replay: keep copies (device ops, no sync).
        return {k: v.clone() for k, v in critic_info.items()}, {k: v.clone() for k, v in actor_info.items()}

    def _capture(self, batch_size: int, update_actor: bool) -> tuple[Callable[[], None], Infos]:
        model = self.model
        model.replay_buffer.refresh_static_bounds()  # type: ignore[union-attr]
        saved = self._snapshot()
        # The warm-up steps and the capture draw random numbers (sampling, smoothing noise): the generator is put
        # back too, so that the first replay draws what an eager step would have drawn in its place.
        random_state = _device_random_state(model.device)
        on_cuda = model.device.type == "cuda"
        stream = th.cuda.Stream() if on_cuda else None
        context = th.cuda.stream(stream) if stream is not None else contextlib.nullcontext()
        if stream is not None:
            stream.wait_stream(th.cuda.current_stream())
        with context, warnings.catch_warnings():
            # torch warns that a capturable optimizer steps outside a capture: these steps are the capture's warm-up.
            warnings.filterwarnings("ignore", message="This instance was constructed with capturable=True")
            for _ in range(self.warmup_steps):
                model.gradient_step(batch_size, update_actor)
        if stream is not None:
            th.cuda.current_stream().wait_stream(stream)
        replay, outputs, self._pool = self.capture(lambda: model.gradient_step(batch_size, update_actor), self._pool)
        self._restore(saved)
        _set_device_random_state(model.device, random_state)
        return replay, outputs

    def _tensors(self) -> list[th.Tensor]:
        """Every tensor a gradient step writes: parameters (online and target), buffers, optimizer states."""
        model = self.model
        tensors = [*model.policy.parameters(), *model.policy.buffers()]
        for optimizer in (model.actor.optimizer, model.critic.optimizer):
            for state in optimizer.state.values():
                tensors.extend(v for v in state.values() if isinstance(v, th.Tensor))
        return tensors

    @th.no_grad()
    def _snapshot(self) -> list[tuple[th.Tensor, th.Tensor]]:
        # Optimizer states may not exist yet (no step taken): the warm-up creates them, and _restore zeroes them.
        return [(t, t.clone()) for t in self._tensors()]

    @th.no_grad()
    def _restore(self, saved: list[tuple[th.Tensor, th.Tensor]]) -> None:
        saved_ids = {id(t) for t, _ in saved}
        for tensor, value in saved:
            tensor.copy_(value)
        # States created during the warm-up start from zero, as a fresh optimizer's would.
        for t in self._tensors():
            if id(t) not in saved_ids:
                t.zero_()
