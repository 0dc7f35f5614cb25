"""x-IMU3 (x-io Technologies) logged CSV files: one folder per sensor.

Each sensor folder holds ``Inertial.csv`` (``Timestamp (us), Gyroscope X/Y/Z (deg/s),
Accelerometer X/Y/Z (g)``), optionally ``Quaternion.csv`` (``Timestamp (us), W, X, Y, Z``, the
on-board AHRS) and ``Magnetometer.csv`` (``Timestamp (us), X/Y/Z (a.u.)``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io._checks import DEG2RAD, G, finish_recording, make_metadata
from kinefuse.io._names import map_segments
from kinefuse.io._text import Table, check_time, read_table, unit_triplet
from kinefuse.io.align import resample_orientation, resample_positions
from kinefuse.io.recording import ImuStream, Recording
from kinefuse.io.xio_csv import read_xio_csv

__all__ = ["EARTH_TO_ENU", "read_ximu3"]

#: Rotation taking vectors from an AHRS earth frame to ENU (``q_ENU_from_earth``), wxyz.
EARTH_TO_ENU = {
    "ENU": np.array([1.0, 0.0, 0.0, 0.0]),
    # NWU -> ENU: north (x) -> +y, west (y) -> -x, up -> up: +90 deg about z
    "NWU": Rotation.from_euler("z", 90, degrees=True).as_quat(scalar_first=True),
    # NED -> ENU: north -> +y, east -> +x, down -> -z
    "NED": Rotation.from_matrix([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).as_quat(
        scalar_first=True
    ),
}

_UNIT = re.compile(r"\(([^)]*)\)\s*$")


def _header_line(path: Path) -> str:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            return fh.readline().strip()
    except OSError as e:
        raise FormatError(path, f"could not read the file: {e}") from None


def _sensor_dirs(path: Path) -> list[Path]:
    if path.is_file():
        if not (path.parent / "Inertial.csv").is_file():
            raise FormatError(
                path.parent,
                f"expected an x-IMU3 sensor folder with Inertial.csv beside {path.name}, found none",
            )
        return [path.parent]
    if (path / "Inertial.csv").is_file():
        return [path]
    dirs = sorted(p for p in path.iterdir() if p.is_dir() and (p / "Inertial.csv").is_file())
    if not dirs:
        raise FormatError(
            path, "expected sensor folders containing Inertial.csv (x-IMU3 log), found none"
        )
    return dirs


def _sensor_name(folder: Path) -> str:
    return re.sub(r"\s*\(UDP\)\s*$", "", folder.name)


def _time(tab: Table) -> np.ndarray:
    col = next((c for c in tab.columns if c.lower().startswith("timestamp")), None)
    if col is None:
        raise FormatError(
            tab.path,
            f"missing column 'Timestamp (us)'; found {tab.columns}",
            line=tab.header_line,
            field="Timestamp (us)",
        )
    m = _UNIT.search(col)
    unit = m.group(1).strip().lower() if m else "us"
    factor = {"us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}.get(unit)
    if factor is None:
        raise FormatError(
            tab.path, f"expected timestamp unit us, ms or s, found {unit!r}", field=col
        )
    return check_time(tab.path, tab.floats(col, allow_empty=False), tab.lines, col) * factor


def read_ximu3(
    path,
    *,
    sensor_map: Mapping[str, str] | None = None,
    earth_frame: str = "NWU",
    include_mag: bool = True,
) -> Recording:
    """Read an x-IMU3 log: a folder of sensor folders, one sensor folder, or a file inside one.

    Parameters
    ----------
    path : str or Path
        Log folder (e.g. ``xio_imu_mocap_lower_body/``), a sensor folder
        (``Right_Upper_Leg_64F61C2E/``), a CSV file inside a sensor folder, or one inertial CSV
        under another name (read alone). x-io's plain CSV export (``Time (s), Gyroscope X
        (deg/s) ...``) is handed to its own reader when this installation has one, else a
        FormatError says what the file is.
    sensor_map : mapping or None
        Folder name -> key overrides. Default: folder names mapped to canonical segments
        (``Right_Upper_Leg_64F61C2E`` -> ``thigh_r``, ``pelvis_64F0EDBF`` -> ``pelvis``); others
        keep their folder name.
    earth_frame : {"NWU", "ENU", "NED"}
        Earth frame of the on-board AHRS quaternion; converted to ENU. x-IMU3 default is NWU
        (verified on the shared log: the magnetic field rotated to the earth frame points
        along +x with a downward component).
    include_mag : bool
        Read ``Magnetometer.csv`` (its own, slower timestamps) linearly resampled to the inertial
        timestamps; NaN where the two magnetometer samples around a time are more than
        1.5 median magnetometer intervals apart.

    Returns
    -------
    Recording
        ``imu[key]``: ``gyr_rad_s`` (N, 3) rad/s (file deg/s), ``acc_m_s2`` (N, 3) m/s²
        (file g), ``q_world_from_sensor`` (N, 4) wxyz sensor -> ENU, ``mag`` (N, 3) a.u.
        Times are the device timestamps in s relative to the earliest first inertial sample of
        all sensors (``metadata["t0_us"]``).

    Raises
    ------
    FormatError
        Missing files/columns, unknown units, truncated lines, non-monotonic timestamps.
    """
    path = Path(path)
    if earth_frame not in EARTH_TO_ENU:
        raise InputError(f"expected earth_frame one of {sorted(EARTH_TO_ENU)}, got {earth_frame!r}")
    if not path.exists():
        raise FormatError(
            path, "expected an x-IMU3 log folder, sensor folder or CSV file, found nothing"
        )
    single = None
    if path.is_file() and not (path.parent / "Inertial.csv").is_file():
        if _is_plain_csv(path):
            rec = read_xio_csv(path, **({"sensor_map": sensor_map} if sensor_map else {}))
            rec.metadata.setdefault("notes", []).append(
                "format='ximu3' given for x-io's plain CSV: read with the 'xio_csv' reader"
            )
            return rec
        single = path  # an Inertial.csv under another name
    dirs = [path.parent] if single is not None else _sensor_dirs(path)
    names = [single.stem] if single is not None else [_sensor_name(d) for d in dirs]
    mapping, notes = map_segments(names, sensor_map)
    raw = {
        name: _read_sensor(d, name, single, earth_frame, include_mag, notes)
        for d, name in zip(dirs, names, strict=True)
    }
    imu, units, t0 = _streams(raw, mapping, earth_frame)
    md = make_metadata(
        path,
        "ximu3",
        subject=None,
        units_converted=sorted(units),
        segment_map=mapping,
        t0_us=t0 * 1e6,
        notes=notes,
    )
    return finish_recording(path, md, imu=imu)


def _streams(raw: dict, mapping: dict, earth_frame: str):
    """(ImuStream per key, times from the earliest first sample of all sensors; conversions, t0)."""
    t0 = min(v[0][0] for v in raw.values())
    imu = {}
    units = set()
    for name, (t, gyr, acc, q, mag, (gu, au)) in raw.items():
        imu[mapping[name]] = ImuStream(
            t_s=t - t0, q_world_from_sensor=q, acc_m_s2=acc, gyr_rad_s=gyr, mag=mag, name=name
        )
        if gu != "rad/s":
            units.add("gyr deg/s -> rad/s")
        if au == "g":
            units.add("acc g -> m/s^2")
        if q is not None and earth_frame != "ENU":
            units.add(f"quaternion earth frame {earth_frame} -> ENU")
    return imu, units, t0


def _is_plain_csv(path: Path) -> bool:
    """True for x-io's plain CSV export, False for an Inertial.csv under another name."""
    head = _header_line(path).lower()
    if head.startswith("timestamp (") and "gyroscope" in head and "accelerometer" in head:
        return False
    if head.startswith("time (s)") and "gyroscope" in head:
        return True
    raise FormatError(
        path,
        "expected an x-IMU3 Inertial.csv ('Timestamp (us), Gyroscope X (deg/s), ..., "
        f"Accelerometer X (g), ...') or a sensor folder, found header {head[:80]!r}",
        line=1,
    )


def _read_sensor(d: Path, name: str, single, earth_frame: str, include_mag: bool, notes):
    """(t, gyr rad/s, acc m/s², q ENU or None, mag or None, (gyr unit, acc unit)) of one sensor."""
    tab = read_table(single if single is not None else d / "Inertial.csv", delimiter=",")
    t = _time(tab)
    gyr, gu = unit_triplet(tab, "Gyroscope")
    acc, au = unit_triplet(tab, "Accelerometer")
    gf = {"deg/s": DEG2RAD, "dps": DEG2RAD, "rad/s": 1.0}.get(gu)
    af = {"g": G, "m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0}.get(au)
    if gf is None:
        raise tab.header_error(f"expected gyroscope unit deg/s or rad/s, found {gu!r}")
    if af is None:
        raise tab.header_error(f"expected accelerometer unit g or m/s^2, found {au!r}")
    q = None
    qf = d / "Quaternion.csv"
    if single is None and qf.is_file():
        qt = read_table(qf, delimiter=",")
        tq = _time(qt)
        qq = np.stack([qt.floats(c) for c in ("W", "X", "Y", "Z")], axis=1)
        if tq.shape == t.shape and np.array_equal(tq, t):
            q = qq
        else:
            q = resample_orientation(tq, qq, t)
            notes.append(
                f"{name}: Quaternion.csv timestamps differ from Inertial.csv; SLERP-resampled"
            )
        q = _to_enu(q, earth_frame)
    mag = None
    mf = d / "Magnetometer.csv"
    if single is None and include_mag and mf.is_file():
        mt = read_table(mf, delimiter=",")
        tm = _time(mt)
        mv = np.stack([mt.floats(c) for c in _mag_cols(mt)], axis=1)
        mag, _ = resample_positions(tm, mv, t)
    return t, gyr * gf, acc * af, q, mag, (gu, au)


def _mag_cols(tab: Table) -> list[str]:
    out = []
    for ax in "XYZ":
        hit = [c for c in tab.columns if c == ax or c.startswith(f"{ax} ")]
        if not hit:
            raise tab.header_error(f"missing column '{ax} (a.u.)'; found {tab.columns}", ax)
        out.append(hit[0])
    return out


def _to_enu(q: np.ndarray, earth_frame: str) -> np.ndarray:
    out = np.full_like(q, np.nan)
    ok = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0)
    if np.any(ok):
        r = Rotation.from_quat(EARTH_TO_ENU[earth_frame], scalar_first=True) * Rotation.from_quat(
            q[ok], scalar_first=True
        )
        out[ok] = r.as_quat(scalar_first=True)
    return out
