"""bf16 for the update: autocast for the hooks' forward passes, and whether this CPU multiplies bf16 in hardware.

``bf16=True`` is how the update runs, not what it computes: the weights, gradients, optimizer states and losses stay
fp32, and only the matrix products are bf16 (the hooks' forward passes run under autocast, eagerly or compiled).
"""

from __future__ import annotations

import contextlib
import platform

import torch as th


def autocast_context(device: th.device, enabled: bool, cache: bool = True) -> contextlib.AbstractContextManager:
    """bf16 autocast for the forward passes (AMX on recent x86 CPUs, tensor cores on GPUs); weights stay fp32.

    ``cache=False`` under CUDA graph capture: cached casts must not outlive the captured region.
    """
    if not enabled:
        return contextlib.nullcontext()
    return th.autocast(device_type=device.type, dtype=th.bfloat16, cache_enabled=cache)


def cpu_bf16_matmul() -> str | None:
    """How this CPU multiplies bf16 matrices: ``"amx"`` (AMX tiles), ``"avx512_bf16"`` (AVX512-BF16 without AMX),
    ``"emulated"`` (neither: oneDNN converts in software), or ``None`` when torch cannot say.

    Only AMX has been measured faster than fp32 (docs/performance.md): AVX512-BF16 alone ran Ant-v5's update slower than
    fp32 on a 2-core Xeon, and emulation is tens of times slower.
    """
    if platform.machine().lower() not in ("x86_64", "amd64", "i386", "i686", "x86"):
        return None
    avx512_bf16, amx = (getattr(th.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"))
    if avx512_bf16 is None or amx is None:
        return None
    return "amx" if amx() else "avx512_bf16" if avx512_bf16() else "emulated"


_USE_FP32 = "Use bf16=False on this machine; bf16 pays off on CPUs with AMX and on GPUs."


def bf16_on_cpu_warning(device: th.device) -> str | None:
    """The warning for ``bf16=True`` on ``device``: set when it is a CPU without AMX, where bf16 was measured slower
    than fp32 (:func:`cpu_bf16_matmul`)."""
    if device.type != "cpu":
        return None
    kind = cpu_bf16_matmul()
    if kind == "emulated":
        capability = th.backends.cpu.get_cpu_capability()
        return (
            f"bf16=True on a CPU without bf16 matrix instructions (no AVX512-BF16 or AMX; torch reports {capability}): "
            f"its bf16 matrix products run in software emulation, tens of times slower than fp32. {_USE_FP32}"
        )
    if kind == "avx512_bf16":
        return (
            "bf16=True on a CPU with AVX512-BF16 but no AMX: on such a CPU (a 2-core Xeon) the bf16 products ran "
            f"slower than fp32 (Ant-v5: 0.80x SB3's TD3 against 1.38x in fp32, docs/performance.md). {_USE_FP32}"
        )
    return None
