"""Sensor-to-segment calibration, frame alignment (Kabsch) and IMU chain positions from a Recording.

SPEC §2.1 "Axis calibration" and §2.2 "Kinect side": the segment axis ``a_i`` in each IMU frame
from (a) a static pose, or (b) a window where a reference or camera sees the joints; (c) the
rotation between the IMU world frame and the camera/reference frame (Kabsch, rotation only).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.io.recording import JointStream, Recording
from kinefuse.kinematics.forward import as_rotation_matrices, forward_kinematics
from kinefuse.kinematics.skeleton import Skeleton, _unit_axis, lengths_from_joints, window_mask
from kinefuse.kinematics.still import (
    MAX_ACC_STD_M_S2,
    MAX_RATE_RAD_S,
    StillWindow,
    find_still_window,
)
from kinefuse.orientation.resample import slerp_resample

__all__ = [
    "Calibration",
    "calibrate",
    "chain_positions",
    "heading_rotation",
    "kabsch_rotation",
    "segment_orientations",
]

#: Angle (deg) beyond which a static-pose segment gets a warning naming it.
POSE_WARN_DEG = 20.0

_DOWN = np.array([0.0, 0.0, -1.0])
_UP = np.array([0.0, 0.0, 1.0])


# ---------------------------------------------------------------------- Kabsch
def _paired(P, Q, weights):
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape:
        raise InputError(
            f"expected P and Q with the same shape (N, 3), got {P.shape} and {Q.shape}"
        )
    w = np.ones(P.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (P.shape[0],) or np.any(w < 0):
        raise InputError(f"expected weights >= 0 with shape (N,) = ({P.shape[0]},), got {w.shape}")
    ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(Q), axis=1) & np.isfinite(w) & (w > 0)
    if not np.any(ok):
        raise InputError("expected at least one finite pair of vectors in P and Q, got none")
    return P[ok], Q[ok], w[ok]


def kabsch_rotation(P, Q, weights=None) -> np.ndarray:
    """Rotation (no translation, no scale) that best maps the vectors ``P`` onto ``Q``.

    Parameters
    ----------
    P, Q : array_like, shape (N, 3)
        Paired vectors (e.g. segment directions in the camera frame and in the IMU world frame).
        Rows with NaN are ignored.
    weights : array_like, shape (N,), optional
        Non-negative weights (default 1).

    Returns
    -------
    R : ndarray, shape (3, 3)
        Proper rotation minimising ``Σ w_k ‖R p_k − q_k‖²``; ``Q ≈ P @ R.T``. Equals
        ``Rotation.align_vectors(Q, P, weights)[0].as_matrix()``.

    Notes
    -----
    Kabsch: ``H = Σ w p qᵀ = U S Vᵀ``, ``R = V diag(1, 1, det(V Uᵀ)) Uᵀ``. With vectors spanning
    fewer than two directions the rotation is not unique (a NumericalWarning is raised).
    """
    P, Q, w = _paired(P, Q, weights)
    H = (P * w[:, None]).T @ Q
    U, S, Vt = np.linalg.svd(H)
    if S[1] <= 1e-10 * max(S[0], 1e-300):
        warnings.warn(
            "kabsch_rotation: the vectors span fewer than two directions; the rotation is not unique",
            NumericalWarning,
            stacklevel=2,
        )
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def heading_rotation(P, Q, weights=None) -> np.ndarray:
    """Rotation about the vertical (z) axis only that best maps ``P`` onto ``Q``.

    Parameters
    ----------
    P, Q : array_like, shape (N, 3)
        Paired vectors in two frames that share the z (up) axis.
    weights : array_like, shape (N,), optional
        Non-negative weights.

    Returns
    -------
    R : ndarray, shape (3, 3)
        ``R_z(ψ)`` with ``ψ = atan2(Σ w (p × q)_z, Σ w (p_x q_x + p_y q_y))`` (least squares in the
        horizontal plane).
    """
    P, Q, w = _paired(P, Q, weights)
    s = np.sum(w * (P[:, 0] * Q[:, 1] - P[:, 1] * Q[:, 0]))
    c = np.sum(w * (P[:, 0] * Q[:, 0] + P[:, 1] * Q[:, 1]))
    psi = np.arctan2(s, c)
    cp, sp = np.cos(psi), np.sin(psi)
    return np.array([[cp, -sp, 0.0], [sp, cp, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------- Calibration
@dataclass(frozen=True, eq=False)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    axes : dict of str -> ndarray, shape (3,)
        Unit segment axis (proximal -> distal) in each segment's IMU frame, ``a_i``.
    lengths_m : dict of str -> float
        Segment lengths measured in the calibration window (reference/vision methods), m; empty
        for the static method.
    R_world_from_camera : ndarray, shape (3, 3), or None
        Rotation taking vectors from the joint stream's frame (camera or reference) into the IMU
        world frame; None when the frames are taken as shared (no alignment estimated).
    method : str
        ``"static"``, ``"reference"`` or ``"vision"``.
    window_s : tuple of float
        ``(start, end)`` of the calibration window, s.
    residual_deg : dict of str -> float
        RMS angle in the window between the modelled segment direction ``R_i a_i`` and the
        observed one (reference/vision) or ``d0`` (static), deg.
    align : str
        Alignment used: ``"none"``, ``"heading"`` or ``"rotation"``.
    frames : dict of str -> ndarray, shape (3, 3)
        Static and functional: ``R_sensor_from_segment`` of each segment, columns = the
        segment's ISB axes (X anterior, Y superior, Z right) in the sensor frame; used for joint
        angles (functional: only segments next to an elbow or knee).
    world_heading_deg : dict of str -> float
        Static with ``heading="static"``: rotation about the vertical that this calibration
        applies to each sensor's world frame, deg (``R_world_from_sensor <- R_z(ψ)
        R_world_from_sensor``, in :func:`chain_positions` and :func:`segment_orientations`).
    still : StillWindow or None
        Static only: the window and how still it was.
    pose_residual_deg : dict of str -> float
        Static with ``mounting``: RMS angle between the declared sensor axis and the assumed
        pose direction in the window, deg.
    hinge_residual_rad_s : dict of str -> float
        Hinge joints whose segment frames come from the measured flexion axis
        (:func:`kinefuse.kinematics.hinge.hinge_frames`): RMS residual of the joint's
        angular-rate constraint, rad/s (0 for an ideal joint).
    """

    axes: Mapping[str, np.ndarray]
    lengths_m: Mapping[str, float] = field(default_factory=dict)
    R_world_from_camera: np.ndarray | None = None
    method: str = "static"
    window_s: tuple[float, float] = (0.0, 0.0)
    residual_deg: Mapping[str, float] = field(default_factory=dict)
    align: str = "none"
    frames: Mapping[str, np.ndarray] = field(default_factory=dict)
    world_heading_deg: Mapping[str, float] = field(default_factory=dict)
    still: StillWindow | None = None
    pose_residual_deg: Mapping[str, float] = field(default_factory=dict)
    hinge_residual_rad_s: Mapping[str, float] = field(default_factory=dict)

    def heading_matrix(self, segment: str) -> np.ndarray:
        """``R_z(ψ)`` applied to ``segment``'s sensor world frame (identity if none), (3, 3)."""
        psi = np.radians(self.world_heading_deg.get(segment, 0.0))
        c, s = np.cos(psi), np.sin(psi)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def q_sensor_from_segment(self, segment: str, segment_axis="+e2") -> np.ndarray:
        """The shortest rotation taking ``segment_axis`` (segment frame) onto ``a_i`` (sensor frame).

        Only the axis is calibrated; the rotation about it is the minimal one (``wxyz``, (4,)).
        """
        if segment not in self.axes:
            raise InputError(
                f"unknown segment {segment!r}; calibrated segments are {sorted(self.axes)}"
            )
        e = _unit_axis(segment_axis, "segment_axis")
        rot = Rotation.align_vectors(self.axes[segment][None], e[None])[0]
        return rot.as_quat(scalar_first=True)

    def apply(self, skeleton: Skeleton, *, lengths: bool = True) -> Skeleton:
        """``skeleton`` with the calibrated axes (and, if ``lengths``, the measured lengths)."""
        sk = skeleton.with_axes({s: a for s, a in self.axes.items() if s in skeleton.segments})
        if lengths and self.lengths_m:
            sk = sk.with_lengths(
                {s: v for s, v in self.lengths_m.items() if s in skeleton.segments}
            )
        return sk


def _imu_orientation(recording: Recording, segment: str, purpose: str):
    if segment not in recording.imu:
        raise InputError(
            f"missing IMU for segment {segment!r} ({purpose}); expected it among the recording's IMUs "
            f"{sorted(recording.imu)}"
        )
    s = recording.imu[segment]
    if s.q_world_from_sensor is None:
        raise InputError(
            f"IMU {segment!r} has raw data but no orientation; estimate it first, e.g. "
            "kinefuse.orientation.estimate(acc, gyr, mag, rate_hz=...)"
        )
    return s


def _stream(recording: Recording, source: str) -> JointStream:
    if source not in ("reference", "vision"):
        raise InputError(f"expected source in ('reference', 'vision'), got {source!r}")
    st = getattr(recording, source)
    if st is None:
        raise InputError(
            f"the recording has no {source} joint stream (needed for {source!r} calibration or root)"
        )
    return st


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


def _static_directions(
    skeleton: Skeleton, segs: Sequence[str], pose: str, facing, directions
) -> dict[str, np.ndarray]:
    out = {}
    if pose not in ("n", "t"):
        raise InputError(f"expected pose in ('n', 't') (arms hanging / T-pose), got {pose!r}")
    right = _body_frame(facing)[:, 2]
    for seg in segs:
        d = _DOWN
        if pose == "t" and (seg.startswith("upper_arm") or seg.startswith("forearm")):
            d = right if seg.endswith("_r") else -right
        out[seg] = d
    for seg, d in dict(directions or {}).items():
        if seg != skeleton.root_segment:
            skeleton.index(seg)
        v = np.asarray(d, dtype=float)
        if v.shape != (3,) or np.linalg.norm(v) < 1e-9:
            raise InputError(f"expected directions[{seg!r}] as a non-zero (3,) vector, got {v}")
        out[seg] = v / np.linalg.norm(v)
    return out


def _static(
    recording,
    skeleton,
    segs,
    imus,
    *,
    window_s,
    start_s,
    pose,
    facing,
    directions,
    heading,
    mounting,
    max_rate_rad_s,
    max_acc_std_m_s2,
) -> Calibration:
    """Static-pose calibration (see :func:`calibrate`)."""
    d0 = _static_directions(skeleton, segs, pose, facing, directions)
    B = _body_frame(facing)
    if start_s is None:
        still = find_still_window(
            imus,
            window_s,
            max_rate_rad_s=max_rate_rad_s,
            max_acc_std_m_s2=max_acc_std_m_s2,
        )
        if not still.still:
            raise InputError(
                f"static calibration: no still window of {window_s:g} s in the recording "
                f"(needs mean angular rate <= {max_rate_rad_s:g} rad/s and acceleration std <= "
                f"{max_acc_std_m_s2:g} m/s² on every sensor); the stillest candidate is "
                f"{still.describe()}. Record the subject holding the pose, give the window "
                "(calibration start_s), or use functional calibration"
            )
    else:
        t_any = next(iter(imus.values())).t_s
        sel0 = window_mask(t_any, start_s, window_s)
        t_w = t_any[sel0]
        span = max(float(t_w[-1] - t_w[0]), 1e-6)
        still = find_still_window(
            {
                s: _crop(st, float(start_s), float(start_s) + float(window_s))
                for s, st in imus.items()
            },
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
                stacklevel=3,
            )
    R_win, R_mean = {}, {}
    for s, st in imus.items():
        sel = window_mask(st.t_s, still.start_s, still.end_s - still.start_s + 1e-6)
        R = as_rotation_matrices(st.q_world_from_sensor[sel], f"IMU {s!r} orientation")
        ok = np.all(np.isfinite(R), axis=(1, 2))
        if not np.any(ok):
            raise InputError(f"IMU {s!r}: no valid orientation sample in the calibration window")
        R_win[s] = R[ok]
        R_mean[s] = Rotation.from_matrix(R[ok]).mean().as_matrix()
    heading_deg: dict[str, float] = {}
    if heading == "static":
        ref = segs[0]
        for s in segs:
            G = R_mean[ref] @ R_mean[s].T
            psi = float(np.arctan2(G[1, 0] - G[0, 1], G[0, 0] + G[1, 1]))
            heading_deg[s] = float(np.degrees(psi))
            Hs = Rotation.from_rotvec([0.0, 0.0, psi]).as_matrix()
            R_win[s] = np.einsum("ij,kjl->kil", Hs, R_win[s])
            R_mean[s] = Hs @ R_mean[s]
    axes, resid, frames, pose_res = {}, {}, {}, {}
    mounting = dict(mounting or {})
    for s in segs:
        a = _normalize(np.einsum("kji,j->i", R_win[s], d0[s]), f"segment {s!r}")
        axes[s] = a
        resid[s] = float(np.sqrt(np.mean(_angles_deg(R_win[s] @ a, d0[s][None]) ** 2)))
        turn = Rotation.align_vectors(d0[s][None], _DOWN[None])[0].as_matrix()
        frames[s] = R_mean[s].T @ (turn @ B)
        if s in mounting:
            m = _unit_axis(mounting[s], f"mounting[{s!r}]")
            pose_res[s] = float(np.sqrt(np.mean(_angles_deg(R_win[s] @ m, d0[s][None]) ** 2)))
    bad = {s: v for s, v in resid.items() if v > POSE_WARN_DEG}
    bad.update({s: v for s, v in pose_res.items() if v > POSE_WARN_DEG})
    for s, v in bad.items():
        warnings.warn(
            f"static calibration: segment {s!r} is {v:.0f} deg from the assumed "
            f"{'N' if pose == 'n' else 'T'}-pose direction {np.round(d0[s], 2).tolist()} in the "
            f"window {still.start_s:.2f}-{still.end_s:.2f} s (threshold {POSE_WARN_DEG:g} deg): "
            "was the subject in the pose, and is the sensor mounted as declared?",
            NumericalWarning,
            stacklevel=3,
        )
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
    )


def _crop(st, t0: float, t1: float):
    """The samples of an ImuStream in ``[t0, t1)`` (same stream type)."""
    from dataclasses import replace

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


def _normalize(v: np.ndarray, where: str) -> np.ndarray:
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-9:
        raise InputError(
            f"{where}: the calibration window gives no usable direction (sum of directions ≈ 0)"
        )
    return v / n


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.clip(
        np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)),
        -1.0,
        1.0,
    )
    return np.degrees(np.arccos(c))


def _solve_alignment(W: dict, U: dict, align: str):
    """Alternating least squares for ``R_world_from_camera`` and the axes, multi-start.

    W[s] : (K, 3, 3) world-from-sensor; U[s] : (K, 3) unit directions in the camera frame.
    """

    def axes_given(Rc):
        return {
            s: _normalize(np.einsum("kji,kj->i", W[s], U[s] @ Rc.T), f"segment {s!r}") for s in W
        }

    def cost(Rc, A):
        return sum(
            float(np.sum((U[s] @ Rc.T - np.einsum("kij,j->ki", W[s], A[s])) ** 2)) for s in W
        )

    def rot_given(A):
        P = np.concatenate([U[s] for s in W])
        Q = np.concatenate([np.einsum("kij,j->ki", W[s], A[s]) for s in W])
        return heading_rotation(P, Q) if align == "heading" else kabsch_rotation(P, Q)

    if align == "heading":
        starts = [Rotation.from_rotvec([0, 0, a]).as_matrix() for a in np.arange(8) * np.pi / 4]
    else:
        starts = list(Rotation.create_group("O").as_matrix())

    def descend(Rc, A, c_old, n_iter):
        for _ in range(n_iter):
            Rc = rot_given(A)
            A = axes_given(Rc)
            c = cost(Rc, A)
            if c_old - c <= 1e-12 * max(c_old, 1.0):
                return c, Rc, A
            c_old = c
        return c_old, Rc, A

    # a few sweeps from every start, then the best one to convergence
    best = None
    for Rc in starts:
        A = axes_given(Rc)
        cand = descend(Rc, A, cost(Rc, A), 20)
        if best is None or cand[0] < best[0] - 1e-12:
            best = cand
    best = descend(best[1], best[2], best[0], 1000)
    return best[1], best[2]


def _alignment_sensitivity(W: dict, U: dict, Rc: np.ndarray, align: str) -> list[str]:
    """World axes about which a 5° change of ``Rc`` hides in the noise [J].

    A 5° rotation of ``Rc`` (axes re-fitted) must add, in quadrature, more than
    ``max(0.5°, RMS misfit)`` to the RMS misfit; otherwise that axis is reported.
    """

    def misfit(R):
        err = []
        for s in W:
            V = U[s] @ R.T
            a = _normalize(np.einsum("kji,kj->i", W[s], V), f"segment {s!r}")
            err.append(_angles_deg(np.einsum("kij,j->ki", W[s], a), V))
        return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))

    base = misfit(Rc)
    weak = []
    for name, e in (("z", (0, 0, 1)), ("x", (1, 0, 0)), ("y", (0, 1, 0)))[
        : 1 if align == "heading" else 3
    ]:
        R = Rotation.from_rotvec(np.radians(5.0) * np.asarray(e, dtype=float)).as_matrix() @ Rc
        if np.sqrt(max(misfit(R) ** 2 - base**2, 0.0)) < max(0.5, base):
            weak.append(name)
    return weak


def calibrate(
    recording: Recording,
    skeleton: Skeleton,
    method: str = "static",
    *,
    window_s: float = 1.0,
    start_s: float | None = None,
    pose: str = "n",
    facing=(0.0, 1.0, 0.0),
    directions: Mapping[str, object] | None = None,
    align: str = "auto",
    segments: Sequence[str] | None = None,
    heading: str = "none",
    mounting: Mapping[str, object] | None = None,
    max_rate_rad_s: float = MAX_RATE_RAD_S,
    max_acc_std_m_s2: float = MAX_ACC_STD_M_S2,
    flexion_axes: str = "auto",
) -> Calibration:
    """Calibrate the segment axis ``a_i`` in each IMU frame (and the camera/reference alignment).

    Parameters
    ----------
    recording : Recording
        IMU orientations per segment (``q_world_from_sensor``), and for ``"reference"`` /
        ``"vision"`` the joint stream with the skeleton's joint names.
    skeleton : Skeleton
        Defines the segments and their proximal/distal joints.
    method : {"static", "functional", "reference", "vision"}
        ``"static"``: the subject holds a known pose in the window (SPEC §2.1). ``"functional"``:
        joint centres from movement, no still pose and no optical data
        (:func:`kinefuse.kinematics.functional.functional_calibration`, with its defaults; it
        returns a :class:`~kinefuse.kinematics.functional.FunctionalCalibration` carrying the
        excitation, residual, heading and hinge axis of every joint). ``"reference"`` /
        ``"vision"``: least squares against the joint directions seen by ``recording.reference`` /
        ``recording.vision`` in the window.
    window_s : float
        Window length, s (default 1 s; ``"functional"`` uses the whole recording unless
        ``start_s`` is given).
    start_s : float, optional
        Window start, s. Default: ``"static"`` searches the earliest window in which every
        sensor holds still (:func:`kinefuse.kinematics.find_still_window`: mean angular rate
        <= ``max_rate_rad_s`` and acceleration standard deviation <= ``max_acc_std_m_s2``;
        without a gyroscope the orientation change rate is used); the other methods use the
        first sample.
    pose : {"n", "t"}
        Static pose: ``"n"`` = arms hanging, every segment points down ``d0 = [0, 0, −1]``;
        ``"t"`` = T-pose: arms point horizontally sideways, legs down.
    facing : array_like, shape (3,)
        T-pose only: the subject's horizontal facing direction in the IMU world frame (default
        north ``[0, 1, 0]``); the right arm points along ``facing × up``.
    directions : mapping, optional
        Static only: explicit ``d0`` per segment (world frame), overriding the pose.
    align : {"auto", "none", "heading", "rotation"}
        Reference/vision only: how the joint stream's frame relates to the IMU world frame.
        ``"none"``: shared frame. ``"heading"``: differs by a rotation about the vertical.
        ``"rotation"``: any rotation (camera frames). ``"auto"``: ``"none"`` when every used IMU
        stream's ``frame`` equals the joint stream's ``frame``, else ``"rotation"``.
    segments : sequence of str, optional
        Calibrate only these skeleton segments (default: all); ``skeleton.root_segment``
        (e.g. ``"pelvis"``) may be included for static calibration.
    heading : {"none", "static"}
        Static only: ``"static"`` brings the sensors' world frames into one heading, assuming
        every sensor faces the same way on the body in the still pose (the heading of each
        sensor's mean orientation is rotated onto that of the first segment's). Use it for 6-D
        orientations (no magnetometer), whose headings are arbitrary per sensor; ``"none"``
        (default) keeps the frames (9-D / magnetometer-referenced data share north).
    mounting : mapping, optional
        The sensor axis declared to run along each segment (proximal -> distal), e.g.
        ``{"thigh_l": "+e1"}``. Static: its angle to the assumed pose direction is reported as
        ``pose_residual_deg`` (a NumericalWarning names segments beyond 20 deg). Functional: the
        axis of a last segment without a sensor beyond it (``declared_axes``).
    max_rate_rad_s, max_acc_std_m_s2 : float
        Static only: stillness thresholds of the window search (and of the check of a given
        window).
    flexion_axes : {"auto", "movement", "pose"}
        Static only: where the segment frames of hinge joints (elbows, knees) get their flexion
        axis. ``"pose"``: from the declared ``facing`` (Notes). ``"movement"``: from the
        recording's relative rotation about the hinge, the pose giving only the long axis, and,
        with ``heading="static"``, the distal sensor's heading refined from the hinge
        (:func:`kinefuse.kinematics.hinge.hinge_frames`); the flexion sign is fixed by anatomy
        (the larger excursion from the pose is flexion). ``"auto"`` (default): ``"movement"``
        when ``heading="static"`` (6-D orientations: the facing is not measured), else
        ``"pose"``.

    Returns
    -------
    Calibration

    Notes
    -----
    Static (SPEC §2.1): ``a_i = normalise(Σ_k R_i(k)ᵀ d0)`` over the window (one sample: paper's
    ``a_i = R_i(k0)ᵀ d0``). The full segment frame (ISB, Wu et al. 2002/2005: X anterior,
    Y superior, Z right) is ``R_sensor_from_segment = R̄_iᵀ B_i`` with ``R̄_i`` the mean
    orientation in the window and ``B_i`` the segment frame of the pose in the world: the body
    frame ``[facing, up, facing × up]`` (N-pose), turned by the shortest rotation from down onto
    ``d0`` for segments that do not hang (T-pose arms). ``residual_deg`` is the RMS angle of
    ``R_i(k) a_i`` to ``d0`` in the window (how still the pose was held). A segment beyond 20 deg
    (in ``residual_deg`` or ``pose_residual_deg``) raises a NumericalWarning naming it. No
    still window (or a given window that is not still) raises an InputError naming the
    stillest candidate and its motion level; a given window that is not still, a
    NumericalWarning.

    Reference/vision: with ``u_i(k)`` the unit vector from the proximal to the distal joint in the
    stream's frame and ``R_c`` = ``R_world_from_camera``, minimise
    ``Σ_k ‖R_i(k) a − R_c u_i(k)‖²`` over unit ``a``: ``a_i = normalise(Σ_k R_i(k)ᵀ R_c u_i(k))``.
    With ``align="none"`` ``R_c = I``. Otherwise ``R_c`` and all ``a_i`` are estimated jointly by
    alternating least squares (``a_i`` as above; ``R_c`` by Kabsch, or its heading-only variant,
    of the stacked ``u_i(k)`` onto ``R_i(k) a_i``), started from the 24 axis-aligned rotations
    (8 headings for ``"heading"``) and keeping the lowest cost. The alignment is only determined
    when the segments rotate about several axes during the window: rotations of ``R_c`` about an
    axis all segments only rotate about are absorbed by the ``a_i``. A NumericalWarning is raised
    when a 5° change of ``R_c`` about a world axis adds less than ``max(0.5°, RMS misfit)`` (in
    quadrature) to the RMS misfit [J]. Segment lengths = median joint distance in the window.

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        Unknown method or segment, a segment without IMU or orientation, joints missing from the
        stream, an empty window.
    """
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    if not isinstance(skeleton, Skeleton):
        raise InputError(f"expected skeleton as a Skeleton, got {type(skeleton).__name__}")
    if method not in ("static", "functional", "reference", "vision"):
        raise InputError(
            f"unknown calibration method {method!r}; expected 'static', 'functional', 'reference' "
            "or 'vision'"
        )
    if method == "functional":
        from kinefuse.kinematics.functional import functional_calibration

        # movement calibration uses the whole recording unless a window start is given
        return functional_calibration(
            recording,
            skeleton,
            start_s=start_s,
            window_s=None if start_s is None else window_s,
            segments=segments,
            declared_axes=mounting,
        )
    if heading not in ("none", "static"):
        raise InputError(f"expected heading in ('none', 'static'), got {heading!r}")
    if flexion_axes not in ("auto", "movement", "pose"):
        raise InputError(
            f"expected flexion_axes in ('auto', 'movement', 'pose'), got {flexion_axes!r}"
        )
    if align not in ("auto", "none", "heading", "rotation"):
        raise InputError(
            f"expected align in ('auto', 'none', 'heading', 'rotation'), got {align!r}"
        )
    segs = list(skeleton.segments) if segments is None else list(segments)
    for s in segs:
        if not (method == "static" and s == skeleton.root_segment):
            skeleton.index(s)
    imus = {s: _imu_orientation(recording, s, "calibration") for s in segs}

    if method == "static":
        cal = _static(
            recording,
            skeleton,
            segs,
            imus,
            window_s=window_s,
            start_s=start_s,
            pose=pose,
            facing=facing,
            directions=directions,
            heading=heading,
            mounting=mounting,
            max_rate_rad_s=max_rate_rad_s,
            max_acc_std_m_s2=max_acc_std_m_s2,
        )
        if flexion_axes == "auto":
            flexion_axes = "movement" if heading == "static" else "pose"
        if flexion_axes == "movement":
            from kinefuse.kinematics.hinge import hinge_frames

            cal = hinge_frames(recording, cal, refine_heading=heading == "static")
        return cal

    stream = _stream(recording, method)
    sel = window_mask(stream.t_s, start_s, window_s)
    t = stream.t_s[sel]
    W, U = {}, {}
    for s in segs:
        i = skeleton.index(s)
        prox, dist = skeleton.proximal[i], skeleton.distal[i]
        lack = [j for j in (prox, dist) if j not in stream.joints]
        if lack:
            raise InputError(
                f"segment {s!r}: expected joints {lack} in the {method} stream, got {list(stream.joints)}"
            )
        d = stream.position(dist)[sel] - stream.position(prox)[sel]
        q = slerp_resample(imus[s].t_s, imus[s].q_world_from_sensor, t)
        R = as_rotation_matrices(q, f"IMU {s!r} orientation")
        n = np.linalg.norm(d, axis=1)
        ok = np.isfinite(n) & (n > 1e-6) & np.all(np.isfinite(R), axis=(1, 2))
        if not np.any(ok):
            raise InputError(
                f"segment {s!r}: no sample in the calibration window with both joints and orientation"
            )
        W[s] = R[ok]
        U[s] = d[ok] / n[ok, None]
    if align == "auto":
        frames = {imus[s].frame for s in segs}
        align = "none" if frames == {stream.frame} else "rotation"
    if align == "none":
        Rc = None
        axes = {s: _normalize(np.einsum("kji,kj->i", W[s], U[s]), f"segment {s!r}") for s in segs}
    else:
        Rc, axes = _solve_alignment(W, U, align)
        weak = _alignment_sensitivity(W, U, Rc, align)
        if weak:
            warnings.warn(
                f"calibrate: the {align} alignment between the IMU world and the {method} frame is poorly "
                f"determined by this window (a 5 deg change about world {weak} stays within the misfit noise); "
                "use a window with rotations about several axes, or align='none' if the frames are shared",
                NumericalWarning,
                stacklevel=2,
            )
    Rc_eff = np.eye(3) if Rc is None else Rc
    resid = {
        s: float(
            np.sqrt(
                np.mean(_angles_deg(np.einsum("kij,j->ki", W[s], axes[s]), U[s] @ Rc_eff.T) ** 2)
            )
        )
        for s in segs
    }
    sub = [
        (s, skeleton.proximal[skeleton.index(s)], skeleton.distal[skeleton.index(s)]) for s in segs
    ]
    lengths = lengths_from_joints(stream, sub, start_s=start_s, window_s=window_s)
    return Calibration(
        axes=axes,
        lengths_m=lengths,
        R_world_from_camera=Rc,
        method=method,
        window_s=(float(t[0]), float(t[-1])),
        residual_deg=resid,
        align=align,
    )


# ---------------------------------------------------------------------- chain positions
def chain_positions(
    recording: Recording,
    skeleton: Skeleton,
    calibration: Calibration | None = None,
    *,
    root: str | Sequence[str] | Mapping[str, object] | None = None,
    source: str = "reference",
    t_s=None,
    use_calibrated_lengths: bool = True,
) -> JointStream:
    """Joint positions of the IMU chain (SPEC §2.1/§2.2) for a recording.

    Parameters
    ----------
    recording : Recording
        IMU orientations per segment; the ``source`` joint stream when roots come from it.
    skeleton : Skeleton
        Topology, lengths and default axes.
    calibration : Calibration, optional
        Calibrated axes (override the skeleton's), measured lengths (if
        ``use_calibrated_lengths``) and the camera/reference alignment.
    root : str, sequence of str, mapping, optional
        Root joint positions. Names are taken from the ``source`` joint stream (the root segment
        carries no sensor: paper A measures the shoulder; for Neura the hip centres come from
        Vicon). A mapping gives arrays ``(T, 3)`` on the timeline ``t_s``. Default: the proximal
        joints of the parentless segments if the stream has them all, else ``skeleton.root``.
    source : {"reference", "vision"}
        Joint stream for named roots, and the output timeline and frame.
    t_s : array_like, shape (T,), optional
        Timeline for mapping roots (default: the source stream's, else the first segment IMU's).
    use_calibrated_lengths : bool
        Use the lengths measured during calibration where available.

    Returns
    -------
    JointStream
        On the root's timeline (IMU orientations SLERP-resampled to it where the times differ),
        in the root stream's frame (``R_world_from_camera`` applied when calibrated), joints = the
        roots and every joint the chain computes; ``available`` False where an input was missing.
    """
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    if calibration is not None:
        skeleton = calibration.apply(skeleton, lengths=use_calibrated_lengths)
    stream = getattr(recording, source, None) if source in ("reference", "vision") else None
    if source not in ("reference", "vision"):
        raise InputError(f"expected source in ('reference', 'vision'), got {source!r}")
    frame = "ENU"
    if isinstance(root, Mapping):
        if t_s is not None:
            t = np.asarray(t_s, dtype=float)
        elif stream is not None:
            t = stream.t_s
        else:
            t = _imu_orientation(recording, skeleton.segments[0], "timeline").t_s
        roots = {}
        for j, v in root.items():
            a = np.asarray(v, dtype=float)
            if a.shape != (t.size, 3):
                raise InputError(
                    f"expected root {j!r} with shape (T, 3) = ({t.size}, 3), got {a.shape}"
                )
            roots[j] = a
        if stream is not None and t_s is None:
            frame = stream.frame
    else:
        stream = _stream(recording, source)
        if root is None:
            starts = [skeleton.proximal[i] for i, p in enumerate(skeleton.parents) if p == -1]
            names = (
                list(dict.fromkeys(starts))
                if all(j in stream.joints for j in starts)
                else [skeleton.root]
            )
        else:
            names = [root] if isinstance(root, str) else list(root)
        lack = [j for j in names if j not in stream.joints]
        if lack:
            raise InputError(
                f"root joint(s) {lack} not in the {source} stream; it has {list(stream.joints)}"
            )
        t = stream.t_s
        roots = {j: stream.position(j) for j in names}
        frame = stream.frame
    Rc = None if calibration is None else calibration.R_world_from_camera
    needed = list(skeleton.segments)
    if skeleton.root_segment is not None and any(j not in roots for j in skeleton.offsets_m):
        needed.append(skeleton.root_segment)
    ori = {}
    for s in needed:
        st = _imu_orientation(recording, s, "chain")
        R = as_rotation_matrices(
            slerp_resample(st.t_s, st.q_world_from_sensor, t), f"IMU {s!r} orientation"
        )
        if calibration is not None and s in calibration.world_heading_deg:
            R = np.einsum("ij,kjl->kil", calibration.heading_matrix(s), R)
        ori[s] = R if Rc is None else np.einsum("ji,kjl->kil", Rc, R)  # camera_from_sensor = Rcᵀ R
    pos = forward_kinematics(skeleton, ori, roots)
    names = [j for j in skeleton.joints if j in pos] + [j for j in pos if j not in skeleton.joints]
    P = np.stack([pos[j] for j in names], axis=1)
    return JointStream(t_s=t, position_m=P, joints=tuple(names), frame=frame)


def segment_orientations(
    recording: Recording,
    calibration: Calibration,
    t_s,
    segments: Sequence[str] | None = None,
) -> dict[str, np.ndarray]:
    """``R_world_from_segment`` (ISB segment frames) of calibrated segments on a timeline.

    Parameters
    ----------
    recording : Recording
        IMU orientations per segment.
    calibration : Calibration
        With ``frames`` (static calibration); its heading corrections are applied.
    t_s : array_like, shape (T,)
        Timeline, s (orientations SLERP-resampled to it).
    segments : sequence of str, optional
        Default: every segment of ``calibration.frames``.

    Returns
    -------
    dict of str -> ndarray, shape (T, 3, 3)
        ``R_z(ψ_i) R_world_from_sensor(t) R_sensor_from_segment``; NaN where the IMU has no
        sample.
    """
    if not calibration.frames:
        raise InputError(
            f"{calibration.method!r} calibration gives segment axes only, not segment frames; "
            "joint angles need a static (or functional) calibration"
        )
    t = np.asarray(t_s, dtype=float)
    out = {}
    for s in calibration.frames if segments is None else segments:
        if s not in calibration.frames:
            raise InputError(
                f"segment {s!r} has no calibrated frame; calibrated: {sorted(calibration.frames)}"
            )
        st = _imu_orientation(recording, s, "segment orientation")
        R = as_rotation_matrices(
            slerp_resample(st.t_s, st.q_world_from_sensor, t), f"IMU {s!r} orientation"
        )
        out[s] = np.einsum(
            "ij,kjl,lm->kim", calibration.heading_matrix(s), R, calibration.frames[s]
        )
    return out
