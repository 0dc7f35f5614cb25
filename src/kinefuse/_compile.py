"""Numba compilation settings shared by all kernels: :func:`njit` and :func:`njit_inline`.

Importing this module imports numba. The cache directory and the switch to interpreted kernels
are decided in :mod:`kinefuse._kernel_mode` (imported first, so ``NUMBA_CACHE_DIR`` is set
before numba reads it; no numba import there) and re-exported here: compiled functions are
cached on disk (``cache=True``), in the package's ``__pycache__`` or, when that is read-only, in
``$XDG_CACHE_HOME/kinefuse/numba``; after :func:`interpret_kernels` (called before the kernel
modules are imported) :func:`njit` returns the plain Python functions, with identical results.
"""

from __future__ import annotations

from kinefuse._kernel_mode import (
    _SENTINELS,
    KERNEL_MODULES,
    drop_stale_kernel_caches,
    interpret_kernels,
    interpreting,
    kernels_cached,
)

if not interpreting():
    drop_stale_kernel_caches()  # before any kernel module loads its cached machine code

# isort: split
import numba  # after kinefuse._kernel_mode has set NUMBA_CACHE_DIR

__all__ = [
    "KERNEL_MODULES",
    "_SENTINELS",
    "interpret_kernels",
    "interpreting",
    "kernels_cached",
    "njit",
    "njit_inline",
]

_numba_njit = numba.njit(cache=True, nogil=True, error_model="numpy")
_numba_njit_inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")


def njit(func):
    """Decorator for every hot loop in kinefuse: compiled once per machine, cached on disk.

    Returns ``func`` itself (interpreted) after :func:`interpret_kernels`.
    """
    return func if interpreting() else _numba_njit(func)


def njit_inline(func):
    """As :func:`njit`, with the callee inlined into its callers at numba IR level."""
    return func if interpreting() else _numba_njit_inline(func)
