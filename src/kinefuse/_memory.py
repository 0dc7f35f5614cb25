"""How kinefuse's own processes ask the kernel for memory: small pages for numpy's arrays.

numpy advises the Linux kernel to back every array of 4 MB or more with transparent huge pages
(``madvise(MADV_HUGEPAGE)``) on kernels 4.6 and newer. Where the system's policy is ``madvise``
for both ``/sys/kernel/mm/transparent_hugepage/enabled`` and ``.../defrag`` (as on this
project's machine), the first touch of such an array may then wait while the kernel compacts
memory into huge pages, in the thread that touches it. A long recording's pipeline allocates
many such arrays (positions and covariances of every method and baseline), so on a machine
whose memory is fragmented the waits add up: on this project's 2-core machine a fresh 64 MB
array took 0.5 to 0.8 s to fill with the advice and 0.02 s without it, and ``kinefuse bench``
prints the paper-B pipeline both ways. Where huge pages were free (a second array of the same
size), the advice made that fill about 10 ms faster (0.011 s); kinefuse gives up those
milliseconds to avoid the stalls.

The choice is made for the command-line processes only (``kinefuse …``, and the worker
processes they start, which inherit the environment): importing kinefuse as a library changes
nothing. numpy reads ``NUMPY_MADVISE_HUGEPAGE`` once, when it is imported
(https://numpy.org/doc/stable/reference/global_state.html); a value the user set is kept.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["HUGEPAGE_ENV", "prefer_small_pages", "user_chose_pages"]

#: numpy's switch for its transparent-hugepage advice (``0`` off, ``1`` on), read at import.
HUGEPAGE_ENV = "NUMPY_MADVISE_HUGEPAGE"

_set_here = False  # whether prefer_small_pages set HUGEPAGE_ENV in this process


def prefer_small_pages() -> bool:
    """Turn numpy's transparent-hugepage advice off in this process and its children.

    Unless :data:`HUGEPAGE_ENV` is set (then the user's choice stands), sets it to ``"0"`` for
    the child processes and switches the advice off in this process's numpy, which has read
    the variable already.

    Returns
    -------
    bool
        True when the advice is now off in this process by this call; False when the user's
        setting was kept, or when this numpy has no switch (then only child processes, which
        read the variable, get small pages).
    """
    global _set_here
    if HUGEPAGE_ENV in os.environ:
        return False
    os.environ[HUGEPAGE_ENV] = "0"
    _set_here = True
    setter = _numpy_switch()
    if setter is None:
        return False
    setter(False)
    return True


def user_chose_pages() -> bool:
    """Whether :data:`HUGEPAGE_ENV` is set, and not by :func:`prefer_small_pages` in this
    process (a child process cannot tell: the variable it inherits counts as the user's)."""
    return HUGEPAGE_ENV in os.environ and not _set_here


def _numpy_switch():
    """numpy's ``_set_madvise_hugepage`` (``numpy._core`` from numpy 2, ``numpy.core``
    before), or None."""
    for name in ("_core", "core"):
        sub = getattr(getattr(np, name, None), "multiarray", None)
        setter = getattr(sub, "_set_madvise_hugepage", None)
        if setter is not None:
            return setter
    return None
