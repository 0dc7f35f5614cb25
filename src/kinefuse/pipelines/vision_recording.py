"""Paper B's inputs from a recording: IMU chain by forward kinematics, camera aligned to it.

:func:`vision_assisted_from_recording` resamples the IMU orientations to the camera clock,
aligns the camera to the IMU world (Kabsch on segment directions), builds the chain (lengths and
offsets from the camera over a calibration window unless given) and runs
:func:`~kinefuse.pipelines.vision_assisted`; the result is a :class:`RecordingFusion`.

Steps
-----
1. IMU orientations are SLERP-resampled to the camera timestamps (SPEC §12.2).
2. Camera alignment [J, SPEC §2.2]: ``R_world_from_camera`` by Kabsch between the camera
   segment directions ``unit(p_distal − p_proximal)`` and the IMU segment directions
   ``R_i a_i`` over the window, pooled over the eight segments (no offsets or lengths
   needed). The camera joints are taken relative to its ``spine_shoulder``:
   ``z^V = R (p_cam − p_cam,spine_shoulder)``.
3. Default offsets: window mean of ``R_chestᵀ R (p_cam,joint − p_cam,spine_shoulder)`` for
   the shoulders and hips; default lengths: window median camera bone lengths.
4. ``z^I`` = forward kinematics from the chest origin (0) in the IMU world (ENU).
5. ``"kinefuse"`` also gets, per joint, the resampled orientations of the segments that move
   it (its segment-frame chain-error model, :func:`~kinefuse.pipelines.features.segment_frame_design`).

Deviations from the paper
-------------------------
Paper B computes positions in the chest IMU frame and never
aligns the camera (SPEC §2.2-2); here both live in ENU, chest-relative.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kinefuse._validation import names_arg
from kinefuse.conventions import PAPER_B_JOINTS
from kinefuse.exceptions import InputError
from kinefuse.io.recording import Recording
from kinefuse.kinematics import forward_kinematics, full_body, kabsch_rotation
from kinefuse.kinematics.forward import as_rotation_matrices
from kinefuse.orientation import slerp_resample
from kinefuse.pipelines.features import joint_rotations, moving_segments
from kinefuse.pipelines.fusion_context import FusionResult
from kinefuse.pipelines.vision_assisted import vision_assisted
from kinefuse.pipelines.vision_params import VisionParams, check_float

__all__ = ["RecordingFusion", "vision_assisted_from_recording"]


@dataclass(frozen=True, eq=False)
class RecordingFusion:
    """Output of :func:`vision_assisted_from_recording`.

    Attributes
    ----------
    result : FusionResult
        Fused positions, ENU chest-relative (origin = upper chest / spine_shoulder), m.
    t_s : ndarray, shape (T,)
        Camera timestamps, s.
    z_imu, z_cam : ndarray, shape (T, J, 3)
        The pipeline inputs (IMU chain; aligned camera, NaN where unavailable), m.
    available : ndarray of bool, shape (T, J)
    reference : ndarray, shape (T, J, 3) or None
        Reference joints at the camera timestamps, relative to the reference's
        ``spine_shoulder``, in the reference frame (ENU), m; None without a reference.
    R_world_from_camera : ndarray, shape (3, 3)
        Camera-to-IMU-world rotation used.
    skeleton : Skeleton
        The chain used for ``z_imu`` (lengths, axes, offsets).
    orientations : dict of str -> ndarray, shape (T, 3, 3)
        The IMU orientations ``z_imu`` was built from (``R_world_from_sensor`` at ``t_s``).
    """

    result: FusionResult
    t_s: np.ndarray
    z_imu: np.ndarray
    z_cam: np.ndarray
    available: np.ndarray
    reference: np.ndarray | None
    R_world_from_camera: np.ndarray
    skeleton: object
    orientations: dict


def vision_assisted_from_recording(
    recording,
    skeleton=None,
    calibration=None,
    method: str = "elm-fir",
    rate_hz: float = 30.0,
    *,
    joints: Sequence[str] | None = None,
    calibration_window_s: tuple[float, float] | None = None,
    causal: bool = False,
    params: VisionParams | None = None,
) -> RecordingFusion:
    """Run :func:`vision_assisted` on a recording with IMU orientations and a camera skeleton.

    Parameters
    ----------
    recording : Recording
        IMU streams with ``q_world_from_sensor`` for ``chest`` and the eight limb segments of
        :func:`kinefuse.kinematics.full_body`; ``vision`` with ``spine_shoulder`` and the
        output joints; optional ``reference``.
    skeleton : Skeleton, optional
        Full-body chain (chest origin). Default: :func:`~kinefuse.kinematics.full_body` with
        lengths = median camera bone lengths and shoulder/hip offsets from the camera, both over
        the calibration window, axes ``e2`` (or the calibration's).
    calibration : Calibration, optional
        Segment axes / lengths (applied to the skeleton) and ``R_world_from_camera`` if it has
        one; otherwise the rotation is estimated here.
    method : str
        As in :func:`vision_assisted`.
    rate_hz : float
        Filter rate, Hz (default 30, SPEC §12.2); the camera timestamps are used and must
        have this median rate within 5 %.
    joints : sequence of str, optional
        Output joints (default :data:`kinefuse.conventions.PAPER_B_JOINTS`).
    calibration_window_s : (float, float), optional
        ``(start, stop)`` s of the alignment window (default: the first 10 s of camera data).
    causal, params
        As in :func:`vision_assisted`.

    Returns
    -------
    RecordingFusion

    Notes
    -----
    The steps and the deviations from the paper are in the module docstring.
    """
    rate, t, cam = _check_recording(recording, rate_hz)
    out_joints = names_arg(joints, "joints") or PAPER_B_JOINTS
    sk = full_body(height_m=1.75) if skeleton is None else skeleton  # default: topology only
    if calibration is not None:
        sk = calibration.apply(sk)
    R = _imu_rotations(recording, sk, t)
    need = {"spine_shoulder", *out_joints, *sk.proximal, *sk.distal}
    lack = sorted(need - set(cam.joints))
    if lack:
        raise InputError(f"expected joints {lack} in the vision stream, got {list(cam.joints)}")
    lo, hi = (t[0], t[0] + 10.0) if calibration_window_s is None else calibration_window_s
    win = (t >= lo) & (t < hi)
    Rc = None if calibration is None else calibration.R_world_from_camera
    Rc = np.asarray(_camera_rotation(cam, sk, R, win) if Rc is None else Rc, dtype=float)
    p0 = cam.position("spine_shoulder")
    rel = {j: (cam.position(j) - p0) @ Rc.T for j in need}
    if skeleton is None:
        sk = _fit_skeleton(sk, R, rel, win, calibration, (lo, hi))
    pos = forward_kinematics(sk, R, np.zeros((t.size, 3)))
    missing = [j for j in out_joints if j not in pos]
    if missing:
        raise InputError(
            f"joints {missing} are not computed by the skeleton; it gives {sorted(pos)}"
        )
    z_imu = np.stack([pos[j] for j in out_joints], axis=1)
    z_cam = np.stack([rel[j] for j in out_joints], axis=1)
    av = np.all(np.isfinite(z_cam), axis=-1)
    z_cam = np.where(av[..., None], z_cam, np.nan)
    res = vision_assisted(
        z_imu, z_cam, av, 1.0 / rate, method, joints=out_joints, causal=causal, params=params,
        segment_rotations=_joint_rotations(R, sk, out_joints) if method == "kinefuse" else None,
    )  # fmt: skip
    ref = _reference(recording, out_joints, t)
    return RecordingFusion(res, t, z_imu, z_cam, av, ref, Rc, sk, R)


def _check_recording(recording, rate_hz):
    """``(rate, t_s, vision stream)`` of a recording with a camera at ``rate_hz`` (±5 %)."""
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    cam = recording.vision
    if cam is None:
        raise InputError("expected a recording with a vision (camera) stream, got vision=None")
    rate = check_float(rate_hz, "rate_hz", lo=0.0, strict=True)
    t = cam.t_s
    if t.size < 2:
        raise InputError(f"expected at least 2 camera samples, got {t.size}")
    cam_rate = 1.0 / float(np.median(np.diff(t)))
    if abs(cam_rate - rate) > 0.05 * rate:
        raise InputError(
            f"expected camera timestamps at rate_hz = {rate:g} Hz (±5 %), got {cam_rate:.3g} Hz"
        )
    return rate, t, cam


def _imu_rotations(recording, sk, t) -> dict:
    """Segment -> ``R_world_from_sensor (T, 3, 3)`` SLERP-resampled to the camera times ``t``."""
    segs = list(sk.segments) + ([sk.root_segment] if sk.root_segment else [])
    R = {}
    for s in segs:
        if s not in recording.imu or recording.imu[s].q_world_from_sensor is None:
            raise InputError(
                f"expected an IMU orientation for segment {s!r}, got IMUs {sorted(recording.imu)}"
            )
        st = recording.imu[s]
        R[s] = as_rotation_matrices(slerp_resample(st.t_s, st.q_world_from_sensor, t), f"IMU {s!r}")
    return R


def _joint_rotations(R, sk, joints) -> np.ndarray:
    """``(T, J, S, 3, 3)``: per joint the orientations of its :func:`moving_segments`."""
    return joint_rotations(R, list(moving_segments(sk, joints, R).values()))


def _camera_rotation(cam, sk, R, win) -> np.ndarray:
    """``R_world_from_camera``: Kabsch between the camera segment directions and the IMU
    segment directions ``R_i a_i`` over the window, pooled over the segments."""
    P_, Q_ = [], []
    for i, s in enumerate(sk.segments):
        d = cam.position(sk.distal[i])[win] - cam.position(sk.proximal[i])[win]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        P_.append(d)
        Q_.append(R[s][win] @ sk.axes[i])
    return kabsch_rotation(np.concatenate(P_), np.concatenate(Q_))


def _fit_skeleton(sk, R, rel, win, calibration, window):
    """Offsets (window mean in the root frame) and lengths (window median camera bone lengths,
    unless the calibration has them) from the aligned camera joints ``rel``."""
    R0 = R[sk.root_segment][win]
    offs = {}
    for j in sk.offsets_m:
        v = np.einsum("kji,kj->ki", R0, rel[j][win])
        offs[j] = np.nanmean(v, axis=0)
    lens = {}
    for i, s in enumerate(sk.segments):
        if calibration is not None and s in calibration.lengths_m:
            continue
        d = np.linalg.norm(rel[sk.distal[i]][win] - rel[sk.proximal[i]][win], axis=-1)
        lens[s] = float(np.nanmedian(d))
    bad = [k for k, v in {**offs, **lens}.items() if not np.all(np.isfinite(v))]
    if bad:
        lo, hi = window
        raise InputError(
            f"no camera samples in the calibration window {lo:g}-{hi:g} s to estimate {bad}; "
            "pass skeleton= or calibration_window_s="
        )
    return sk.with_offsets(offs).with_lengths(lens) if lens else sk.with_offsets(offs)


def _reference(recording, out_joints, t):
    """Reference joints at ``t`` relative to its ``spine_shoulder`` (None without them)."""
    rs = recording.reference
    if rs is None or not all(j in rs.joints for j in ("spine_shoulder", *out_joints)):
        return None
    cols = []
    for j in ("spine_shoulder", *out_joints):
        pj = rs.position(j)
        cols.append(
            np.stack(
                [np.interp(t, rs.t_s, pj[:, k], left=np.nan, right=np.nan) for k in range(3)], -1
            )
        )
    return np.stack(cols[1:], axis=1) - cols[0][:, None, :]
