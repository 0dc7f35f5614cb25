"""Segment frames of hinge joints (elbows, knees) from movement, not from an assumed facing.

A static pose gives each segment's long axis in its sensor frame (the vertical), but not the
direction the subject faced: with 6-D orientations (no magnetometer) every sensor's heading is
arbitrary, so an anterior axis taken from a declared facing is a guess, and a wrong guess puts
the flexion axis anywhere in the horizontal plane. For elbows and knees the flexion axis can be
measured instead, from the two adjacent sensors' orientations alone (no hand or foot sensor):
the relative angular velocity of a flexion (axis ``j1`` fixed in the proximal segment) /
pronation (the distal long axis ``j2``) joint lies in ``span(j1, j2)`` (Laidig, Müller & Seel
2017 for the elbow; a pure hinge such as the knee is the special case without pronation).
Each segment frame then is

- ``Y`` (superior) = minus the calibrated segment axis (proximal -> distal), from the pose,
- ``Z`` (right, the ISB flexion axis) = the flexion axis, made perpendicular to ``Y``: in the
  proximal segment the fitted ``j1``; in the distal one ``j1`` carried into the distal sensor in
  the pose (so that the pose is zero flexion, adduction and rotation),
- ``X`` (anterior) = ``Y × Z``.

Sign rule (anatomy): the axis's sign is not observable from the motion; a hinge's range is
mostly flexion (elbow 0...150°, knee 0...140°, hyperextension a few degrees), so the sign is
the one for which the larger excursion from the pose (99th vs minus the 1st percentile) is
flexion, i.e. flexion is positive when the distal segment moves towards the proximal one's
anterior side.

Heading: where the sensors' headings are not shared (6-D), the distal sensor's heading relative
to the proximal one is a third unknown of the same fit, held by a weak prior
(:data:`HEADING_PRIOR`) at the static pose's estimate where the motion leaves it free (a
hinge flexed with the proximal segment still does not determine it).

Assumptions and failure modes: the pose has both segments along the vertical with the elbow or
knee extended (its flexion becomes the zero; an N-pose held with the elbow bent 10° reads full
extension as −10°); the joint flexes enough during the recording (RMS flexion rate at least
:data:`MIN_HINGE_RATE_RAD_S`, else a warning and the pose frames); a slowly drifting relative
heading (6-D fusion over minutes) is taken as constant. A fitted axis tilted more than
:data:`MAX_AXIS_TILT_DEG` from perpendicular to the proximal long axis is fitted again held
perpendicular (the anatomy of elbows and knees), and that refit is used unless it fits the
movement much worse (:data:`PERPENDICULAR_REFIT_MAX_RATIO`: then the pose is wrong, and the
pose frames are kept); a warning either way.

References
----------
D. Laidig, P. Müller, T. Seel, "Automatic anatomical calibration for IMU-based elbow angle
measurement in disturbed magnetic fields", Current Directions in Biomedical Engineering
3(2):167-170, 2017.
T. Seel, J. Raisch, T. Schauer, "IMU-based joint angle measurement for gait analysis", Sensors
14(4):6891-6909, 2014.
G. Wu et al., ISB recommendations, J. Biomech. 35 (2002), 38 (2005): segment frames.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import NumericalWarning
from kinefuse.io.recording import Recording
from kinefuse.kinematics.angles import JOINTS, joint_angles
from kinefuse.kinematics.calibration_result import Calibration, oriented_imu
from kinefuse.kinematics.forward import as_rotation_matrices, rotation_z
from kinefuse.kinematics.skeleton import window_mask
from kinefuse.orientation.resample import slerp_resample

__all__ = [
    "FACING_SPREAD_DEG",
    "HEADING_PRIOR",
    "HINGES",
    "MAX_AXIS_TILT_DEG",
    "MIN_HINGE_RATE_RAD_S",
    "OPPOSITE_DEG",
    "PERPENDICULAR_REFIT_MAX_RATIO",
    "ROBUST_SCALE_FLOOR",
    "foot_headings",
    "hinge_facing",
    "hinge_frames",
    "limb_headings",
    "limb_segments",
    "opposite_hinges_advice",
    "pose_anterior",
    "segment_frame",
]

#: Joints treated as hinges for their segment frames.
HINGES = tuple(j for j in JOINTS if j.startswith(("elbow", "knee")))

#: Least RMS relative angular rate about the hinge axis, rad/s: below it the axis is not
#: determined by the data (a limb held still) and the pose frames are kept with a warning.
MIN_HINGE_RATE_RAD_S = 0.2

#: Weight of the prior holding the distal heading at the pose's (see :func:`hinge_frames`).
HEADING_PRIOR = 0.01

#: Least scale of the hinge fit's robust (Cauchy) refinement, rad/s (its scale is the
#: least-squares residuals' 1.4826 MAD; the floor keeps noise-free data well posed).
ROBUST_SCALE_FLOOR = 0.01


def segment_frame(axis, hinge) -> np.ndarray:
    """ISB segment frame from a long axis and a flexion axis, both in the sensor frame.

    Parameters
    ----------
    axis : array_like, shape (3,)
        Segment axis, proximal -> distal.
    hinge : array_like, shape (3,)
        Flexion axis (not parallel to ``axis``).

    Returns
    -------
    ndarray, shape (3, 3)
        ``R_sensor_from_segment``: columns ``X = Y × Z``, ``Y = −axis``, ``Z`` = ``hinge`` made
        perpendicular to ``Y`` (unit vectors).
    """
    axis = np.asarray(axis, dtype=float)
    hinge = np.asarray(hinge, dtype=float)
    y = -axis / np.linalg.norm(axis)
    z = hinge - np.dot(hinge, y) * y
    z = z / np.linalg.norm(z)
    return np.stack([np.cross(y, z), y, z], axis=1)


def _world_rate(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-frame angular velocity of orientations ``R`` (K, 3, 3) on times ``t``, rad/s."""
    dR = np.einsum("kij,klj->kil", R[1:], R[:-1])  # R(k+1) R(k)ᵀ
    rv = Rotation.from_matrix(dR).as_rotvec() / np.diff(t)[:, None]
    w = np.empty((R.shape[0], 3))
    w[:-1] = rv
    w[-1] = rv[-1]
    return w


def _cross(a, b):
    """Row-wise cross product of ``(3, K)`` arrays (``np.cross`` costs more than it computes)."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _rate_constraint(u1, u2, u3, b_world, wA, wB, w_prior: float, refine_heading: bool):
    """Residual and analytic Jacobian of :func:`_fit_flexion_axis`'s rate constraint.

    ``x = (azimuth, elevation, ψ)``; ``u1, u2, u3`` (K, 3): A's frame vectors ``e1, e2, a1`` in
    the world, so the axis in the world is ``cos x1 (cos x0 u1 + sin x0 u2) + sin x1 u3``;
    ``b_world``, ``wB`` (K, 3) are turned by ``ψ`` about z. Rows: ``(wB(ψ) − wA) · n̂`` with
    ``n = u × b(ψ)``, then the heading prior ``w_prior ψ``. The Jacobian is exact (tested
    against finite differences); it replaces scipy's finite differences, about 4x fewer
    residual evaluations.
    """
    u1, u2, u3, b_world, wA, wB = (np.ascontiguousarray(v.T) for v in (u1, u2, u3, b_world, wA, wB))
    K = u1.shape[1]
    last = {}

    def parts(x):  # the Jacobian is asked at the point just evaluated: computed once
        if last.get("x") is not None and np.array_equal(last["x"], x):
            return last["parts"]
        c0, s0, c1, s1 = np.cos(x[0]), np.sin(x[0]), np.cos(x[1]), np.sin(x[1])
        psi = x[2] if refine_heading else 0.0
        c, s = np.cos(psi), np.sin(psi)
        b = np.stack([c * b_world[0] - s * b_world[1], s * b_world[0] + c * b_world[1], b_world[2]])
        w = np.stack([c * wB[0] - s * wB[1], s * wB[0] + c * wB[1], wB[2]])
        u = c1 * (c0 * u1 + s0 * u2) + s1 * u3
        n = _cross(u, b)
        norm = np.sqrt(np.einsum("ik,ik->k", n, n))
        clamped = norm < 1e-9
        norm = np.maximum(norm, 1e-9)
        out = (c0, s0, c1, s1), u, b, w, w - wA, n / norm, norm, clamped
        last["x"], last["parts"] = np.array(x, dtype=float), out
        return out

    def res(x):
        _, _, _, _, d, nh, _, _ = parts(x)
        return np.append(np.einsum("ik,ik->k", d, nh), w_prior * x[2])

    def jac(x):
        (c0, s0, c1, s1), u, b, w, d, nh, norm, clamped = parts(x)

        def d_rate(dn):  # d · (derivative of n / |n|; of n / 1e-9 where the norm is clamped)
            along = np.where(clamped, 0.0, np.einsum("ik,ik->k", nh, dn))
            return (np.einsum("ik,ik->k", d, dn) - np.einsum("ik,ik->k", d, nh) * along) / norm

        J = np.zeros((K + 1, 3))
        J[:K, 0] = d_rate(_cross(c1 * (-s0 * u1 + c0 * u2), b))
        J[:K, 1] = d_rate(_cross(-s1 * (c0 * u1 + s0 * u2) + c1 * u3, b))
        if refine_heading:  # d/dψ of R_z(ψ) v is e_z × R_z(ψ) v
            zero = np.zeros(K)
            db, dw = np.stack([-b[1], b[0], zero]), np.stack([-w[1], w[0], zero])
            J[:K, 2] = np.einsum("ik,ik->k", dw, nh) + d_rate(_cross(u, db))
        J[K, 2] = w_prior
        return J

    return res, jac


def _fit_flexion_axis(RA, RB, wA, wB, axis_a, axis_b, refine_heading: bool, perpendicular=False):
    """Flexion axis in A's frame and the distal heading change, from the 2-DoF elbow model.

    The relative angular velocity of a flexion (axis ``j1`` fixed in A) / pronation (axis
    ``j2`` = B's long axis) joint lies in ``span(R_A j1, R_B j2)``, so its component along their
    unit normal vanishes (Laidig, Müller & Seel 2017; for a pure hinge too). Least squares over
    ``j1`` (azimuth and elevation about A's long axis) and, if ``refine_heading``, the heading
    ``ψ`` applied to B's world frame; the best of four starting azimuths (times four headings),
    each refined with a Cauchy loss on the least-squares residuals' scale (1.4826 MAD, at
    least :data:`ROBUST_SCALE_FLOOR`): outliers such as foot strikes weigh less. Returns
    ``(j1, ψ, RMS residual rad/s)``. ``perpendicular``: ``j1`` held perpendicular to A's long
    axis (the elevation fixed at zero; the anatomical prior of :func:`hinge_frames`'s refit).
    """
    a1 = -axis_a / np.linalg.norm(axis_a)
    a2 = -axis_b / np.linalg.norm(axis_b)
    e1 = np.cross(a1, [1.0, 0.0, 0.0] if abs(a1[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a1, e1)

    def j1_of(x):  # azimuth about the proximal long axis, elevation from its normal plane
        return np.cos(x[1]) * (np.cos(x[0]) * e1 + np.sin(x[0]) * e2) + np.sin(x[1]) * a1

    # weak prior keeping the heading at the pose's where the motion leaves it free (a hinge
    # moved about its axis only): 1 rad costs a 1 % RMS relative-rate misfit per sample
    w_prior = HEADING_PRIOR * np.sqrt(RA.shape[0]) * float(np.sqrt(np.mean((wB - wA) ** 2)))
    res, jac = _rate_constraint(RA @ e1, RA @ e2, RA @ a1, RB @ a2, wA, wB, w_prior, refine_heading)
    if perpendicular:  # the same problem in (azimuth, heading) with the elevation zero
        free_res, free_jac = res, jac

        def res(x):
            return free_res([x[0], 0.0, x[-1]])

        def jac(x):
            return free_jac([x[0], 0.0, x[-1]])[:, [0, 2]]

    # the heading is multimodal where the sensors' headings are unrelated (6-D): four starts
    psi0 = np.radians([0.0, 90.0, 180.0, -90.0]) if refine_heading else [0.0]
    scale = [1.0, 0.1] if perpendicular else [1.0, 1.0, 0.1]
    starts = [
        [th0, p0] if perpendicular else [th0, 0.0, p0]
        for th0 in np.radians([0.0, 45.0, 90.0, 135.0])
        for p0 in psi0
    ]

    fits = [least_squares(res, x0, jac=jac, x_scale=scale) for x0 in starts]
    best = min(fits, key=lambda sol: sol.cost)
    # robust: residuals far beyond the typical one (foot strikes, soft tissue, a knocked
    # sensor) weigh less; Cauchy loss on the least-squares residuals' own scale (1.4826 MAD),
    # refined from every least-squares optimum (the basins stay those of the starts)
    f_scale = max(ROBUST_SCALE_FLOOR, 1.4826 * float(np.median(np.abs(best.fun[:-1]))))
    robust = [
        least_squares(res, sol.x, jac=jac, x_scale=scale, loss="cauchy", f_scale=f_scale)
        for sol in fits
    ]
    best = min(robust, key=lambda sol: sol.cost)
    x = [best.x[0], 0.0, best.x[1]] if perpendicular else best.x
    dpsi = float(x[2]) if refine_heading else 0.0
    return j1_of(x), dpsi, float(np.sqrt(np.mean(best.fun[:-1] ** 2)))


def hinge_frames(
    recording: Recording,
    calibration: Calibration,
    *,
    joints: Sequence[str] | None = None,
    refine_heading: bool = False,
    start_s: float | None = None,
    window_s: float | None = None,
) -> Calibration:
    """``calibration`` with the frames of hinge segments built from the measured flexion axis.

    Parameters
    ----------
    recording : Recording
        IMU orientations (and angular rates) of both segments of each hinge.
    calibration : Calibration
        With ``axes`` of both segments (static or functional); its heading corrections
        (``world_heading_deg``) are applied to the orientations first.
    joints : sequence of str, optional
        Hinges (:data:`HINGES`) to use; default every hinge whose two segments are calibrated.
    refine_heading : bool
        Also estimate the distal sensor's heading relative to the proximal one from the joint
        (for 6-D orientations; keep False when the headings are shared, e.g. magnetometer).
    start_s, window_s : float, optional
        Samples used (default: the whole recording).

    Returns
    -------
    Calibration
        Same type, ``frames`` of the hinge segments replaced (columns X anterior, Y superior, Z
        right in the sensor frame), ``world_heading_deg`` updated if ``refine_heading``.
        ``hinge_residual_rad_s`` per joint: RMS residual of the rate constraint, rad/s.

    Warns
    -----
    NumericalWarning
        A hinge that hardly moved (RMS relative rate about the axis below
        :data:`MIN_HINGE_RATE_RAD_S`): its segments keep the frames they had. A fitted axis
        tilted beyond :data:`MAX_AXIS_TILT_DEG`: whether its perpendicular refit is used (else
        the segments keep their frames).
    """
    axes = calibration.axes
    if joints is None:
        joints = [j for j in HINGES if JOINTS[j][0] in axes and JOINTS[j][1] in axes]
    frames = dict(calibration.frames)
    heading = dict(calibration.world_heading_deg)
    resid = dict(getattr(calibration, "hinge_residual_rad_s", {}) or {})
    for j in joints:
        prox, dist, _ = JOINTS[j]
        RA, RB0, tk = _hinge_orientations(recording, calibration, j, start_s, window_s)
        psi0 = np.radians(heading.get(dist, 0.0))
        # relative angular velocity from the orientations (finite differences), world frame
        wA, wB0 = _world_rate(RA, tk), _world_rate(RB0, tk)
        fit = (RA, RB0, wA, wB0, axes[prox], axes[dist], refine_heading)
        jA, dpsi, rms = _fit_flexion_axis(*fit)
        tilt = _tilt_deg(jA, axes[prox])
        if tilt > MAX_AXIS_TILT_DEG:
            jA, dpsi, rms_perp = _fit_flexion_axis(*fit, perpendicular=True)
            if not _refit_holds(j, prox, dist, tilt, rms, rms_perp):
                continue
            rms = rms_perp
        psi = psi0 + dpsi
        RB = rotation_z(psi - psi0) @ RB0
        # the distal frame's Z: the flexion axis carried into the distal sensor in the pose
        # (static: the calibration window; else the whole recording)
        w0 = (tk >= calibration.window_s[0]) & (tk <= calibration.window_s[1])
        if calibration.still is None or not np.any(w0):
            w0 = np.ones(tk.shape, dtype=bool)
        jB = np.einsum("kji,kjl,l->i", RB[w0], RA[w0], jA)
        jB /= np.linalg.norm(jB)
        Fa, Fb = segment_frame(axes[prox], jA), segment_frame(axes[dist], jB)
        fl = joint_angles({prox: RA @ Fa, dist: RB @ Fb}, [j])[j][:, 0]
        if not _moved(fl, tk, j, prox, dist):
            continue
        resid[j] = rms
        # sign by anatomy: the larger excursion from the pose is flexion
        lo, hi = np.nanpercentile(fl, [1.0, 99.0])
        if -lo > hi:
            Fa, Fb = segment_frame(axes[prox], -jA), segment_frame(axes[dist], -jB)
        frames[prox], frames[dist] = Fa, Fb
        if refine_heading:
            heading[dist] = float((np.degrees(psi) + 180.0) % 360.0 - 180.0)
    return replace(
        calibration, frames=frames, world_heading_deg=heading, hinge_residual_rad_s=resid
    )


#: Largest angle between the facings that two hinges imply, deg: beyond it the hinges disagree
#: (a wrong sign or a sensor that slipped) and no facing is estimated.
FACING_SPREAD_DEG = 45.0


def hinge_facing(
    recording: Recording, calibration: Calibration, joints: Sequence[str] | None = None
) -> tuple[np.ndarray, dict] | None:
    """The subject's facing implied by the hinge frames fitted to the movement.

    A hinge segment frame from :func:`hinge_frames` has its flexion axis from the data and its
    sign by anatomy, so its anterior axis ``X = Y × Z`` is the subject's front, whatever facing
    the pose assumed. Per hinge in ``calibration.hinge_residual_rad_s``: the proximal segment's
    ``X`` in the world at the calibration window (mean over the window of ``R_world_from_sensor
    X``), made horizontal. ``joints``: only these hinges (default all fitted ones); a hinge
    whose segments' static axes depend on the assumed facing (the arms in a T-pose) cannot
    tell it.

    Returns
    -------
    (facing, per_joint) or None
        ``facing (3,)``: horizontal unit vector, the normalised mean of the hinges' directions;
        ``per_joint``: each hinge's direction as degrees from north towards east. None when no
        hinge was fitted or two hinges' directions differ by more than
        :data:`FACING_SPREAD_DEG` (then a NumericalWarning names them, and a hinge nearly
        opposite to the others as a possibly swapped pair of sensors).
    """
    dirs = {}
    for j in sorted(calibration.hinge_residual_rad_s):
        if joints is not None and j not in joints:
            continue
        x = pose_anterior(recording, calibration, j)
        if x is not None:
            dirs[j] = x
    if not dirs:
        return None
    f = np.sum(list(dirs.values()), axis=0)
    if np.linalg.norm(f) < 1e-6:
        f = np.zeros(3)
    else:
        f /= np.linalg.norm(f)
    off = {j: float(np.degrees(np.arccos(np.clip(d @ f, -1.0, 1.0)))) for j, d in dirs.items()}
    if not np.any(f) or max(off.values()) > FACING_SPREAD_DEG / 2:
        warnings.warn(
            "facing: the flexion axes of "
            + ", ".join(f"{j} ({_deg_from_north(d):.0f} deg from north)" for j, d in dirs.items())
            + f" imply facings more than {FACING_SPREAD_DEG:g} deg apart; the facing is not "
            "estimated (declare it: [calibration] facing)" + opposite_hinges_advice(dirs),
            NumericalWarning,
            stacklevel=2,
        )
        return None
    return f, {j: _deg_from_north(d) for j, d in dirs.items()}


#: Two hinges whose implied facings are at least this far apart, deg, are taken as opposite:
#: what a hinge whose two sensors are swapped gives (its fitted axis, signed by anatomy,
#: points backwards), or sensors whose headings are not shared.
OPPOSITE_DEG = 135.0


def _deg_from_north(d: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(d[0], d[1])))


def opposite_hinges_advice(dirs: Mapping[str, np.ndarray]) -> str:
    """Advice when hinges imply opposite facings (at least :data:`OPPOSITE_DEG` apart): the
    sensors of the odd one out (of each, with two hinges) may be swapped; empty otherwise.

    ``dirs``: per hinge, its horizontal anterior direction in the pose (:func:`pose_anterior`).
    """
    names = list(dirs)
    gap = {
        j: [np.degrees(np.arccos(np.clip(dirs[j] @ dirs[k], -1.0, 1.0))) for k in names if k != j]
        for j in names
    }
    if not any(max(g, default=0.0) >= OPPOSITE_DEG for g in gap.values()):
        return ""
    odd = [j for j in names if gap[j] and np.median(gap[j]) >= OPPOSITE_DEG]
    odd = odd or [j for j in names if max(gap[j], default=0.0) >= OPPOSITE_DEG]
    pairs = " or ".join(f"{JOINTS[j][0]} and {JOINTS[j][1]} ({j})" for j in odd)
    return (
        f". {' and '.join(odd)} points the subject's front backwards: are the sensors of "
        f"{pairs} swapped in [imu.segments]? A swapped pair reverses the fitted flexion axis. "
        "Otherwise the sensors' headings are not shared (a disturbed magnetometer): "
        'heading = "static" turns each limb to its own flexion axis'
    )


def pose_anterior(recording: Recording, calibration: Calibration, j: str) -> np.ndarray | None:
    """The horizontal unit direction (world, heading corrections applied) of the anterior axis
    ``X`` of hinge ``j``'s proximal segment frame, mean over the calibration window; None if
    the window holds no sample or ``X`` is vertical there."""
    prox = JOINTS[j][0]
    RA, _, tk = _hinge_orientations(recording, calibration, j, None, None)
    w0 = (tk >= calibration.window_s[0]) & (tk <= calibration.window_s[1])
    if not np.any(w0):
        return None
    x = np.einsum("kij,j->i", RA[w0], calibration.frames[prox][:, 0])
    x[2] = 0.0
    n = np.linalg.norm(x)
    return x / n if n > 1e-6 else None


def limb_segments(j: str) -> tuple[str, str, str]:
    """The segments of hinge ``j``'s limb, proximal first: upper arm, forearm, hand (elbows);
    thigh, shank, foot (knees)."""
    prox, dist, _ = JOINTS[j]
    return prox, dist, ("hand_" if j.startswith("elbow") else "foot_") + j[-1]


def limb_headings(
    recording: Recording, calibration: Calibration, facing, joints: Sequence[str] | None = None
) -> Calibration:
    """6-D orientations: turn each fitted hinge's limb so that its flexion axis is the body's
    medio-lateral axis in the pose.

    With arbitrary sensor headings, :func:`hinge_frames` relates a hinge's two sensors to each
    other but not its limb to the trunk: the heading a static pose gives each sensor assumes
    every sensor sits on the body with the same heading, which sensors on the side or the back
    of a limb do not, and the shoulder or hip then reads that difference as internal rotation
    in the pose. This turns every sensor of the limb (:func:`limb_segments`, those
    calibrated) about the vertical by the angle from the proximal frame's anterior axis in the
    pose (:func:`pose_anterior`) to ``facing``, the direction every other pose frame faces:
    the limb's relations within itself are kept, and the shoulder or hip reads zero in the pose
    as it does by construction elsewhere (ISB: the neutral pose).

    Parameters
    ----------
    recording : Recording
        The orientations :func:`hinge_frames` was fitted to.
    calibration : Calibration
        After :func:`hinge_frames` (its ``hinge_residual_rad_s`` names the fitted hinges).
    facing : array_like, shape (3,)
        The horizontal facing of the pose frames (world, heading corrections applied).
    joints : sequence of str, optional
        Only these fitted hinges (default all).

    Returns
    -------
    Calibration
        ``world_heading_deg`` of the limbs' sensors changed; ``limb_heading_deg``: the turn
        applied per hinge, deg.
    """
    f = np.asarray(facing, dtype=float).copy()
    f[2] = 0.0
    f /= np.linalg.norm(f)
    heading = dict(calibration.world_heading_deg)
    turns = dict(calibration.limb_heading_deg)
    for j in sorted(calibration.hinge_residual_rad_s):
        if joints is not None and j not in joints:
            continue
        x = pose_anterior(recording, calibration, j)
        if x is None:
            continue
        psi = float(np.degrees(np.arctan2(x[0] * f[1] - x[1] * f[0], x @ f)))
        for s in limb_segments(j):
            if s in calibration.axes:
                heading[s] = float((heading.get(s, 0.0) + psi + 180.0) % 360.0 - 180.0)
        turns[j] = psi
    return replace(calibration, world_heading_deg=heading, limb_heading_deg=turns)


def foot_headings(recording: Recording, calibration: Calibration) -> Calibration:
    """6-D orientations: each foot sensor's heading relative to its shank's, from the ankle.

    The static pose gives a foot sensor the heading of the common-heading assumption (every
    sensor faces the same way on the body), which a sensor on the top or the side of the foot
    does not. A foot sensor turned by ``δ`` on the body turns every ankle movement since the
    pose by ``δ`` about the vertical: dorsiflexion then reads as inversion and axial rotation
    (on the qmt 6-D example, ankle adduction up to 56 deg and rotation up to 82 deg). The ankle
    is fitted as :func:`hinge_frames` fits an elbow (Laidig, Müller & Seel 2017), with the
    foot's heading as the unknown: its relative angular velocity lies in ``span(R_A j1, R_B
    j2)``, ``j1`` the talocrural (flexion) axis fixed in the shank and held perpendicular to
    its long axis (anatomy; its azimuth free), ``j2`` the foot's vertical in the pose (its
    axial rotation; heading-free, unlike the foot's long axis). The subtalar joint's inversion
    and eversion, about an oblique axis, is what the model leaves out: it is the residual,
    weighed down by the fit's robust loss (with foot strikes).

    Parameters
    ----------
    recording : Recording
        IMU orientations of the shanks and feet.
    calibration : Calibration
        Static (a still window), with the axes of both segments of an ankle and its headings
        (``world_heading_deg``) so far.

    Returns
    -------
    Calibration
        ``world_heading_deg`` of each fitted foot changed by the fitted turn, and
        ``foot_heading_deg``: that turn per ankle, deg. Only the ankles whose two segments are
        calibrated and that moved enough (RMS relative rate of at least
        :data:`MIN_HINGE_RATE_RAD_S`, else a NumericalWarning and the heading kept).
    """
    if calibration.still is None:
        return calibration
    heading = dict(calibration.world_heading_deg)
    turns = dict(calibration.foot_heading_deg)
    for side in "lr":
        j = f"ankle_{side}"
        shank, foot, _ = JOINTS[j]
        if shank not in calibration.axes or foot not in calibration.axes:
            continue
        RA, RB, tk = _hinge_orientations(recording, calibration, j, None, None)
        w0 = (tk >= calibration.window_s[0]) & (tk <= calibration.window_s[1])
        if RA.shape[0] < 3 or not np.any(w0):
            continue
        wA, wB = _world_rate(RA, tk), _world_rate(RB, tk)
        rate = float(np.sqrt(np.mean(np.sum((wB - wA) ** 2, axis=1))))
        if rate < MIN_HINGE_RATE_RAD_S:
            warnings.warn(
                f"foot heading: {j} hardly moved (RMS relative rate {rate:.2f} rad/s < "
                f"{MIN_HINGE_RATE_RAD_S:g}); {foot}'s heading is kept as the pose gave it",
                NumericalWarning,
                stacklevel=2,
            )
            continue
        up = np.einsum("kji,j->i", RB[w0], [0.0, 0.0, 1.0])  # the foot's vertical, sensor frame
        _, dpsi, _ = _fit_flexion_axis(
            RA, RB, wA, wB, calibration.axes[shank], -up, True, perpendicular=True
        )
        turns[j] = float((np.degrees(dpsi) + 180.0) % 360.0 - 180.0)
        heading[foot] = float((heading.get(foot, 0.0) + turns[j] + 180.0) % 360.0 - 180.0)
    return replace(calibration, world_heading_deg=heading, foot_heading_deg=turns)


def _hinge_orientations(recording, calibration, j: str, start_s, window_s):
    """Heading-corrected world-from-sensor of both segments of hinge ``j`` where both are valid."""
    prox, dist, _ = JOINTS[j]
    sa = oriented_imu(recording, prox, f"hinge axis of {j}")
    sb = oriented_imu(recording, dist, f"hinge axis of {j}")
    t = sa.t_s[window_mask(sa.t_s, start_s, window_s)]
    RA = calibration.heading_matrix(prox) @ as_rotation_matrices(
        slerp_resample(sa.t_s, sa.q_world_from_sensor, t), f"IMU {prox!r} orientation"
    )
    RB0 = calibration.heading_matrix(dist) @ as_rotation_matrices(
        slerp_resample(sb.t_s, sb.q_world_from_sensor, t), f"IMU {dist!r} orientation"
    )
    ok = np.all(np.isfinite(RA), axis=(1, 2)) & np.all(np.isfinite(RB0), axis=(1, 2))
    return RA[ok], RB0[ok], t[ok]


#: Largest angle, deg, between a flexion axis fitted to the movement and the plane
#: perpendicular to its proximal segment's long axis from the pose: an elbow's or knee's axis is
#: close to perpendicular to the upper arm or thigh (within the carrying or valgus angle, and
#: how upright the pose was held); beyond it the axis is fitted again held perpendicular
#: (:data:`PERPENDICULAR_REFIT_MAX_RATIO` decides whether that refit is used).
MAX_AXIS_TILT_DEG = 30.0


#: A refit with the flexion axis held perpendicular to the proximal long axis is used when its
#: RMS residual is at most this factor times the free fit's: the movement then hardly
#: determines the tilt (a 6-D relative heading that drifts over minutes, soft tissue), and the
#: anatomy does. A larger increase means the movement demands the tilt: the pose's long axis
#: is wrong (the subject was not in the pose) and neither fit is used.
PERPENDICULAR_REFIT_MAX_RATIO = 1.25


def _tilt_deg(jA, axis) -> float:
    """Angle of the flexion axis ``jA`` from the plane perpendicular to the long ``axis``, deg."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return float(np.degrees(np.arcsin(min(1.0, abs(float(jA @ a)) / np.linalg.norm(jA)))))


def _refit_holds(j: str, prox: str, dist: str, tilt: float, rms: float, rms_perp: float) -> bool:
    """Whether the perpendicular refit of a tilted hinge fit is used; a NumericalWarning either
    way, naming the joint, the tilt, both residuals and what to check."""
    used = rms_perp <= PERPENDICULAR_REFIT_MAX_RATIO * rms
    head = (
        f"hinge frames: the flexion axis of {j} fitted to the movement is {tilt:.0f} deg from "
        f"perpendicular to {prox}'s long axis in the pose (limit {MAX_AXIS_TILT_DEG:g} deg; RMS "
        f"residual {rms:.2f} rad/s; held perpendicular: {rms_perp:.2f} rad/s)"
    )
    if used:
        tail = (
            ": the movement hardly determines the tilt, so the axis held perpendicular to the "
            f"{prox} (the anatomy of an elbow or knee) is used. Check that both sensors were "
            "strapped firmly; with 6-D sensors over minutes, a relative heading that drifts "
            "blurs the fit"
        )
    else:
        tail = (
            ": the movement and the pose contradict each other, so the frames of "
            f"{prox!r} and {dist!r} are kept as the pose gave them (their flexion axis from the "
            "facing and the sensors' headings in the pose). Check that both sensors were "
            "strapped firmly and that the still window is the N-pose; the angles of this limb "
            "are unreliable. With 9-D sensors, declare [calibration] facing with "
            'flexion_axes = "pose"'
        )
    warnings.warn(head + tail, NumericalWarning, stacklevel=3)
    return used


def _moved(fl: np.ndarray, tk: np.ndarray, j: str, prox: str, dist: str) -> bool:
    """Whether the hinge flexed enough to determine its axis (else a NumericalWarning)."""
    rate = float(np.sqrt(np.mean(np.gradient(np.radians(np.unwrap(fl, period=360.0)), tk) ** 2)))
    if not np.isfinite(rate) or rate < MIN_HINGE_RATE_RAD_S:
        warnings.warn(
            f"hinge frames: {j} hardly moved (RMS flexion rate {rate:.2f} rad/s < "
            f"{MIN_HINGE_RATE_RAD_S:g}); its flexion axis is not determined by the data, the "
            f"frames of {prox!r} and {dist!r} are kept as calibrated",
            NumericalWarning,
            stacklevel=3,
        )
        return False
    return True
