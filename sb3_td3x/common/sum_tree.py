"""Sampling in proportion to priorities in a few tensor operations: a sum tree whose levels are torch tensors.

Prioritised replay draws transition ``i`` with probability ``p_i / sum_j p_j``. TD7's buffer (sfujim/TD7, buffer.py,
lines 55-58) takes the cumulative sum of every priority at each batch and searches it; that reads the whole buffer
at every gradient step (a million floats on MuJoCo). The tree below keeps the partial sums instead: a draw walks
down its levels and an update walks up, ``depth`` steps of fixed-shape tensor operations each (4 for a million
transitions), with no host synchronisation and no Python branch on tensor values, so that ``torch.compile`` and CUDA
graphs take them as they are. Outside a compiled update, ``backend`` runs :meth:`SumTree.find` and :meth:`SumTree.set`
through ``torch.compile`` too: eagerly, each level is a dozen tensor operations of a few microseconds each.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import torch as th

log = logging.getLogger(__name__)

#: Children per node: 32 ** 4 leaves (about a million transitions) in 4 levels above the leaves.
FANOUT = 32


class SumTree:
    """The sums (and, with ``with_maxima``, the maxima) of ``size`` non-negative leaves, in a tree of fan-out 32.

    ``sums[0]`` holds the leaves, padded with zeros to ``32 ** depth``; ``sums[k]`` holds the sums of consecutive groups
    of 32 nodes of ``sums[k - 1]``, and ``sums[depth]`` the total (one element). ``maxima`` is the same tree with
    ``max`` in place of the sum (the leaves are shared). A node is always recomputed from its children (never updated
    by a difference), so the same leaves written in the same order give the same tree to the bit.

    :param size: the number of leaves
    :param device: where the levels live
    :param with_maxima: also keep the maxima (the largest leaf is then :attr:`max`, in the same operations)
    """

    #: ``torch.compile``'s backend for :meth:`find` and :meth:`set` where they are called outside a compiled function
    #: (a batch drawn before the compiled update, a new transition's priority); ``None``: eager kernels. TD3X's
    #: compiled update on a CPU sets its own (``update_paths.choose``). The same tree either way, to the bit where the
    #: backend's sums round as eager ones (``aot_eager``), and to float rounding of the inner sums otherwise.
    backend: str | None = None

    def __init__(self, size: int, device: th.device | str = "cpu", with_maxima: bool = False):
        depth = 1
        while FANOUT**depth < size:
            depth += 1
        self.size = size
        self.sums = [th.zeros(FANOUT ** (depth - k), device=device) for k in range(depth + 1)]
        self.maxima = [self.sums[0]] + [th.zeros_like(level) for level in self.sums[1:]] if with_maxima else None

    @property
    def leaves(self) -> th.Tensor:
        """The leaves, shape ``(32 ** depth,)``: ``size`` of them, then zeros."""
        return self.sums[0]

    @property
    def total(self) -> th.Tensor:
        """The sum of the leaves, shape ``(1,)``."""
        return self.sums[-1]

    @property
    def max(self) -> th.Tensor:
        """The largest leaf, shape ``()`` (``with_maxima=True`` only)."""
        if self.maxima is None:
            raise ValueError("this SumTree keeps no maxima: build it with with_maxima=True")
        return self.maxima[-1][0]

    def set(self, indices: th.Tensor, values: th.Tensor) -> None:
        """``leaves[indices] = values``, and every node above them recomputed from its children.

        A leaf given more than once takes the largest of its values (one deterministic choice, where an indexed write
        keeps an unspecified one on a GPU).

        :param indices: shape ``(n,)``, long, each in ``[0, size)``
        :param values: shape ``(n,)``, non-negative
        """
        self._run(_set, self.sums, self.maxima, indices, values)

    def find(self, mass: th.Tensor) -> th.Tensor:
        """For each ``mass`` in ``[0, total)``, the leaf ``i`` with ``c_{i-1} < mass <= c_i``, ``c`` the cumulative sums
        of the leaves: what ``torch.searchsorted(leaves.cumsum(0), mass)`` finds (TD7's buffer.py, lines 56-58), to
        the rounding of the partial sums. A leaf of zero is never found (a mass of exactly 0 finds the first leaf
        above zero), and a mass that rounding puts past a node's children finds its last leaf above zero.

        :param mass: shape ``(n,)``
        :return: the leaves' indices, shape ``(n,)``, long
        """
        return self._run(_find, self.sums, mass)

    def _run(self, fn: Callable[..., th.Tensor | None], *args: object) -> th.Tensor | None:
        """``fn(*args)``, through ``torch.compile`` (:attr:`backend`) outside a compiled function; a compilation that
        fails (a missing compiler, say) is said once and the tree goes on eagerly."""
        if self.backend is None or th.compiler.is_compiling():
            return fn(*args)
        try:
            return _compiled(fn, self.backend)(*args)
        except (th._dynamo.exc.TorchDynamoException, th._dynamo.exc.FailOnRecompileLimitHit) as error:  # before it ran
            log.warning("SumTree: torch.compile(backend=%r) failed (%s): eager from now on", self.backend, error)
            self.backend = None
            return fn(*args)

    def to(self, device: th.device | str) -> SumTree:
        """This tree on ``device`` (itself when it is there already)."""
        if self.sums[0].device == th.device(device):
            return self
        moved = SumTree.__new__(SumTree)
        moved.size = self.size
        moved.backend = self.backend if th.device(device).type == "cpu" else None  # compiled on a CPU only (choose_update)
        moved.sums = [level.to(device) for level in self.sums]
        moved.maxima = None if self.maxima is None else [moved.sums[0]] + [level.to(device) for level in self.maxima[1:]]
        return moved

    def nbytes(self) -> int:
        levels = self.sums + (self.maxima[1:] if self.maxima is not None else [])
        return sum(level.numel() * level.element_size() for level in levels)


def _set(sums: list[th.Tensor], maxima: list[th.Tensor] | None, indices: th.Tensor, values: th.Tensor) -> None:
    """:meth:`SumTree.set` on the levels ``sums`` (and ``maxima``)."""
    values = values.to(sums[0].dtype)
    if th.compiler.is_compiling() and len(indices) <= 4096:
        # The same leaves as the scatter below, in a form Inductor writes in place: each value replaced by the largest
        # given for its leaf (so repeated writes agree), then an indexed write. Inductor copies the whole leaf level
        # for a scatter_reduce_ (0.6 ms a call for a million leaves on a CPU).
        same = indices.unsqueeze(1) == indices.unsqueeze(0)
        sums[0].index_put_((indices,), th.where(same, values.unsqueeze(0), values.new_tensor(-th.inf)).amax(1))
    else:
        sums[0].scatter_reduce_(0, indices, values, reduce="amax", include_self=False)
    nodes = indices
    for k in range(1, len(sums)):
        nodes = nodes // FANOUT
        sums[k].index_put_((nodes,), sums[k - 1].view(-1, FANOUT)[nodes].sum(1))
        if maxima is not None:
            maxima[k].index_put_((nodes,), maxima[k - 1].view(-1, FANOUT)[nodes].amax(1))


def _find(sums: list[th.Tensor], mass: th.Tensor) -> th.Tensor:
    """:meth:`SumTree.find` on the levels ``sums``."""
    node = th.zeros(mass.shape, dtype=th.long, device=mass.device)
    mass = mass.clamp(min=th.finfo(mass.dtype).tiny)
    for k in range(len(sums) - 2, -1, -1):
        children = sums[k].view(-1, FANOUT)[node]  # (n, FANOUT)
        running = children.cumsum(1)
        mass = th.minimum(mass, running[:, -1])
        child = (running < mass.unsqueeze(1)).sum(1)  # the first child whose running sum reaches the mass
        before = running.gather(1, (child - 1).clamp(min=0).unsqueeze(1)).squeeze(1)
        mass = mass - th.where(child > 0, before, th.zeros_like(before))
        node = node * FANOUT + child
    return node


@functools.cache
def _compiled(fn: Callable[..., th.Tensor | None], backend: str) -> Callable[..., th.Tensor | None]:
    """``fn`` (:func:`_find` or :func:`_set`) through ``torch.compile`` with ``backend``, made once: one graph per shape
    of the tree and of the batch, shared by every tree (their levels are the graph's inputs)."""
    return th.compile(fn, fullgraph=True, backend=backend)


__all__ = ["FANOUT", "SumTree"]
