"""OpenSim storage tables: ``.mot`` / ``.sto`` (joint coordinates, states) and OpenSense orientations.

Layout (what OpenSim's ``STOFileAdapter`` reads and writes)::

    Coordinates                    <- free text (the table's name, notes)
    version=1                      <- key=value header lines
    nRows=151
    inDegrees=yes
    endheader
    time<TAB>pelvis_tilt<TAB>...   <- column labels, the first is the independent column
    0.0<TAB>10.33<TAB>...          <- rows; DataType=Quaternion/Vec3 fields are "w,x,y,z" / "x,y,z"

:func:`read_opensim_table` returns the values exactly as stored (as OpenSim does: no unit
conversion), with the units of every column (:meth:`OpenSimTable.units`) and an SI view
(:meth:`OpenSimTable.si_values`). :func:`read_opensense_sto` reads an OpenSense orientation table
(``DataType=Quaternion``, one column per IMU) into a :class:`Recording`, and
:func:`write_opensense_sto` writes kinefuse's sensor orientations in that layout, the input of
OpenSense inverse kinematics (``OpenSim::IMUInverseKinematicsTool``).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError, FormatWarning, InputError
from kinefuse.io._checks import make_metadata
from kinefuse.io._names import map_segments
from kinefuse.io._text import check_time, read_text
from kinefuse.io._write import printf_rows, write_text_safely
from kinefuse.io.recording import ImuStream, Recording

__all__ = [
    "OPENSIM_IMU_BODIES",
    "OpenSimTable",
    "read_opensense_sto",
    "read_opensim_mot",
    "read_opensim_table",
    "write_opensense_sto",
]

#: Canonical segment -> OpenSim body of the Rajagopal / gait2392 models (OpenSense names its IMU
#: frames ``<body>_imu``).
OPENSIM_IMU_BODIES = {
    "chest": "torso",
    "pelvis": "pelvis",
    "upper_arm_l": "humerus_l",
    "upper_arm_r": "humerus_r",
    "forearm_l": "radius_l",
    "forearm_r": "radius_r",
    "thigh_l": "femur_l",
    "thigh_r": "femur_r",
    "shank_l": "tibia_l",
    "shank_r": "tibia_r",
    "foot_l": "calcn_l",
    "foot_r": "calcn_r",
}

#: Values per field of each OpenSim ``DataType``.
_ELEMENTS = {"double": 1, "Vec3": 3, "UnitVec3": 3, "Quaternion": 4, "Vec6": 6}
_TRANSLATION_SUFFIXES = ("_tx", "_ty", "_tz")
#: Frame label of OpenSense orientation tables (written values, never converted).
STO_FRAME = "opensense_world"


@dataclass(frozen=True, eq=False)
class OpenSimTable:
    """An OpenSim storage table, values as stored in the file.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        The independent (first) column, s.
    columns : tuple of str
        Labels of the dependent columns (C of them).
    values : ndarray, shape (T, C) or (T, C, k)
        Values as written (``k`` = 3 for ``Vec3``, 4 for ``Quaternion``, wxyz); NaN = missing.
    data_type : str
        ``"double"`` (no ``DataType`` line), ``"Vec3"``, ``"Quaternion"``...
    header : dict of str -> str
        The ``key=value`` header lines (``version``, ``nRows``, ``inDegrees``, ``DataRate``...).
    description : tuple of str
        The other header lines (the table's name, notes such as "Angles are in degrees.").
    time_label : str
        Label of the independent column (``"time"``).
    """

    t_s: np.ndarray
    columns: tuple[str, ...]
    values: np.ndarray
    data_type: str = "double"
    header: dict = field(default_factory=dict)
    description: tuple[str, ...] = ()
    time_label: str = "time"

    @property
    def in_degrees(self) -> bool | None:
        """``inDegrees`` of the header (True/False), None when the header does not say."""
        v = self.header.get("inDegrees")
        return None if v is None else v.strip().lower() in ("yes", "true", "1")

    @property
    def rate_hz(self) -> float | None:
        """``DataRate`` of the header, Hz (None when absent)."""
        v = self.header.get("DataRate")
        try:
            return None if v is None else float(v)
        except ValueError:
            return None

    def column(self, name: str) -> np.ndarray:
        """Values ``(T,)`` (or ``(T, k)``) of column ``name``; a clear error lists the labels."""
        try:
            return self.values[:, self.columns.index(name)]
        except ValueError:
            raise InputError(
                f"unknown column {name!r}; this table has {list(self.columns)}"
            ) from None

    def units(self) -> dict[str, str]:
        """Unit of each column: ``"deg"``/``"rad"`` (rotational coordinates, per ``inDegrees``),
        ``"m"`` (OpenSim translational coordinates ``*_tx/_ty/_tz``), ``""`` when the header
        does not say (``inDegrees`` absent) or the table is not a double table.

        A coordinate is taken as rotational unless its label ends with ``_tx``, ``_ty`` or
        ``_tz`` (OpenSim's naming of translational coordinates; the model, not the file, is
        the authority: a translation named otherwise, such as a FreeJoint's default
        ``*_coord_3..5``, is reported as an angle).
        """
        deg = self.in_degrees
        out = {}
        for c in self.columns:
            if self.data_type != "double" or deg is None:
                out[c] = ""
            elif c.endswith(_TRANSLATION_SUFFIXES):
                out[c] = "m"
            else:
                out[c] = "deg" if deg else "rad"
        return out

    def si_values(self) -> np.ndarray:
        """``values`` with degree columns converted to radians (``(T, C)``); others unchanged."""
        v = np.array(self.values, dtype=float)
        for j, u in enumerate(self.units().values()):
            if u == "deg":
                v[:, j] = np.deg2rad(v[:, j])
        return v

    def __len__(self) -> int:
        return int(self.t_s.size)


def _parse_fields(path: Path, text: str, lineno: int, labels: list[str], k: int) -> list[float]:
    n = len(labels)
    fields = text.split("\t")
    if len(fields) != n and len(fields) == 1:
        fields = text.split()  # space-separated legacy files
    if len(fields) > n and not any(f.strip() for f in fields[n:]):
        fields = fields[:n]
    if len(fields) != n:
        what = "truncated line?" if len(fields) < n else "extra fields"
        raise FormatError(
            path,
            f"expected {n} fields as in the column labels, found {len(fields)} ({what})",
            line=lineno,
        )
    out = []
    for j, f in enumerate(fields):
        parts = f.split(",") if (k > 1 and j > 0) else [f]
        if len(parts) != (k if j > 0 else 1):
            raise FormatError(
                path,
                f"expected {k} comma-separated values in a field, found {len(parts)} ({f.strip()!r})",
                line=lineno,
                field=labels[j],
            )
        for p in parts:
            try:
                out.append(float(p))
            except ValueError:
                raise FormatError(
                    path,
                    f"expected a number, found {p.strip()!r}",
                    line=lineno,
                    field=labels[j],
                ) from None
    return out


def _table_header(path: Path, lines: list[str]):
    """(``key=value`` header, description lines, index of the labels line, column labels)."""
    end = next((i for i, ln in enumerate(lines) if ln.strip().lower() == "endheader"), None)
    if end is None:
        raise FormatError(
            path,
            "expected an OpenSim table header ending with a line 'endheader', found none "
            "(is this an OpenSim .mot/.sto file?)",
        )
    header: dict[str, str] = {}
    description: list[str] = []
    for ln in lines[:end]:
        s = ln.strip()
        if "=" in s and " " not in s.split("=", 1)[0]:
            k, v = s.split("=", 1)
            header[k.strip()] = v.strip()
        elif s:
            description.append(s)
    k_lab = end + 1
    while k_lab < len(lines) and not lines[k_lab].strip():
        k_lab += 1
    if k_lab >= len(lines):
        raise FormatError(
            path, "expected column labels after 'endheader', found the end of the file"
        )
    raw = lines[k_lab]
    labels = [c.strip() for c in (raw.split("\t") if "\t" in raw else raw.split())]
    while labels and not labels[-1]:
        labels.pop()
    if len(labels) < 2 or any(not c for c in labels):
        raise FormatError(
            path,
            f"expected tab-separated column labels (time first), found {raw.strip()!r}",
            line=k_lab + 1,
        )
    return header, description, k_lab, labels


def read_opensim_table(path) -> OpenSimTable:
    """Read an OpenSim ``.mot`` / ``.sto`` table (any version OpenSim reads).

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    OpenSimTable
        Values exactly as stored (OpenSim's ``STOFileAdapter`` returns the same numbers); units
        from ``inDegrees`` via :meth:`OpenSimTable.units`.

    Raises
    ------
    FormatError
        No ``endheader`` line, no column labels, an unknown ``DataType``, a row with another
        number of fields than the labels, a non-numeric value, non-increasing time.

    Warns
    -----
    FormatWarning
        ``nRows`` / ``nColumns`` in the header disagree with the table (the rows there are are
        read, as OpenSim does).
    """
    path = Path(path)
    lines = read_text(path).splitlines()
    header, description, k_lab, labels = _table_header(path, lines)
    dtype = header.get("DataType", "double")
    if dtype not in _ELEMENTS:
        raise FormatError(
            path,
            f"unsupported DataType {dtype!r}; kinefuse reads {sorted(_ELEMENTS)}",
            field="DataType",
        )
    k = _ELEMENTS[dtype]
    n = len(labels)
    rows, line_no = [], []
    for j in range(k_lab + 1, len(lines)):
        if not lines[j].strip():
            continue
        rows.append(_parse_fields(path, lines[j], j + 1, labels, k))
        line_no.append(j + 1)
    data = np.asarray(rows, dtype=float).reshape(len(rows), 1 + (n - 1) * k)
    t = check_time(path, data[:, 0], np.asarray(line_no), labels[0])
    values = data[:, 1:].reshape(len(rows), n - 1, k)
    if k == 1:
        values = values[..., 0]
    for key, found in (("nRows", len(rows)), ("nColumns", n)):
        if key in header and header[key].strip().isdigit() and int(header[key]) != found:
            warnings.warn(
                f"{path}: header says {key}={header[key]}, the table has {found}; read what is there",
                FormatWarning,
                stacklevel=2,
            )
    return OpenSimTable(t, tuple(labels[1:]), values, dtype, header, tuple(description), labels[0])


def read_opensense_sto(path, *, sensor_map: Mapping[str, str] | None = None) -> Recording:
    """Read an OpenSense orientation table (``.sto``, ``DataType=Quaternion``) as IMU orientations.

    Parameters
    ----------
    path : str or Path
        The ``*_orientations.sto`` file (e.g. written by OpenSense's ``IMUDataReader`` or by
        :func:`write_opensense_sto`).
    sensor_map : mapping or None
        Column label (``femur_r_imu``) -> segment key; default: OpenSim body names mapped to
        canonical segments (``torso`` -> ``chest``, ``femur`` -> thigh, ``tibia`` -> shank,
        ``calcn`` -> foot, ``humerus`` -> upper arm, ``radius`` -> forearm).

    Returns
    -------
    Recording
        ``imu[key].q_world_from_sensor`` (T, 4) wxyz as written (not re-normalised), frame
        :data:`STO_FRAME`; ``metadata["rate_hz"]`` = ``DataRate``; ``metadata["table"]`` the
        :class:`OpenSimTable`.

    Raises
    ------
    FormatError
        Not a quaternion table, or quaternions far from unit norm (|‖q‖ − 1| > 1e-3).
    """
    path = Path(path)
    tab = read_opensim_table(path)
    if tab.data_type != "Quaternion":
        raise FormatError(
            path,
            f"expected an OpenSense orientation table (DataType=Quaternion), found DataType={tab.data_type}; "
            "read it with read_opensim_table",
            field="DataType",
        )
    if len(tab) == 0:
        raise FormatError(path, "expected at least one row after the column labels, found none")
    norm = np.linalg.norm(tab.values, axis=-1)
    bad = np.isfinite(norm) & (np.abs(norm - 1.0) > 1e-3)
    if np.any(bad):
        i, j = (int(v[0]) for v in np.nonzero(bad))
        raise FormatError(
            path,
            f"expected unit quaternions, found |q| = {norm[i, j]:.6g} at time {tab.t_s[i]:g}",
            field=tab.columns[j],
        )
    overrides = {c: (sensor_map or {}).get(c) for c in tab.columns}
    mapping, notes = map_segments(tab.columns, {c: v for c, v in overrides.items() if v})
    imu = {
        mapping[c]: ImuStream(
            t_s=tab.t_s, q_world_from_sensor=tab.values[:, j], name=c, frame=STO_FRAME
        )
        for j, c in enumerate(tab.columns)
    }
    md = make_metadata(
        path,
        "opensense_sto",
        segment_map=mapping,
        rate_hz=tab.rate_hz,
        table=tab,
        frame_notes=(
            "orientations as written (OpenSense's readers keep the IMU vendor's world frame, z up for "
            "Xsens/APDM; OpenSense IK rotates it with sensor_to_opensim_rotations); not converted"
        ),
        notes=notes,
    )
    return Recording(imu=imu, metadata=md)


def _sto_rows(t: np.ndarray, qs: list) -> list[str]:
    """The data rows of an orientation ``.sto``: time, then each ``(T, 4)`` quaternion's four
    values joined by commas, tab-separated; each value its shortest round-trip ``repr``
    (``NaN`` if not finite), formatted in one pass (tests/test_io_number_text.py compares it
    with formatting value by value)."""
    cols = [t] + [c for q in qs for c in np.asarray(q, float).T]
    return printf_rows(cols, "\t".join(["%r"] + [",".join(["%r"] * 4)] * len(qs)))


def write_opensense_sto(
    path,
    imu,
    *,
    rate_hz: float | None = None,
    names: Mapping[str, str] | None = None,
    force: bool = False,
) -> Path:
    """Write sensor orientations as an OpenSense orientation table (input of OpenSense IK).

    Parameters
    ----------
    path : str or Path
        Destination ``.sto``; never overwritten unless ``force`` (nor, even then, the file a
        recording was read from).
    imu : Recording or mapping of str -> ImuStream
        Streams with ``q_world_from_sensor`` (wxyz), all on the same timeline (use
        :func:`kinefuse.io.resample_recording` first otherwise).
    rate_hz : float or None
        ``DataRate`` of the header; default ``metadata["rate_hz"]`` of a recording that has it
        (the rate the source file declared), else ``1 / median(diff(t))``.
    names : mapping or None
        Segment key -> column label; default ``<OpenSim body>_imu`` (:data:`OPENSIM_IMU_BODIES`,
        e.g. ``thigh_r`` -> ``femur_r_imu``), other keys ``<key>_imu`` (kept if they already end
        in ``_imu``).
    force : bool
        Replace an existing file.

    Returns
    -------
    Path

    Raises
    ------
    InputError
        No streams, a stream without orientation, streams on different timelines, duplicate
        column labels.
    FileExistsError
        ``path`` exists and ``force`` is False.

    Notes
    -----
    OpenSense expects its world with y up; for z-up worlds (ENU, Xsens) set
    ``sensor_to_opensim_rotations`` to ``-1.5707963 0 0`` in the IMU IK setup, as in the
    OpenSense tutorial. NaN (missing) orientations are written as ``NaN``.
    """
    md = imu.metadata if isinstance(imu, Recording) else {}
    streams = imu.imu if isinstance(imu, Recording) else dict(imu)
    if not streams:
        raise InputError("write_opensense_sto: expected at least one IMU stream, got none")
    t, labels = _timeline_and_labels(streams, names)
    if rate_hz is None:
        rate_hz = md.get("rate_hz") or (1.0 / float(np.median(np.diff(t))) if t.size > 1 else None)
    if rate_hz is None or not (float(rate_hz) > 0):
        raise InputError(f"write_opensense_sto: expected rate_hz > 0, got {rate_hz!r}")
    out = [f"DataRate={float(rate_hz):.6f}", "DataType=Quaternion", "version=3", "endheader"]
    out.append("\t".join(["time", *labels]))
    out += _sto_rows(t, [s.q_world_from_sensor for s in streams.values()])
    protect = [md.get("source")] + list(md.get("files", []))
    return write_text_safely(path, "\n".join(out) + "\n", force=force, protect=protect)


def _timeline_and_labels(streams: Mapping, names) -> tuple[np.ndarray, list[str]]:
    """The streams' common time (checked) and their column labels (checked unique)."""
    t = None
    labels = []
    for key, s in streams.items():
        if not isinstance(s, ImuStream) or s.q_world_from_sensor is None:
            raise InputError(
                f"write_opensense_sto: IMU {key!r} has no orientation (q_world_from_sensor)"
            )
        if t is None:
            t = s.t_s
        elif s.t_s.shape != t.shape or not np.array_equal(s.t_s, t):
            raise InputError(
                f"write_opensense_sto: IMU {key!r} is on another timeline than the first stream "
                f"({s.t_s.size} vs {t.size} samples); resample first (kinefuse.io.resample_recording)"
            )
        if names and key in names:
            lab = names[key]
        else:
            body = OPENSIM_IMU_BODIES.get(key, key)
            lab = body if body.endswith("_imu") else f"{body}_imu"
        if lab in labels or not lab or any(c in lab for c in "\t\n, "):
            raise InputError(
                f"write_opensense_sto: bad or duplicate column label {lab!r} for {key!r}"
            )
        labels.append(lab)
    return t, labels


def read_opensim_mot(path) -> Recording:
    """:func:`kinefuse.io.load` entry for OpenSim tables that are not orientations (``.mot``, ``.sto``).

    Returns
    -------
    Recording
        No streams; ``metadata["table"]`` the :class:`OpenSimTable` (values as stored),
        ``metadata["units"]`` column -> unit, ``metadata["rate_hz"]`` (``DataRate`` or None).
        A quaternion table is read by :func:`read_opensense_sto` instead.
    """
    path = Path(path)
    tab = read_opensim_table(path)
    if tab.data_type == "Quaternion":
        return read_opensense_sto(path)
    md = make_metadata(
        path,
        "opensim_table",
        table=tab,
        units=tab.units(),
        rate_hz=tab.rate_hz,
        notes=[f"OpenSim table of {len(tab.columns)} columns (DataType={tab.data_type})"],
    )
    return Recording(metadata=md)
