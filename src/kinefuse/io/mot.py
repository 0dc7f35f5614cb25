"""OpenSim motion (``.mot``) writer: joint angles over time, as OpenSim's Storage reads them.

The layout (OpenSim documentation, "Motion (.mot) files"; the same Storage format as ``.sto``)::

    <name>
    version=1
    nRows=<T>
    nColumns=<1 + C>
    inDegrees=yes
    <key>=<value>          (optional, kinefuse writes e.g. root=, frame=, convention=)
    endheader
    time<TAB><col 1><TAB>...
    <t><TAB><v 1><TAB>...

Readers of ``.mot`` / ``.sto`` live in :mod:`kinefuse.io.opensim`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.io._common import write_text_safely

__all__ = ["write_mot"]


def write_mot(
    path,
    t_s,
    columns: Mapping[str, object],
    *,
    name: str | None = None,
    in_degrees: bool = True,
    metadata: Mapping[str, str] | None = None,
    force: bool = False,
    decimals: int = 6,
) -> Path:
    """Write named time series (joint angles) as an OpenSim ``.mot`` file.

    Parameters
    ----------
    path : str or Path
        Destination; never overwritten unless ``force``.
    t_s : array_like, shape (T,)
        Time, s, strictly increasing.
    columns : mapping of str -> array_like, shape (T,)
        Column name -> values (deg if ``in_degrees``, else rad). NaN is written as ``nan``,
        which OpenSim reads as not-a-number.
    name : str, optional
        First header line (default: the file stem).
    in_degrees : bool
        Header ``inDegrees=yes|no``.
    metadata : mapping of str -> str, optional
        Extra ``key=value`` header lines (one line each, no ``=`` in the key, no newlines).
    force : bool
        Replace an existing file.
    decimals : int
        Digits after the decimal point.

    Returns
    -------
    Path

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        Shapes that do not match ``t_s``, non-increasing time, names with tabs or newlines.
    FileExistsError
        ``path`` exists and ``force`` is False.
    """
    path = Path(path)
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise InputError(f"write_mot: expected finite t_s with shape (T,), got {t.shape}")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise InputError("write_mot: expected strictly increasing t_s")
    names: Sequence[str] = list(columns)
    data = []
    for c in names:
        if not c or any(ch in c for ch in "\t\n\r ") or c == "time":
            raise InputError(
                f"write_mot: column name {c!r} must be non-empty, not 'time', without spaces/tabs"
            )
        v = np.asarray(columns[c], dtype=float)
        if v.shape != t.shape:
            raise InputError(
                f"write_mot: expected column {c!r} with shape (T,) = {t.shape}, got {v.shape}"
            )
        data.append(v)
    head = [name or path.stem, "version=1", f"nRows={t.size}", f"nColumns={1 + len(names)}"]
    head.append(f"inDegrees={'yes' if in_degrees else 'no'}")
    for k, v in (metadata or {}).items():
        if "=" in k or "\n" in k or "\n" in str(v) or not k:
            raise InputError(f"write_mot: metadata {k!r}={v!r} must be one key=value line")
        head.append(f"{k}={v}")
    head += ["endheader", "\t".join(["time", *names])]
    M = np.column_stack([t, *data]) if data else t[:, None]
    body = ["\t".join(f"{x:.{decimals}f}" if np.isfinite(x) else "nan" for x in row) for row in M]
    return write_text_safely(path, "\n".join(head + body) + "\n", force=force)
