"""UTD-MHAD reader: wearable inertial ``.mat`` + Kinect v1 skeleton ``.mat`` of one trial.

Files are named ``a<action>_s<subject>_t<trial>_inertial.mat`` (folder ``Inertial/``) and
``a<action>_s<subject>_t<trial>_skeleton.mat`` (folder ``Skeleton/``). Either file may be given;
the partner is found by that naming.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import scipy.io

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import (
    DEG2RAD,
    ZERO_RULE,
    G,
    finish_recording,
    make_metadata,
    zero_is_missing,
)
from kinefuse.io._names import KINECT_LIMB_JOINTS
from kinefuse.io.recording import ImuStream, JointStream, Recording

__all__ = ["KINECT_V1_JOINTS", "KINECT_V1_TO_CANONICAL", "read_utd_mhad", "utd_mhad_partner"]

#: Kinect v1 joint order of UTD-MHAD (``Skeleton_joint_order.txt``, 1-based there).
KINECT_V1_JOINTS = (
    "head",
    "shoulder_center",
    "spine",
    "hip_center",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "left_hand",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "right_hand",
    "left_hip",
    "left_knee",
    "left_ankle",
    "left_foot",
    "right_hip",
    "right_knee",
    "right_ankle",
    "right_foot",
)
#: The same joints under kinefuse's canonical names (ShoulderCenter -> spine_shoulder, Spine ->
#: spine_mid, HipCenter -> spine_base, as Kinect v2 renamed them).
KINECT_V1_TO_CANONICAL = ("head", "spine_shoulder", "spine_mid", "spine_base", *KINECT_LIMB_JOINTS)

_NAME = re.compile(r"^a(\d+)_s(\d+)_t(\d+)_(inertial|skeleton)\.mat$", re.IGNORECASE)
_KIND_DIR = {"inertial": "Inertial", "skeleton": "Skeleton"}


def _parse_name(path: Path):
    m = _NAME.match(path.name)
    if not m:
        return None
    return int(m.group(1)), int(m.group(2)), int(m.group(3)), m.group(4).lower()


def utd_mhad_partner(path) -> Path | None:
    """The partner file (inertial <-> skeleton) of a UTD-MHAD trial file, or None if absent.

    Looks in the sibling folder (``Inertial/`` <-> ``Skeleton/``) and in the same folder.
    """
    path = Path(path)
    parsed = _parse_name(path)
    if parsed is None:
        return None
    a, s, t, kind = parsed
    other = "skeleton" if kind == "inertial" else "inertial"
    name = f"a{a}_s{s}_t{t}_{other}.mat"
    candidates = [path.parent.parent / _KIND_DIR[other] / name, path.parent / name]
    for c in candidates:
        if c.is_file():
            return c
    return None


def _loadmat(path: Path, var: str, expected: str) -> np.ndarray:
    try:
        d = scipy.io.loadmat(path)
    except Exception as e:  # scipy raises ValueError/TypeError/MatReadError on corrupt files
        raise FormatError(
            path, f"expected a MATLAB v5 file with variable {var!r}, could not read it: {e}"
        ) from None
    if var not in d:
        found = sorted(k for k in d if not k.startswith("__"))
        raise FormatError(
            path, f"missing variable {var!r} {expected}; found variables {found}", field=var
        )
    a = d[var]
    if not isinstance(a, np.ndarray) or not np.issubdtype(a.dtype, np.number):
        raise FormatError(
            path,
            f"expected {var} as a numeric array {expected}, found {type(a).__name__}",
            field=var,
        )
    return np.asarray(a, dtype=np.float64)


def read_utd_mhad(
    path,
    skeleton_path=None,
    *,
    imu_rate_hz: float = 50.0,
    skeleton_rate_hz: float | None = None,
    segment: str | None = None,
) -> Recording:
    """Read one UTD-MHAD trial (inertial and/or Kinect v1 skeleton).

    Parameters
    ----------
    path : str or Path
        ``..._inertial.mat`` or ``..._skeleton.mat``; the partner is looked up by name.
    skeleton_path : str or Path or None
        Explicit skeleton file when ``path`` is the inertial file (overrides the lookup).
    imu_rate_hz : float
        Inertial sampling rate (the dataset description says 50 Hz; the files hold no times).
    skeleton_rate_hz : float or None
        Skeleton frame rate. ``None`` (default) stretches the skeleton frames uniformly over the
        inertial duration (first to last sample), as the dataset's SOURCE.md advises because the
        ratio of samples does not match 50/30 Hz. Without an inertial file, ``None`` means 30 Hz.
    segment : str or None
        Key of the IMU. ``None`` -> ``forearm_r`` for actions 1-21 (right wrist) and ``thigh_r``
        for actions 22-27 (right thigh).

    Returns
    -------
    Recording
        ``imu[segment]``: ``acc_m_s2`` (T, 3) in m/s² (file: g), ``gyr_rad_s`` (T, 3) in rad/s
        (file: deg/s), sensor frame, no orientation. ``vision``: 20 Kinect v1 joints (T, 20, 3)
        in metres in the Kinect v1 camera frame (x toward the sensor's left, y up, z away from
        the sensor), canonical joint names; ``available`` = finite and not all-zero (Kinect v1
        exports have no tracking state).

    Raises
    ------
    FormatError
        Unreadable file, missing variable, wrong shape.
    """
    path = Path(path)
    parsed = _parse_name(path)
    iner_path, skel_path = _trial_files(path, parsed, skeleton_path)
    names = [(q, _parse_name(q)) for q in (iner_path, skel_path) if q is not None]
    trials = {tuple(n[:3]) for _, n in names if n is not None}
    if len(trials) > 1:  # two trials' files read as one recording: wrong without a sign
        a, b = names
        raise FormatError(
            b[0],
            f"is the skeleton of trial a{b[1][0]}_s{b[1][1]}_t{b[1][2]}, given with the inertial "
            f"file of trial a{a[1][0]}_s{a[1][1]}_t{a[1][2]} ({a[0].name}); give the two files "
            "of one trial",
        )
    notes: list[str] = []
    imu, t_end = {}, None
    action = parsed[0] if parsed else None
    if iner_path is not None:
        segment = _default_segment(action, notes) if segment is None else segment
        imu[segment] = _inertial(iner_path, imu_rate_hz)
        t_end = float(imu[segment].t_s[-1])
        notes.append(f"inertial times assumed: t = n / {imu_rate_hz} Hz (files have no timestamps)")
    else:
        _warn_no_partner(path, "inertial", "the skeleton")
    vision = None
    if skel_path is not None:
        vision = _skeleton(skel_path, skeleton_rate_hz, t_end, notes)
    elif iner_path == path:
        _warn_no_partner(path, "skeleton", "the inertial data")
    md = make_metadata(
        path,
        "utd_mhad",
        subject=f"s{parsed[1]}" if parsed else None,
        units_converted=["acc g -> m/s^2", "gyr deg/s -> rad/s"] if imu else [],
        action=action,
        trial=parsed[2] if parsed else None,
        files={
            "inertial": str(iner_path) if iner_path else None,
            "skeleton": str(skel_path) if skel_path else None,
        },
        segment_map={"utd_mhad_inertial": segment} if imu else {},
        joint_map=dict(zip(KINECT_V1_JOINTS, KINECT_V1_TO_CANONICAL, strict=True)),
        availability_rule=f"finite; {ZERO_RULE} (Kinect v1 has no tracking state)",
        frame_notes="vision in Kinect v1 camera frame: x toward the sensor's left, y up, z away from the sensor",
        notes=notes,
    )
    return finish_recording(path, md, imu=imu, vision=vision)


def _warn_no_partner(path: Path, missing: str, reading: str) -> None:
    warnings.warn(
        f"{path}: {missing} partner file not found; reading {reading} only",
        UserWarning,
        stacklevel=3,
    )


def _trial_files(path: Path, parsed, skeleton_path) -> tuple[Path | None, Path | None]:
    """(inertial file, skeleton file) of the trial ``path`` belongs to (None: not found)."""
    kind = parsed[3] if parsed else None
    if kind is None:
        try:
            names = {n for n, _, _ in scipy.io.whosmat(path)}
        except Exception as e:
            raise FormatError(
                path, f"expected a UTD-MHAD MATLAB file, could not read it: {e}"
            ) from None
        kind = "inertial" if "d_iner" in names else ("skeleton" if "d_skel" in names else None)
        if kind is None:
            raise FormatError(
                path, f"expected variable 'd_iner' or 'd_skel', found {sorted(names)}"
            )
    if kind == "inertial":
        return path, Path(skeleton_path) if skeleton_path is not None else utd_mhad_partner(path)
    if skeleton_path is not None:
        raise FormatError(path, "skeleton_path given but path is already the skeleton file")
    return utd_mhad_partner(path), path


def _default_segment(action: int | None, notes: list[str]) -> str:
    """``forearm_r`` for actions 1-21 (right wrist), ``thigh_r`` for 22-27 (right thigh)."""
    if action is None:
        notes.append("action unknown (file name not a<A>_s<S>_t<T>); IMU kept as 'imu'")
        return "imu"
    return "forearm_r" if action <= 21 else "thigh_r"


def _inertial(iner_path: Path, imu_rate_hz: float) -> ImuStream:
    x = _loadmat(iner_path, "d_iner", "(N, 6): acc x,y,z [g], gyro x,y,z [deg/s]")
    if x.ndim != 2 or x.shape[1] != 6 or x.shape[0] < 2:
        raise FormatError(
            iner_path, f"expected d_iner with shape (N>=2, 6), found {x.shape}", field="d_iner"
        )
    return ImuStream(
        t_s=np.arange(x.shape[0]) / float(imu_rate_hz),
        acc_m_s2=x[:, :3] * G,
        gyr_rad_s=x[:, 3:] * DEG2RAD,
        name="utd_mhad_inertial",
        frame="ENU",
    )


def _skeleton(skel_path: Path, skeleton_rate_hz, t_end, notes: list[str]) -> JointStream:
    s = _loadmat(skel_path, "d_skel", "(20, 3, T) joint positions [m]")
    if s.ndim != 3 or s.shape[:2] != (20, 3) or s.shape[2] < 1:
        raise FormatError(
            skel_path, f"expected d_skel with shape (20, 3, T), found {s.shape}", field="d_skel"
        )
    pos = np.transpose(s, (2, 0, 1)).copy()  # (T, 20, 3)
    T = pos.shape[0]
    if skeleton_rate_hz is not None:
        ts = np.arange(T) / float(skeleton_rate_hz)
        notes.append(f"skeleton times assumed: t = n / {skeleton_rate_hz} Hz")
    elif t_end is not None and T > 1:
        ts = np.linspace(0.0, t_end, T)
        notes.append(
            f"skeleton frames stretched uniformly over the inertial duration 0..{t_end:.3f} s "
            f"(effective {(T - 1) / t_end:.2f} Hz); expect some timing error"
        )
    else:
        ts = np.arange(T) / 30.0
        notes.append("skeleton times assumed: t = n / 30 Hz")
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero_is_missing(pos)
    return JointStream(
        t_s=ts,
        position_m=pos,
        available=avail,
        joints=KINECT_V1_TO_CANONICAL,
        frame="kinect_v1_camera",
    )
