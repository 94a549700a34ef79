"""``cuda_graph=True``: the whole gradient step, sampling included, captured in CUDA graphs and replayed.

It runs :meth:`TD3X.gradient_step` as it is (every hook as written, overridden or not), so it replaces no hook;
what it requires (a CUDA device, the tensor replay buffer, capturable Adam) is checked when the model is built.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch as th

if TYPE_CHECKING:
    from sb3_td3x.td3x.td3x import TD3X

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]


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
    The whole gradient step (sampling included) captured once per (batch size, actor update or not) and replayed.

    Requirements, checked by ``TD3X``: a CUDA device, the tensor replay buffer (sampled on the device from bounds
    kept in device tensors), no ``VecNormalize`` (it normalises on the host), and Adam with ``capturable=True``.
    The warm-up steps that precede a capture are undone (parameters, optimizer states and the device's random
    generator restored), so capturing does not change what is learned: each replay computes the eager step that
    would have run in its place, with the same random draws (``tests/gpu/test_cuda.py`` checks it on a GPU).

    :param model: the TD3X model
    :param capture: how to capture a step; ``cuda_graph_capture`` on a GPU. Tests on the CPU pass an eager stand-in,
        which checks everything but the capture itself: static bounds, cloned outputs, restored warm-up.
    :param warmup_steps: eager steps run before a capture (CUDA needs them on a side stream to set up its kernels)
    """

    def __init__(
        self,
        model: TD3X,
        capture: Callable[[Callable[[], Infos], Any | None], tuple[Callable[[], None], Infos, Any]] = cuda_graph_capture,
        warmup_steps: int = 3,
    ):
        self.model = model
        self.capture = capture
        self.warmup_steps = warmup_steps
        self._graphs: dict[tuple[int, bool], tuple[Callable[[], None], Infos]] = {}
        self._pool: Any | None = None

    def __call__(self, batch_size: int, update_actor: bool) -> Infos:
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
        with context:
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
