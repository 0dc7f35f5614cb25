"""Xsens MVN exports in MVNX (XML): the MVN body model's segments and the suit's sensors.

An MVNX file holds, under ``<subject frameRate=...>``: ``<segments>`` (label, and the points of
each segment in its own frame, ``pos_b``, m), ``<sensors>`` (the segments that carry an IMU),
``<joints>`` (``connector1`` parent segment/point, ``connector2`` child segment/point) and
``<frames>``: calibration poses (``type="identity"``, ``"tpose"``, ``"tpose-isb"``, ``"npose"``)
and the recording (``type="normal"``), each with space-separated values per segment/sensor.

Units and frames (Xsens MVN user manual, MVNX section): positions m, velocities m/s,
accelerations m/s², angular velocities rad/s, all of segments in the MVN global frame (z up,
x along the heading reference of the session); quaternions ``q0 q1 q2 q3`` = wxyz, segment or
sensor frame -> global; ``sensorFreeAcceleration`` m/s² in the global frame with gravity removed;
``sensorMagneticField`` a.u. in the sensor frame; joint angles deg (ZXY Euler, ISB).

The file is read with :func:`xml.etree.ElementTree.iterparse`, one frame at a time.
"""

from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import finish_recording, make_metadata
from kinefuse.io._names import map_segments
from kinefuse.io.recording import ImuStream, JointStream, Recording
from kinefuse.io.xsens_dot import specific_force_from_free_acc

__all__ = ["MVN_JOINTS", "MVN_SEGMENTS", "MVNX_FRAME", "read_mvnx"]

#: Frame label of MVNX positions and orientations (not converted: MVN's x is the session's
#: heading reference, which the file does not state).
MVNX_FRAME = "xsens_mvn_global_z_up"

#: Xsens segment label -> kinefuse segment key, where :func:`canonical_segment` needs help.
MVN_SEGMENTS = {"T8": "chest"}

#: kinefuse joint name -> (MVN segment, point labels averaged in that segment's frame).
#: Segment origins are MVN's joints (``jRightElbow`` is the RightForeArm origin); ``hand`` is the
#: palm point, ``head`` the midpoint of the two ear (auricularis) points.
MVN_JOINTS = {
    "pelvis": ("Pelvis", ("pHipOrigin",)),
    "spine_base": ("Pelvis", ("pHipOrigin",)),
    "spine_mid": ("T8", ("jT9T8",)),
    "spine_shoulder": ("Neck", ("jT1C7",)),
    "neck": ("Head", ("jC1Head",)),
    "head": ("Head", ("pRightAuricularis", "pLeftAuricularis")),
    **{
        f"{j}_{s}": (seg.format(side), (pt.format(side),))
        for s, side in (("r", "Right"), ("l", "Left"))
        for j, seg, pt in (
            ("shoulder", "{}UpperArm", "j{}Shoulder"),
            ("elbow", "{}ForeArm", "j{}Elbow"),
            ("wrist", "{}Hand", "j{}Wrist"),
            ("hand", "{}Hand", "p{}HandPalm"),
            ("hip", "{}UpperLeg", "j{}Hip"),
            ("knee", "{}LowerLeg", "j{}Knee"),
            ("ankle", "{}Foot", "j{}Ankle"),
            ("foot", "{}Toe", "j{}BallFoot"),
        )
    },
}

_PER_SEGMENT = {"orientation": 4, "position": 3, "velocity": 3, "acceleration": 3}
_PER_SEGMENT |= {"angularVelocity": 3, "angularAcceleration": 3}
_PER_SENSOR = {"sensorOrientation": 4, "sensorFreeAcceleration": 3, "sensorMagneticField": 3}
_PER_SENSOR |= {"sensorAcceleration": 3, "sensorAngularVelocity": 3}


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _floats(path: Path, el, what: str) -> np.ndarray:
    try:
        return np.array((el.text or "").split(), dtype=float)
    except ValueError:
        bad = next(v for v in (el.text or "").split() if not _is_float(v))
        raise FormatError(path, f"expected numbers in <{what}>, found {bad!r}") from None


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _parse(path: Path):
    subject: dict = {}
    segments: dict[str, dict[str, np.ndarray]] = {}
    sensors: list[str] = []
    poses: dict[str, dict[str, np.ndarray]] = {}
    frames: list[dict] = []
    seg_label = None
    try:
        for event, el in ET.iterparse(path, events=("start", "end")):
            tag = _local(el.tag)
            if event == "start":
                if tag == "subject":
                    subject = dict(el.attrib)
                elif tag == "segment":
                    seg_label = el.get("label")
                    segments[seg_label] = {}
                continue
            if tag == "point" and seg_label is not None:
                pb = next((c for c in el if _local(c.tag) == "pos_b"), None)
                if pb is not None:
                    segments[seg_label][el.get("label")] = _floats(path, pb, "pos_b")
            elif tag == "segment":
                seg_label = None
            elif tag == "sensor" and el.get("label"):
                sensors.append(el.get("label"))
            elif tag == "frame":
                rec = {_local(c.tag): _floats(path, c, _local(c.tag)) for c in el}
                kind = el.get("type", "normal")
                if kind == "normal":
                    rec["@time"] = el.get("time")
                    rec["@index"] = el.get("index")
                    rec["@ms"] = el.get("ms")
                    frames.append(rec)
                else:
                    poses[kind] = rec
                el.clear()
    except ET.ParseError as e:
        raise FormatError(
            path, f"expected well-formed MVNX XML, found a parse error ({e})", line=e.position[0]
        ) from None
    return subject, segments, sensors, poses, frames


def _block(path: Path, recs: list[dict], name: str, n: int, k: int) -> np.ndarray | None:
    if not recs or name not in recs[0]:
        return None
    out = np.full((len(recs), n, k), np.nan)
    for i, r in enumerate(recs):
        v = r.get(name)
        if v is None or v.size != n * k:
            found = "nothing" if v is None else f"{v.size} values"
            raise FormatError(
                path,
                f"expected {n} x {k} = {n * k} values in <{name}> of frame {i}, found {found}",
                field=name,
            )
        out[i] = v.reshape(n, k)
    return out


def _joint_positions(segs, seg_names, pos, q) -> tuple[tuple[str, ...], np.ndarray]:
    """Joint names and positions (T, J, 3) from segment positions (T, S, 3) and quaternions."""
    names, cols = [], []
    for joint, (seg, points) in MVN_JOINTS.items():
        if seg not in seg_names or not all(p in segs.get(seg, {}) for p in points):
            continue
        s = seg_names.index(seg)
        pb = np.mean([segs[seg][p] for p in points], axis=0)
        ok = np.all(np.isfinite(q[:, s]), axis=1)
        p = np.full(pos[:, s].shape, np.nan)
        if np.any(ok):
            p[ok] = pos[ok, s] + Rotation.from_quat(q[ok, s], scalar_first=True).apply(pb)
        names.append(joint)
        cols.append(p)
    return tuple(names), np.stack(cols, axis=1)


def read_mvnx(
    path, *, sensor_map: Mapping[str, str] | None = None, derive_raw: bool = True
) -> Recording:
    """Read an Xsens MVNX export: reference skeleton, segment orientations, IMU streams, poses.

    Parameters
    ----------
    path : str or Path
        The ``.mvnx`` file.
    sensor_map : mapping or None
        Xsens segment label -> key for the sensors and segment orientations; default the label
        mapped to a canonical segment (``RightUpperArm`` -> ``upper_arm_r``, ``T8`` -> ``chest``,
        ``RightLowerLeg`` -> ``shank_r``), other labels kept (``Head``, ``RightShoulder``).
    derive_raw : bool
        MVNX stores the sensors' orientation, free acceleration and magnetic field, not their raw
        accelerometer and gyroscope. With ``derive_raw`` (default) ``acc_m_s2`` is
        ``R_sensorᵀ (a_free + g e_z)`` (:func:`~kinefuse.io.xsens_dot.specific_force_from_free_acc`)
        and ``gyr_rad_s`` is the carrying segment's angular velocity rotated into the sensor
        frame (a rigidly attached sensor turns with its segment), listed in
        ``metadata["units_converted"]``. ``sensorAcceleration`` / ``sensorAngularVelocity``,
        where a file has them, are used as they are.

    Returns
    -------
    Recording
        ``reference``: joint positions (T, J, 3) m, frame :data:`MVNX_FRAME`, joints of
        :data:`MVN_JOINTS` -- MVN's own body-model estimate from the same IMUs, not an
        independent optical truth. ``reference_orientation[key]``: every segment's orientation.
        ``imu[key]``: each sensor's ``q_world_from_sensor``, ``acc_m_s2``, ``gyr_rad_s``,
        ``mag``. Time ``t = index / frameRate`` (checked against each frame's ``time`` in ms).
        ``metadata``: see :data:`METADATA`.

    Raises
    ------
    FormatError
        Malformed XML, no ``frameRate``, no segments or frames, a frame whose value count does
        not match the segment/sensor count, non-increasing time.
    """
    path = Path(path)
    mvnx = _parse_checked(path)
    subject, segs, sensor_labels, poses, frames = mvnx
    seg_names = list(segs)
    rate = _frame_rate(path, subject)
    t = _frame_times(path, frames, rate)
    blocks = {n: _block(path, frames, n, len(seg_names), k) for n, k in _PER_SEGMENT.items()}
    sblocks = {n: _block(path, frames, n, len(sensor_labels), k) for n, k in _PER_SENSOR.items()}
    q_seg, pos = blocks.pop("orientation"), blocks.pop("position")
    if q_seg is None or pos is None:
        raise FormatError(
            path, "expected <orientation> and <position> in every frame", field="position"
        )
    names = list(dict.fromkeys(seg_names + sensor_labels))
    overrides = {n: (sensor_map or {}).get(n) or MVN_SEGMENTS.get(n) for n in names}
    mapping, notes = map_segments(names, {n: v for n, v in overrides.items() if v})
    joints, jpos = _joint_positions(segs, seg_names, pos, q_seg)
    reference = JointStream(t_s=t, position_m=jpos, joints=joints, frame=MVNX_FRAME)
    ref_ori = {
        mapping[s]: ImuStream(t_s=t, q_world_from_sensor=q_seg[:, i], name=s, frame=MVNX_FRAME)
        for i, s in enumerate(seg_names)
    }
    imu, units = _sensor_streams(
        t, sensor_labels, seg_names, sblocks, blocks["angularVelocity"], derive_raw, mapping, notes
    )
    free = sblocks["sensorFreeAcceleration"]
    md = _metadata(path, mvnx, blocks, free, mapping, joints, rate, units, notes)
    return finish_recording(path, md, imu=imu, reference=reference, reference_orientation=ref_ori)


#: What :func:`read_mvnx` puts in ``metadata`` besides the standard keys: ``rate_hz``,
#: ``segments`` (point ``pos_b`` per segment, m), ``calibration_poses``
#: (``identity``/``npose``/``tpose``/``tpose-isb``: ``joints``, ``position_m`` (J, 3),
#: ``segments``, ``q_world_from_segment`` (S, 4)), ``free_acc_world_m_s2`` per sensor,
#: ``frames`` (the other per-frame arrays: velocity, acceleration, jointAngle (deg),
#: centerOfMass, footContacts ...), ``t0_unix_ms``. Joints: segment origins are MVN joints,
#: hand = palm point, head = midpoint of the ears.
METADATA = (
    "rate_hz",
    "segments",
    "calibration_poses",
    "free_acc_world_m_s2",
    "frames",
    "t0_unix_ms",
)


class _Mvnx(NamedTuple):
    subject: dict
    segments: dict
    sensors: list
    poses: dict
    frames: list


def _parse_checked(path: Path) -> _Mvnx:
    """:func:`_parse` of an ``.mvnx`` file that has segments and recorded frames."""
    if path.is_dir():
        found = sorted(p.name for p in path.glob("*.mvnx"))
        raise FormatError(
            path, f"expected an .mvnx file, found a folder (with .mvnx files {found})"
        )
    subject, segs, sensor_labels, poses, frames = _parse(path)
    if not segs or not frames:
        raise FormatError(
            path,
            f"expected MVNX <segments> and <frame type='normal'> elements, found {len(segs)} "
            f"segments and {len(frames)} frames",
        )
    return _Mvnx(subject, segs, sensor_labels, poses, frames)


def _frame_times(path: Path, frames: list[dict], rate: float) -> np.ndarray:
    """``index / frameRate`` from 0 (the frames' ``time`` in ms where it disagrees by > 1 ms)."""
    idx = [r["@index"] for r in frames]
    ms = np.array([float(r["@time"]) if r["@time"] is not None else np.nan for r in frames])
    if all(i is not None for i in idx):
        t = np.array([float(i) for i in idx]) / rate
        off = np.abs(t * 1e3 - ms)
        if np.any(off > 1.0 + 1e-9):
            k = int(np.nanargmax(off))
            warnings.warn(
                f"{path}: frame index/frameRate disagrees with the frame's time attribute by "
                f"{off[k]:.3g} ms at frame {k}; using time",
                UserWarning,
                stacklevel=3,
            )
            t = ms / 1e3
    else:
        t = ms / 1e3
    return t - t[0]


def _frame_rate(path: Path, subject: dict) -> float:
    try:
        return float(subject["frameRate"])
    except (KeyError, ValueError):
        raise FormatError(
            path, "expected <subject frameRate=...>, found none", field="frameRate"
        ) from None


def _sensor_streams(t, sensor_labels, seg_names, sblocks, omega, derive_raw, mapping, notes):
    """ImuStream per sensor key and the derivations done (a note for each sensor not read)."""
    imu, units = {}, []
    for i, s in enumerate(sensor_labels):
        stream = _sensor_stream(t, s, i, seg_names, sblocks, omega, derive_raw, units)
        if stream is None:
            notes.append(f"sensor {s!r}: no orientation or raw data in the file; not read")
        else:
            imu[mapping[s]] = stream
    return imu, units


def _sensor_stream(t, s, i, seg_names, sblocks, omega, derive_raw, units) -> ImuStream | None:
    """Sensor ``s`` (column ``i``) as an ImuStream (None without orientation or raw data)."""

    def col(name):
        return None if sblocks[name] is None else sblocks[name][:, i]

    q, acc, gyr = col("sensorOrientation"), col("sensorAcceleration"), col("sensorAngularVelocity")
    free = col("sensorFreeAcceleration")
    if derive_raw and q is not None:
        if acc is None and free is not None:
            acc = specific_force_from_free_acc(q, free)
            units.append(
                f"{s}: acc_m_s2 derived = R_sensor^T (sensorFreeAcceleration + 9.80665 e_z)"
            )
        if gyr is None and omega is not None and s in seg_names:
            gyr = Rotation.from_quat(q, scalar_first=True).inv().apply(omega[:, seg_names.index(s)])
            units.append(f"{s}: gyr_rad_s derived = R_sensor^T angularVelocity of segment {s}")
    if q is None and (acc is None or gyr is None):
        return None
    return ImuStream(
        t_s=t,
        q_world_from_sensor=q,
        acc_m_s2=acc,
        gyr_rad_s=gyr,
        mag=col("sensorMagneticField"),
        name=s,
        frame=MVNX_FRAME,
    )


def _calibration_poses(path: Path, segs, poses: dict) -> dict:
    """Joint positions and segment orientations of each calibration pose in the file."""
    seg_names = list(segs)
    calib = {}
    for kind, rec in poses.items():
        pq = _block(path, [rec], "orientation", len(seg_names), 4)
        pp = _block(path, [rec], "position", len(seg_names), 3)
        if pq is None or pp is None:
            continue
        pj, pjp = _joint_positions(segs, seg_names, pp, pq)
        calib[kind] = {
            "joints": pj,
            "position_m": pjp[0],
            "segments": tuple(seg_names),
            "q_world_from_segment": pq[0],
        }
    return calib


def _other_frame_arrays(frames: list[dict], blocks: dict) -> dict:
    """The per-frame arrays not read into streams (velocity, jointAngle, centerOfMass ...)."""
    other = {}
    for n in frames[0]:
        if n.startswith("@") or n in _PER_SEGMENT or n in _PER_SENSOR:
            continue
        sizes = {r[n].size for r in frames if n in r}
        if len(sizes) == 1 and all(n in r for r in frames):
            other[n] = np.stack([r[n] for r in frames])
    for n, v in blocks.items():
        if v is not None:
            other[n] = v
    return other


def _metadata(path, mvnx: _Mvnx, blocks, free, mapping, joints, rate, units, notes) -> dict:
    subject, segs, sensor_labels, poses, frames = mvnx
    t0_ms = frames[0]["@ms"]
    return make_metadata(
        path,
        "mvnx",
        subject=subject.get("label"),
        units_converted=units,
        segment_map=mapping,
        joint_map={j: f"{MVN_JOINTS[j][0]}/{'+'.join(MVN_JOINTS[j][1])}" for j in joints},
        rate_hz=rate,
        segments=segs,
        sensors=tuple(sensor_labels),
        calibration_poses=_calibration_poses(path, segs, poses),
        free_acc_world_m_s2={}
        if free is None
        else {mapping[s]: free[:, i] for i, s in enumerate(sensor_labels)},
        frames=_other_frame_arrays(frames, blocks),
        t0_unix_ms=float(t0_ms) if t0_ms is not None and math.isfinite(float(t0_ms)) else None,
        configuration=subject.get("configuration"),
        frame_notes=(
            "MVN global frame: z up, x the session's heading reference (not stated in the file; "
            "not converted to ENU). reference = MVN's body-model estimate from the same IMUs."
        ),
        notes=notes,
    )
