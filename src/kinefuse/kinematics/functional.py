"""Functional sensor-to-segment calibration from movement (no still pose, no optical data).

Joint centres from the accelerations and angular rates of the two sensors next to each joint
(Seel, Schauer & Raisch 2012; the one-sensor, still-proximal form of Crabolu et al. 2017 where
the proximal segment has no sensor), hinge axes from the relative rotation (SARA's direction,
Ehrig et al. 2007) with the angular-rate hinge test of Seel et al. 2012/2014, and a
heading offset between adjacent sensors' world frames estimated from the same joint constraint.
Each segment's axis in its sensor frame is the direction from its proximal to its distal joint
centre, and its length their distance.

Notes
-----
Rigid-body model: a point at ``r`` (sensor frame) on a segment whose sensor measures specific
force ``a``, angular rate ``ω`` and angular acceleration ``ω̇`` has specific force
``a + K r`` with ``K = [ω̇]× + [ω]×²``. Two segments joined at a centre share its
acceleration (Seel et al. 2012, Eq. 8); with the orientations ``R_A, R_B`` this holds in the
world frame up to the heading ``ψ`` between the sensors' world frames::

    Rz(ψ) R_A(k) (a_A(k) + K_A(k) r_A) = R_B(k) (a_B(k) + K_B(k) r_B)

solved for ``(r_A, r_B, ψ)`` by ``scipy.optimize.least_squares`` from the linear solution at
``ψ = 0``, both sides low-passed (``cutoff_hz``). ``ψ`` is always free in the fit, which makes the centres immune to the heading
errors of the orientation filter (the least reliable part of its output). Where the
proximal segment has no IMU (paper A's shoulder, measured once) the centre is taken as still
(Crabolu et al. 2017): ``R_B (a_B + K_B r_B) = [0, 0, g]``. ``ω̇`` is the time derivative of
the gyro.

A segment with sensor ``s``, proximal centre at ``r_P`` and distal centre at ``r_D`` (both in
frame ``s``) gets the axis ``(r_D − r_P)/‖r_D − r_P‖`` and the length ``‖r_D − r_P‖``.
Hinge prior: for a joint in ``hinge_joints`` whose axial excitation (the excitation of the
centre moving along the hinge axis in both frames at once, ``(j_A, j_B)/√2``) is below
``min_excitation_s2``, ``r_D − r_P`` is first projected on the plane normal to the hinge
axis (the femoral and tibial mechanical axes are perpendicular to the knee flexion axis
within a few degrees). CMU's own 1-DoF knees give 0.1-1.6 s⁻² with ideal sensors and
1.2-5.3 s⁻² with the simulator's soft-tissue artefact (CMU 02_01 and BVH 131_02 walks); with the
simulator's knee rotations (:mod:`kinefuse.sim.knee`, internal/external rotation and
ab/adduction of the measured ranges) 2.7-11.8 s⁻², and real knees in walking 10-16 s⁻² (Neura,
x-IMU3: not used). Real knees also rotate off the flexion axis more than the simulator's
(``kinefuse experiment realism``, measure (iv)), so the threshold was not chosen on virtual walks.

Excitation of a joint: ``min`` over its sensors of ``sqrt(λ₂)``, ``λ₂`` the middle
eigenvalue of ``mean_k K(k)ᵀ K(k)``: the acceleration change per metre of centre error in
the second-best-determined direction (the best two directions are all a hinge can give; the
third, along the hinge axis, is not needed to be excited). For a rotation at rate ``ω`` it is
about ``sqrt(ω⁴ + ω̇²)``; walking gives 5-30 s⁻², a still limb about the gyro noise.

Hinge axis: the invariant axis of the relative rotation, the top singular vectors of
``mean_k R_A(k)ᵀ R_B(k)`` (the direction part of SARA, Ehrig et al. 2007, J. Biomech.
40:2150); reported with the RMS relative angular rate about each principal axis (Seel et
al. 2012/2014: a hinge has one large rate). Seel et al. 2012's gyro-only cost
``‖ω_A × j_A‖ − ‖ω_B × j_B‖`` was tried and not kept: on CMU virtual walking it was no better
(≤ 1.1° vs ≤ 0.7°) and in real walking, which rotates mostly about one axis, it is poorly
determined.

Assumptions and failure modes

- Rigid segments and sensors (soft-tissue motion adds error, mostly at heel strike; the
  low-pass removes the impact band).
- The joint is a centre of rotation (ball or hinge). For a pure hinge the centre's position
  along the axis is not observable (the fit would return the minimum-norm point and tilt
  the segment axis by ``atan(offset / length)``): the hinge prior above handles it.
- Orientations of both sensors must be right up to a common heading; inclination errors of
  ``ε`` rad give acceleration errors of ``g·ε``.
- The fitted heading also absorbs model error (soft tissue): on the Neura walk, whose IMU
  frames agree with Vicon within a few degrees, the knee_l and ankle_r fits return −24° and
  −18° with standard deviations near 1°. Apply it (``heading="estimate"``) only when the
  frames really differ.
- Too little motion (a still or slowly moving limb): the centre is undetermined; an
  :class:`~kinefuse.exceptions.InputError` names the joint whose excitation fell below
  ``min_excitation_s2``.
- One-sensor model: only valid while the proximal segment is still.

References
----------
T. Seel, T. Schauer, J. Raisch, "Joint axis and position estimation from inertial measurement
data by exploiting kinematic constraints", IEEE CCA 2012, 45-49.
T. Seel, J. Raisch, T. Schauer, "IMU-based joint angle measurement for gait analysis", Sensors
14(4):6891-6909, 2014.
M. Crabolu et al., centre-of-rotation estimation from one magneto-inertial sensor with the
proximal segment still, J. Biomech. 2017.
R. M. Ehrig et al., "A survey of formal methods for determining functional joint axes",
J. Biomech. 40(10):2150-2157, 2007 (SARA).
D. A. Winter, "Biomechanics and Motor Control of Human Movement", 4th ed., Wiley 2009, §2.2
(6 Hz low-pass for gait kinematics).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from kinefuse._validation import names_arg
from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.io.recording import Recording
from kinefuse.kinematics.calibration_result import Calibration, oriented_imu, turned_heading
from kinefuse.kinematics.hinge import hinge_frames
from kinefuse.kinematics.joint_centre import GRAVITY_M_S2, JointFit, fit_joint, joint_signals
from kinefuse.kinematics.skeleton import Skeleton, unit_axis, window_mask

__all__ = [
    "CUTOFF_HZ",
    "DISTAL_SEGMENTS",
    "GRAVITY_M_S2",
    "HINGE_JOINTS",
    "LENGTH_WARN_FRACTION",
    "MIN_EXCITATION_S2",
    "FunctionalCalibration",
    "JointFit",
    "align_headings",
    "functional_calibration",
]

#: Low-pass cut-off for gyro and accelerometer before the fit, Hz (Winter 2009 §2.2: 6 Hz for
#: gait kinematics; heel-strike impacts and soft-tissue wobble above it break the rigid model).
CUTOFF_HZ = 6.0

#: Least excitation accepted, s⁻² (see :func:`functional_calibration`, Notes). A residual
#: accelerometer error of 0.05 m/s² (a few mg, typical of a calibrated MEMS accelerometer) maps to
#: a joint-position error of about ``0.05 / excitation`` m: 2 s⁻² bounds it near 2.5 cm.
MIN_EXCITATION_S2 = 2.0

#: Joints whose flexion axis is taken as perpendicular to both adjacent segment axes.
HINGE_JOINTS = ("knee_l", "knee_r")

#: A functional length farther than this fraction from the skeleton's (tape or anthropometric)
#: length raises a warning: height-scaled tables predict segment lengths within about 10 %.
LENGTH_WARN_FRACTION = 0.25

#: The sensor beyond a skeleton's last joint (the segment after it is not in the skeleton).
DISTAL_SEGMENTS = {
    "ankle_l": "foot_l",
    "ankle_r": "foot_r",
    "wrist_l": "hand_l",
    "wrist_r": "hand_r",
}


@dataclass(frozen=True, eq=False)
class FunctionalCalibration(Calibration):
    """:class:`~kinefuse.kinematics.Calibration` from movement, with the fit's report data.

    Attributes
    ----------
    joints : dict of str -> JointFit
        Every joint fitted (including the ones beyond the skeleton, e.g. ankles from foot IMUs).
    excitation_s2 : dict of str -> float
        Excitation per joint, s⁻².
    heading_deg : dict of str -> float
        Heading of each sensor's world frame relative to the first sensor of its chain (the
        root segment's when it has an IMU), accumulated over the joints, deg (empty with
        ``constraint="norm"``).
    heading : str
        ``"shared"`` (frames taken as one; the estimates only reported) or ``"estimate"``
        (:func:`align_headings` should be applied before using the orientations together).
    hinge_prior : tuple of str
        Hinge joints whose centre was not observable along the axis, so that the adjacent
        segment axes were made perpendicular to the hinge axis.
    cutoff_hz : float
        Low-pass cut-off used, Hz.
    declared : tuple of str
        Segments without a sensor beyond their distal joint whose axis is the declared sensor
        axis (``declared_axes``; no functional length).
    """

    joints: Mapping[str, JointFit] = field(default_factory=dict)
    excitation_s2: Mapping[str, float] = field(default_factory=dict)
    heading_deg: Mapping[str, float] = field(default_factory=dict)
    heading: str = "shared"
    hinge_prior: tuple[str, ...] = ()
    cutoff_hz: float = CUTOFF_HZ
    declared: tuple[str, ...] = ()


# ---------------------------------------------------------------------- public
def functional_calibration(
    recording: Recording,
    skeleton: Skeleton,
    *,
    start_s: float | None = None,
    window_s: float | None = None,
    segments: Sequence[str] | None = None,
    distal_segments: Mapping[str, str] | None = None,
    proximal_segments: Mapping[str, str] | None = None,
    heading: str = "auto",
    hinge_joints: Sequence[str] | None = None,
    constraint: str = "vector",
    cutoff_hz: float = CUTOFF_HZ,
    min_excitation_s2: float = MIN_EXCITATION_S2,
    declared_axes: Mapping[str, object] | None = None,
) -> FunctionalCalibration:
    """Segment axes (and lengths) in each sensor frame from movement, by joint-centre estimation.

    Parameters
    ----------
    recording : Recording
        IMU streams with ``q_world_from_sensor``, ``acc_m_s2`` and ``gyr_rad_s`` for every
        calibrated segment, for the root segment (e.g. ``pelvis``, locating the hips) and for
        the segment beyond each last joint (``foot_l`` for ``ankle_l``, see ``distal_segments``).
    skeleton : Skeleton
        Segments with their proximal and distal joints.
    start_s, window_s : float, optional
        Window (default: the whole recording; walking data can be used from its first sample).
    segments : sequence of str, optional
        Calibrate only these skeleton segments (default: all).
    distal_segments : mapping joint -> segment, optional
        The IMU beyond a distal joint no skeleton segment starts at (default
        :data:`DISTAL_SEGMENTS`).
    proximal_segments : mapping joint -> segment, optional
        The IMU proximal to a root joint, overriding the skeleton's ``root_segment`` (e.g.
        ``{"shoulder_r": "chest"}`` for paper A's chain with a trunk IMU). A root joint with
        neither is taken as still (one-sensor model).
    heading : {"auto", "shared", "estimate"}
        Whether the IMU world frames are one frame. ``"shared"``: yes; the heading offsets the
        joint fits find are reported only. ``"estimate"``: they differ by a heading (6-D fusion,
        magnetic disturbance); the accumulated offsets are returned in ``heading_deg`` and
        :func:`align_headings` brings the orientations into the first sensor's frame.
        ``"auto"``: ``"shared"`` when every used IMU stream declares the same ``frame``, else
        ``"estimate"``.
    hinge_joints : sequence of str, optional
        Joints whose flexion axis is anatomically perpendicular to both adjacent segment axes
        (default :data:`HINGE_JOINTS`, the knees); used only where the data cannot locate the
        centre along the axis (Notes).
    constraint : {"vector", "norm"}
        ``"vector"``: the joint-acceleration equality in the world frame with a free constant
        heading (Notes). ``"norm"``: Seel et al. 2012's orientation-free form
        ``‖a_A + K_A r_A‖ = ‖a_B + K_B r_B‖``, for long recordings whose relative heading
        drifts (6-D fusion); no heading is estimated (``heading_deg`` NaN).
    cutoff_hz : float or None
        Zero-phase low-pass (2nd-order Butterworth run forwards and backwards), Hz, below 0.45
        of the sampling rate; None: no low-pass (default
        :data:`CUTOFF_HZ`, Winter 2009). It is applied to both sides of the linear model, the
        measured acceleration ``R a`` and the regressor ``R K`` (not to ``K``'s inputs, which
        would break the model's ``ω²`` term for fast motion); the hinge axes use the low-passed
        gyro.
    min_excitation_s2 : float
        Least excitation per joint, s⁻² (default :data:`MIN_EXCITATION_S2`).
    declared_axes : mapping of str -> axis, optional
        Sensor axis declared along a segment (``"-e1"`` or a 3-vector, proximal -> distal),
        used for a last segment whose distal joint has no sensor beyond it (a forearm without a
        hand IMU, a shank without a foot IMU): its axis is then the declared one and its length
        must come from the session (tape measure); listed in ``declared``.

    Returns
    -------
    FunctionalCalibration
        ``axes`` and ``lengths_m`` (estimated, m) per segment with both joint centres located,
        ``method="functional"``, ``window_s``, and the report data (``joints``,
        ``excitation_s2``, ``heading_deg``, ``heading``, ``hinge_prior``). ``residual_deg`` is
        empty (there is no observed direction to compare with). ``frames`` (for
        :func:`~kinefuse.kinematics.joint_angles`) of the segments next to an elbow or knee:
        long axis = the calibrated axis, flexion axis from the movement
        (:func:`kinefuse.kinematics.hinge.hinge_frames`; zero flexion = the long axes aligned,
        sign by anatomy); a hinge that hardly moved gets no frames (a NumericalWarning).

    Notes
    -----
    The model, the excitation measure, the hinge prior and the failure modes:
    :mod:`kinefuse.kinematics.functional`.

    Warns
    -----
    NumericalWarning
        A segment whose functional length differs from the skeleton's by more than
        :data:`LENGTH_WARN_FRACTION` (its axis is then suspect too).

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        A segment without IMU, orientation, acc or gyro; a segment whose proximal or distal
        centre cannot be located (no IMU on the other side); a joint lacking excitation; an
        unknown ``heading``.
    """
    _check_arguments(recording, skeleton, constraint, heading, min_excitation_s2)
    segs = names_arg(segments, "segments")
    segs = list(skeleton.segments if segs is None else segs)
    if not segs:
        raise InputError("expected segments with at least one segment name, or None for all")
    for s in segs:
        skeleton.index(s)
    beyond = dict(DISTAL_SEGMENTS if distal_segments is None else distal_segments)
    hinges = set(HINGE_JOINTS if hinge_joints is None else hinge_joints)
    declared = {
        seg: unit_axis(a, f"declared_axes[{seg!r}]") for seg, a in (declared_axes or {}).items()
    }
    pairs = _joint_pairs(recording, skeleton, segs, proximal_segments or {}, beyond, declared)
    used = sorted({x for pr in pairs.values() for x in pr if x is not None})
    streams = {s: oriented_imu(recording, s, "functional calibration") for s in used}
    t_all = streams[segs[0]].t_s
    t = t_all[window_mask(t_all, start_s, window_s)]
    if t.size < 10:
        raise InputError(
            f"functional calibration: expected at least 10 samples in the window, got {t.size}"
        )
    _check_cutoff(cutoff_hz, t)
    sig = {s: joint_signals(st, s, t, cutoff_hz) for s, st in streams.items()}
    if heading == "auto":
        heading = "shared" if len({st.frame for st in streams.values()}) == 1 else "estimate"
    fits = _fit_joints(pairs, sig, t, cutoff_hz, min_excitation_s2, constraint)
    axes, lengths, prior = _segment_axes(skeleton, segs, fits, hinges, declared, min_excitation_s2)
    head = {} if constraint == "norm" else _chain_headings(pairs, fits)
    cal = FunctionalCalibration(
        axes=axes,
        lengths_m=lengths,
        method="functional",
        window_s=(float(t[0]), float(t[-1])),
        residual_deg={},
        align="none",
        joints=fits,
        excitation_s2={j: f.excitation_s2 for j, f in fits.items()},
        heading_deg={s: float((v + 180.0) % 360.0 - 180.0) for s, v in head.items()},
        heading=heading,
        hinge_prior=tuple(sorted(prior)),
        cutoff_hz=float(cutoff_hz),
        declared=tuple(s for s in segs if s not in lengths),
    )
    # segment frames of elbows and knees for joint angles: long axes from the joint centres,
    # flexion axes from the movement (kinefuse.kinematics.hinge), orientations in one heading
    same = recording if heading == "shared" else align_headings(recording, cal)
    return hinge_frames(same, cal, start_s=start_s, window_s=window_s)


def _check_arguments(recording, skeleton, constraint, heading, min_excitation_s2) -> None:
    """Validate the arguments of :func:`functional_calibration`."""
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    if not isinstance(skeleton, Skeleton):
        raise InputError(f"expected skeleton as a Skeleton, got {type(skeleton).__name__}")
    if constraint not in ("vector", "norm"):
        raise InputError(f"expected constraint in ('vector', 'norm'), got {constraint!r}")
    if heading not in ("auto", "shared", "estimate"):
        raise InputError(f"expected heading in ('auto', 'shared', 'estimate'), got {heading!r}")
    if not (np.isfinite(min_excitation_s2) and min_excitation_s2 >= 0):
        raise InputError(f"expected min_excitation_s2 >= 0, got {min_excitation_s2}")


def _check_cutoff(cutoff_hz, t: np.ndarray) -> None:
    """``cutoff_hz`` None (no low-pass) or a number in (0, 0.45 fs): at or above that the
    low-pass would be skipped, a NaN would switch it off, both silently."""
    if cutoff_hz is None:
        return
    fs = 1.0 / float(np.median(np.diff(t)))
    c = float(cutoff_hz) if isinstance(cutoff_hz, (int, float, np.number)) else np.nan
    if isinstance(cutoff_hz, (bool, np.bool_)) or not (np.isfinite(c) and 0 < c < 0.45 * fs):
        raise InputError(
            f"expected cutoff_hz in (0, {0.45 * fs:.3g}) Hz (0.45 x the {fs:.4g} Hz sampling "
            f"rate) or None for no low-pass, got {cutoff_hz!r}"
        )


def _joint_pairs(
    recording, skeleton, segs, proximal_segments, beyond, declared
) -> dict[str, tuple[str | None, str]]:
    """The two sensors (proximal or None, distal) of each joint the segments need."""
    pairs: dict[str, tuple[str | None, str]] = {}
    for s in segs:
        i = skeleton.index(s)
        prox, dist = skeleton.proximal[i], skeleton.distal[i]
        pairs[prox] = _proximal_pair(recording, skeleton, s, proximal_segments.get(prox))
        children = [skeleton.segments[k] for k, q in enumerate(skeleton.parents) if q == i]
        if children and children[0] in recording.imu:
            pairs[dist] = (s, children[0])
        elif not children and beyond.get(dist) in recording.imu:
            pairs[dist] = (s, beyond[dist])
        elif not children and s in declared:
            continue  # the declared sensor axis and the session's length stand in
        else:
            want = children[0] if children else beyond.get(dist)
            raise InputError(
                f"segment {s!r}: locating its distal joint {dist!r} needs an IMU on the next segment"
                + (f" ({want!r})" if want else " (pass distal_segments={joint: segment})")
                + f"; the recording has {sorted(recording.imu)}. Without it, declare the "
                f'sensor axis along {s!r} ([skeleton.axes] {s} = "-e1" or similar; '
                f"declared_axes=) and its measured length ([skeleton.lengths] {s})"
            )
    return pairs


def _proximal_pair(recording, skeleton, s: str, before: str | None) -> tuple[str | None, str]:
    """The sensors of segment ``s``'s proximal joint (``before``: a given proximal IMU)."""
    i = skeleton.index(s)
    prox, p = skeleton.proximal[i], skeleton.parents[i]
    if p >= 0:
        return (skeleton.segments[p], s)
    if before is not None:
        if before not in recording.imu:
            raise InputError(
                f"proximal_segments[{prox!r}] = {before!r}: no such IMU; the recording has "
                f"{sorted(recording.imu)}"
            )
        return (before, s)
    if skeleton.root_segment is not None and skeleton.root_segment in recording.imu:
        return (skeleton.root_segment, s)
    if skeleton.root_segment is not None:
        raise InputError(
            f"segment {s!r}: locating joint {prox!r} needs an IMU on the root segment "
            f"{skeleton.root_segment!r}; the recording has {sorted(recording.imu)}"
        )
    return (None, s)  # fixed centre (paper A's shoulder)


def _fit_joints(pairs, sig, t, cutoff_hz, min_excitation_s2, constraint) -> dict[str, JointFit]:
    """:func:`fit_joint` for every joint, residuals weighted by the effective sample count."""
    fs = 1.0 / float(np.median(np.diff(t)))
    n_eff_ratio = min(1.0, 2.0 * cutoff_hz / fs) if cutoff_hz else 1.0
    fits: dict[str, JointFit] = {}
    for joint, (a, b) in pairs.items():
        fits[joint], _ = fit_joint(
            joint,
            a,
            b,
            None if a is None else sig[a],
            sig[b],
            min_excitation_s2,
            n_eff_ratio,
            constraint,
        )
    return fits


def _segment_axes(skeleton, segs, fits, hinges, declared, min_excitation_s2):
    """Axis and length of each segment from its joint centres (hinge prior where needed)."""

    def r_in(seg: str, joint: str) -> np.ndarray:
        f = fits[joint]
        return f.r_distal_m if f.distal == seg else f.r_proximal_m

    def hinge_in(seg: str, joint: str) -> np.ndarray:
        f = fits[joint]
        return f.axis_distal if f.distal == seg else f.axis_proximal

    axes, lengths, prior = {}, {}, set()
    for s in segs:
        i = skeleton.index(s)
        if skeleton.distal[i] not in fits:  # no sensor beyond: the declared axis
            axes[s] = declared[s]
            continue
        d = r_in(s, skeleton.distal[i]) - r_in(s, skeleton.proximal[i])
        for jn in (skeleton.proximal[i], skeleton.distal[i]):
            f = fits[jn]
            if (
                jn in hinges
                and hinge_in(s, jn) is not None
                and f.axial_excitation_s2 < min_excitation_s2
            ):
                h = hinge_in(s, jn)
                d = d - h * np.dot(d, h)
                prior.add(jn)
        n = float(np.linalg.norm(d))
        if not np.isfinite(n) or n < 1e-3:
            raise InputError(
                f"segment {s!r}: the functional joint centres {skeleton.proximal[i]!r} and "
                f"{skeleton.distal[i]!r} coincide ({n:.3g} m apart); the movement does not separate them"
            )
        axes[s], lengths[s] = d / n, n
        _warn_length(s, n, skeleton.lengths_m[i])
    return axes, lengths, prior


def _warn_length(s: str, n: float, expect: float) -> None:
    """A NumericalWarning when a functional length is far from the skeleton's."""
    if expect > 0 and abs(n - expect) > LENGTH_WARN_FRACTION * expect:
        warnings.warn(
            f"functional calibration: segment {s!r} spans {n:.3f} m between its joint centres, "
            f"the skeleton says {expect:.3f} m ({100 * (n / expect - 1):+.0f} %); its centres, "
            "hence its axis, may be wrong (soft tissue, sensor saturation, a joint that is not "
            "a centre of rotation, or too little motion)",
            NumericalWarning,
            stacklevel=4,
        )


def _chain_headings(pairs, fits) -> dict[str, float]:
    """Heading of each sensor's world frame relative to its chain's first sensor, deg."""
    distal_side = {b for _, b in pairs.values()}
    head = {a: 0.0 for a, _ in pairs.values() if a is not None and a not in distal_side}
    head.update({b: 0.0 for a, b in pairs.values() if a is None})
    for _ in range(len(pairs)):
        for joint, (a, b) in pairs.items():
            if a in head and b not in head:
                head[b] = head[a] + fits[joint].heading_deg
    return head


def align_headings(recording: Recording, calibration: FunctionalCalibration) -> Recording:
    """The recording with each IMU orientation turned into its chain's first sensor's world frame.

    ``q_world_from_sensor ← Rz(−ψ_s) q_world_from_sensor`` with ``ψ_s`` =
    ``calibration.heading_deg[s]``; streams without an estimate are kept as they are.
    """
    if not isinstance(calibration, FunctionalCalibration):
        raise InputError(f"expected a FunctionalCalibration, got {type(calibration).__name__}")
    imu = dict(recording.imu)
    for s, psi in calibration.heading_deg.items():
        st = imu.get(s)
        if st is None or st.q_world_from_sensor is None or psi == 0.0:
            continue
        imu[s] = turned_heading(st, -psi)
    return replace(recording, imu=imu)
