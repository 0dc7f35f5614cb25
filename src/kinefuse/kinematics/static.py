"""Static-pose sensor-to-segment calibration: the subject holds a known pose (SPEC §2.1 (a)).

The segment axis ``a_i`` in each IMU frame, and the full ISB segment frame, from the IMU
orientations in a still window (found, or given) and the pose's segment directions.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.io.recording import ImuStream
from kinefuse.kinematics.alignment import angles_deg, unit_direction
from kinefuse.kinematics.angles import joint_angles
from kinefuse.kinematics.calibration_result import Calibration
from kinefuse.kinematics.forward import as_rotation_matrices
from kinefuse.kinematics.skeleton import Skeleton, unit_axis, window_mask
from kinefuse.kinematics.still import MIN_STILL_S, StillWindow, find_still_window

__all__ = [
    "POSE_WARN_DEG",
    "facing_free_segments",
    "pose_headings",
    "relative_yaw",
    "static_calibration",
    "window_orientations",
]

#: Angle (deg) beyond which a static-pose segment gets a warning naming it.
POSE_WARN_DEG = 20.0

_DOWN = np.array([0.0, 0.0, -1.0])
_UP = np.array([0.0, 0.0, 1.0])


def _body_frame(facing) -> np.ndarray:
    """World-from-body rotation of a subject facing ``facing``: columns X fwd, Y up, Z right."""
    f = np.asarray(facing, dtype=float)
    if f.shape != (3,) or not np.all(np.isfinite(f)):
        raise InputError(f"expected facing with shape (3,), got {np.shape(facing)}")
    f = f - f[2] * _UP
    if np.linalg.norm(f) < 1e-9:
        raise InputError(f"expected a horizontal facing direction, got {facing}")
    f = f / np.linalg.norm(f)
    return np.stack([f, _UP, np.cross(f, _UP)], axis=1)


def facing_free_segments(
    skeleton: Skeleton, segs: Sequence[str], pose: str, directions
) -> set[str]:
    """The segments whose pose direction is vertical (their static axis does not depend on the
    facing): all of them in the N-pose, the legs in the T-pose, per ``directions`` if given."""
    d0 = _static_directions(skeleton, segs, pose, (0.0, 1.0, 0.0), directions)
    return {s for s, d in d0.items() if abs(float(d @ _DOWN)) > 0.999}


def _static_directions(
    skeleton: Skeleton, segs: Sequence[str], pose: str, facing, directions
) -> dict[str, np.ndarray]:
    out = {}
    if pose not in ("n", "t"):
        raise InputError(f"expected pose in ('n', 't') (arms hanging / T-pose), got {pose!r}")
    body = _body_frame(facing)
    right = body[:, 2]
    for seg in segs:
        d = _DOWN
        if pose == "t" and (seg.startswith("upper_arm") or seg.startswith("forearm")):
            d = right if seg.endswith("_r") else -right
        if seg.startswith("foot_"):  # standing, the foot points forward (ankle -> toe)
            d = body[:, 0]
        out[seg] = d
    for seg, d in dict(directions or {}).items():
        if seg != skeleton.root_segment:
            skeleton.index(seg)
        v = np.asarray(d, dtype=float)
        if v.shape != (3,) or np.linalg.norm(v) < 1e-9:
            raise InputError(f"expected directions[{seg!r}] as a non-zero (3,) vector, got {v}")
        out[seg] = v / np.linalg.norm(v)
    return out


def static_calibration(
    skeleton: Skeleton,
    segs: Sequence[str],
    imus: dict[str, ImuStream],
    *,
    window_s: float,
    start_s: float | None,
    pose: str,
    facing,
    directions,
    heading: str,
    mounting,
    max_rate_rad_s: float,
    max_acc_std_m_s2: float,
) -> Calibration:
    """Static-pose calibration of the segments ``segs`` (arguments and Notes: :func:`calibrate`).

    ``imus`` holds the oriented IMU stream of every segment. A NumericalWarning names a segment
    farther than :data:`POSE_WARN_DEG` from the pose, and a given window that is not still.
    """
    d0 = _static_directions(skeleton, segs, pose, facing, directions)
    B = _body_frame(facing)
    thresholds = {"max_rate_rad_s": max_rate_rad_s, "max_acc_std_m_s2": max_acc_std_m_s2}
    if start_s is None:
        still = _search_still(imus, window_s, **thresholds)
    else:
        still = _check_still(imus, start_s, window_s, **thresholds)
    R_win, R_mean = window_orientations(imus, still)
    heading_deg = _common_heading(segs, R_win, R_mean) if heading == "static" else {}
    axes, resid, frames, pose_res, in_pose = {}, {}, {}, {}, {}
    mounting = dict(mounting or {})
    for s in segs:
        a = unit_direction(np.einsum("kji,j->i", R_win[s], d0[s]), f"segment {s!r}")
        axes[s] = a
        resid[s] = float(np.sqrt(np.mean(angles_deg(R_win[s] @ a, d0[s][None]) ** 2)))
        # the pose frame turned with the segment; a foot's (X along it) is the body's
        turn = (np.eye(3) if s.startswith("foot_")
                else Rotation.align_vectors(d0[s][None], _DOWN[None])[0].as_matrix())  # fmt: skip
        in_pose[s] = turn @ B  # R_world_from_segment in the pose
        frames[s] = R_mean[s].T @ in_pose[s]
        if s in mounting:
            m = unit_axis(mounting[s], f"mounting[{s!r}]")
            pose_res[s] = float(np.sqrt(np.mean(angles_deg(R_win[s] @ m, d0[s][None]) ** 2)))
    _warn_off_pose(resid, pose_res, d0, pose, still)
    return Calibration(
        axes=axes,
        method="static",
        window_s=(still.start_s, still.end_s),
        residual_deg=resid,
        align="none",
        frames=frames,
        world_heading_deg=heading_deg,
        still=still,
        pose_residual_deg=pose_res,
        pose_angles_deg={
            j: a[0] for j, a in joint_angles({s: R[None] for s, R in in_pose.items()}).items()
        },
    )


def _search_still(imus, window_s, *, max_rate_rad_s, max_acc_std_m_s2) -> StillWindow:
    """The earliest still window of every sensor; an InputError naming the stillest if none."""
    still = find_still_window(
        imus,
        window_s,
        max_rate_rad_s=max_rate_rad_s,
        max_acc_std_m_s2=max_acc_std_m_s2,
    )
    span = still.end_s - still.start_s
    if span < MIN_STILL_S:
        raise InputError(
            f"static calibration: the IMU streams share only {span:.2f} s, too short to hold a "
            f"pose (at least {MIN_STILL_S:g} s; the still window is {window_s:g} s): stillness "
            "cannot be told from a pause in a movement over less; record the subject holding "
            f"the pose for {window_s:g} s, or use functional calibration"
        )
    dt = max(
        (float(np.median(np.diff(st.t_s))) for st in imus.values() if st.t_s.size > 1), default=0.0
    )
    if span + dt < float(window_s) - 1e-9:  # (n samples span (n - 1) sample intervals)
        warnings.warn(
            f"static calibration: the recording is shorter than the still window of "
            f"{window_s:g} s; the window is the whole recording, {span:.2f} s",
            NumericalWarning,
            stacklevel=5,
        )
    if not still.still:
        raise InputError(
            f"static calibration: no still window of {window_s:g} s in the recording "
            f"(needs mean angular rate <= {max_rate_rad_s:g} rad/s and acceleration std <= "
            f"{max_acc_std_m_s2:g} m/s² on every sensor); the stillest candidate is "
            f"{still.describe()}. Record the subject holding the pose, give the window "
            "(calibration start_s), or use functional calibration"
        )
    return still


def _check_still(imus, start_s, window_s, *, max_rate_rad_s, max_acc_std_m_s2) -> StillWindow:
    """The given window's stillness; a NumericalWarning when it is not still."""
    t_any = next(iter(imus.values())).t_s
    sel0 = window_mask(t_any, start_s, window_s)
    t_w = t_any[sel0]
    span = max(float(t_w[-1] - t_w[0]), 1e-6)
    still = find_still_window(
        {s: _crop(st, float(start_s), float(start_s) + float(window_s)) for s, st in imus.items()},
        span,
        max_rate_rad_s=max_rate_rad_s,
        max_acc_std_m_s2=max_acc_std_m_s2,
        step_s=span,
    )
    if not still.still:
        warnings.warn(
            f"static calibration: the given window is not still ({still.describe()}; "
            f"thresholds {max_rate_rad_s:g} rad/s, {max_acc_std_m_s2:g} m/s²)",
            NumericalWarning,
            stacklevel=5,
        )
    return still


def window_orientations(imus, still: StillWindow):
    """The orientations of a still window, per sensor.

    Parameters
    ----------
    imus : mapping of str -> ImuStream
        Sensors with ``q_world_from_sensor``.
    still : StillWindow
        The window (its ``start_s`` and ``end_s``, s).

    Returns
    -------
    R_win, R_mean : dict of str -> ndarray
        The valid ``R_world_from_sensor`` samples in the window, shape (K, 3, 3), and their
        mean rotation (chordal, :meth:`scipy.spatial.transform.Rotation.mean`), shape (3, 3).

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        A sensor has no valid orientation sample in the window.
    """
    R_win, R_mean = {}, {}
    for s, st in imus.items():
        sel = window_mask(st.t_s, still.start_s, still.end_s - still.start_s + 1e-6)
        R = as_rotation_matrices(st.q_world_from_sensor[sel], f"IMU {s!r} orientation")
        ok = np.all(np.isfinite(R), axis=(1, 2))
        if not np.any(ok):
            raise InputError(f"IMU {s!r}: no valid orientation sample in the calibration window")
        R_win[s] = R[ok]
        R_mean[s] = Rotation.from_matrix(R[ok]).mean().as_matrix()
    return R_win, R_mean


def relative_yaw(R_ref: np.ndarray, R: np.ndarray) -> float:
    """The angle about the vertical (rad, ENU z) from ``R``'s heading to ``R_ref``'s: the
    rotation part of the horizontal block of ``R_ref Rᵀ``; additive under turns about z."""
    G = R_ref @ R.T
    return float(np.arctan2(G[1, 0] - G[0, 1], G[0, 0] + G[1, 1]))


def pose_headings(
    imus, frames, window_s: float, *, max_rate_rad_s: float, max_acc_std_m_s2: float,
    pose_yaw_rad=None,
) -> tuple[StillWindow, dict[str, float] | None]:  # fmt: skip
    """Heading offsets that bring sensors of arbitrary headings (6-D) into one world frame,
    from a still pose and the sensors' calibrated segment frames.

    In the calibration pose every segment frame (``R_world_from_sensor @ R_sensor_from_segment``)
    has the same heading; each sensor's world frame is turned about the vertical so that its
    segment frame's heading equals the first sensor's (the reference, ψ = 0).

    Parameters
    ----------
    imus : mapping of str -> ImuStream
        Orientations (``q_world_from_sensor``) of every sensor, in their own world frames.
    frames : mapping of str -> ndarray, shape (3, 3)
        ``R_sensor_from_segment`` of each sensor (a static calibration's ``frames``).
    window_s : float
        Length of the still window, s (the earliest one, :func:`find_still_window`).
    max_rate_rad_s, max_acc_std_m_s2 : float
        Stillness thresholds.
    pose_yaw_rad : mapping of str -> float, optional
        The heading of each segment frame relative to the first's in the calibration pose, as
        the calibration found it (:func:`relative_yaw`; default 0): kept, so that the frames
        relate as they did there, including a calibration whose frames did not quite agree.

    Returns
    -------
    still : StillWindow
    psi_rad : dict of str -> float, or None
        Per sensor, the rotation about the vertical (rad, ENU z) to apply to its world frame:
        ``q ← R_z(ψ) q``; None when no window is still (``still.still`` False).
    """
    still = find_still_window(
        imus, window_s, max_rate_rad_s=max_rate_rad_s, max_acc_std_m_s2=max_acc_std_m_s2
    )
    if not still.still:
        return still, None
    _, R_mean = window_orientations(imus, still)
    names = list(imus)
    seg = {s: R_mean[s] @ np.asarray(frames[s], dtype=float) for s in names}
    keep = dict(pose_yaw_rad or {})
    psi = {s: relative_yaw(seg[names[0]], seg[s]) - keep.get(s, 0.0) for s in names}
    return still, psi


def _common_heading(segs, R_win: dict, R_mean: dict) -> dict[str, float]:
    """Turn every sensor's world frame onto the first segment's heading (in place); ψ in deg."""
    heading_deg: dict[str, float] = {}
    ref = segs[0]
    for s in segs:
        psi = relative_yaw(R_mean[ref], R_mean[s])
        heading_deg[s] = float(np.degrees(psi))
        Hs = Rotation.from_rotvec([0.0, 0.0, psi]).as_matrix()
        R_win[s] = np.einsum("ij,kjl->kil", Hs, R_win[s])
        R_mean[s] = Hs @ R_mean[s]
    return heading_deg


def _warn_off_pose(resid, pose_res, d0, pose: str, still: StillWindow) -> None:
    """A NumericalWarning for each segment beyond :data:`POSE_WARN_DEG` from the pose."""
    bad = {s: v for s, v in resid.items() if v > POSE_WARN_DEG}
    bad.update({s: v for s, v in pose_res.items() if v > POSE_WARN_DEG})
    for s, v in bad.items():
        warnings.warn(
            f"static calibration: segment {s!r} is {v:.0f} deg from the assumed "
            f"{'N' if pose == 'n' else 'T'}-pose direction {np.round(d0[s], 2).tolist()} in the "
            f"window {still.start_s:.2f}-{still.end_s:.2f} s (threshold {POSE_WARN_DEG:g} deg): "
            "was the subject in the pose, and is the sensor mounted as declared?",
            NumericalWarning,
            stacklevel=4,
        )


def _crop(st, t0: float, t1: float):
    """The samples of an ImuStream in ``[t0, t1)`` (same stream type)."""
    sel = (st.t_s >= t0 - 1e-9) & (st.t_s < t1 - 1e-9)
    if np.count_nonzero(sel) < 2:
        raise InputError(
            f"IMU {st.name!r}: fewer than 2 samples in the calibration window {t0:.3f}-{t1:.3f} s"
        )
    return replace(
        st,
        t_s=st.t_s[sel],
        **{
            k: getattr(st, k)[sel]
            for k in ("q_world_from_sensor", "acc_m_s2", "gyr_rad_s", "mag")
            if getattr(st, k) is not None
        },
    )
