"""Writing text files safely: atomic replace, no silent overwrite, the process umask, number text.

Private module, used by every writer (TRC, MOT, STO, the generic CSVs) and the output folder.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

__all__ = ["current_umask", "fmt_float", "write_text_safely"]


def current_umask() -> int:
    """The process umask (read without changing it where /proc allows, else set and restore)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_text_safely(path, text: str, *, force: bool = False, protect: Iterable = ()) -> Path:
    """Write ``text`` to ``path`` atomically; refuse to overwrite unless ``force``.

    Parameters
    ----------
    path : str or Path
        Destination.
    text : str
        Content.
    force : bool
        Allow replacing an existing file.
    protect : iterable of path
        Files that must never be written (the inputs a recording was read from), even with
        ``force``.

    Raises
    ------
    FileExistsError
        ``path`` exists and ``force`` is False (the message names the file and says to use
        ``force=True``), or ``path`` is one of ``protect``.
    """
    path = Path(path)
    target = path.resolve()
    for p in protect:
        if p and Path(p).exists() and Path(p).resolve() == target:
            raise FileExistsError(f"{path}: refusing to write over an input file of this recording")
    if path.exists() and not force:
        raise FileExistsError(
            f"{path}: file exists; refusing to overwrite it (pass force=True to replace it)"
        )
    if path.is_dir():
        raise FileExistsError(f"{path}: is a directory")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates 0600; the file gets the mode open() would give it (issue 12)
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def fmt_float(v: float, decimals: int) -> str:
    """Fixed-point text of ``v``; NaN as an empty field."""
    if not math.isfinite(v):
        return ""
    s = f"{v:.{decimals}f}"
    return "0" if s.strip("-0.") == "" else s
