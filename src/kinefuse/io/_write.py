"""Writing text files safely: atomic replace, no silent overwrite, the process umask, number text.

Private module, used by every writer (TRC, MOT, STO, the generic CSVs) and the output folder.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from kinefuse.exceptions import InputError

__all__ = ["current_umask", "fixed_point_rows", "fmt_float", "printf_rows", "write_text_safely"]


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


def fixed_point_rows(columns: Sequence[np.ndarray], decimals: int, sep: str = ",") -> list[str]:
    """The rows of a table as text, each value as :func:`fmt_float` writes it, in one pass.

    Parameters
    ----------
    columns : sequence of ndarray, shape (T,)
        Float columns (fixed point with ``decimals``; NaN and ±inf as an empty field; a value
        that rounds to zero as ``0``), bool or integer columns (``%d``).
    decimals : int
    sep : str
        Field separator.

    Returns
    -------
    list of str
        T rows, the fields of each joined by ``sep``; identical to joining :func:`fmt_float` /
        ``str(int(v))`` of every value (tested), about 10x faster on large tables.

    Raises
    ------
    TypeError
        A column of another dtype (strings, objects): format those per value.
    InputError
        ``decimals`` not an integer in 0..17.
    """
    if (
        isinstance(decimals, bool)
        or not isinstance(decimals, (int, np.integer))
        or not (0 <= int(decimals) <= 17)
    ):
        raise InputError(f"expected decimals as an integer from 0 to 17, got {decimals!r}")
    specs, values = [], []
    for c in columns:
        a = np.asarray(c)
        if a.dtype.kind == "f":
            specs.append(f"%.{int(decimals)}f")
            values.append(a.tolist())
        elif a.dtype.kind in "biu":
            specs.append("%d")
            values.append(a.astype(np.int64).tolist())
        else:
            raise TypeError(f"column of dtype {a.dtype}: not a number column")
    if not values or not len(values[0]):
        return []
    fmt = sep.join(specs)
    text = "\n".join(fmt % row for row in zip(*values, strict=True))
    field = rf"(?:(?<={re.escape(sep)})|^)"
    end = rf"(?={re.escape(sep)}|$)"
    text = re.sub(rf"{field}-?(?:nan|inf){end}", "", text, flags=re.M)
    text = re.sub(rf"{field}-?0(?:\.0+)?{end}", "0", text, flags=re.M)
    return text.split("\n")


#: A non-finite value's text (``nan``, ``inf``, ``-inf``) as a whole field: between tabs, commas
#: or line ends.
_NON_FINITE_FIELD = re.compile(r"(?<![^\t,\n])-?(?:nan|inf)(?![^\t,\n])")


def printf_rows(columns: Sequence, row_format: str, nan: str = "NaN") -> list[str]:
    """The rows ``row_format % (v_1, …, v_n)`` of float columns, in one pass; a non-finite
    value is written ``nan``.

    Parameters
    ----------
    columns : sequence of array_like, shape (T,)
        Float columns.
    row_format : str
        A ``%`` format with one conversion per column (``%r``, ``%.6f``…), its fields separated
        by tabs or commas (how a non-finite field is found).
    nan : str
        The text of a non-finite value (``NaN``; ``""``: an empty field).

    Returns
    -------
    list of str
        T rows; identical to formatting value by value with ``nan`` for a non-finite value
        (tested for the ``.mot``, orientation ``.sto`` and joint-angle CSV writers).
    """
    values = [np.asarray(c, dtype=float).tolist() for c in columns]
    if not values or not len(values[0]):
        return []
    text = "\n".join(row_format % row for row in zip(*values, strict=True))
    return _NON_FINITE_FIELD.sub(nan, text).split("\n")
