"""Numba compilation settings shared by all kernels.

Compiled functions are cached on disk (``cache=True``). Numba writes the cache next to the
source file (``__pycache__`` inside the installed package). When that directory is not writable
(e.g. a system-wide, read-only site-packages), numba itself falls back to a per-user cache
directory; we make that explicit: unless ``NUMBA_CACHE_DIR`` is already set, it is set to
``$XDG_CACHE_HOME/kinefuse/numba`` (default ``~/.cache/kinefuse/numba``) when the package
directory is read-only. Paying the compile cost once per machine is expected; later processes
load the cached machine code.
"""

from __future__ import annotations

import os
from pathlib import Path


def _configure_cache_dir() -> None:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    pkg_dir = Path(__file__).resolve().parent
    if os.access(pkg_dir, os.W_OK):
        return
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    cache_dir = base / "kinefuse" / "numba"
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
    except OSError:  # pragma: no cover - nowhere writable; numba will compile in memory
        return
    os.environ["NUMBA_CACHE_DIR"] = str(cache_dir)


_configure_cache_dir()

import numba  # noqa: E402

#: Decorator for every hot loop in kinefuse: compiled once per machine, cached on disk.
#: Use as ``@njit``.
njit = numba.njit(cache=True, nogil=True, error_model="numpy")
