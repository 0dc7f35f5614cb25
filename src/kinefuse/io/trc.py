"""TRC (OpenSim / Motion Analysis track row column) marker files: read and write.

Layout (tab-separated)::

    PathFileType  4  (X/Y/Z)  <file name>
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    100.0     100.0       955        3           m      100.0         1                   955
    Frame#  Time  elbow_r          wrist_r          ...
                  X1   Y1   Z1     X2   Y2   Z2
    1       0.00  ...

Missing markers are empty fields (or all-zero coordinates, read as missing too).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kinefuse.exceptions import FormatError, FormatWarning, InputError
from kinefuse.io._checks import ZERO_RULE, finish_recording, make_metadata, zero_samples
from kinefuse.io._names import map_joints
from kinefuse.io._text import check_time, read_text
from kinefuse.io._write import fixed_point_rows, write_text_safely
from kinefuse.io.recording import JointStream, Recording

__all__ = ["read_trc", "write_trc"]

_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "meters": 1.0, "millimeters": 1e-3}
_HEADER_KEYS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units")


def _split(line: str, sep: str) -> list[str]:
    """Header tokens as OpenSim's TRCFileAdapter reads them: split on ``sep``, empty ones dropped."""
    return [v.strip() for v in line.split(sep) if v.strip()]


def read_trc(
    path, *, role: str = "reference", map_names: bool = True, zero_is_missing: bool = True
) -> Recording:
    """Read a TRC marker file.

    Parameters
    ----------
    path : str or Path
        ``.trc`` file (tab-separated as OpenSim writes it; the comma-separated variant some tools
        write is read too, with a note).
    role : {"reference", "vision"}
        Where the markers go in the Recording.
    map_names : bool
        Map marker names that name a joint to canonical joint names (``metadata["joint_map"]``);
        others are kept.
    zero_is_missing : bool
        Treat a marker whose three coordinates are all exactly 0 as missing
        (:data:`kinefuse.io._checks.ZERO_RULE`, the "not tracked" encoding of many TRC writers).

    Returns
    -------
    Recording
        ``reference`` (or ``vision``): positions (T, M, 3) in m (converted from the header's
        ``Units``), frame ``"trc_lab"``, times from the ``Time`` column; ``available`` = all
        three coordinates present (and not all zero). ``metadata["rate_hz"]`` is the header's
        ``DataRate``; ``metadata["header"]`` holds every header key (``DataRate``,
        ``CameraRate``, ``OrigDataRate``, ``OrigDataStartFrame`` ...) so that
        ``write_trc(..., header=rec.metadata["header"])`` keeps them.

    Notes
    -----
    As OpenSim's ``TRCFileAdapter``: empty tokens of the header rows (repeated tabs) are dropped,
    and the rows there are are read when ``NumFrames`` disagrees with them (a
    :class:`~kinefuse.exceptions.FormatWarning` says so).

    Raises
    ------
    FormatError
        Missing header keys, unknown units, wrong field counts, non-numbers, time out of order.
    """
    path = Path(path)
    if role not in ("reference", "vision"):
        raise InputError(f"expected role 'reference' or 'vision', got {role!r}")
    lines = read_text(path).splitlines()
    h = _read_header(path, lines)
    data, line_no = _read_rows(path, lines, h.sep, h.markers, h.n_frames)
    if len(data) != h.n_frames:
        msg = (
            f"{path}: header NumFrames = {h.n_frames} but the file has {len(data)} data rows; "
            f"read the {len(data)} rows (as OpenSim does)"
        )
        warnings.warn(msg, FormatWarning, stacklevel=2)
        h.notes.append(msg)
    t = check_time(path, data[:, 1], np.asarray(line_no), "Time")
    pos = data[:, 2:].reshape(-1, len(h.markers), 3) * h.factor
    zero, n_zero = zero_samples(pos, zero_is_missing)
    pos[zero] = np.nan
    if map_names:
        joints, jmap = map_joints(h.markers)
    else:
        joints, jmap = tuple(h.markers), {m: m for m in h.markers}
    js = JointStream(t_s=t, position_m=pos, joints=joints, frame="trc_lab")
    md = make_metadata(
        path,
        "trc",
        units_converted=[f"positions {h.unit} -> m"] if h.factor != 1.0 else [],
        joint_map=jmap,
        rate_hz=h.rate,
        header=h.header,
        frame_numbers=data[:, 0].copy(),
        availability_rule=f"all three coordinates present; {ZERO_RULE}"
        if zero_is_missing
        else "all three coordinates present",
        n_zero_samples=n_zero,
        notes=h.notes,
    )
    return finish_recording(path, md, **{role: js})


class _Header(NamedTuple):
    sep: str
    header: dict[str, str]
    rate: float
    n_frames: int
    unit: str
    factor: float
    markers: list[str]
    notes: list[str]


def _read_header(path: Path, lines: list[str]) -> _Header:
    """The four header lines: separator, keys and values, units, marker names."""
    if len(lines) < 5:
        raise FormatError(
            path,
            f"expected at least 5 header lines (PathFileType, keys, values, names, XYZ), found {len(lines)}",
        )
    if not lines[0].startswith("PathFileType"):
        raise FormatError(
            path, f"expected 'PathFileType' on the first line, found {lines[0][:40]!r}", line=1
        )
    notes = []
    sep = "\t"
    if "\t" not in lines[1] and "," in lines[1]:
        sep = ","
        notes.append("comma-separated TRC (OpenSim reads only tab-separated TRC)")
    keys = _split(lines[1], sep)
    vals = _split(lines[2], sep)
    if len(keys) != len(vals):
        notes.append(f"header has {len(keys)} keys and {len(vals)} values; paired in order")
    hdr = dict(zip(keys, vals, strict=False))
    for k in _HEADER_KEYS:
        if k not in hdr:
            raise FormatError(path, f"missing header key {k!r}; found keys {keys}", line=2, field=k)
    try:
        rate = float(hdr["DataRate"])
        n_frames = int(float(hdr["NumFrames"]))
        n_markers = int(float(hdr["NumMarkers"]))
    except ValueError:
        raise FormatError(
            path, f"expected numbers for DataRate/NumFrames/NumMarkers, found {vals}", line=3
        ) from None
    unit = hdr["Units"]
    factor = _TO_M.get(unit.lower())
    if factor is None:
        raise FormatError(
            path, f"expected Units one of {sorted(_TO_M)}, found {unit!r}", line=3, field="Units"
        )
    markers = _marker_names(path, lines[3], sep, n_markers)
    return _Header(sep, hdr, rate, n_frames, unit, factor, markers, notes)


def _marker_names(path: Path, line: str, sep: str, n_markers: int) -> list[str]:
    names_f = line.split(sep)
    if len(names_f) < 2 or names_f[0].strip() != "Frame#" or names_f[1].strip() != "Time":
        raise FormatError(
            path, f"expected 'Frame#<tab>Time<tab><markers>', found {line[:60]!r}", line=4
        )
    markers = [m.strip() for m in names_f[2:] if m.strip()]
    if len(markers) != n_markers:
        raise FormatError(
            path,
            f"expected {n_markers} marker names (NumMarkers), found {len(markers)}",
            line=4,
            field="NumMarkers",
        )
    return markers


def _read_rows(path: Path, lines: list[str], sep: str, markers: list[str], n_frames: int):
    """Data rows (n, 2 + 3 M) as floats (NaN = empty marker field) and their line numbers."""
    n_markers = len(markers)
    n_fields = 2 + 3 * n_markers
    rows = []
    line_no = []
    for j in range(5, len(lines)):
        f = lines[j].split(sep)
        if not any(x.strip() for x in f):
            continue
        if len(f) > n_fields and not any(x.strip() for x in f[n_fields:]):
            f = f[:n_fields]
        if len(f) != n_fields:
            raise FormatError(
                path,
                f"expected {n_fields} fields (Frame#, Time, 3 x {n_markers} markers), found {len(f)}",
                line=j + 1,
            )
        rows.append(_row_values(path, f, j + 1, markers))
        line_no.append(j + 1)
    if not rows:
        n_frames = int(
            float(
                dict(zip(_split(lines[1], sep), _split(lines[2], sep), strict=False))["NumFrames"]
            )
        )
        raise FormatError(path, f"expected {n_frames} frames (NumFrames), found no data rows")
    return np.asarray(rows).reshape(len(rows), n_fields), line_no


def _row_values(path: Path, fields: list[str], line: int, markers: list[str]) -> np.ndarray:
    row = np.empty(len(fields))
    for i, v in enumerate(fields):
        v = v.strip()
        if not v:
            if i < 2:
                raise FormatError(
                    path,
                    "expected a value, found an empty field",
                    line=line,
                    field=("Frame#", "Time")[i],
                )
            row[i] = np.nan
            continue
        try:
            row[i] = float(v)
        except ValueError:
            fld = (
                ("Frame#", "Time")[i] if i < 2 else f"{markers[(i - 2) // 3]}.{'XYZ'[(i - 2) % 3]}"
            )
            raise FormatError(
                path, f"expected a number, found {v!r}", line=line, field=fld
            ) from None
    return row


def _nice_rate(t_s: np.ndarray) -> float:
    """Sampling rate from the span of the times, snapped to 6 significant digits when that is
    within 1e-6 (so rounded time columns and float noise give 60, not 58.82 or 120.000005)."""
    if t_s.size < 2:
        return 0.0
    rate = float((t_s.size - 1) / (t_s[-1] - t_s[0]))
    nice = float(f"{rate:.6g}")
    return nice if abs(nice - rate) <= 1e-6 * rate else rate


def write_trc(
    path,
    stream: JointStream,
    *,
    units: str = "m",
    decimals: int | None = None,
    force: bool = False,
    masked: bool = True,
    rate_hz: float | None = None,
    header: Mapping[str, str] | None = None,
    note: str | None = None,
) -> Path:
    """Write a joint stream as a TRC file (tab-separated, readable by OpenSim).

    Parameters
    ----------
    path : str or Path
        Destination ``.trc``; never overwritten unless ``force``.
    stream : JointStream
        Positions (T, J, 3) in m; joint names become marker names.
    units : {"m", "mm", "cm"}
        Unit written in the header and used for the values.
    decimals : int or None
        Digits after the decimal point; default 6 for m, 3 for mm, 4 for cm (µm resolution).
    force : bool
        Replace an existing file.
    masked : bool
        Write unavailable samples as empty fields (TRC's missing-marker convention).
    rate_hz : float or None
        ``DataRate`` (and, unless ``header`` says otherwise, ``CameraRate``/``OrigDataRate``).
        Default ``header["DataRate"]`` if given, else ``(T - 1) / (t[-1] - t[0])`` snapped to
        6 significant digits.
    header : mapping or None
        Header values of the file the stream was read from (``rec.metadata["header"]`` of
        :func:`read_trc`): ``DataRate``, ``CameraRate``, ``OrigDataRate``,
        ``OrigDataStartFrame`` and ``OrigNumFrames`` are written as given (``NumFrames``,
        ``NumMarkers`` and ``Units`` always describe the data written).
    note : str, optional
        Free text appended to the first line after the file name (e.g. the root and frame of
        the positions); readers, OpenSim's included, ignore it. No tabs or newlines.

    Returns
    -------
    Path

    Raises
    ------
    FileExistsError
        ``path`` exists and ``force`` is False.
    """
    path = Path(path)
    factor, decimals, hdr = _check_write_args(stream, units, decimals, header, note)
    T, J = len(stream), len(stream.joints)
    p = stream.position_m * factor
    if masked:
        p = np.where(stream.available[..., None], p, np.nan)
    out_hdr = _out_header(stream, hdr, units, rate_hz)
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}" + (f"\t{note}" if note else ""),
        "\t".join(out_hdr),
        "\t".join(out_hdr.values()),
        "\t".join(["Frame#", "Time"] + [f"{j}\t\t" for j in stream.joints]).rstrip("\t"),
        "\t".join(["", ""] + [f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(J)]),
        "",
    ]
    flat = p.reshape(T, 3 * J)
    values = fixed_point_rows([flat[:, i] for i in range(3 * J)], decimals, "\t")
    for k in range(T):
        row = f"{k + 1}\t{float(stream.t_s[k])!r}" + (f"\t{values[k]}" if J else "")
        # OpenSim's tokenizer drops one trailing empty field: a row ending in a missing marker
        # gets a closing tab so that every row keeps 2 + 3 J fields there too
        out.append(row + "\t" if J and not np.isfinite(flat[k, -1]) else row)
    return write_text_safely(path, "\n".join(out) + "\n", force=force)


#: TRC header values the writer takes as given and a reader parses as numbers.
_RATE_KEYS = frozenset({"DataRate", "CameraRate", "OrigDataRate"})
_NUMBER_KEYS = _RATE_KEYS | {"OrigDataStartFrame", "OrigNumFrames"}


def _is_number(text: str, rate: bool) -> bool:
    """``text`` a finite rate > 0 (``rate``) or a whole number."""
    try:
        x = float(text)
    except ValueError:
        return False
    return bool(np.isfinite(x) and (x > 0 if rate else x == int(x)))


def _check_write_args(stream, units: str, decimals, header, note) -> tuple[float, int, dict]:
    """(factor from m, decimals, header values as text) after checking what TRC can hold."""
    if not isinstance(stream, JointStream):
        raise InputError(f"expected a JointStream, got {type(stream).__name__}")
    factor = {"m": 1.0, "mm": 1e3, "cm": 1e2}.get(units)
    if factor is None:
        raise InputError(f"expected units 'm', 'mm' or 'cm', got {units!r}")
    if decimals is None:
        decimals = {"m": 6, "mm": 3, "cm": 4}[units]
    for j in stream.joints:
        if "\t" in j or not j.strip():
            raise InputError(f"joint name {j!r} cannot be written to TRC (empty or contains a tab)")
    hdr = {str(k): str(v).strip() for k, v in (header or {}).items()}
    for k, v in hdr.items():
        if "\t" in v or not v:
            raise InputError(f"header value {k}={v!r} cannot be written to TRC (empty or a tab)")
        if k in _NUMBER_KEYS and not _is_number(v, k in _RATE_KEYS):
            what = "a rate > 0" if k in _RATE_KEYS else "a whole number"
            raise InputError(
                f"header value {k}={v!r}: expected {what} (read_trc refuses anything else)"
            )
    if note is not None and ("\t" in note or "\n" in note):
        raise InputError(f"TRC note must be one line without tabs, got {note!r}")
    return factor, decimals, hdr


def _out_header(stream: JointStream, hdr: dict, units: str, rate_hz) -> dict[str, str]:
    """The header keys and values written: rates as given or from the data, sizes of the data."""
    T, J = len(stream), len(stream.joints)
    if rate_hz is not None:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise InputError(f"expected rate_hz finite and > 0, got {rate_hz!r}")
        rate = f"{float(rate_hz):.10g}"
    else:
        rate = hdr.get("DataRate") or f"{_nice_rate(stream.t_s):.10g}"
    return {
        "DataRate": rate,
        "CameraRate": hdr.get("CameraRate", rate),
        "NumFrames": str(T),
        "NumMarkers": str(J),
        "Units": units,
        "OrigDataRate": hdr.get("OrigDataRate", rate),
        "OrigDataStartFrame": hdr.get("OrigDataStartFrame", "1"),
        "OrigNumFrames": hdr.get("OrigNumFrames", str(T)),
    }
