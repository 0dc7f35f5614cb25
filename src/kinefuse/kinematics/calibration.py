"""Sensor-to-segment calibration from a Recording: :func:`calibrate`.

SPEC §2.1 "Axis calibration" and §2.2 "Kinect side": the segment axis ``a_i`` in each IMU frame
from (a) a static pose (:mod:`kinefuse.kinematics.static`), or (b) a window where a reference or
camera sees the joints; (c) the rotation between the IMU world frame and the camera/reference
frame (Kabsch, rotation only: :mod:`kinefuse.kinematics.alignment`); or from movement alone
(:mod:`kinefuse.kinematics.functional`). The result is a
:class:`~kinefuse.kinematics.Calibration`; :mod:`kinefuse.kinematics.chain` turns it into joint
positions and segment orientations.

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
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from kinefuse._validation import names_arg
from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.io.recording import Recording
from kinefuse.kinematics.alignment import (
    alignment_sensitivity,
    angles_deg,
    heading_rotation,
    kabsch_rotation,
    solve_alignment,
    unit_direction,
)
from kinefuse.kinematics.angles import JOINTS
from kinefuse.kinematics.calibration_result import Calibration, joint_stream, oriented_imu
from kinefuse.kinematics.chain import chain_positions, segment_orientations
from kinefuse.kinematics.forward import as_rotation_matrices, rotation_z
from kinefuse.kinematics.functional import functional_calibration
from kinefuse.kinematics.hinge import (
    HINGES,
    foot_headings,
    hinge_facing,
    hinge_frames,
    limb_headings,
)
from kinefuse.kinematics.pelvis_heading import pelvis_heading
from kinefuse.kinematics.skeleton import Skeleton, lengths_from_joints, window_mask
from kinefuse.kinematics.static import (
    POSE_WARN_DEG,
    facing_free_segments,
    static_calibration,
    window_orientations,
)
from kinefuse.kinematics.still import MAX_ACC_STD_M_S2, MAX_RATE_RAD_S
from kinefuse.orientation.resample import slerp_resample

#: Trunk segments a static calibration gives a frame (the pose: upright, facing forward) without
#: being skeleton segments: the pelvis (places the hips), the chest (the shoulders).
TRUNK_SEGMENTS = ("pelvis", "chest")

#: The default facing: north in the IMU world frame (ENU).
_NORTH = (0.0, 1.0, 0.0)

__all__ = [
    "POSE_WARN_DEG",
    "Calibration",
    "calibrate",
    "chain_positions",
    "heading_rotation",
    "kabsch_rotation",
    "segment_orientations",
]


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
    proximal_segments: Mapping[str, str] | None = None,
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
        ``"t"`` = T-pose: arms point horizontally sideways, legs down. In both the feet point
        forward (``facing``), and a foot's frame is its shank's carried into the foot sensor
        in the pose (ISB: the calcaneus frame coincides with the tibia's in the neutral pose,
        Wu et al. 2002), its long axis that frame's anterior axis.
    facing : array_like, shape (3,), or "auto"
        Static: the subject's horizontal facing direction in the IMU world frame (default north
        ``[0, 1, 0]``): the pose frames' anterior axis, and in the T-pose the right arm points
        along ``facing × up``. ``"auto"``: not known; the flexion axes of elbows and knees are
        then fitted to the movement and the facing they imply
        (:func:`kinefuse.kinematics.hinge.hinge_facing`) is used for every segment's pose frame
        (north when no hinge moved enough); ``Calibration.facing_from`` says which.
    directions : mapping, optional
        Static only: explicit ``d0`` per segment (world frame), overriding the pose.
    align : {"auto", "none", "heading", "rotation"}
        Reference/vision only: how the joint stream's frame relates to the IMU world frame.
        ``"none"``: shared frame. ``"heading"``: differs by a rotation about the vertical.
        ``"rotation"``: any rotation (camera frames). ``"auto"``: ``"none"`` when every used IMU
        stream's ``frame`` equals the joint stream's ``frame``, else ``"rotation"``.
    segments : sequence of str, optional
        Calibrate only these skeleton segments (default: all); ``skeleton.root_segment`` and
        the trunk segments :data:`TRUNK_SEGMENTS` (``"pelvis"``, ``"chest"``) may be included
        for static calibration (their frame in the pose).
    heading : {"none", "static"}
        Static only: ``"static"`` brings the sensors' world frames into one heading, assuming
        every sensor faces the same way on the body in the still pose (the heading of each
        sensor's mean orientation is rotated onto that of the first segment's). Use it for 6-D
        orientations (no magnetometer), whose headings are arbitrary per sensor; ``"none"``
        (default) keeps the frames (9-D / magnetometer-referenced data share north). With
        flexion axes from the movement, each fitted elbow's or knee's limb is then turned so
        that its flexion axis is the body's medio-lateral axis in the pose
        (:func:`kinefuse.kinematics.hinge.limb_headings`; ``Calibration.limb_heading_deg``):
        its sensors need not face as the others do; and each foot sensor's heading is fitted
        to its ankle's movement relative to the shank
        (:func:`kinefuse.kinematics.hinge.foot_headings`; ``Calibration.foot_heading_deg``).
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
        when the facing is not known (``heading="static"``: 6-D orientations; or
        ``facing="auto"``), else ``"pose"``.

    proximal_segments : mapping joint -> segment, optional
        Functional only: the IMU proximal to a root joint, instead of the skeleton's
        ``root_segment`` (e.g. ``{"shoulder_l": "chest", "shoulder_r": "chest"}``; see
        :func:`~kinefuse.kinematics.functional.functional_calibration`).
    Returns
    -------
    Calibration

    Notes
    -----
    The methods' equations, checks and warnings: :mod:`kinefuse.kinematics.calibration`.

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        Unknown method or segment, a segment without IMU or orientation, joints missing from the
        stream, an empty window.
    """
    _check_options(recording, skeleton, method, heading, flexion_axes, align)
    if method == "functional":
        # movement calibration uses the whole recording unless a window start is given
        return functional_calibration(
            recording,
            skeleton,
            start_s=start_s,
            window_s=None if start_s is None else window_s,
            segments=segments,
            declared_axes=mounting,
            proximal_segments=proximal_segments,
        )
    segs = names_arg(segments, "segments")
    segs = list(skeleton.segments if segs is None else segs)
    if not segs:
        raise InputError("expected segments with at least one segment name, or None for all")
    for s in segs:
        if not (method == "static" and s in (skeleton.root_segment, *TRUNK_SEGMENTS)):
            skeleton.index(s)
    imus = {s: oriented_imu(recording, s, "calibration") for s in segs}
    if method != "static":
        return _joint_stream_calibration(
            recording, skeleton, segs, imus, method, start_s=start_s, window_s=window_s, align=align
        )
    auto_facing = isinstance(facing, str) and facing == "auto"
    if isinstance(facing, str) and not auto_facing:
        raise InputError(f"expected facing as 'auto' or a direction [x, y, z], got {facing!r}")
    kw = dict(
        window_s=window_s, start_s=start_s, pose=pose, directions=directions, heading=heading,
        mounting=mounting, max_rate_rad_s=max_rate_rad_s, max_acc_std_m_s2=max_acc_std_m_s2,
    )  # fmt: skip
    f0 = _NORTH if auto_facing else facing
    cal = static_calibration(skeleton, segs, imus, facing=f0, **kw)
    if flexion_axes == "auto":
        flexion_axes = "movement" if heading == "static" or auto_facing else "pose"
    if flexion_axes == "movement":
        cal = hinge_frames(recording, cal, refine_heading=heading == "static")
    source = "default" if auto_facing else "declared"
    if flexion_axes == "movement":  # the hinges whose two segments the facing leaves free
        free = facing_free_segments(skeleton, segs, pose, directions)
    if auto_facing and flexion_axes == "movement":
        kept = [j for j in cal.hinge_residual_rad_s if set(JOINTS[j][:2]) <= free]
        with warnings.catch_warnings():  # 6-D: limbs that disagree are turned below
            if heading == "static":
                warnings.simplefilter("ignore", NumericalWarning)
            est = hinge_facing(recording, cal, kept)
        if est is not None:  # every pose frame (pelvis, hips, T-pose arms) in that facing
            f0, source = est[0], "hinges"
            with warnings.catch_warnings():  # the first pass said it all (same data)
                warnings.simplefilter("ignore", NumericalWarning)
                cal = _in_facing(recording, skeleton, segs, imus, cal, f0, kept, kw)
    if heading == "static" and flexion_axes == "movement":
        turn = [j for j in cal.hinge_residual_rad_s if set(JOINTS[j][:2]) <= free]
        cal = limb_headings(recording, cal, f0, turn)  # the limbs face as the trunk does
        cal = foot_headings(recording, cal)  # each foot sensor to its shank's heading
        cal = pelvis_heading(recording, cal)  # the pelvis sensor turned as its hips say
        cal, f0 = _keep_reference_heading(cal, segs[0], f0)
    cal = _feet_on_shanks(imus, cal)
    return replace(cal, facing=np.asarray(f0, dtype=float), facing_from=source)


def _keep_reference_heading(cal: Calibration, ref: str, facing):
    """Turn the whole common world (every heading, and ``facing``) so that the reference
    sensor ``ref`` (the first segment: the world frame keeps its heading) has heading 0 again;
    the segment frames, in the sensors, and every relative heading are unchanged."""
    psi = float(cal.world_heading_deg.get(ref, 0.0))
    if abs(psi) <= 1e-9:
        return cal, facing
    heading = {
        s: 0.0 if s == ref else float((h - psi + 180.0) % 360.0 - 180.0)
        for s, h in cal.world_heading_deg.items()
    }
    f = rotation_z(np.radians(-psi)) @ np.asarray(facing, dtype=float)
    return replace(cal, world_heading_deg=heading), f


def _feet_on_shanks(imus: Mapping, cal: Calibration) -> Calibration:
    """Each calibrated foot takes its shank's final frame (after any hinge fit), carried into
    the foot sensor in the pose: the ankle reads zero there (ISB neutral), its flexion axis is
    the shank's, and the foot's long axis (ankle -> toe) is that frame's anterior ``X``."""
    pairs = [(f"foot_{s}", f"shank_{s}") for s in "lr"]
    pairs = [(f, s) for f, s in pairs if f in cal.frames and s in cal.frames]
    if not pairs or cal.still is None:
        return cal
    frames, axes = dict(cal.frames), dict(cal.axes)
    _, R_mean = window_orientations({x: imus[x] for p in pairs for x in p}, cal.still)
    for f, s in pairs:
        R_f, R_s = cal.heading_matrix(f) @ R_mean[f], cal.heading_matrix(s) @ R_mean[s]
        frames[f] = R_f.T @ R_s @ frames[s]
        axes[f] = frames[f][:, 0]
    return replace(cal, frames=frames, axes=axes)


def _in_facing(recording, skeleton, segs, imus, first: Calibration, facing, kept, kw: dict):
    """The static calibration again in ``facing``: new pose frames; the hinges in ``kept``
    (fitted, their segments' axes facing-free, so their fit does not depend on the facing)
    keep ``first``'s frames, residuals and refined headings; the other hinges are fitted
    again (their axes, or the frames they fall back to, follow the facing)."""
    cal = static_calibration(skeleton, segs, imus, facing=facing, **kw)
    frames, heading = dict(cal.frames), dict(cal.world_heading_deg)
    for j in kept:
        for s in JOINTS[j][:2]:
            frames[s] = first.frames[s]
        dist = JOINTS[j][1]
        if dist in first.world_heading_deg:
            heading[dist] = first.world_heading_deg[dist]
    resid = {j: first.hinge_residual_rad_s[j] for j in kept}
    cal = replace(cal, frames=frames, world_heading_deg=heading, hinge_residual_rad_s=resid)
    redo = [j for j in HINGES if j not in kept and set(JOINTS[j][:2]) <= set(cal.axes)]
    if not redo:
        return cal
    return hinge_frames(recording, cal, joints=redo, refine_heading=kw["heading"] == "static")


def _check_options(recording, skeleton, method, heading, flexion_axes, align) -> None:
    """Validate the arguments of :func:`calibrate` (InputError naming expected and actual)."""
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
        return
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


def _joint_stream_calibration(
    recording, skeleton, segs, imus, method, *, start_s, window_s, align
) -> Calibration:
    """Reference/vision calibration: axes (and ``R_world_from_camera``) from joint directions."""
    stream = joint_stream(recording, method)
    sel = window_mask(stream.t_s, start_s, window_s)
    t = stream.t_s[sel]
    W, U = {}, {}
    for s in segs:
        W[s], U[s] = _paired_directions(skeleton, s, stream, imus[s], sel, t, method)
    if align == "auto":
        frames = {imus[s].frame for s in segs}
        align = "none" if frames == {stream.frame} else "rotation"
    if align == "none":
        Rc = None
        axes = {
            s: unit_direction(np.einsum("kji,kj->i", W[s], U[s]), f"segment {s!r}") for s in segs
        }
    else:
        Rc, axes = solve_alignment(W, U, align)
        weak = alignment_sensitivity(W, U, Rc, align)
        if weak:
            warnings.warn(
                f"calibrate: the {align} alignment between the IMU world and the {method} frame is poorly "
                f"determined by this window (a 5 deg change about world {weak} stays within the misfit noise); "
                "use a window with rotations about several axes, or align='none' if the frames are shared "
                '(a session: [method.parameters] align = "none")',
                NumericalWarning,
                stacklevel=3,
            )
    Rc_eff = np.eye(3) if Rc is None else Rc
    resid = {
        s: float(
            np.sqrt(
                np.mean(angles_deg(np.einsum("kij,j->ki", W[s], axes[s]), U[s] @ Rc_eff.T) ** 2)
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
        frames=_trunk_frames(recording, stream, sel, t, Rc_eff),
    )


#: The joints a trunk frame is built from in a joint stream: right axis from the left to the
#: right joint of the pair, superior axis from the mid-hip to the mid-shoulder point.
_TRUNK_JOINTS = ("shoulder_l", "shoulder_r", "hip_l", "hip_r")


def _trunk_frames(recording, stream, sel, t, Rc) -> dict[str, np.ndarray]:
    """ISB frames (``R_sensor_from_segment``: X anterior, Y superior, Z right) of the ``chest``
    and ``pelvis`` IMUs from the joint stream's shoulders and hips in the window: Z along
    shoulder_l -> shoulder_r (chest) or hip_l -> hip_r (pelvis), Y along mid-hip -> mid-shoulder
    made perpendicular to Z, X = Y x Z; each averaged in the sensor frame over the window
    (``Rc``: stream frame -> IMU world). Empty without those joints or trunk IMUs; a trunk
    IMU's frame otherwise is the sensor taken as right-front-up, which places the shoulders
    wherever that sensor happens to point."""
    trunk = [s for s in ("chest", "pelvis") if s in recording.imu]
    if not trunk or not all(j in stream.joints for j in _TRUNK_JOINTS):
        return {}
    p = {j: stream.position(j)[sel] for j in _TRUNK_JOINTS}
    up = 0.5 * (p["shoulder_l"] + p["shoulder_r"] - p["hip_l"] - p["hip_r"])
    pairs = {"chest": ("shoulder_l", "shoulder_r"), "pelvis": ("hip_l", "hip_r")}
    frames = {}
    for seg in trunk:
        imu = recording.imu[seg]
        if imu.q_world_from_sensor is None:
            continue
        right = p[pairs[seg][1]] - p[pairs[seg][0]]
        ok = np.all(np.isfinite(right), axis=1) & np.all(np.isfinite(up), axis=1)
        R = as_rotation_matrices(slerp_resample(imu.t_s, imu.q_world_from_sensor, t))
        ok &= np.all(np.isfinite(R), axis=(1, 2))
        if not np.any(ok):
            continue
        r_k, u_k = right[ok], up[ok]
        r_k = r_k / np.linalg.norm(r_k, axis=1, keepdims=True)
        u_k = u_k / np.linalg.norm(u_k, axis=1, keepdims=True)
        # each direction in the sensor frame: R_world_from_sensorᵀ · Rc · d, summed
        z = np.einsum("kji,jl,kl->i", R[ok], Rc, r_k)
        y = np.einsum("kji,jl,kl->i", R[ok], Rc, u_k)
        z = z / np.linalg.norm(z)
        y = y - z * np.dot(y, z)
        n = np.linalg.norm(y)
        if not np.isfinite(n) or n < 1e-6:
            continue
        y = y / n
        frames[seg] = np.stack([np.cross(y, z), y, z], axis=1)
    return frames


def _paired_directions(skeleton, s, stream, imu, sel, t, method):
    """Segment ``s``: world-from-sensor (K, 3, 3) and unit joint directions (K, 3) in the window."""
    i = skeleton.index(s)
    prox, dist = skeleton.proximal[i], skeleton.distal[i]
    lack = [j for j in (prox, dist) if j not in stream.joints]
    if lack:
        raise InputError(
            f"segment {s!r}: expected joints {lack} in the {method} stream, got {list(stream.joints)}"
        )
    d = stream.position(dist)[sel] - stream.position(prox)[sel]
    as_rotation_matrices(imu.q_world_from_sensor, f"IMU {s!r} orientation")  # unit norm, before
    q = slerp_resample(imu.t_s, imu.q_world_from_sensor, t)  # SLERP normalises what it blends
    R = as_rotation_matrices(q, f"IMU {s!r} orientation")
    n = np.linalg.norm(d, axis=1)
    ok = np.isfinite(n) & (n > 1e-6) & np.all(np.isfinite(R), axis=(1, 2))
    if not np.any(ok):
        raise InputError(
            f"segment {s!r}: no sample in the calibration window with both joints and orientation"
        )
    return R[ok], d[ok] / n[ok, None]
