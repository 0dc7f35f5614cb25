"""OpenSim motion (``.mot``) writer: joint angles over time, as OpenSim's Storage reads them.

The layout (OpenSim documentation, "Motion (.mot) files"; the same Storage format as ``.sto``)::

    <name>
    version=1
    nRows=<T>
    nColumns=<1 + C>
    inDegrees=yes
    DataRate=<Hz>          (optional)
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
from kinefuse.io._write import printf_rows, write_text_safely

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
    rate_hz: float | None = None,
    missing: str = "drop",
) -> Path:
    """Write named time series (joint angles) as an OpenSim ``.mot`` file.

    Parameters
    ----------
    path : str or Path
        Destination; never overwritten unless ``force``.
    t_s : array_like, shape (T,)
        Time, s, strictly increasing.
    columns : mapping of str -> array_like, shape (T,)
        Column name -> values (deg if ``in_degrees``, else rad); NaN = missing (see
        ``missing``).
    name : str, optional
        First header line (default: the file stem).
    in_degrees : bool
        Header ``inDegrees=yes|no``.
    metadata : mapping of str -> str, optional
        Extra ``key=value`` header lines (one line each, no ``=`` in the key, no newlines).
    force : bool
        Replace an existing file.
    decimals : int
        Digits after the decimal point of the values (time: at least 9, so that a time step is
        kept to 1 ns whatever the rate).
    rate_hz : float, optional
        Header ``DataRate=`` (Hz) as the data states it (e.g. the recording's nominal rate); not
        recomputed from the time steps. Default: no ``DataRate`` line.
    missing : {"drop", "nan"}
        Rows with a NaN: ``"drop"`` (default) leaves them out and says how many in the header
        (``rows_omitted=``): OpenSim's ``Storage``, which its tools and GUI load ``.mot`` files
        with, stops reading at the first NaN row (OpenSim 4.5/4.6), so a NaN would silently
        truncate the motion; the time column keeps the gaps. ``"nan"`` writes them as ``NaN``
        (read by ``TimeSeriesTable``, not by ``Storage``).

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
    t, names, data = _check_series(t_s, columns)
    if not names:
        raise InputError("write_mot: expected at least one column besides time, got none")
    if name is not None and (not str(name).strip() or any(ch in str(name) for ch in "\n\r")):
        raise InputError(f"write_mot: expected name as one non-empty line, got {name!r}")
    if missing not in ("drop", "nan"):
        raise InputError(f"write_mot: expected missing in ('drop', 'nan'), got {missing!r}")
    M = np.column_stack([t, *data]) if data else t[:, None]
    keep = np.all(np.isfinite(M), axis=1) if missing == "drop" else np.ones(t.size, dtype=bool)
    M = M[keep]
    head = [name or path.stem, "version=1", f"nRows={M.shape[0]}", f"nColumns={1 + len(names)}"]
    head += _header_lines(in_degrees, rate_hz, int(np.sum(~keep)), metadata)
    head += ["endheader", "\t".join(["time", *names])]
    body = _mot_rows(M, decimals)
    return write_text_safely(path, "\n".join(head + body) + "\n", force=force)


def _mot_rows(M: np.ndarray, decimals: int) -> list[str]:
    """The data rows of ``M (T, 1 + n)`` (time first), tab-separated: time with
    ``max(decimals, 9)`` digits, values with ``decimals``, ``NaN`` where not finite (one pass:
    :func:`~kinefuse.io._write.printf_rows`)."""
    spec = [f"%.{max(int(decimals), 9)}f"] + [f"%.{int(decimals)}f"] * (M.shape[1] - 1)
    return printf_rows(M.T, "\t".join(spec))


def _check_series(t_s, columns: Mapping[str, object]):
    """(t (T,), column names, column values (T,) each) after checking names and shapes."""
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
    return t, names, data


def _header_lines(in_degrees: bool, rate_hz, n_omitted: int, metadata) -> list[str]:
    """``inDegrees``, ``DataRate``, ``rows_omitted`` and the metadata ``key=value`` lines."""
    head = [f"inDegrees={'yes' if in_degrees else 'no'}"]
    if rate_hz is not None:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise InputError(f"write_mot: expected rate_hz > 0, got {rate_hz!r}")
        head.append(f"DataRate={float(rate_hz):.6f}")
    if n_omitted:
        head.append(f"rows_omitted={n_omitted} (a NaN value; OpenSim's Storage stops at one)")
    for k, v in (metadata or {}).items():
        if "=" in k or "\n" in k or "\n" in str(v) or not k:
            raise InputError(f"write_mot: metadata {k!r}={v!r} must be one key=value line")
        head.append(f"{k}={v}")
    return head
