"""What the compiled update asks of Inductor beyond its defaults: three rewrites of the update's graph as traced, on
a CPU (:func:`cpu_passes`, Inductor's last post-grad pass), over whatever hooks, networks and optimizer steps it holds.

- :func:`bias_after_product`: each ``addmm(bias, x, w)`` (a ``Linear``'s forward, whoever wrote it) becomes
  ``mm(x, w) + bias``, and each ``baddbmm`` ``bmm(x, w) + bias``, so that the bias is added by the pointwise kernel
  Inductor generates after the product (the ReLU's, the loss's) instead of inside the product. ATen's CPU ``addmm``
  first copies the broadcast bias into its output, then calls the BLAS product with ``beta=1``, which reads that
  output back; Inductor already unfuses it so on a GPU (``unfuse_bias_add_to_pointwise``), not on a CPU. The same sum,
  rounded once more apart: ``x @ w`` is rounded before the bias is added, as an eager ``x @ w + b`` is.
- :func:`scalars_once`: each single number the graph computes (Adam's bias corrections, from the step count) and an
  op over a whole tensor reads is computed once, into a buffer of its own. Inductor otherwise inlines it into the
  loop of its reader, and its generated C++ computes it again for every 16 elements: two ``std::pow`` per vector
  step of each parameter's Adam update (the compiler cannot hoist them: the loop's stores may alias the step count it
  reads). The same numbers, computed once.
- :func:`products_read_in_part`: a product whose one reader keeps some of its columns (or rows) computes only those.
  The actor's loss differentiates the critic's first layer with respect to its whole input, the observation and the
  action concatenated, and keeps the action's columns: on Ant-v5, 8 columns of 113 (1% of a gradient step).

Measured in ``docs/performance_log.md``.
"""

from __future__ import annotations

import functools
from typing import Any

import torch as th


def bias_after_product(graph: th.fx.Graph) -> None:
    """``addmm(bias, x, w)`` on a CPU, in float32 or float64 with ``alpha = beta = 1``: ``mm(x, w) + bias``; and
    ``baddbmm`` (critics or seeds stacked in one batched product), as ``bmm(x, w) + bias``. Other dtypes keep theirs
    (in bfloat16 the fused sum is rounded once, the product's would be rounded before)."""
    aten = th.ops.aten
    products = {aten.addmm.default: aten.mm.default, aten.baddbmm.default: aten.bmm.default}
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target not in products:
            continue
        val = node.meta.get("val")
        if not _cpu_float(val) or node.kwargs.get("alpha", 1) != 1 or node.kwargs.get("beta", 1) != 1:
            continue
        bias, x, w = node.args[:3]
        with graph.inserting_before(node):
            product = graph.call_function(products[node.target], (x, w))
            product.meta["val"] = val.new_empty(val.shape)
            total = graph.call_function(aten.add.Tensor, (product, bias))
            total.meta["val"] = val
        node.replace_all_uses_with(total)
        graph.erase_node(node)


def scalars_once(graph: th.fx.Graph) -> None:
    """Each 0-d CPU tensor that a pointwise op computes and an op over a tensor of one dimension or more reads, read
    by it through ``as_strided(value, [], [])``: the identity on a 0-d tensor, which Inductor lowers by computing the
    value into a buffer (it realizes an ``as_strided``'s input) that the reader's loop loads."""
    for node in list(graph.nodes):
        val = node.meta.get("val")
        if (node.op != "call_function" or not isinstance(node.target, th._ops.OpOverload)
                or th.Tag.pointwise not in node.target.tags
                or not isinstance(val, th.Tensor) or val.dim() != 0 or val.device.type != "cpu"):  # fmt: skip
            continue
        readers = [user for user in node.users if _has_dimensions(user.meta.get("val"))]
        if not readers:
            continue
        with graph.inserting_after(node):
            computed = graph.call_function(th.ops.aten.as_strided.default, (node, [], []))
            computed.meta["val"] = val
        for user in readers:
            user.replace_input_with(node, computed)


#: :func:`products_read_in_part` rewrites a product only where it leaves out at least this many multiply-adds: MKL's
#: product of a few columns costs 9 to 17 us at any size, so on Hopper-v5 (100 by 400 by 14, 3 columns kept, 440,000
#: left out) the part took 12.7 us against the whole one's 8.9; on Ant-v5 (256 by 400 by 113, 8 kept) 17 against 98.
LEFT_OUT_AT_LEAST = 1_000_000


def products_read_in_part(graph: th.fx.Graph) -> None:
    """``mm(x, w)[:, a:b]`` becomes ``mm(x, w[:, a:b])``, and ``mm(x, w)[a:b]`` ``mm(x[a:b], w)``, where the slice (of
    step 1) is the product's only reader and what it leaves out is worth it (:data:`LEFT_OUT_AT_LEAST`); on a CPU, in
    float32 or float64 (as measured). Each element of the result is the same sum of the same products; the BLAS may
    block it otherwise, so the rounding can differ."""
    aten = th.ops.aten
    for node in list(graph.nodes):
        val = node.meta.get("val")
        if node.op != "call_function" or node.target is not aten.mm.default or len(node.users) != 1 or not _cpu_float(val):
            continue
        (part,) = node.users
        if part.target is not aten.slice.Tensor or part.kwargs or len(part.args) not in (4, 5):
            continue
        dim, start, end, step = (*part.args[1:], 1)[:4]
        if dim not in (0, 1, -1, -2) or step != 1 or not all(isinstance(i, int) for i in (start, end)):
            continue
        x, w = node.args
        sliced, operand_dim = (x, 0) if dim in (0, -2) else (w, 1)
        (rows, inner), (kept_rows, kept_columns) = x.meta["val"].shape, part.meta["val"].shape
        if (rows * val.shape[1] - kept_rows * kept_columns) * inner < LEFT_OUT_AT_LEAST:
            continue
        with graph.inserting_before(node):
            kept = graph.call_function(aten.slice.Tensor, (sliced, operand_dim, start, end))
            kept.meta["val"] = sliced.meta["val"][(slice(None),) * operand_dim + (slice(start, end),)]
            product = graph.call_function(aten.mm.default, (kept, w) if operand_dim == 0 else (x, kept))
            product.meta["val"] = part.meta["val"].new_empty(part.meta["val"].shape)
        part.replace_all_uses_with(product)
        graph.erase_node(part)
        graph.erase_node(node)


def _cpu_float(val: Any) -> bool:
    """Whether an op's result is a float32 or float64 tensor on a CPU: where the product rewrites were measured."""
    return isinstance(val, th.Tensor) and val.device.type == "cpu" and val.dtype in (th.float32, th.float64)


def _has_dimensions(val: Any) -> bool:
    """Whether an op's result (a tensor, or a list of them) has a tensor of one dimension or more."""
    if isinstance(val, (list, tuple)):
        return any(_has_dimensions(v) for v in val)
    return isinstance(val, th.Tensor) and val.dim() > 0


@functools.cache
def cpu_passes() -> Any:
    """The three rewrites as one Inductor custom pass (one instance: Inductor's cache keys on its :meth:`uuid`, the hash of
    this file); imported with Inductor, at the first compiled step. ``None`` with a torch whose Inductor has no
    ``custom_graph_pass`` module (older than the 2.13 this is measured on): the update is then compiled without them."""
    try:
        from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files
    except ImportError:
        return None

    class CpuPasses(CustomGraphPass):
        def __call__(self, graph: th.fx.Graph) -> None:
            bias_after_product(graph)
            scalars_once(graph)
            products_read_in_part(graph)

        def uuid(self) -> bytes:
            return get_hash_for_files((__file__,))

    return CpuPasses()


def inductor_options(options: dict[str, Any] | None) -> dict[str, Any] | None:
    """``torch.compile``'s ``options`` for the update: :func:`cpu_passes` as Inductor's last post-grad pass, unless
    ``options`` (:attr:`CompiledUpdate.options`) or Inductor's global config already name a pass of their own, which
    then runs alone."""
    from torch._inductor import config as inductor_config

    key, passes = "post_grad_custom_post_pass", cpu_passes()
    if (options or {}).get(key) is not None or getattr(inductor_config, key, None) is not None or passes is None:
        return options
    return {key: passes, **(options or {})}
