"""Flush denormal floats to zero on every CPU thread that runs torch's operators, for the length of a block.

Adam's second moment ``v <- beta2 v + (1 - beta2) g^2`` makes denormal numbers (below 1.2e-38 in fp32) out of the
tiny gradients of rarely active ReLU units. On x86 each arithmetic operation on a denormal takes a microcode assist of
about a hundred cycles, enough to make Adam's step several times slower. Flush-to-zero (FTZ) and
denormals-are-zero (DAZ) make those values 0, which changes nothing that fp32 training can see (the same setting
is the default of XLA on CPU and of TensorFlow's thread pools).

``torch.set_flush_denormal`` only sets the floating-point control register (MXCSR) of the calling thread, and the
OpenMP worker threads that run half of every parallel operator keep their own. :func:`flush_denormals` also sets
theirs: it runs glibc's ``fesetenv`` on every thread of the OpenMP team with libgomp's ``GOMP_parallel`` (the
thread pool torch and MKL use in the official wheels), and restores every thread's previous setting on exit.
Where that is not possible (no x86, no glibc, another OpenMP runtime) it sets the calling thread only.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import platform
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch as th

_FENV_BYTES = 64  # glibc's fenv_t is 32 bytes on x86-64; room to spare


class _TeamFenv:
    """``fegetenv``/``fesetenv`` on the calling thread, and ``fesetenv`` on every thread of the OpenMP team."""

    def __init__(self, libm: ctypes.CDLL, gomp: ctypes.CDLL | None):
        self.fegetenv = libm.fegetenv
        self.fesetenv_ptr = ctypes.cast(libm.fesetenv, ctypes.c_void_p)
        self.fesetenv = libm.fesetenv
        self.gomp_parallel = None
        if gomp is not None:
            self.gomp_parallel = gomp.GOMP_parallel
            self.gomp_parallel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint]
            self.gomp_parallel.restype = None

    def get(self) -> ctypes.Array:
        env = ctypes.create_string_buffer(_FENV_BYTES)
        self.fegetenv(env)
        return env

    def set_all(self, env: ctypes.Array) -> None:
        if self.gomp_parallel is not None:
            # Every thread of the team (the calling thread included) runs fesetenv(env); num_threads=0: the default
            # team, the one torch's parallel regions use.
            self.gomp_parallel(self.fesetenv_ptr, ctypes.cast(env, ctypes.c_void_p), 0, 0)
        else:
            self.fesetenv(env)


def _loaded_libgomp() -> str | None:
    """The path of the libgomp this process has loaded (torch's wheels ship their own copy), if any."""
    try:
        with open("/proc/self/maps") as maps:
            for line in maps:
                path = line.rsplit(" ", 1)[-1].strip()
                if "libgomp" in os.path.basename(path) and ".so" in path:
                    return path
    except OSError:
        return None
    return None


@functools.lru_cache(maxsize=1)
def _team_fenv() -> _TeamFenv | None:
    """The fenv functions, or None when denormals cannot be flushed on this platform."""
    if platform.machine().lower() not in ("x86_64", "amd64"):  # FTZ/DAZ as set here are x86's MXCSR bits
        return None
    libm_name = ctypes.util.find_library("m")
    if libm_name is None:
        return None
    try:
        libm = ctypes.CDLL(libm_name)
        libm.fegetenv  # noqa: B018 (glibc-specific symbols: fail here, not later)
        libm.fesetenv  # noqa: B018
    except (OSError, AttributeError):
        return None
    gomp = None
    path = _loaded_libgomp()
    if path is not None and "OpenMP" in th.__config__.parallel_info():
        try:
            gomp = ctypes.CDLL(path)
            gomp.GOMP_parallel  # noqa: B018
        except (OSError, AttributeError):
            gomp = None
    return _TeamFenv(libm, gomp)


def flushes_all_threads() -> bool:
    """Whether :func:`flush_denormals` reaches torch's OpenMP worker threads here (not only the calling thread)."""
    fenv = _team_fenv()
    return fenv is not None and fenv.gomp_parallel is not None


@contextmanager
def flush_denormals(enabled: bool = True) -> Iterator[None]:
    """Flush denormals to zero (FTZ and DAZ) on the calling thread and torch's OpenMP threads inside the block.

    Every thread's previous floating-point environment is restored on exit. A no-op when ``enabled`` is False or the
    platform does not allow it.
    """
    fenv = _team_fenv() if enabled else None
    if fenv is None:
        yield
        return
    before = fenv.get()
    if not th.set_flush_denormal(True):
        yield
        return
    flushed = fenv.get()
    fenv.set_all(flushed)
    try:
        yield
    finally:
        fenv.set_all(before)


def same_fp_environment() -> Callable[[], None]:
    """A function that gives the thread it runs on the calling thread's floating-point environment (its FTZ and DAZ
    bits, its rounding mode): for worker threads that must compute what the calling thread would (a thread starts
    with the process's default environment, not its creator's)."""
    fenv = _team_fenv()
    if fenv is None:
        return lambda: None
    env = fenv.get()
    return lambda: fenv.fesetenv(env)  # type: ignore[no-any-return]
