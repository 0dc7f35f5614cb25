"""kinefuse's documented generic CSV formats: IMU data and joint positions (read and write).

IMU CSV (one row per sensor sample; ``sensor`` may be omitted for a single sensor)::

    # kinefuse-imu-csv 1
    # acc_unit: m/s^2          (or g)
    # gyr_unit: rad/s          (or deg/s)
    # frame: ENU               (world frame of the quaternions)
    t_s,sensor,qw,qx,qy,qz,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z,mag_x,mag_y,mag_z

Each group (``qw..qz``, ``acc_*``, ``gyr_*``, ``mag_*``) is optional but all-or-nothing; a sensor
needs the quaternion or both acc and gyr.

Joint CSV (one row per time)::

    # kinefuse-joint-csv 1
    # units: m                 (or mm, cm)
    # frame: ENU
    # role: vision             (or reference)
    # joints: elbow_r,wrist_r
    t_s,elbow_r_x,elbow_r_y,elbow_r_z,elbow_r_available,wrist_r_x,...,<extra columns>

Extra columns (the fused output's per-sample source/mode and uncertainty) are
``<name>`` (one value per row), ``<joint>_<name>`` (per joint) or ``<joint>_<name>_x/_y/_z`` (per
joint and axis). Empty fields are NaN.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io._checks import DEG2RAD, G, finish_recording, make_metadata
from kinefuse.io._names import map_joints, map_segments
from kinefuse.io._text import Table, check_time, read_table, table_time, time_column_s
from kinefuse.io._write import fixed_point_rows, fmt_float, write_text_safely
from kinefuse.io.recording import ImuStream, JointStream, Recording

__all__ = ["read_generic_csv", "read_imu_csv", "read_joint_csv", "write_imu_csv", "write_joint_csv"]

IMU_GROUPS = {
    "q_world_from_sensor": ("qw", "qx", "qy", "qz"),
    "acc_m_s2": ("acc_x", "acc_y", "acc_z"),
    "gyr_rad_s": ("gyr_x", "gyr_y", "gyr_z"),
    "mag": ("mag_x", "mag_y", "mag_z"),
}
_ACC_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "g": G}
_GYR_UNITS = {"rad/s": 1.0, "deg/s": DEG2RAD, "dps": DEG2RAD}
_POS_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


def _is_imu_table(tab: Table) -> bool:
    cols = set(tab.columns)
    return any(set(g) <= cols for g in IMU_GROUPS.values()) or any(
        c in cols for c in ("qw", "acc_x", "gyr_x")
    )


def read_generic_csv(path, **options) -> Recording:
    """Read a kinefuse generic CSV, IMU or joint layout, chosen from the header."""
    tab = read_table(path)
    first = tab.comments[0].lower() if tab.comments else ""
    if first.startswith("kinefuse-imu-csv") or (
        not first.startswith("kinefuse-joint-csv") and _is_imu_table(tab)
    ):
        return read_imu_csv(path, **options)
    return read_joint_csv(path, **options)


def read_imu_csv(
    path,
    *,
    acc_unit: str | None = None,
    gyr_unit: str | None = None,
    sensor_map: Mapping[str, str] | None = None,
) -> Recording:
    """Read the generic IMU CSV.

    Parameters
    ----------
    path : str or Path
    acc_unit : {"m/s^2", "g"} or None
        Unit of ``acc_*``; default from the ``# acc_unit:`` header line, else m/s².
    gyr_unit : {"rad/s", "deg/s"} or None
        Unit of ``gyr_*``; default from ``# gyr_unit:``, else rad/s.
    sensor_map : mapping or None
        Sensor name -> key overrides (keys default to canonical segments where recognised).

    Returns
    -------
    Recording
        ``imu[key]`` per sensor, SI units; quaternions wxyz in the ``# frame:`` (default ENU).

    Raises
    ------
    FormatError
        Missing time column, incomplete column group, non-numeric field, non-monotonic time
        within a sensor, a sensor with neither orientation nor acc+gyr.
    """
    path = Path(path)
    tab = read_table(path, fast=True)  # large recordings: NumPy's parser (same numbers)
    hdr = tab.comment_dict()
    acc_unit, gyr_unit = _imu_units(path, hdr, acc_unit, gyr_unit)
    times = time_column_s(tab)
    groups = _imu_groups(tab)
    sensors = tab.strings("sensor") if tab.has("sensor") else ["imu"] * len(tab)
    order = list(dict.fromkeys(sensors))
    mapping, notes = map_segments(order, sensor_map)
    imu = _imu_streams(
        tab, times, groups, np.asarray(sensors), order, mapping, (acc_unit, gyr_unit), hdr
    )
    units = []
    if acc_unit == "g" and any(g == "acc_m_s2" for g in groups):
        units.append("acc g -> m/s^2")
    if gyr_unit in ("deg/s", "dps") and "gyr_rad_s" in groups:
        units.append("gyr deg/s -> rad/s")
    md = make_metadata(
        path,
        "imu_csv",
        subject=hdr.get("subject"),
        units_converted=units,
        segment_map=mapping,
        header=hdr,
        notes=notes,
    )
    return finish_recording(path, md, imu=imu)


def _imu_units(path: Path, hdr: dict, acc_unit, gyr_unit) -> tuple[str, str]:
    """The acc and gyr units: given, else the header's, else SI; checked."""
    acc_unit = acc_unit or hdr.get("acc_unit", "m/s^2")
    gyr_unit = gyr_unit or hdr.get("gyr_unit", "rad/s")
    if acc_unit not in _ACC_UNITS:
        raise FormatError(
            path,
            f"expected acc_unit one of {sorted(_ACC_UNITS)}, found {acc_unit!r}",
            field="acc_unit",
        )
    if gyr_unit not in _GYR_UNITS:
        raise FormatError(
            path,
            f"expected gyr_unit one of {sorted(_GYR_UNITS)}, found {gyr_unit!r}",
            field="gyr_unit",
        )
    return acc_unit, gyr_unit


def _imu_groups(tab: Table) -> dict[str, np.ndarray]:
    """ImuStream field -> (n, k) values of the :data:`IMU_GROUPS` present (each all-or-nothing)."""
    groups = {}
    for name, cols in IMU_GROUPS.items():
        present = [c for c in cols if tab.has(c)]
        if present and len(present) != len(cols):
            miss = next(c for c in cols if not tab.has(c))
            raise tab.header_error(
                f"missing column {miss!r} (the group {cols} is all-or-nothing)", miss
            )
        if present:
            groups[name] = np.stack([tab.floats(c) for c in cols], axis=1)
    if not groups:
        raise tab.header_error(
            f"expected IMU columns (qw..qz and/or acc_x.. gyr_x..), found {tab.columns}"
        )
    return groups


def _imu_streams(
    tab: Table, times, groups, sensors, order, mapping, units, hdr
) -> dict[str, ImuStream]:
    """One ImuStream per sensor (rows of that sensor; time checked per sensor), SI units."""
    acc_unit, gyr_unit = units
    frame = hdr.get("frame", "ENU")
    t_all, tcol = times
    imu = {}
    for s in order:
        m = sensors == s
        t = check_time(tab.path, t_all[m], tab.lines[m], tcol)
        kw = {k: v[m] for k, v in groups.items() if np.any(np.isfinite(v[m]))}
        if "acc_m_s2" in kw:
            kw["acc_m_s2"] = kw["acc_m_s2"] * _ACC_UNITS[acc_unit]
        if "gyr_rad_s" in kw:
            kw["gyr_rad_s"] = kw["gyr_rad_s"] * _GYR_UNITS[gyr_unit]
        try:
            imu[mapping[s]] = ImuStream(t_s=t, name=s, frame=frame, **kw)
        except InputError as e:
            raise FormatError(tab.path, f"sensor {s!r}: {e}") from None
    return imu


def _joint_columns(tab: Table, declared: list[str] | None) -> list[str]:
    cols = set(tab.columns)
    if declared:
        for j in declared:
            for a in "xyz":
                if f"{j}_{a}" not in cols:
                    raise FormatError(
                        tab.path,
                        f"missing column '{j}_{a}' for declared joint {j!r}",
                        line=tab.header_line,
                        field=f"{j}_{a}",
                    )
        return declared
    cands = []
    for c in tab.columns:
        if c.endswith("_x"):
            j = c[:-2]
            if f"{j}_y" in cols and f"{j}_z" in cols:
                cands.append(j)
            else:
                miss = f"{j}_y" if f"{j}_y" not in cols else f"{j}_z"
                raise FormatError(
                    tab.path,
                    f"missing column {miss!r} (found {c!r})",
                    line=tab.header_line,
                    field=miss,
                )
    # '<joint>_<name>_x' are extras of '<joint>'
    return [j for j in cands if not any(j.startswith(k + "_") for k in cands if k != j)]


def read_joint_csv(
    path,
    *,
    role: str | None = None,
    units: str | None = None,
    map_names: bool = False,
    rate_hz: float | None = None,
) -> Recording:
    """Read the generic joint-position CSV (also the fused output written by :func:`write_joint_csv`).

    Parameters
    ----------
    path : str or Path
    role : {"vision", "reference"} or None
        Where the joints go; default from ``# role:``, else ``"vision"``.
    units : {"m", "mm", "cm"} or None
        Position unit; default from ``# units:``, else m.
    map_names : bool
        Map joint names to canonical names where recognised (``metadata["joint_map"]``).
    rate_hz : float or None
        Frame rate when the file has a ``frame`` column instead of times.

    Returns
    -------
    Recording
        ``vision`` (or ``reference``): positions (T, J, 3) in m, frame from ``# frame:``
        (default ENU); ``available`` from ``<joint>_available`` columns (1/0) where present,
        always also requiring finite coordinates. ``metadata["extra_columns"]``: name -> array
        of shape (T,), (T, J) or (T, J, 3) (float, or str where not numeric).

    Raises
    ------
    FormatError
        Missing time column, a coordinate column without its partners, a declared joint without
        columns, non-numeric coordinates, non-monotonic time.
    """
    path = Path(path)
    tab = read_table(path, fast=True)  # large recordings: NumPy's parser (same numbers)
    hdr = tab.comment_dict()
    role, units = _joint_options(path, hdr, role, units)
    t, tcol = table_time(tab, rate_hz=rate_hz)
    declared = (
        [j.strip() for j in hdr["joints"].split(",") if j.strip()] if "joints" in hdr else None
    )
    joints = _joint_columns(tab, declared)
    if not joints:
        raise tab.header_error(
            f"expected joint columns '<joint>_x,<joint>_y,<joint>_z', found {tab.columns}"
        )
    pos, avail, used = _joint_values(tab, joints)
    used.add(tcol)
    pos *= _POS_UNITS[units]
    extras = _read_extras(tab, joints, used)
    names = tuple(joints)
    jmap = {j: j for j in joints}
    if map_names:
        names, jmap = map_joints(joints)
    js = JointStream(
        t_s=t, position_m=pos, available=avail, joints=names, frame=hdr.get("frame", "ENU")
    )
    md = make_metadata(
        path,
        "joint_csv",
        subject=hdr.get("subject"),
        units_converted=[f"positions {units} -> m"] if units != "m" else [],
        joint_map=jmap,
        header=hdr,
        extra_columns=extras,
    )
    return finish_recording(path, md, **{role: js})


def _joint_options(path: Path, hdr: dict, role, units) -> tuple[str, str]:
    """Role and position unit: given, else the header's, else vision and m; checked."""
    role = role or hdr.get("role", "vision")
    if role not in ("vision", "reference"):
        raise FormatError(
            path, f"expected role 'vision' or 'reference', found {role!r}", field="role"
        )
    units = units or hdr.get("units", "m")
    if units not in _POS_UNITS:
        raise FormatError(
            path, f"expected units one of {sorted(_POS_UNITS)}, found {units!r}", field="units"
        )
    return role, units


def _joint_values(tab: Table, joints: list[str]):
    """Positions (n, J, 3) in the file's unit, availability (n, J) and the columns read."""
    used = set()
    pos = np.empty((len(tab), len(joints), 3))
    avail = np.ones((len(tab), len(joints)), dtype=bool)
    for j, name in enumerate(joints):
        for a, ax in enumerate("xyz"):
            pos[:, j, a] = tab.floats(f"{name}_{ax}")
            used.add(f"{name}_{ax}")
        ac = f"{name}_available"
        if tab.has(ac):
            v = tab.floats(ac)
            bad = ~np.isin(v, (0.0, 1.0))
            if np.any(bad):
                k = int(np.flatnonzero(bad)[0])
                raise tab.error_at(k, f"expected 0 or 1, found {v[k]!r}", ac)
            avail[:, j] = v == 1.0
            used.add(ac)
    return pos, avail, used


def _column_values(tab: Table, c: str) -> np.ndarray:
    try:
        return tab.floats(c)
    except FormatError:
        return np.asarray(tab.strings(c))


def _read_extras(tab: Table, joints: list[str], used: set[str]) -> dict[str, np.ndarray]:
    rest = [c for c in tab.columns if c not in used]
    per_joint: dict[str, dict[str, str]] = {}
    extras: dict[str, np.ndarray] = {}
    for c in rest:
        owner = next(
            (j for j in sorted(joints, key=len, reverse=True) if c.startswith(j + "_")), None
        )
        if owner is None:
            extras[c] = _column_values(tab, c)
        else:
            per_joint.setdefault(c[len(owner) + 1 :], {})[owner] = c
    # group '<name>_x/_y/_z' into (T, J, 3)
    vec_names = {n[:-2] for n in per_joint if n[-2:] in ("_x", "_y", "_z")}
    for base in sorted(vec_names):
        parts = [per_joint.get(f"{base}_{a}", {}) for a in "xyz"]
        if all(set(p) == set(joints) for p in parts):
            extras[base] = np.stack(
                [np.stack([tab.floats(p[j]) for j in joints], axis=1) for p in parts], axis=2
            )
            for a in "xyz":
                per_joint.pop(f"{base}_{a}")
    for name, by_joint in per_joint.items():
        if set(by_joint) == set(joints):
            cols = [_column_values(tab, by_joint[j]) for j in joints]
            extras[name] = np.stack(cols, axis=1)
        else:
            for c in by_joint.values():
                extras[c] = _column_values(tab, c)
    return extras


# ------------------------------------------------------------------------------------------------
# writers
# ------------------------------------------------------------------------------------------------
def _cell(v, decimals: int) -> str:
    if isinstance(v, (float, np.floating)):
        return fmt_float(float(v), decimals)
    if isinstance(v, (bool, np.bool_)):
        return "1" if v else "0"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    s = str(v)
    if "," in s or "\n" in s:
        raise InputError(f"cannot write {s!r} to CSV (contains a comma or newline)")
    return s


def _check_name(name: str, what: str) -> None:
    if not name or any(ch in name for ch in ",\n\r#") or name != name.strip():
        raise InputError(
            f"{what} {name!r} cannot be a CSV column name (empty, spaces at the ends, ',' or '#')"
        )


def write_joint_csv(
    path,
    stream: JointStream,
    extra_columns: Mapping[str, np.ndarray] | None = None,
    *,
    force: bool = False,
    role: str = "vision",
    units: str = "m",
    decimals: int | None = None,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write joint positions (e.g. the fused output) as the generic joint CSV.

    Parameters
    ----------
    path : str or Path
        Destination; never overwritten unless ``force``.
    stream : JointStream
        Positions (T, J, 3) in m; all positions are written (also unavailable ones, flagged by
        ``<joint>_available``), NaN as empty fields.
    extra_columns : mapping of str -> array_like, optional
        Per-sample extras, e.g. ``{"source": (T, J) int, "mode": (T, J) int,
        "std_m": (T, J, 3) float, "innovation_norm": (T,)}``. Shape (T,) -> column ``<name>``;
        (T, J) -> ``<joint>_<name>``; (T, J, 3) -> ``<joint>_<name>_x/_y/_z``.
    force : bool
        Replace an existing file.
    role : {"vision", "reference"}
        Written to the header; :func:`read_joint_csv` puts the joints there.
    units : {"m", "mm", "cm"}
        Unit of the written coordinates (header ``# units:``).
    decimals : int or None
        Digits after the decimal point for floats; default 6 for m (µm), 3 for mm, 4 for cm.
    metadata : mapping of str -> str, optional
        Extra ``# key: value`` header lines (e.g. subject, pipeline settings).

    Returns
    -------
    Path

    Raises
    ------
    FileExistsError
        ``path`` exists and ``force`` is False.
    InputError
        Wrong extra-column shape, names unusable as CSV columns.
    """
    if not isinstance(stream, JointStream):
        raise InputError(f"expected a JointStream, got {type(stream).__name__}")
    if role not in ("vision", "reference"):
        raise InputError(f"expected role 'vision' or 'reference', got {role!r}")
    if units not in _POS_UNITS:
        raise InputError(f"expected units one of {sorted(_POS_UNITS)}, got {units!r}")
    if decimals is None:
        decimals = {"m": 6, "mm": 3, "cm": 4}[units]
    T = len(stream)
    for j in stream.joints:
        _check_name(j, "joint name")
    header, cols = _position_columns(stream, units)
    for name, val in (extra_columns or {}).items():
        _extra_columns(name, np.asarray(val), stream, header, cols)
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise InputError(f"duplicate column {dup!r}; rename the extra column")
    lines = [
        "# kinefuse-joint-csv 1",
        f"# units: {units}",
        f"# frame: {stream.frame}",
        f"# role: {role}",
        f"# joints: {','.join(stream.joints)}",
    ]
    for k, v in (metadata or {}).items():
        lines.append(f"# {k}: {v}".replace("\n", " "))
    lines.append(",".join(header))
    times = [repr(float(t)) for t in stream.t_s]
    try:
        values = fixed_point_rows(cols[1:], decimals)
    except TypeError:  # an extra column of text: value by value
        values = [",".join(_cell(c[i], decimals) for c in cols[1:]) for i in range(T)]
    lines += [f"{t},{v}" if cols[1:] else t for t, v in zip(times, values or [""] * T, strict=True)]
    return write_text_safely(path, "\n".join(lines) + "\n", force=force)


def _position_columns(stream: JointStream, units: str) -> tuple[list[str], list[np.ndarray]]:
    """Header names and values of ``t_s`` and every joint's ``_x/_y/_z`` and ``_available``."""
    header = ["t_s"]
    cols: list[np.ndarray] = [stream.t_s.astype(object)]
    p = stream.position_m / _POS_UNITS[units]
    for j, name in enumerate(stream.joints):
        for a, ax in enumerate("xyz"):
            header.append(f"{name}_{ax}")
            cols.append(p[:, j, a])
        header.append(f"{name}_available")
        cols.append(stream.available[:, j])
    return header, cols


def _extra_columns(name: str, v: np.ndarray, stream: JointStream, header: list, cols: list) -> None:
    """Append the columns of one extra: (T,) -> ``name``, (T, J) -> ``<joint>_name``, (T, J, 3)."""
    T, J = len(stream), len(stream.joints)
    _check_name(name, "extra column")
    if name.endswith(("_x", "_y", "_z")) or name in ("available", "t_s"):
        raise InputError(
            f"extra column {name!r}: names ending in _x/_y/_z, 'available' and 't_s' are reserved"
        )
    if v.shape == (T,):
        header.append(name)
        cols.append(v)
    elif v.shape == (T, J):
        for j, jn in enumerate(stream.joints):
            header.append(f"{jn}_{name}")
            cols.append(v[:, j])
    elif v.shape == (T, J, 3):
        for j, jn in enumerate(stream.joints):
            for a, ax in enumerate("xyz"):
                header.append(f"{jn}_{name}_{ax}")
                cols.append(v[:, j, a])
    else:
        raise InputError(
            f"extra column {name!r}: expected shape ({T},), ({T}, {J}) or ({T}, {J}, 3), got {v.shape}"
        )


def write_imu_csv(
    path, imu: Mapping[str, ImuStream] | Recording, *, force: bool = False, decimals: int = 9
) -> Path:
    """Write IMU streams as the generic IMU CSV (SI units, one row per sensor sample).

    Parameters
    ----------
    path : str or Path
        Destination; never overwritten unless ``force``.
    imu : Recording or mapping of str -> ImuStream
        Streams keyed by segment; the key is written in the ``sensor`` column.
    force : bool
        Replace an existing file.
    decimals : int
        Significant digits of the values.

    Returns
    -------
    Path
    """
    streams = imu.imu if isinstance(imu, Recording) else dict(imu)
    if not streams:
        raise InputError("expected at least one IMU stream, got none")
    frames = {s.frame for s in streams.values()}
    if len(frames) > 1:
        raise InputError(f"expected all IMU streams in one world frame, got {sorted(frames)}")
    groups = [g for g in IMU_GROUPS if any(getattr(s, g) is not None for s in streams.values())]
    header = ["t_s", "sensor"] + [c for g in groups for c in IMU_GROUPS[g]]
    lines = [
        "# kinefuse-imu-csv 1",
        "# acc_unit: m/s^2",
        "# gyr_unit: rad/s",
        f"# frame: {frames.pop()}",
        ",".join(header),
    ]
    for key, s in streams.items():
        _check_name(key, "sensor key")
        for i in range(len(s)):
            row = [repr(float(s.t_s[i])), key]
            for g in groups:
                a = getattr(s, g)
                row += [""] * len(IMU_GROUPS[g]) if a is None else [_g(v, decimals) for v in a[i]]
            lines.append(",".join(row))
    return write_text_safely(path, "\n".join(lines) + "\n", force=force)


def _g(v: float, digits: int) -> str:
    return "" if not np.isfinite(v) else f"{v:.{digits}g}"
