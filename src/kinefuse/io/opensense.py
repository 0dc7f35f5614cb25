"""Xsens MT Manager text exports (as shipped with the OpenSim OpenSense example).

One tab-separated file per sensor, ``//`` header lines (``Update Rate: 100.0Hz``), then columns
``PacketCounter``, ``SampleTimeFine``, ..., ``Acc_X..Z`` (m/s²), optionally ``Gyr_X..Z`` (rad/s),
``Mag_X..Z`` (a.u.), and the orientation either as ``Mat[1][1] ... Mat[3][3]`` (matrix listed
column by column) or as ``Quat_q0..q3`` (wxyz).
"""

from __future__ import annotations

import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError, FormatWarning, InputError
from kinefuse.io._checks import finish_recording, make_metadata
from kinefuse.io._names import canonical_segment, map_segments
from kinefuse.io._text import Table, check_time, read_table
from kinefuse.io.recording import ImuStream, Recording
from kinefuse.io.xsens_dot import specific_force_from_free_acc

__all__ = ["OPENSENSE_EXAMPLE_SENSORS", "XSENS_FRAME", "read_opensense", "read_xsens_txt"]

#: Sensor id -> segment of the OpenSense example (from ``myIMUMappings.xml`` in opensim-core).
OPENSENSE_EXAMPLE_SENSORS = {
    "00B42268": "chest",  # torso
    "00B42279": "pelvis",
    "00B4227C": "thigh_r",  # femur_r
    "00B4227D": "shank_r",  # tibia_r
    "00B421EE": "thigh_l",
    "00B421ED": "shank_l",
    "00B421EF": "foot_r",  # calcn_r
    "00B421E6": "foot_l",
}
#: World frame label of Xsens orientations: z up (verified: R @ acc = +g z at rest); the
#: horizontal axes follow the MT Manager setting (ENU by default in MT Manager 4.x, NWU in older
#: versions) and cannot be verified without a magnetometer column.
XSENS_FRAME = "xsens_global_z_up"

_MAT_COLS = [f"Mat[{r}][{c}]" for c in (1, 2, 3) for r in (1, 2, 3)]
_RATE = re.compile(r"update\s*rate\s*:\s*([0-9.]+)\s*hz", re.IGNORECASE)
_COUNTER_WRAP = 65536


def _is_xsens(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return "PacketCounter" in head and ("Mat[1][1]" in head or "Quat_q0" in head or "Acc_X" in head)


def _sensor_id(path: Path) -> str:
    return path.stem.split("_")[-1]


def read_xsens_txt(path, *, rate_hz: float | None = None) -> dict:
    """Parse one Xsens text export into arrays (no time origin, no mapping).

    Returns
    -------
    dict
        ``counter`` (N,) unwrapped packet counter, ``sample_time_s`` (N,) from
        ``SampleTimeFine`` (unwrapped at 2³², s, see :func:`_sample_time_fine`) or None when the
        column is absent or empty, ``sample_time_note`` (str or None: how its tick was chosen,
        and whether it disagrees with the Update Rate), ``rate_hz``, ``acc`` (N, 3) m/s² or None,
        ``gyr`` (N, 3) rad/s or None, ``mag`` (N, 3) or None, ``q`` (N, 4) wxyz sensor -> Xsens
        global, or None; ``lines`` (N,) file line numbers.
    """
    path = Path(path)
    tab: Table = read_table(path, delimiter="\t", comment_prefixes=("//",))
    rate = _update_rate(tab) if rate_hz is None else rate_hz
    counter = _unwrap(tab.floats("PacketCounter", allow_empty=False), _COUNTER_WRAP)
    check_time(path, counter, tab.lines, "PacketCounter")
    fine_s, fine_note = _sample_time_fine(tab, rate)

    acc = tab.column_group(["Acc_X", "Acc_Y", "Acc_Z"])
    gyr = tab.column_group(["Gyr_X", "Gyr_Y", "Gyr_Z"])
    mag = tab.column_group(["Mag_X", "Mag_Y", "Mag_Z"])
    q = _orientation(tab)
    if q is None and (acc is None or gyr is None):
        raise FormatError(
            path,
            "expected an orientation (Mat[i][j] or Quat_q0..3) or both Acc_X..Z and Gyr_X..Z columns, found neither",
            line=tab.header_line,
        )
    return {
        "counter": counter,
        "sample_time_s": fine_s,
        "sample_time_note": fine_note,
        "rate_hz": rate,
        "acc": acc,
        "gyr": gyr,
        "mag": mag,
        "q": q,
        "lines": tab.lines,
    }


def _update_rate(tab: Table) -> float:
    """The rate of the last ``// Update Rate: <x>Hz`` header line."""
    rate = None
    for c in tab.comments:
        m = _RATE.search(c)
        if m:
            rate = float(m.group(1))
    if rate is None:
        raise FormatError(
            tab.path, "missing '// Update Rate: <x>Hz' header line; pass rate_hz=", line=1
        )
    return rate


def _orientation(tab: Table) -> np.ndarray | None:
    """Quaternions (N, 4) wxyz from ``Mat[i][j]`` (checked orthonormal) or ``Quat_q0..3``."""
    mat = tab.column_group(_MAT_COLS)
    if mat is None:
        return tab.column_group(["Quat_q0", "Quat_q1", "Quat_q2", "Quat_q3"])
    R = mat.reshape(-1, 3, 3).transpose(0, 2, 1)  # listed column by column -> R[n][row][col]
    q = np.full((R.shape[0], 4), np.nan)
    ok = np.all(np.isfinite(mat), axis=1)
    if np.any(ok):
        dev = np.abs(R[ok] @ R[ok].transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
        if np.any(dev > 1e-2):
            i = int(np.flatnonzero(ok)[int(np.argmax(dev))])
            raise tab.error_at(
                i,
                f"expected an orthonormal orientation matrix, found |R R^T - I| = {dev.max():.3g}",
                "Mat[1][1]",
            )
        q[ok] = Rotation.from_matrix(R[ok]).as_quat(scalar_first=True)
    return q


def _unwrap(v: np.ndarray, period: float) -> np.ndarray:
    """Undo the wrap-around of an unsigned counter (a drop by more than half the period)."""
    wraps = np.concatenate([[0], np.cumsum(np.diff(v) < -period / 2)])
    return v + period * wraps


#: SampleTimeFine tick candidates, s: MTi devices count 10 kHz ticks, Xsens DOT microseconds.
_FINE_TICKS_S = {"10 kHz ticks (MTi)": 1e-4, "microseconds (Xsens DOT)": 1e-6}


def _sample_time_fine(tab: Table, rate_hz: float) -> tuple[np.ndarray | None, str | None]:
    """Device times (s, unwrapped, not shifted) from the ``SampleTimeFine`` column, or (None, None).

    The column is a uint32 (wraps at 2³²) whose tick depends on the device: the tick of
    :data:`_FINE_TICKS_S` whose median step is closest (in ratio) to ``1 / rate_hz`` is used.
    A step that still disagrees with the header's Update Rate by more than 1 % is reported in
    the note (the times are then the device's, not the header's).
    """
    if not tab.has("SampleTimeFine") or len(tab) < 2:
        return None, None
    raw = tab.floats("SampleTimeFine")
    if not np.all(np.isfinite(raw)):
        return None, None
    fine = _unwrap(raw, 2.0**32)
    if np.any(np.diff(fine) <= 0):
        k = int(np.flatnonzero(np.diff(fine) <= 0)[0]) + 1
        return None, (
            f"SampleTimeFine not increasing at line {int(tab.lines[k])}; times from PacketCounter"
        )
    step = float(np.median(np.diff(fine)))
    name, tick = min(_FINE_TICKS_S.items(), key=lambda kv: abs(np.log(step * kv[1] * rate_hz)))
    t = fine * tick
    measured = 1.0 / (step * tick)
    note = f"SampleTimeFine in {name}"
    if abs(measured - rate_hz) > 0.01 * rate_hz:
        note += (
            f": its median step gives {measured:.4g} Hz, the header's Update Rate says {rate_hz:g} Hz; "
            f"times from SampleTimeFine: {t[-1] - t[0]:.3f} s (the Update Rate would give "
            f"{(len(t) - 1) / rate_hz:.3f} s)"
        )
    return t, note


def _xml_mapping(folder: Path) -> dict[str, str]:
    """Sensor id -> OpenSim body name from an OpenSense ``*Mappings*.xml`` file, if present."""
    out: dict[str, str] = {}
    for xml in sorted(folder.glob("*.xml")):
        try:
            root = ET.parse(xml).getroot()
        except ET.ParseError:
            continue
        for el in root.iter("ExperimentalSensor"):
            name = (el.get("name") or "").lstrip("_")
            model = el.findtext("name_in_model") or ""
            if name and model:
                out[name] = re.sub(r"_imu$", "", model.strip())
    return out


_FREE_ACC_MAX = 3.0  # m/s^2: a worn sensor's specific force has median |f| ~ g


def _acc_kind(acc, q, acceleration: str) -> str:
    if acc is None:
        return "none"
    if acceleration != "auto":
        return acceleration
    n = np.linalg.norm(acc, axis=1)
    n = n[np.isfinite(n)]
    if q is not None and n.size and float(np.median(n)) < _FREE_ACC_MAX:
        return "free"
    return "specific_force"


def read_opensense(
    path,
    *,
    sensor_map: Mapping[str, str] | None = None,
    rate_hz: float | None = None,
    acceleration: str = "auto",
) -> Recording:
    """Read Xsens MT Manager exports: one ``.txt`` file or a folder of them (one per sensor).

    Parameters
    ----------
    path : str or Path
        A ``MT_<...>_<sensorID>.txt`` file or a folder of such files.
    sensor_map : mapping or None
        Sensor id (file-name suffix, e.g. ``00B4227C``) -> segment key or OpenSim body name
        (``femur_r``). Default: an OpenSense ``*.xml`` mapping file in the folder if there is
        one, else :data:`OPENSENSE_EXAMPLE_SENSORS` for the ids it knows; unknown ids keep
        their own name.
    rate_hz : float or None
        Sampling rate; default from the ``// Update Rate`` header line.
    acceleration : {"auto", "specific_force", "free"}
        What ``Acc_X..Z`` hold. ``"free"``: free acceleration (gravity removed, in the
        orientation's world frame, as Movella DOT exports converted to MT Manager text carry);
        the specific force is rebuilt from it and the orientation. ``"auto"``: free when the
        file has an orientation and the median ``|acc|`` is below 3 m/s² (a worn sensor's
        specific force has median ``|f|`` near g).

    Returns
    -------
    Recording
        ``imu[key]``: ``q_world_from_sensor`` (N, 4) wxyz from the orientation matrix (via
        :class:`scipy.spatial.transform.Rotation`), frame :data:`XSENS_FRAME`; ``acc_m_s2``
        (N, 3) specific force in the sensor frame; ``gyr_rad_s``/``mag`` when the export has
        them. Times: when every file has ``SampleTimeFine`` (µs on DOT, 10 kHz ticks on MTi,
        unwrapped at 2³²), ``t = SampleTimeFine time - the earliest first one over all sensors``
        (synchronised sensors share that clock; a :class:`~kinefuse.exceptions.FormatWarning`
        when it disagrees with the Update Rate); else ``t = (PacketCounter - c0) / rate``, with ``c0`` the smallest first counter over
        all sensors, so sensors stay aligned by packet counter (they start at different
        counters). ``metadata["time_source"]`` says which.

    Raises
    ------
    FormatError
        Missing columns, truncated lines, non-numeric fields, non-monotonic counters,
        non-orthonormal matrices; a folder without Xsens files.
    """
    path = Path(path)
    if acceleration not in ("auto", "specific_force", "free"):
        raise InputError(
            f"expected acceleration 'auto', 'specific_force' or 'free', got {acceleration!r}"
        )
    files, folder = _files(path)
    parsed = {_sensor_id(f): (f, read_xsens_txt(f, rate_hz=rate_hz)) for f in files}
    mapping, notes = map_segments(list(parsed), _overrides(parsed, sensor_map, folder))
    use_fine, t0, c0 = _time_base(parsed, notes)
    imu, free_acc, units = _streams(parsed, mapping, (use_fine, t0, c0), acceleration, notes)
    md = make_metadata(
        path,
        "opensense",
        subject=None,
        units_converted=units,
        segment_map=mapping,
        time_source="SampleTimeFine" if use_fine else "PacketCounter / Update Rate",
        free_acc_m_s2=free_acc,
        files=[str(f) for f, _ in parsed.values()],
        packet_counter_origin=int(c0),
        frame_notes=(
            "orientation frame: Xsens global, z up (R @ acc = +g z at rest); heading axes as set in MT Manager "
            "(ENU default in 4.x), not converted"
        ),
        notes=notes,
    )
    return finish_recording(path, md, imu=imu)


def _streams(parsed: dict, mapping: dict, time_base, acceleration: str, notes: list[str]):
    """(ImuStream per key, free acceleration per key where Acc holds it, conversions done)."""
    use_fine, t0, c0 = time_base
    imu, free_acc, units = {}, {}, ["orientation matrix -> quaternion wxyz"]
    for sid, (_f, p) in parsed.items():
        if use_fine:  # synchronised sensors share the SampleTimeFine clock
            t = p["sample_time_s"] - t0
        else:
            t = (p["counter"] - c0) / p["rate_hz"]
        acc = p["acc"]
        if _acc_kind(acc, p["q"], acceleration) == "free":
            free_acc[mapping[sid]] = acc
            acc = specific_force_from_free_acc(p["q"], acc)
            units = sorted(
                set(units) | {"free acceleration (world) -> specific force (sensor frame)"}
            )
        imu[mapping[sid]] = ImuStream(
            t_s=t,
            q_world_from_sensor=p["q"],
            acc_m_s2=acc,
            gyr_rad_s=p["gyr"],
            mag=p["mag"],
            name=sid,
            frame=XSENS_FRAME,
        )
    if free_acc:
        notes.append(
            f"Acc_X..Z of {sorted(free_acc)} hold free acceleration (gravity removed, world frame; median "
            f"|acc| < {_FREE_ACC_MAX} m/s^2); specific force rebuilt as R^T (a_free + g e_z), the "
            "free acceleration kept in metadata['free_acc_m_s2']"
        )
    return imu, free_acc, units


def _files(path: Path) -> tuple[list[Path], Path]:
    """The Xsens text files of ``path`` (a file or a folder) and the folder they are in."""
    if not path.is_dir():
        return [path], path.parent
    files = sorted(p for p in path.glob("*.txt") if _is_xsens(p))
    if not files:
        raise FormatError(
            path,
            "expected Xsens MT Manager .txt exports (with a PacketCounter column), found none",
        )
    return files, path


def _overrides(parsed: dict, sensor_map, folder: Path) -> dict[str, str]:
    """Sensor id -> key from ``sensor_map``, else the folder's XML mapping or the example's ids."""
    xml_map = _xml_mapping(folder)
    overrides = {}
    for sid in parsed:
        target = None
        if sensor_map is not None and sid in sensor_map:
            target = sensor_map[sid]
        elif sensor_map is None and sid in xml_map:
            target = xml_map[sid]
        elif sensor_map is None and sid in OPENSENSE_EXAMPLE_SENSORS:
            target = OPENSENSE_EXAMPLE_SENSORS[sid]
        if target is not None:
            overrides[sid] = canonical_segment(target) or target
    return overrides


def _time_base(parsed: dict, notes: list[str]) -> tuple[bool, float, float]:
    """(SampleTimeFine for all sensors?, its earliest first time, the smallest first counter)."""
    c0 = min(p["counter"][0] for _, p in parsed.values())
    rates = {p["rate_hz"] for _, p in parsed.values()}
    if len(rates) > 1:
        notes.append(f"sensors report different update rates {sorted(rates)}")
    use_fine = all(p["sample_time_s"] is not None for _, p in parsed.values())
    for sid, (f, p) in parsed.items():
        note = p["sample_time_note"]
        if not use_fine and note and "not increasing" in note:
            notes.append(f"{sid}: {note}")
        if use_fine and note and "Update Rate" in note:
            warnings.warn(f"{f}: {note}", FormatWarning, stacklevel=3)
            notes.append(f"{sid}: {note}")
    fine0 = min(p["sample_time_s"][0] for _, p in parsed.values()) if use_fine else 0.0
    return use_fine, fine0, c0
