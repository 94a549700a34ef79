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


def cpu_bf16_matmul_is_native() -> bool | None:
    """Whether this CPU multiplies bf16 matrices in hardware (AVX512-BF16 or AMX), or ``None`` when torch cannot say.

    Without them (an AVX2-only x86 CPU), oneDNN converts bf16 in software, far slower than fp32; with AMX, bf16 is
    faster than fp32 (measurements: docs/performance.md).
    """
    if platform.machine().lower() not in ("x86_64", "amd64", "i386", "i686", "x86"):
        return None
    probes = [getattr(th.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    if any(probe is None for probe in probes):
        return None
    return any(probe() for probe in probes)  # type: ignore[misc]


def bf16_on_cpu_warning(device: th.device) -> str | None:
    """The warning for ``bf16=True`` on ``device``: set when it is a CPU without bf16 matrix instructions."""
    if device.type != "cpu" or cpu_bf16_matmul_is_native() is not False:
        return None
    capability = th.backends.cpu.get_cpu_capability()
    return (
        f"bf16=True on a CPU without bf16 matrix instructions (no AVX512-BF16 or AMX; torch reports {capability}): "
        "its bf16 matrix products run in software emulation, tens of times slower than fp32. Use bf16=False on "
        "this machine; bf16 pays off on CPUs with AMX and on GPUs."
    )
