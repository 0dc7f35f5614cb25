"""Movella / Xsens DOT CSV exports (Xsens DOT app, Movella DOT app, DOT SDK): one file per sensor.

A file is a ``key:,value`` preamble (``sep=,``, ``DeviceTag:,zdt``, ``OutputRate:,60Hz``,
``SyncStatus:,Synced``, ``Measurement Mode:,...``), then a comma-separated header and rows::

    PacketCounter,SampleTimeFine,Quat_W,Quat_X,Quat_Y,Quat_Z,FreeAcc_X,FreeAcc_Y,FreeAcc_Z,Status

Columns depend on the measurement mode: ``Quat_W..Z`` or ``Euler_X..Z`` (deg, roll/pitch/yaw,
ZYX), ``FreeAcc_X..Z`` (m/s², local earth frame, gravity removed), ``Acc_X..Z`` (m/s², sensor
frame), ``Gyr_X..Z`` (**deg/s**), ``Mag_X..Z`` (a.u.). Units and frames are those of the Xsens
DOT user manual (XD0502P, §4.2): the orientation maps the sensor frame to the local earth frame
ENU; ``SampleTimeFine`` is a 1 MHz device clock (µs) that wraps at 2³².
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError, FormatWarning
from kinefuse.io._checks import DEG2RAD, G, finish_recording, make_metadata
from kinefuse.io._names import map_segments
from kinefuse.io._text import Table, check_time, read_text
from kinefuse.io.recording import ImuStream, Recording

__all__ = ["is_xsens_dot_csv", "read_xsens_dot", "specific_force_from_free_acc"]

_STF_WRAP = 2**32
_RATE = re.compile(r"([0-9.]+)\s*hz", re.IGNORECASE)


def specific_force_from_free_acc(q_world_from_sensor, free_acc_world_m_s2, g: float = G):
    """Specific force in the sensor frame from Xsens free acceleration: ``R(q)ᵀ (a_free + g e_z)``.

    Parameters
    ----------
    q_world_from_sensor : ndarray, shape (..., 4)
        wxyz, sensor -> z-up world.
    free_acc_world_m_s2 : ndarray, shape (..., 3)
        Acceleration in the world frame with gravity removed (Xsens "free acceleration"), m/s².
    g : float
        Gravity removed by the device, m/s² (Xsens does not state its value; 9.80665 is used, so
        the result may be off by ~0.01 m/s² along the vertical).

    Returns
    -------
    ndarray, shape (..., 3)
        What an accelerometer in the sensor frame reads (gravity included), m/s²; NaN where
        either input is.
    """
    q = np.asarray(q_world_from_sensor, dtype=float)
    a = np.asarray(free_acc_world_m_s2, dtype=float) + np.array([0.0, 0.0, g])
    out = np.full(a.shape, np.nan)
    ok = np.all(np.isfinite(q), axis=-1) & np.all(np.isfinite(a), axis=-1)
    if np.any(ok):
        out[ok] = Rotation.from_quat(q[ok], scalar_first=True).inv().apply(a[ok])
    return out


def is_xsens_dot_csv(path) -> bool:
    """True when the first 4 kB look like a DOT export (``PacketCounter`` and ``SampleTimeFine``
    in a comma-separated header)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return any(
        ln.startswith("PacketCounter,") and "SampleTimeFine" in ln for ln in head.splitlines()
    )


def _parse(path: Path) -> tuple[Table, dict[str, str]]:
    lines = read_text(path).splitlines()
    k = next(
        (i for i, ln in enumerate(lines) if ln.startswith("PacketCounter") and "," in ln), None
    )
    if k is None:
        raise FormatError(
            path,
            "expected a Movella/Xsens DOT CSV header 'PacketCounter,SampleTimeFine,...', found none",
        )
    info = {}
    for ln in lines[:k]:
        if ":" in ln and "," in ln:
            key, val = ln.split(",", 1)
            info[key.strip().rstrip(":").strip()] = val.strip()
    columns = [c.strip() for c in lines[k].split(",")]
    while columns and not columns[-1]:
        columns.pop()
    rows, nums = [], []
    for j in range(k + 1, len(lines)):
        if not lines[j].strip():
            continue
        f = lines[j].split(",")
        if len(f) > len(columns) and not any(x.strip() for x in f[len(columns) :]):
            f = f[: len(columns)]
        if len(f) != len(columns):
            what = "truncated line?" if len(f) < len(columns) else "extra fields"
            raise FormatError(
                path,
                f"expected {len(columns)} fields as in the header, found {len(f)} ({what})",
                line=j + 1,
            )
        rows.append(f)
        nums.append(j + 1)
    if not rows:
        raise FormatError(path, "expected data rows after the header, found none", line=k + 1)
    return Table(path, columns, rows, np.asarray(nums), [], k + 1), info


def _group(tab: Table, prefix: str, axes: str) -> np.ndarray | None:
    return tab.column_group([f"{prefix}_{a}" for a in axes])


def _read_one(path: Path) -> dict:
    tab, info = _parse(path)
    stf = tab.floats("SampleTimeFine", allow_empty=False)
    wraps = np.concatenate([[0], np.cumsum(np.diff(stf) < -_STF_WRAP / 2)])
    stf = stf + _STF_WRAP * wraps
    check_time(path, stf, tab.lines, "SampleTimeFine")
    counter = tab.floats("PacketCounter", allow_empty=False)
    counter = counter + _STF_WRAP * np.concatenate(
        [[0], np.cumsum(np.diff(counter) < -_STF_WRAP / 2)]
    )
    q = _group(tab, "Quat", "WXYZ")
    if q is None:
        euler = _group(tab, "Euler", "XYZ")
        if euler is not None:
            q = np.full((len(tab), 4), np.nan)
            ok = np.all(np.isfinite(euler), axis=1)
            # Xsens Euler angles: roll (x), pitch (y), yaw (z), R = Rz(yaw) Ry(pitch) Rx(roll)
            q[ok] = Rotation.from_euler("xyz", euler[ok], degrees=True).as_quat(scalar_first=True)
    gyr = _group(tab, "Gyr", "XYZ")
    out = {
        "stf_us": stf,
        "counter": counter,
        "q": q,
        "free_acc": _group(tab, "FreeAcc", "XYZ"),
        "acc": _group(tab, "Acc", "XYZ"),
        "gyr": None if gyr is None else gyr * DEG2RAD,
        "mag": _group(tab, "Mag", "XYZ"),
        "info": info,
        "euler": q is not None and not tab.has("Quat_W"),
        "dq": _group(tab, "dq", "WXYZ"),
        "dv": _group(tab, "dv", "XYZ"),
    }
    has_acc = out["acc"] is not None or out["dv"] is not None
    has_gyr = out["gyr"] is not None or out["dq"] is not None
    if out["q"] is None and not (has_acc and has_gyr):
        raise FormatError(
            path,
            "expected an orientation (Quat_W..Z or Euler_X..Z) or both Acc_X..Z (or dv_X..Z) and "
            f"Gyr_X..Z (or dq_W..Z), found columns {tab.columns}",
            line=tab.header_line,
        )
    return out


def _sensor_name(path: Path, info: Mapping[str, str]) -> str:
    """``LFemur_20210820_202113_831.csv`` -> ``LFemur`` (the part before the date)."""
    m = re.match(r"(.+?)_\d{8}_\d{6}", path.stem)
    return m.group(1) if m else (info.get("DeviceTag") or path.stem)


def read_xsens_dot(
    path,
    *,
    sensor_map: Mapping[str, str] | None = None,
    derive_acc: bool = False,
    rate_tolerance: float = 0.02,
) -> Recording:
    """Read Movella/Xsens DOT CSV exports: one file, or a folder of them (one per sensor).

    Parameters
    ----------
    path : str or Path
        A DOT ``.csv`` file or a folder of them (the folder is one recording).
    sensor_map : mapping or None
        Sensor name (file name before the date, e.g. ``LFemur``, or the ``DeviceTag``) -> segment
        key. Default: the name mapped to a canonical segment where recognised (``LFemur`` ->
        ``thigh_l``, ``LTibia`` -> ``shank_l``, ``Pelvis`` -> ``pelvis``), else kept.
    derive_acc : bool
        Fill ``acc_m_s2`` from free acceleration and orientation
        (:func:`specific_force_from_free_acc`) when the file has no ``Acc_*``. Default False: free
        acceleration is not specific force, so it is kept apart
        (``metadata["free_acc_world_m_s2"]``).
    rate_tolerance : float
        Relative disagreement between the header's ``OutputRate`` and the rate of
        ``SampleTimeFine`` that triggers a warning.

    Returns
    -------
    Recording
        ``imu[key]``: ``q_world_from_sensor`` (wxyz, frame ENU, the DOT local earth frame),
        ``acc_m_s2`` (from ``Acc_*``), ``gyr_rad_s`` (``Gyr_*`` deg/s -> rad/s), ``mag`` (a.u.).
        Time ``t = (SampleTimeFine − s0) / 1e6`` s, unwrapped at 2³², with ``s0`` the earliest
        first ``SampleTimeFine`` of all sensors when every file says ``SyncStatus: Synced``
        (synchronised DOTs share one clock), else each sensor's own first sample.
        ``metadata``: ``rate_hz`` per sensor (the header's), ``dropped_packets`` per sensor
        (from ``PacketCounter`` gaps), ``free_acc_world_m_s2`` per sensor, ``device_info``.

    Raises
    ------
    FormatError
        No DOT header, missing or non-numeric columns, truncated lines, non-increasing time, a
        folder without DOT files.

    Warns
    -----
    FormatWarning
        ``OutputRate`` disagrees with ``SampleTimeFine`` by more than ``rate_tolerance``.
    """
    path = Path(path)
    parsed = _read_files(path)
    mapping, notes = map_segments(list(parsed), _overrides(parsed, sensor_map))
    synced, s0_common = _common_clock(parsed, notes)
    imu, rates, dropped, free, units = {}, {}, {}, {}, set()
    for name, (f, p) in parsed.items():
        key = mapping[name]
        t = (p["stf_us"] - (s0_common if synced else p["stf_us"][0])) / 1e6
        rates[key] = rate = _rate(f, p, t, rate_tolerance)
        dc = np.diff(p["counter"])
        dropped[key] = int(np.sum(dc[dc > 1] - 1))
        imu[key] = _stream(f, p, name, t, rate, derive_acc, units)
        if p["free_acc"] is not None:
            free[key] = p["free_acc"]
    md = make_metadata(
        path,
        "xsens_dot",
        units_converted=sorted(units),
        segment_map=mapping,
        files=[str(f) for f, _ in parsed.values()],
        rate_hz=rates,
        dropped_packets=dropped,
        free_acc_world_m_s2=free,
        device_info={mapping[n]: p["info"] for n, (_f, p) in parsed.items()},
        time_origin_us=int(s0_common) if synced else None,
        frame_notes=(
            "orientation: sensor -> DOT local earth frame ENU (heading from the magnetometer unless a "
            "heading reset was done); free acceleration in the same frame, gravity removed"
        ),
        notes=notes,
    )
    return finish_recording(path, md, imu=imu)


def _read_files(path: Path) -> dict[str, tuple[Path, dict]]:
    """Sensor name -> (file, :func:`_read_one` result) of one DOT file or a folder of them."""
    if path.is_dir():
        files = sorted(p for p in path.glob("*.csv") if is_xsens_dot_csv(p))
        if not files:
            raise FormatError(
                path,
                "expected Movella/Xsens DOT .csv exports (PacketCounter,SampleTimeFine,...), found none",
            )
    else:
        files = [path]
    parsed: dict[str, tuple[Path, dict]] = {}
    for f in files:
        p = _read_one(f)
        name = _sensor_name(f, p["info"])
        if name in parsed:
            name = f.stem
        parsed[name] = (f, p)
    return parsed


def _overrides(parsed: dict, sensor_map) -> dict[str, str]:
    """``sensor_map`` entries by sensor name or DeviceTag, keyed by sensor name."""
    overrides = {}
    for name, (_f, p) in parsed.items():
        tag = p["info"].get("DeviceTag")
        if sensor_map and (name in sensor_map or tag in sensor_map):
            overrides[name] = sensor_map.get(name) or sensor_map[tag]
    return overrides


def _common_clock(parsed: dict, notes: list[str]) -> tuple[bool, float]:
    """(all files synced, the earliest first SampleTimeFine, unwrapped across sensors)."""
    synced = all(p["info"].get("SyncStatus", "").lower() == "synced" for _, p in parsed.values())
    firsts = [p["stf_us"][0] for _, p in parsed.values()]
    if synced and max(firsts) - min(firsts) > _STF_WRAP / 2:
        # the shared clock wrapped between two sensors' first samples: unwrap the late starters
        for _, p in parsed.values():
            if p["stf_us"][0] < _STF_WRAP / 2:
                p["stf_us"] = p["stf_us"] + _STF_WRAP
    s0_common = min(p["stf_us"][0] for _, p in parsed.values())
    if not synced and len(parsed) > 1:
        notes.append(
            "not every file says SyncStatus: Synced; each sensor's time starts at its own first sample "
            "(their clocks are independent)"
        )
    return synced, s0_common


def _rate(f: Path, p: dict, t: np.ndarray, rate_tolerance: float) -> float | None:
    """The header's OutputRate (else the measured one); warns when they disagree."""
    m = _RATE.search(p["info"].get("OutputRate", ""))
    rate = float(m.group(1)) if m else None
    dc = np.diff(p["counter"])
    if t.size > 1 and np.any(dc > 0):
        # time per packet (dropped packets leave longer steps, not a slower rate)
        measured = 1.0 / float(np.median(np.diff(t)[dc > 0] / dc[dc > 0]))
        if rate is not None and abs(measured - rate) > rate_tolerance * rate:
            warnings.warn(
                f"{f}: header OutputRate {rate:g} Hz disagrees with SampleTimeFine "
                f"({measured:.4g} Hz per packet); times follow SampleTimeFine",
                FormatWarning,
                stacklevel=3,
            )
        rate = rate if rate is not None else measured
    return rate


def _stream(f: Path, p: dict, name: str, t, rate, derive_acc: bool, units: set) -> ImuStream:
    """One sensor's ImuStream (acc from deltas or, with ``derive_acc``, from free acceleration)."""
    acc, gyr = _raw_from_deltas(f, p, rate, units)
    if p["free_acc"] is not None and acc is None and derive_acc and p["q"] is not None:
        acc = specific_force_from_free_acc(p["q"], p["free_acc"])
        units.add("acc_m_s2 derived from FreeAcc: R(q)^T (FreeAcc + 9.80665 e_z)")
    if p["q"] is None and acc is None:
        raise FormatError(
            f, "expected an orientation or Acc_X..Z with Gyr_X..Z; found only free acceleration"
        )
    return ImuStream(
        t_s=t,
        q_world_from_sensor=p["q"],
        acc_m_s2=acc,
        gyr_rad_s=gyr,
        mag=p["mag"],
        name=name,
        frame="ENU",
    )


def _raw_from_deltas(f: Path, p: dict, rate, units: set) -> tuple:
    """(acc, gyr): the file's, else from the delta quantities dv/dq and the output rate."""
    acc, gyr = p["acc"], p["gyr"]
    if (acc is None and p["dv"] is not None) or (gyr is None and p["dq"] is not None):
        if rate is None:
            raise FormatError(f, "delta quantities (dq/dv) need the OutputRate header line")
        # DOT manual: calibrated acceleration = dv / dt, dt = 1 / output rate; dq likewise
        if acc is None and p["dv"] is not None:
            acc = p["dv"] * rate
            units.add("dv (m/s per sample) -> acc_m_s2 = dv * OutputRate")
        if gyr is None and p["dq"] is not None:
            dq = p["dq"]
            gyr = np.full((dq.shape[0], 3), np.nan)
            ok = np.all(np.isfinite(dq), axis=1)
            rv = Rotation.from_quat(dq[ok], scalar_first=True).as_rotvec()
            gyr[ok] = rv * rate
            units.add("dq (orientation increment) -> gyr_rad_s = rotvec(dq) * OutputRate")
    if p["gyr"] is not None:
        units.add("gyr deg/s -> rad/s")
    if p["euler"]:
        units.add("Euler roll/pitch/yaw deg (ZYX) -> quaternion wxyz")
    return acc, gyr
