"""Shared helpers of the readers and writers: text tables, name mapping, unit checks, safe writes.

Private module: nothing here is public API. Readers validate at their boundary and raise
:class:`~kinefuse.exceptions.FormatError` naming the file, line/field, expected and found.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinefuse.conventions import GRAVITY_M_S2, JOINTS, SEGMENTS
from kinefuse.exceptions import FormatError, InputError, UnitWarning

__all__ = [
    "DEG2RAD",
    "G",
    "ZERO_RULE",
    "Table",
    "canonical_joint",
    "canonical_segment",
    "current_umask",
    "check_time",
    "check_units",
    "make_metadata",
    "zero_is_missing",
    "map_joints",
    "map_segments",
    "read_table",
    "write_text_safely",
]

G = GRAVITY_M_S2
DEG2RAD = math.pi / 180.0


# --------------------------------------------------------------------------------------------
# text tables
# --------------------------------------------------------------------------------------------
@dataclass
class Table:
    """A delimited text table held as strings, with the file line number of every row.

    Attributes
    ----------
    path : Path
        The file read.
    columns : list of str
        Header names, stripped.
    rows : list of list of str
        Fields of each data row (already padded/validated to ``len(columns)``).
    lines : ndarray of int, shape (n,)
        1-based line number of each row in the file.
    comments : list of str
        Comment lines before the header, without the comment prefix.
    header_line : int
        1-based line number of the header.
    """

    path: Path
    columns: list[str]
    rows: list[list[str]]
    lines: np.ndarray
    comments: list[str] = field(default_factory=list)
    header_line: int = 1

    def __len__(self) -> int:
        return len(self.rows)

    def has(self, name: str) -> bool:
        return name in self.columns

    def index(self, name: str) -> int:
        try:
            return self.columns.index(name)
        except ValueError:
            raise FormatError(
                self.path,
                f"missing column {name!r}; found columns {self.columns}",
                line=self.header_line,
                field=name,
            ) from None

    def strings(self, name: str) -> list[str]:
        i = self.index(name)
        return [r[i].strip() for r in self.rows]

    def floats(self, name: str, *, allow_empty: bool = True) -> np.ndarray:
        """Column ``name`` as float64; empty fields are NaN when ``allow_empty``.

        Raises
        ------
        FormatError
            Naming the line and column of the first field that is not a number.
        """
        i = self.index(name)
        raw = [r[i] for r in self.rows]
        try:
            out = np.array(raw, dtype=np.float64)
        except ValueError:
            out = None
        if out is not None:
            self._check_no_inf(out, raw, name)
            return out
        out = np.empty(len(raw), dtype=np.float64)
        for k, v in enumerate(raw):
            s = v.strip()
            if not s:
                if not allow_empty:
                    raise FormatError(
                        self.path,
                        "expected a number, found an empty field",
                        line=int(self.lines[k]),
                        field=name,
                    )
                out[k] = np.nan
                continue
            try:
                out[k] = float(s)
            except ValueError:
                raise FormatError(
                    self.path,
                    f"expected a number, found {s!r}",
                    line=int(self.lines[k]),
                    field=name,
                ) from None
        self._check_no_inf(out, raw, name)
        return out

    def _check_no_inf(self, out: np.ndarray, raw: list[str], name: str) -> None:
        """Infinite values are never data (NaN, an empty field, is missing): issue 12."""
        bad = np.flatnonzero(np.isinf(out))
        if bad.size:
            k = int(bad[0])
            raise FormatError(
                self.path,
                f"expected a finite number, found {raw[k].strip()!r} ({bad.size} infinite "
                "value(s) in this column); leave the field empty for a missing sample",
                line=int(self.lines[k]),
                field=name,
            )

    def comment_dict(self) -> dict[str, str]:
        """``key: value`` pairs found in the comment lines (keys lower-cased)."""
        out = {}
        for c in self.comments:
            if ":" in c:
                k, v = c.split(":", 1)
                out[k.strip().lower()] = v.strip()
        return out


def _read_text(path: Path) -> str:
    try:
        raw = path.read_bytes()
    except IsADirectoryError:
        raise FormatError(path, "expected a file, found a directory") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise FormatError(
            path, f"expected UTF-8 text, found undecodable byte 0x{raw[e.start]:02x}", line=line
        ) from None


def read_table(
    path,
    *,
    delimiter: str | None = None,
    comment_prefixes: Sequence[str] = ("#", "//"),
    min_rows: int = 1,
    is_header=None,
) -> Table:
    """Read a delimited text file with an optional comment preamble and one header line.

    Parameters
    ----------
    path : str or Path
        The file.
    delimiter : str or None
        Field separator; ``None`` sniffs the header (tab, then ``,``, then ``;``).
    comment_prefixes : sequence of str
        Lines starting with one of these are comments (kept when they precede the header).
    min_rows : int
        Minimum number of data rows; fewer is a truncated file.
    is_header : callable or None
        ``is_header(line) -> bool``: the header is the first line it accepts; lines before it are
        a preamble, kept in ``comments`` (for exports whose preamble has no comment prefix).
        None: the first line that is not a comment.

    Returns
    -------
    Table

    Raises
    ------
    FormatError
        Empty file, too few rows, or a row with a different number of fields than the header
        (naming the line, the expected and found counts).
    """
    path = Path(path)
    text = _read_text(path)
    lines = text.splitlines()
    comments: list[str] = []
    k = 0
    while k < len(lines) and (
        not lines[k].strip() or lines[k].lstrip().startswith(tuple(comment_prefixes))
    ):
        s = lines[k].strip()
        for p in comment_prefixes:
            if s.startswith(p):
                s = s[len(p) :].strip()
                break
        if s:
            comments.append(s)
        k += 1
    if is_header is not None:
        j = k
        while j < len(lines) and not is_header(lines[j]):
            j += 1
        if j >= len(lines):
            raise FormatError(
                path,
                "expected a header line with column names, found none that this reader recognises",
            )
        comments += [ln.strip() for ln in lines[k:j] if ln.strip()]
        k = j
    if k >= len(lines):
        raise FormatError(
            path,
            "expected a header line with column names, found no data (empty or truncated file)",
        )
    header = lines[k]
    if delimiter is None:
        delimiter = (
            "\t" if "\t" in header else ("," if "," in header else (";" if ";" in header else ","))
        )
    columns = [c.strip() for c in header.split(delimiter)]
    while columns and not columns[-1]:
        columns.pop()
    header_line = k + 1
    n = len(columns)
    rows: list[list[str]] = []
    line_no: list[int] = []
    for j in range(k + 1, len(lines)):
        ln = lines[j]
        if not ln.strip() or ln.lstrip().startswith(tuple(comment_prefixes)):
            continue
        f = ln.split(delimiter)
        if len(f) > n and not any(x.strip() for x in f[n:]):
            f = f[:n]
        if len(f) != n:
            what = "truncated line?" if len(f) < n else "extra fields"
            raise FormatError(
                path, f"expected {n} fields as in the header, found {len(f)} ({what})", line=j + 1
            )
        rows.append(f)
        line_no.append(j + 1)
    if len(rows) < min_rows:
        raise FormatError(
            path, f"expected at least {min_rows} data rows after the header, found {len(rows)}"
        )
    return Table(path, columns, rows, np.asarray(line_no, dtype=int), comments, header_line)


def check_time(path, t: np.ndarray, lines: np.ndarray | None, field: str) -> np.ndarray:
    """Require finite, strictly increasing times; otherwise a FormatError naming the line."""
    t = np.asarray(t, dtype=float)
    bad = ~np.isfinite(t)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(
            path,
            f"expected a finite time, found {float(t[i])!r}",
            line=None if lines is None else int(lines[i]),
            field=field,
        )
    if t.size > 1:
        d = np.diff(t)
        if np.any(d <= 0):
            i = int(np.flatnonzero(d <= 0)[0]) + 1
            raise FormatError(
                path,
                f"expected strictly increasing time, found {float(t[i])!r} after {float(t[i - 1])!r} (non-monotonic or duplicate)",
                line=None if lines is None else int(lines[i]),
                field=field,
            )
    return t


TIME_COLUMNS = {
    # lower-cased column name -> factor to seconds
    "t_s": 1.0,
    "time_s": 1.0,
    "time": 1.0,
    "timestamp_s": 1.0,
    "t_ms": 1e-3,
    "time_ms": 1e-3,
    "timestamp_ms": 1e-3,
    "t_us": 1e-6,
    "time_us": 1e-6,
    "timestamp_us": 1e-6,
    "timestamp_usec": 1e-6,
    "relative_time_100ns": 1e-7,
    "relativetime": 1e-7,
}


def table_time(table: Table, *, rate_hz: float | None = None) -> tuple[np.ndarray, str]:
    """Time in seconds from the table's time column, or ``frame / rate_hz``.

    Returns
    -------
    t_s : ndarray, shape (n,)
    column : str
        The column used (``"<row index>"`` if neither a time nor a frame column exists).
    """
    lower = {c.lower(): c for c in table.columns}
    for name, factor in TIME_COLUMNS.items():
        if name in lower:
            col = lower[name]
            t = table.floats(col, allow_empty=False) * factor
            return check_time(table.path, t, table.lines, col), col
    for name in ("frame", "frame#", "frame_index"):
        if name in lower:
            if rate_hz is None:
                raise FormatError(
                    table.path,
                    f"found a frame column but no time column (one of {sorted(TIME_COLUMNS)}); pass rate_hz=",
                    line=table.header_line,
                )
            col = lower[name]
            t = table.floats(col, allow_empty=False) / float(rate_hz)
            return check_time(table.path, t, table.lines, col), col
    if rate_hz is not None:
        return np.arange(len(table)) / float(rate_hz), "<row index>"
    raise FormatError(
        table.path,
        f"missing time column: expected one of {sorted(TIME_COLUMNS)} (or a 'frame' column with rate_hz=)",
        line=table.header_line,
        field="t_s",
    )


# --------------------------------------------------------------------------------------------
# name mapping
# --------------------------------------------------------------------------------------------
_SIDE = {"l": "l", "left": "l", "lt": "l", "r": "r", "right": "r", "rt": "r"}
_DROP = {"imu", "sensor", "udp", "body", "segment"}
_SEGMENT_PARTS = {
    "chest": "chest",
    "torso": "chest",
    "thorax": "chest",
    "sternum": "chest",
    "trunk": "chest",
    "upper_back": "chest",
    "upperback": "chest",
    "pelvis": "pelvis",
    "hip": "pelvis",
    "hips": "pelvis",
    "sacrum": "pelvis",
    "upper_arm": "upper_arm",
    "upperarm": "upper_arm",
    "humerus": "upper_arm",
    "forearm": "forearm",
    "fore_arm": "forearm",
    "lower_arm": "forearm",
    "lowerarm": "forearm",
    "radius": "forearm",
    "ulna": "forearm",
    "thigh": "thigh",
    "upper_leg": "thigh",
    "upperleg": "thigh",
    "up_leg": "thigh",
    "upleg": "thigh",
    "femur": "thigh",
    "shank": "shank",
    "lower_leg": "shank",
    "lowerleg": "shank",
    "tibia": "shank",
    "shin": "shank",
    "foot": "foot",
    "calcn": "foot",
}
_UNSIDED_SEGMENTS = {"chest", "pelvis"}


def _tokens(name: str) -> list[str]:
    out = []
    for part in re.split(r"[^A-Za-z0-9]+", str(name)):
        if not part or _is_device_id(part.lower()):
            continue
        part = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", part)
        out += [t for t in part.lower().split("_") if t]
    return out


def _is_device_id(tok: str) -> bool:
    return len(tok) >= 6 and bool(re.fullmatch(r"[0-9a-f]+", tok)) and any(c.isdigit() for c in tok)


def canonical_segment(name: str) -> str | None:
    """Canonical segment name for a sensor/body label, or None when not recognised.

    Understands ``Right_Upper_Leg_64F61C2E``, ``upper_arm_left``, ``femur_r``, ``LUpLeg`` style
    labels; a trailing device id (hex) and the words ``imu``/``sensor`` are ignored.
    """
    if name in SEGMENTS:
        return name
    side = None
    rest = []
    for tok in _tokens(name):
        if tok in _SIDE:
            if side is not None and side != _SIDE[tok]:
                return None
            side = _SIDE[tok]
        elif tok in _DROP or _is_device_id(tok):
            continue
        else:
            rest.append(tok)
    if not rest:
        return None
    part = _SEGMENT_PARTS.get("_".join(rest))
    if part is None and len(rest) == 1 and len(rest[0]) > 1 and rest[0][0] in "lr" and side is None:
        # "lupleg" / "rthigh" style
        part = _SEGMENT_PARTS.get(rest[0][1:])
        side = rest[0][0] if part else None
    if part is None:
        return None
    if part in _UNSIDED_SEGMENTS:
        return part if side is None else None
    return f"{part}_{side}" if side else None


def map_segments(
    names: Iterable[str], overrides: Mapping[str, str] | None = None
) -> tuple[dict[str, str], list[str]]:
    """Map source sensor names to keys: canonical segment where recognised, else the own name.

    Parameters
    ----------
    names : iterable of str
        Source sensor names in file order.
    overrides : mapping or None
        Source name -> key, taking precedence (e.g. a user's ``sensor_map=``).

    Returns
    -------
    mapping : dict
        Source name -> key (unique keys).
    notes : list of str
        Human-readable notes (unrecognised names, clashes).
    """
    overrides = dict(overrides or {})
    mapping: dict[str, str] = {}
    notes: list[str] = []
    used: set[str] = set()
    for n in names:
        key = overrides.get(n) or canonical_segment(n)
        if key is None:
            key = n
            notes.append(f"sensor {n!r} not mapped to a canonical segment; kept under its own name")
        if key in used:
            notes.append(f"sensor {n!r} maps to {key!r}, already used; kept under its own name")
            key = n
        if key in used:
            raise InputError(f"two sensors are both named {n!r}")
        used.add(key)
        mapping[n] = key
    return mapping, notes


_JOINT_PARTS = {
    "shoulder": "shoulder",
    "elbow": "elbow",
    "wrist": "wrist",
    "hand": "hand",
    "hip": "hip",
    "knee": "knee",
    "ankle": "ankle",
    "foot": "foot",
    "foot_index": "foot",
}
_UNSIDED_JOINTS = {
    "head": "head",
    "neck": "neck",
    "spine_shoulder": "spine_shoulder",
    "shoulder_center": "spine_shoulder",
    "spine_mid": "spine_mid",
    "spine": "spine_mid",
    "spine_base": "spine_base",
    "hip_center": "spine_base",
    "pelvis": "pelvis",
}
#: Plug-in-Gait joint-centre labels (as in the gaittoolbox/Neura Vicon export).
PLUG_IN_GAIT_JOINTS = {
    "LFEP": "hip_l",
    "RFEP": "hip_r",
    "LFEO": "knee_l",
    "RFEO": "knee_r",
    "LTIO": "ankle_l",
    "RTIO": "ankle_r",
}


#: Shoulders to feet, left then right, in the order Kinect v1 and v2 both list them (their
#: skeleton tables differ only in the spine/head joints around this run).
KINECT_LIMB_JOINTS = (
    "shoulder_l", "elbow_l", "wrist_l", "hand_l", "shoulder_r", "elbow_r", "wrist_r", "hand_r",
    "hip_l", "knee_l", "ankle_l", "foot_l", "hip_r", "knee_r", "ankle_r", "foot_r",
)  # fmt: skip


def canonical_joint(label: str) -> str | None:
    """Canonical joint name for a label (``ShoulderLeft``, ``left_wrist``, ``RFEO``...) or None."""
    if label in JOINTS:
        return label
    if label.upper() in PLUG_IN_GAIT_JOINTS:
        return PLUG_IN_GAIT_JOINTS[label.upper()]
    side = None
    rest = []
    for tok in _tokens(label):
        if tok in _SIDE:
            if side is not None and side != _SIDE[tok]:
                return None
            side = _SIDE[tok]
        else:
            rest.append(tok)
    part = "_".join(rest)
    if side is None:
        return _UNSIDED_JOINTS.get(part)
    p = _JOINT_PARTS.get(part)
    return f"{p}_{side}" if p else None


def map_joints(labels: Sequence[str]) -> tuple[tuple[str, ...], dict[str, str]]:
    """Map labels to canonical joint names where they match, else keep the label (unique)."""
    out: list[str] = []
    mapping: dict[str, str] = {}
    for lab in labels:
        key = canonical_joint(lab) or lab
        if key in out:
            key = lab
        if key in out:
            key = f"{lab}#{len(out)}"
        out.append(key)
        mapping[lab] = key
    return tuple(out), mapping


# --------------------------------------------------------------------------------------------
# missing markers
# --------------------------------------------------------------------------------------------
#: The one rule every position reader applies (documented in ``docs/formats.md``).
ZERO_RULE = "a point whose three coordinates are all exactly 0 is missing (not tracked)"


def zero_is_missing(position: np.ndarray) -> np.ndarray:
    """Mask of samples encoded as "not tracked" by all-zero coordinates.

    TRC and C3D writers (and Kinect v1, read by :mod:`kinefuse.io.utd_mhad`) write an untracked
    marker as ``0, 0, 0``; a real marker exactly at the origin to the file's resolution is
    unlikely enough that every kinefuse position reader treats an all-zero point as missing
    (:data:`ZERO_RULE`); readers take ``zero_is_missing=False`` to keep such samples.

    Parameters
    ----------
    position : ndarray, shape (..., 3)

    Returns
    -------
    ndarray of bool, shape (...)
        True where all three coordinates are exactly 0.
    """
    return np.all(np.asarray(position) == 0.0, axis=-1)


# --------------------------------------------------------------------------------------------
# metadata, unit checks
# --------------------------------------------------------------------------------------------
def make_metadata(path, fmt: str, *, subject=None, units_converted=(), **extra) -> dict:
    """The standard metadata dict: subject, source, format, units_converted, plus reader notes."""
    md = {
        "subject": subject,
        "source": str(path),
        "format": fmt,
        "units_converted": list(units_converted),
    }
    md.update(extra)
    return md


def _finite_norm(a: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(a, axis=-1)
    return n[np.isfinite(n)]


def check_units(recording, *, where: str = "", stacklevel: int = 3) -> list[str]:
    """Warn (:class:`~kinefuse.exceptions.UnitWarning`) when magnitudes suggest wrong units.

    Rules (heuristics, documented in ``docs/formats.md``):

    * accelerometer: median ``|acc|`` between 0.5 and 2.0 -> looks like g, not m/s²;
    * gyroscope: 99th percentile of ``|gyr|`` above 35 rad/s (2000 deg/s) -> looks like deg/s;
    * joint positions: median distance of the joints from their per-frame centroid (0.2-0.6 m
      for a body) above 100 -> looks like millimetres, above 10 -> looks like centimetres (with
      one joint: median ``|p|`` above 100) -> looks like millimetres.

    Returns
    -------
    list of str
        The warning messages issued.
    """
    msgs = []
    prefix = f"{where}: " if where else ""
    for key, s in recording.imu.items():
        if s.acc_m_s2 is not None:
            n = _finite_norm(s.acc_m_s2)
            if n.size and 0.5 < float(np.median(n)) < 2.0:
                msgs.append(
                    f"{prefix}IMU {key!r}: median |acc| = {np.median(n):.3g}, which looks like g, not m/s^2 "
                    "(multiply by 9.80665 or declare the unit)"
                )
        if s.gyr_rad_s is not None:
            n = _finite_norm(s.gyr_rad_s)
            if n.size and float(np.percentile(n, 99)) > 35.0:
                msgs.append(
                    f"{prefix}IMU {key!r}: 99th percentile |gyr| = {np.percentile(n, 99):.3g} rad/s, which looks "
                    "like deg/s (multiply by pi/180 or declare the unit)"
                )
    for role in ("vision", "reference"):
        js = getattr(recording, role)
        if js is None or len(js) == 0:
            continue
        p = np.where(js.available[..., None], js.position_m, np.nan)
        if p.shape[1] >= 2:
            ok = np.isfinite(p)
            n = ok.sum(axis=1, keepdims=True)
            c = np.where(ok, p, 0.0).sum(axis=1, keepdims=True) / np.where(n > 0, n, 1)
            d = np.linalg.norm(p - c, axis=-1)
            d = d[np.isfinite(d)]
            if d.size and float(np.median(d)) > 10.0:
                unit, div = (
                    ("millimetres", 1000) if float(np.median(d)) > 100.0 else ("centimetres", 100)
                )
                msgs.append(
                    f"{prefix}{role} joints: median joint spread {np.median(d):.3g} 'm', which looks like "
                    f"{unit} (divide by {div} or declare the unit)"
                )
        else:
            n = _finite_norm(p.reshape(-1, 3))
            if n.size and float(np.median(n)) > 100.0:
                msgs.append(
                    f"{prefix}{role} position: median |p| = {np.median(n):.3g} 'm', which looks like millimetres"
                )
    for m in msgs:
        warnings.warn(m, UnitWarning, stacklevel=stacklevel)
    return msgs


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------
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
