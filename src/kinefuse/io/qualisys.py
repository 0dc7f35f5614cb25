"""Qualisys Track Manager (QTM) TSV export of 3D marker trajectories.

QTM's "Export to TSV" (QTM user manual, "TSV export") writes a tab-separated header of
``KEY<TAB>value`` lines, then one row per frame::

    NO_OF_FRAMES      6916
    NO_OF_CAMERAS     13
    NO_OF_MARKERS     3
    FREQUENCY         120
    NO_OF_ANALOG      0
    ANALOG_FREQUENCY  0
    DESCRIPTION       --
    TIME_STAMP        2024-04-15, 10:39:38.777   406646.66137317
    DATA_INCLUDED     3D
    MARKER_NAMES      Wrist_L   Hip_L   Foot_Index_L
    TRAJECTORY_TYPES  Measured  Measured  Measured
    -473.521  191.980  613.382  -677.077  164.814  615.497  -138.493  187.190  53.579
    ...

Coordinates are millimetres in the QTM global (lab) frame. Newer QTM versions add a column
header ``Frame<TAB>Time<TAB>Wrist_L X<TAB>...`` before the rows, and the rows then start with
the frame number and the time (s). A marker that was not tracked is written as ``0 0 0`` (or
left empty): both are missing (:data:`kinefuse.io._checks.ZERO_RULE`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io._checks import ZERO_RULE, finish_recording, make_metadata, zero_samples
from kinefuse.io._names import map_joints
from kinefuse.io._text import check_time, header_number, read_text
from kinefuse.io.recording import JointStream, Recording

__all__ = ["read_qualisys_tsv", "sniff"]


def sniff(head: str) -> bool:
    """True for the start of a QTM TSV export (``NO_OF_FRAMES`` first, ``MARKER_NAMES`` below)."""
    first = next((ln for ln in head.splitlines() if ln.strip()), "")
    return first.startswith("NO_OF_FRAMES") and "MARKER_NAMES" in head


def read_qualisys_tsv(path, *, role: str = "reference", map_names: bool = True) -> Recording:
    """Read a QTM TSV export of 3D marker trajectories (layout in the module docstring).

    Parameters
    ----------
    path : str or Path
        The ``.tsv`` file.
    role : {"reference", "vision"}
        Where the markers go in the Recording (optical motion capture is usually the reference).
    map_names : bool
        Map marker names that name a joint (``Wrist_L``, ``Hip_L``) to canonical joint names
        (``metadata["joint_map"]``); others are kept.

    Returns
    -------
    Recording
        ``reference`` (or ``vision``): positions (T, M, 3) in m (file mm), frame
        ``"qualisys_lab"``; times from the ``Time`` column when the file has one, else
        ``frame / FREQUENCY``; ``available`` = three coordinates present and not all zero.
        ``metadata["header"]``: every header key and its value(s).

    Raises
    ------
    FormatError
        Missing header keys, data other than 3D, a marker count that disagrees with
        ``NO_OF_MARKERS``, wrong field counts, non-numbers, time out of order.
    """
    path = Path(path)
    if role not in ("reference", "vision"):
        raise InputError(f"expected role 'reference' or 'vision', got {role!r}")
    lines = read_text(path).splitlines()
    header, k = _header(path, lines)
    rate = header_number(path, header["FREQUENCY"][0], "FREQUENCY", what="a rate in Hz")
    if not rate > 0:
        raise FormatError(path, f"expected FREQUENCY > 0, found {rate}", field="FREQUENCY")
    markers = header["MARKER_NAMES"]
    n_markers = header_number(path, header["NO_OF_MARKERS"][0], "NO_OF_MARKERS", cast=int)
    if len(markers) != n_markers:
        raise FormatError(
            path,
            f"expected {n_markers} MARKER_NAMES (NO_OF_MARKERS), found {len(markers)}",
            field="MARKER_NAMES",
        )
    timed = k < len(lines) and lines[k].startswith("Frame\tTime")
    data, line_no = _rows(path, lines, k + timed, 3 * len(markers) + 2 * timed)
    t = data[:, 1] if timed else np.arange(len(data)) / rate
    t = check_time(path, t, line_no, "Time" if timed else "frame")
    pos = data[:, 2 * timed :].reshape(len(data), len(markers), 3) * 1e-3
    zero, n_zero = zero_samples(pos)
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero
    joints, jmap = map_joints(markers) if map_names else (tuple(markers), {m: m for m in markers})
    js = JointStream(t_s=t, position_m=pos, available=avail, joints=joints, frame="qualisys_lab")
    notes = []
    if str(len(data)) != header["NO_OF_FRAMES"][0]:
        notes.append(f"header NO_OF_FRAMES = {header['NO_OF_FRAMES'][0]}, read {len(data)} rows")
    md = make_metadata(
        path,
        "qualisys_tsv",
        units_converted=["positions mm -> m"],
        joint_map=jmap,
        rate_hz=rate,
        header=header,
        time_source="Time column" if timed else "frame / FREQUENCY",
        availability_rule=f"three coordinates present; {ZERO_RULE}",
        n_zero_samples=n_zero,
        notes=notes,
    )
    return finish_recording(path, md, **{role: js})


_REQUIRED = ("NO_OF_FRAMES", "NO_OF_MARKERS", "FREQUENCY", "DATA_INCLUDED", "MARKER_NAMES")


def _header(path: Path, lines: list[str]) -> tuple[dict[str, list[str]], int]:
    """(``KEY -> values`` of the header lines, index of the first line after them)."""
    header: dict[str, list[str]] = {}
    k = 0
    while k < len(lines) and lines[k].split("\t", 1)[0].strip().isupper():
        key, *values = lines[k].rstrip("\r").split("\t")
        header.setdefault(key.strip(), [v.strip() for v in values if v.strip()])
        k += 1
    missing = [key for key in _REQUIRED if not header.get(key)]
    if missing:
        raise FormatError(path, f"expected QTM TSV header keys {missing}, found {sorted(header)}")
    if header["DATA_INCLUDED"][0] != "3D":
        raise FormatError(
            path,
            f"expected DATA_INCLUDED 3D (marker trajectories), found {header['DATA_INCLUDED'][0]!r}",
            field="DATA_INCLUDED",
        )
    return header, k


def _rows(path: Path, lines: list[str], start: int, n_fields: int):
    """The data rows (n, n_fields) as floats (an empty field is NaN) and their line numbers."""
    rows, line_no = [], []
    for j in range(start, len(lines)):
        fields = lines[j].rstrip("\r").split("\t")
        while len(fields) > n_fields and not fields[-1].strip():
            fields.pop()  # QTM ends some rows with a tab
        if not "".join(fields).strip():
            continue
        if len(fields) != n_fields:
            raise FormatError(
                path, f"expected {n_fields} fields per row, found {len(fields)}", line=j + 1
            )
        try:
            rows.append([float(f) if f.strip() else np.nan for f in fields])
        except ValueError as e:  # "could not convert string to float: 'x'"
            found = str(e).rsplit(": ", 1)[-1]
            raise FormatError(path, f"expected a number, found {found}", line=j + 1) from None
        if any(np.isinf(v) for v in rows[-1]):
            raise FormatError(
                path,
                "expected finite numbers, found an infinite one (leave missing empty)",
                line=j + 1,
            )
        line_no.append(j + 1)
    if not rows:
        raise FormatError(path, "expected data rows after the header, found none")
    return np.asarray(rows, dtype=float), np.asarray(line_no)
