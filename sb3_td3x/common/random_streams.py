"""A model's random streams: the generators it draws from, the global ones or its own copies of them.

SB3's TD3 draws from the global generators that ``set_random_seed`` seeds: numpy's (replay indices, Gaussian action
noise), torch's (target policy smoothing noise), Python's ``random``, and the CUDA generator of its device. TD3X's own
code draws from ``model.random_streams`` instead, which is bound to those same global generators: a lone TD3X draws
the numbers SB3's TD3 draws, in the same order. :meth:`RandomStreams.detach` gives the model private copies of them,
taken where they stand; from then on its own code draws from the copies, so many models can run side by side in one
process without swapping global state (``SeedBatch``), and :meth:`RandomStreams.installed` makes the copies the
global generators for a while, around code that draws from the globals itself (a user's action noise or hook).
"""

from __future__ import annotations

import contextlib
import random
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch as th


def _cuda_index(device: th.device | str) -> int | None:
    device = th.device(device)
    if device.type != "cuda":
        return None
    return device.index if device.index is not None else th.cuda.current_device()


class RandomStreams:
    """The generators a model draws from (see the module's docstring).

    :param device: the model's device: with a GPU, its CUDA generator is one of the streams
    """

    def __init__(self, device: th.device | str = "cpu"):
        self.cuda_index = _cuda_index(device)
        if self.cuda_index is not None:
            th.cuda.init()  # fills th.cuda.default_generators
        self._own: tuple[random.Random, np.random.RandomState, th.Generator, th.Generator | None] | None = None
        self._installed = False

    # The generators to draw from now: the global ones while bound or installed, else the model's own copies.
    @property
    def bound(self) -> bool:
        """Whether the streams are the global generators now (not detached, or installed)."""
        return self._own is None or self._installed

    def _generators(self) -> tuple[random.Random, np.random.RandomState, th.Generator, th.Generator | None]:
        if not self.bound:
            return self._own  # type: ignore[return-value]
        cuda = None if self.cuda_index is None else th.cuda.default_generators[self.cuda_index]
        # random.random and np.random.* are methods of these two instances.
        return random._inst, np.random.mtrand._rand, th.default_generator, cuda  # type: ignore[attr-defined]

    @property
    def python(self) -> random.Random:
        return self._generators()[0]

    @property
    def numpy(self) -> np.random.RandomState:
        return self._generators()[1]

    def torch(self, device: th.device) -> th.Generator:
        """The torch generator of ``device`` (the model's CPU or CUDA one)."""
        generators = self._generators()
        return generators[3] if device.type == "cuda" else generators[2]  # type: ignore[return-value]

    # ------------------------------------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Every stream's state, as checkpoints keep it."""
        py, np_rng, torch_rng, cuda = self._generators()
        return {
            "python": py.getstate(),
            "numpy": np_rng.get_state(),
            "torch": torch_rng.get_state(),
            "torch_cuda": None if cuda is None else cuda.get_state(),
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Put the streams where :meth:`state` found them."""
        py, np_rng, torch_rng, cuda = self._generators()
        py.setstate(state["python"])
        np_rng.set_state(state["numpy"])
        torch_rng.set_state(state["torch"])
        cuda_state = state.get("torch_cuda")
        if isinstance(cuda_state, (list, tuple)):  # an older checkpoint: every device's state
            cuda_state = cuda_state[self.cuda_index] if self.cuda_index is not None and cuda_state else None
        if cuda is not None and cuda_state is not None:
            cuda.set_state(cuda_state)

    def detach(self) -> RandomStreams:
        """From now on, draw from private copies of the generators, taken where the bound ones stand."""
        if self._own is None:
            state = self.state()
            cuda = None if self.cuda_index is None else th.Generator(device=f"cuda:{self.cuda_index}")
            self._own = (random.Random(), np.random.RandomState(), th.Generator(), cuda)
            self.set_state(state)
        return self

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        """Detached streams as the global generators inside (what is drawn there is kept); the global state is put
        back at the end. Bound or already installed streams: nothing to do."""
        if self.bound:
            yield
            return
        own = self.state()
        caller = RandomStreams(th.device("cpu") if self.cuda_index is None else th.device("cuda", self.cuda_index))
        saved = caller.state()
        self._installed = True
        try:
            self.set_state(own)
            yield
        finally:
            drawn = self.state()
            self._installed = False
            self.set_state(drawn)
            caller.set_state(saved)


def detached_streams(model: Any) -> RandomStreams:
    """``model``'s streams, detached where they stand (the global state now, for a model that has none of its own,
    as SB3's algorithms: it must then run with them installed)."""
    streams = getattr(model, "random_streams", None)
    if not isinstance(streams, RandomStreams):
        streams = RandomStreams(model.device)
    return streams.detach()


__all__ = ["RandomStreams", "detached_streams"]
