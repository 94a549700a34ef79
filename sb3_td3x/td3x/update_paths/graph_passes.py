"""What the compiled update asks of Inductor beyond its defaults: a graph pass over the update as traced.

:class:`BiasAfterProduct`: on a CPU, each ``addmm(bias, x, w)`` of the graph (a ``Linear``'s forward, whoever wrote
it) becomes ``mm(x, w) + bias``, and each ``baddbmm`` ``bmm(x, w) + bias``, so that the bias is added by the pointwise
kernel Inductor generates after the product (the ReLU's, the loss's) instead of inside the product. ATen's CPU
``addmm`` first copies the broadcast bias into its output, then calls the BLAS product with ``beta=1``, which reads
that output back; Inductor already unfuses it so on a GPU (``unfuse_bias_add_to_pointwise``), not on a CPU. The same
sum, rounded once more apart: ``x @ w`` is rounded before the bias is added, as an eager ``x @ w + b`` is. Measured in
``docs/performance_log.md``.
"""

from __future__ import annotations

import functools
from typing import Any

import torch as th


@functools.cache
def bias_after_product() -> Any:
    """The pass (one instance: Inductor's cache keys on its :meth:`uuid`); imported with Inductor, at the first
    compiled step."""
    from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files

    class BiasAfterProduct(CustomGraphPass):
        """``addmm(bias, x, w)`` on a CPU, in float32 or float64 with ``alpha = beta = 1``: ``mm(x, w) + bias``; and
        ``baddbmm`` (critics or seeds stacked in one batched product), as ``bmm(x, w) + bias``. Other dtypes keep
        theirs (in bfloat16 the fused sum is rounded once, the product's would be rounded before)."""

        def __call__(self, graph: th.fx.Graph) -> None:
            aten = th.ops.aten
            products = {aten.addmm.default: aten.mm.default, aten.baddbmm.default: aten.bmm.default}
            for node in list(graph.nodes):
                if node.op != "call_function" or node.target not in products:
                    continue
                val = node.meta.get("val")
                if (not isinstance(val, th.Tensor) or val.device.type != "cpu"
                        or val.dtype not in (th.float32, th.float64)
                        or node.kwargs.get("alpha", 1) != 1 or node.kwargs.get("beta", 1) != 1):  # fmt: skip
                    continue
                bias, x, w = node.args[:3]
                with graph.inserting_before(node):
                    product = graph.call_function(products[node.target], (x, w))
                    product.meta["val"] = val.new_empty(val.shape)
                    total = graph.call_function(aten.add.Tensor, (product, bias))
                    total.meta["val"] = val
                node.replace_all_uses_with(total)
                graph.erase_node(node)

        def uuid(self) -> bytes:
            return get_hash_for_files((__file__,))

    return BiasAfterProduct()


def inductor_options(options: dict[str, Any] | None) -> dict[str, Any] | None:
    """``torch.compile``'s ``options`` for the update: :func:`bias_after_product` as Inductor's last post-grad pass,
    unless ``options`` (:attr:`CompiledUpdate.options`) or Inductor's global config already name a pass of their own,
    which then runs alone."""
    from torch._inductor import config as inductor_config

    key = "post_grad_custom_post_pass"
    if (options or {}).get(key) is not None or getattr(inductor_config, key) is not None:
        return options
    return {key: bias_after_product(), **(options or {})}
