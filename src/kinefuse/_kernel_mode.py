"""Where compiled kernels are cached, and the switch to interpreted kernels; no numba import.

The numba decorators live in :mod:`kinefuse._compile`, which imports numba (about half a
second). This module holds what must be decided before that: the cache directory (set when the
package is imported, before numba reads its configuration) and the interpreted-kernel switch,
which ``kinefuse demo`` consults without importing numba (so ``kinefuse --help`` stays fast).

Cache directory
---------------
Compiled functions are cached on disk (``cache=True``). Numba writes the cache next to the
source file (``__pycache__`` inside the installed package). When that directory is not writable
(e.g. a system-wide, read-only site-packages), numba itself falls back to a per-user cache
directory; we make that explicit: unless ``NUMBA_CACHE_DIR`` is already set, it is set to
``$XDG_CACHE_HOME/kinefuse/numba`` (default ``~/.cache/kinefuse/numba``) when the package
directory is read-only. Paying the compile cost once per machine is expected; later processes
load the cached machine code.

Stale caches
------------
Numba checks a cached function against a hash of *its own* source file only. Most kernels
inline helpers from other kernel modules (``njit_inline``), so after a change to a helper file
alone (an upgrade, or a developer's edit) numba would load machine code built from the old
helper. :func:`drop_stale_kernel_caches` (run by :mod:`kinefuse._compile` before any kernel is
loaded) keeps, next to each kernel module's cache files, a hash of the module and every kernel
module it imports, directly or not; when it no longer matches, that module's cache files are
removed (it is compiled again), the others are kept.

Interpreted kernels
-------------------
Compiling every kernel takes minutes on a small machine, which is far more than a small workload
(the built-in demo: a few hundred samples per joint) needs. :func:`interpret_kernels`, called
before the kernel modules are imported, makes :func:`kinefuse._compile.njit` return the plain
Python functions: identical results, no compile cost, slower per step. ``kinefuse demo`` uses it
when :func:`kernels_cached` says this machine has not compiled the kernels yet.
"""

from __future__ import annotations

import glob
import hashlib
import os
import re
import sys
from pathlib import Path

__all__ = ["KERNEL_MODULES", "interpret_kernels", "interpreting", "kernels_cached"]


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

_interpret = False

#: Modules holding compiled kernels (imported lazily by the filters and pipelines).
KERNEL_MODULES = (
    "kinefuse.filters._kernels",
    "kinefuse.filters._kernels_axis",
    "kinefuse.filters._kernels_block2",
    "kinefuse.filters._kernels_blocks",
    "kinefuse.filters._kernels_common",
    "kinefuse.filters._kernels_em",
    "kinefuse.filters._kernels_imm",
    "kinefuse.filters._kernels_integrated",
    "kinefuse.filters._kernels_linalg",
    "kinefuse.filters._kernels_ufir",
    "kinefuse.filters._kernels_ufir_cov",
    "kinefuse.filters._kernels_ufir_run",
    "kinefuse.pipelines._kinefuse_kernels",
    "kinefuse.streaming._kernels",
)
# A kernel of each heavy module: if their cache index files exist, the kernels were compiled.
_SENTINELS = (
    ("filters", "_kernels_integrated.integrated_run-*.nbi"),
    ("filters", "_kernels_ufir_run.ufir_run-*.nbi"),
    ("filters", "_kernels_imm.imm_run_paper_b-*.nbi"),
)


_IMPORT = re.compile(rb"^from (kinefuse\.[\w.]+) import", re.MULTILINE)

#: Suffix of the stamp file kept next to a kernel module's numba cache files.
STAMP_SUFFIX = ".kinefuse-deps"


def _cache_dirs(src_dir: Path) -> list[Path]:
    """Where numba keeps the cache of a module in ``src_dir``: ``__pycache__`` beside it and,
    with ``NUMBA_CACHE_DIR`` set, numba's mirror of it there (``<dir name>_<sha1 of the dir>``).
    The last one is where numba writes."""
    dirs = [src_dir / "__pycache__"]
    user = os.environ.get("NUMBA_CACHE_DIR")
    if user:
        hashed = hashlib.sha1(str(src_dir).encode()).hexdigest()
        dirs.append(Path(user) / f"{src_dir.name}_{hashed}")
    return dirs


def drop_stale_kernel_caches(root: Path | None = None, modules=KERNEL_MODULES) -> list[str]:
    """Remove the numba cache files of every kernel module whose source or kernel-module imports
    changed since they were written (see "Stale caches" above).

    Parameters
    ----------
    root : Path, optional
        The directory holding the ``kinefuse`` package (default: this installation's).
    modules : sequence of str
        Dotted names of the kernel modules.

    Returns
    -------
    list of str
        The modules whose cache files were removed. Unreadable sources or unwritable cache
        directories are skipped (numba then behaves as before).
    """
    if root is None:  # as numba spells the path (abspath, symlinks kept)
        root = Path(os.path.abspath(__file__)).parent.parent
    paths = {m: root.joinpath(*m.split(".")).with_suffix(".py") for m in modules}
    try:
        text = {m: p.read_bytes() for m, p in paths.items()}
    except OSError:
        return []
    direct = {m: {d.decode() for d in _IMPORT.findall(t)} & set(modules) for m, t in text.items()}
    dropped = []
    for m in modules:
        closure, todo = {m}, [m]
        while todo:
            for d in direct[todo.pop()] - closure:
                closure.add(d)
                todo.append(d)
        digest = hashlib.sha256()
        for d in sorted(closure):
            digest.update(d.encode() + b"\0" + text[d] + b"\0")
        stamp = digest.hexdigest()
        base = paths[m].stem
        dirs = _cache_dirs(paths[m].parent)
        for cache in dirs:
            mark = cache / (base + STAMP_SUFFIX)
            try:
                if mark.read_text() == stamp:
                    continue
            except OSError:
                pass  # no stamp yet (or unreadable): rewrite it
            stale = glob.glob(str(cache / f"{glob.escape(base)}.*.nb[ic]"))
            try:
                for f in stale:
                    os.remove(f)
                if cache == dirs[-1]:  # numba writes here: stamp it before it does
                    cache.mkdir(parents=True, exist_ok=True)
                if cache.is_dir():
                    mark.write_text(stamp)
            except OSError:
                continue
            if stale:
                dropped.append(m)
    return dropped


def interpreting() -> bool:
    """True after :func:`interpret_kernels`: kernels run as plain Python in this process.

    Kernel modules that choose an implementation by argument type (``numba.extending.overload``)
    read it at import time and then dispatch in Python instead.
    """
    return _interpret


def interpret_kernels() -> bool:
    """Run the kernels as plain Python in this process (no compilation).

    Must be called before any kernel module is imported; returns False (and changes nothing) if
    one already is.
    """
    global _interpret
    if any(m in sys.modules for m in KERNEL_MODULES):
        return False
    _interpret = True
    return True


def kernels_cached() -> bool:
    """True when this machine's numba cache holds the compiled kernels (checked without importing)."""
    pkg = Path(__file__).resolve().parent
    user_dir = os.environ.get("NUMBA_CACHE_DIR")  # numba looks there first when it is set
    for sub, pattern in _SENTINELS:
        if user_dir:
            found = glob.glob(str(Path(user_dir) / "**" / pattern), recursive=True)
        else:
            found = glob.glob(str(pkg / sub / "__pycache__" / pattern))
        if not found:
            return False
    return True
