"""The calibration step of :func:`kinefuse.pipelines.run.process_recording` and what it gives.

:func:`calibrate_session` runs :func:`kinefuse.kinematics.calibrate` as the session asks
(static pose, functional movement, camera or reference joints) and says in the notes and the
provenance what calibrated what; the calibrated sensor orientations and the joint angles
(where the calibration gives segment frames) are derived from it.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import NumericalWarning
from kinefuse.kinematics import (
    calibrate,
    find_still_window,
    joint_angles,
    segment_orientations,
)
from kinefuse.kinematics.angles import JOINTS, angle_words
from kinefuse.kinematics.calibration_result import turn_heading
from kinefuse.kinematics.functional import align_headings
from kinefuse.kinematics.hinge import OPPOSITE_DEG
from kinefuse.kinematics.still import MIN_STILL_S
from kinefuse.orientation.resample import slerp_resample
from kinefuse.session_file.from_recording import (
    NO_HEIGHT_RATIO,
    RecordingSketch,
    sketch_recording,
)

__all__ = ["CALIBRATION_WINDOW_S", "calibrate_session", "no_still_window", "sketch_for_session"]

#: Plausible flexion of hinge joints, deg (1st-99th percentile check of the joint angles):
#: knee -10 (hyperextension) to 150, elbow -10 to 160 (e.g. Soucie et al. 2011, Haemophilia 17);
#: ankle -60 (plantarflexion) to 40 (dorsiflexion of a deep squat), looser than the passive
#: ranges of that study (about -55 to 25), since a loaded ankle dorsiflexes further.
_HINGE_RANGE_DEG = {"knee": (-10.0, 150.0), "elbow": (-10.0, 160.0), "ankle": (-60.0, 40.0)}

_WHAT = {
    "static": "still pose, IMU data only",
    "functional": "movement, IMU data only",
    "vision": "camera joints",
    "reference": "REFERENCE joints (evaluation data used for calibration, as asked)",
}


def _facing(value):
    """``[calibration] facing``: ``"auto"`` (default: estimated from the movement of elbows and
    knees, see :func:`kinefuse.kinematics.calibrate`) or a declared direction."""
    return value if isinstance(value, str) else tuple(float(x) for x in value)


#: Default still-window length of a static calibration (``[calibration] window_s``), s.
CALIBRATION_WINDOW_S = 2.0


def sketch_for_session(recording, session_dir, fmt: str | None = None) -> RecordingSketch:
    """:func:`~kinefuse.session_file.from_recording.sketch_recording` with the static
    calibration's still-window search (its default window, :data:`CALIBRATION_WINDOW_S`):
    ``kinefuse init-session --from`` chooses functional calibration when nothing holds still."""
    return sketch_recording(recording, session_dir, fmt, still=no_still_window)


def no_still_window(streams: Mapping) -> str:
    """Empty when the IMU ``streams`` of body-height-sized segments (not the feet or hands:
    :data:`~kinefuse.session_file.from_recording.NO_HEIGHT_RATIO`) hold still together for
    :data:`CALIBRATION_WINDOW_S` somewhere (a static calibration can work), else why not: the
    stillest window and its angular rate. Chooses the calibration where the user did not
    (``init-session --from``, ``kinefuse evaluate``); empty without such a stream."""
    sized = {s: st for s, st in streams.items() if s not in NO_HEIGHT_RATIO}
    if not sized:
        return ""
    w = find_still_window(sized, CALIBRATION_WINDOW_S)
    if w.end_s - w.start_s < MIN_STILL_S:
        return (
            f"the IMUs share only {w.end_s - w.start_s:.2f} s, too short to hold a pose for a "
            "static calibration"
        )
    if w.still:
        return ""
    return (
        f"no still window of {w.end_s - w.start_s:.0f} s for a static calibration (stillest "
        f"{w.start_s:.1f}-{w.end_s:.1f} s: {w.rate_rad_s:.2f} rad/s on {w.worst_rate})"
    )


def _calibration_kwargs(params: Mapping, calib: str, six_d, axes_decl, cal_segs,
                        proximal=None) -> dict:  # fmt: skip
    """Keyword arguments of :func:`kinefuse.kinematics.calibrate` for ``calib``."""
    window = float(params.get("calibration_window_s", CALIBRATION_WINDOW_S))
    start = params.get("calibration_start_s")
    kw = {"window_s": window, "start_s": None if start is None else float(start)}
    if calib == "static":
        heading = params.get("heading", "auto")
        if heading == "auto":
            heading = "static" if six_d else "none"
        kw.update(
            pose=params.get("pose", "n"),
            facing=_facing(params.get("facing", "auto")),
            heading=heading,
            flexion_axes=params.get("flexion_axes", "auto"),
            mounting={s: a for s, a in axes_decl.items() if s in cal_segs},
            segments=cal_segs,
        )
        for k in ("max_rate_rad_s", "max_acc_std_m_s2"):
            if k in params:
                kw[k] = float(params[k])
    elif calib in ("vision", "reference"):
        kw["align"] = params.get("align", "auto")
    elif calib == "functional":
        kw["mounting"] = {s: a for s, a in axes_decl.items() if s in cal_segs}
        if proximal:
            kw["proximal_segments"] = dict(proximal)
    return kw


def calibrate_session(
    recording,
    skeleton,
    params: Mapping,
    calib: str,
    six_d,
    axes_decl: Mapping,
    cal_segs: Sequence[str],
    notes: list[str],
    provenance: dict,
    proximal: Mapping[str, str] | None = None,
    run_warnings: list[str] | None = None,
):
    """Calibrate the chain as ``calib`` says; notes and provenance are appended to in place.

    ``proximal``: the IMU proximal to each root joint the functional calibration locates, where
    it is not the skeleton's ``root_segment`` (e.g. the chest for the shoulders).
    ``run_warnings``: the calibration's own warnings (a segment far from the pose, a window that
    is not still, a hinge axis that contradicts the pose...) are appended to it too, so that the
    user sees them where the run's warnings are shown, not only in the report's notes.

    Returns
    -------
    recording : Recording
        ``recording``, or a copy with the sensors' headings aligned (functional calibration).
    cal : Calibration or None
        None for ``calib = "none"``.
    """
    if calib == "none":
        notes.append("calibration: none; the segment axes are the configured sensor axes")
        return recording, None
    kw = _calibration_kwargs(params, calib, six_d, axes_decl, cal_segs, proximal)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cal = calibrate(recording, skeleton, calib, **kw)
    notes += [f"calibration: {w.message}" for w in caught]
    if run_warnings is not None:
        run_warnings += [str(w.message) for w in caught if issubclass(w.category, NumericalWarning)]
    if calib == "functional" and cal.declared:
        notes.append(
            "calibration: no sensor beyond the distal joint of "
            f"{', '.join(cal.declared)}: the declared sensor axis ([skeleton.axes]) is its "
            "axis and its length comes from the session"
        )
    if calib == "functional" and getattr(cal, "heading", "shared") == "estimate":
        recording = align_headings(recording, cal)
        notes.append(
            "heading: each sensor's world frame turned into its chain's first sensor's, "
            "from the joint constraints of the functional calibration (deg): "
            + ", ".join(f"{s} {v:.1f}" for s, v in cal.heading_deg.items())
        )
        provenance["heading"] = "joint constraints (functional)"
    res = ", ".join(f"{s} {v:.1f}" for s, v in cal.residual_deg.items())
    line = (
        f"calibration {calib!r} ({_WHAT[calib]}) over {cal.window_s[0]:.2f}-"
        f"{cal.window_s[1]:.2f} s, alignment {cal.align!r}"
        + (f"; RMS residual (deg): {res}" if res else "")
    )
    if cal.still is not None:
        line += f"; stillness {cal.still.describe()}"
    if cal.pose_residual_deg:
        line += "; declared sensor axis vs the pose (deg): " + ", ".join(
            f"{s} {v:.1f}" for s, v in cal.pose_residual_deg.items()
        )
    notes.append(line)
    provenance["calibration_window_s"] = list(cal.window_s)
    if calib == "static":
        _static_notes(cal, six_d, cal_segs, notes, provenance)
    return recording, cal


def _static_notes(cal, six_d, cal_segs, notes: list[str], provenance: dict):
    """What a static calibration took from the pose, the movement and the declared facing."""
    f = [round(float(x), 3) for x in cal.facing] if cal.facing is not None else [0.0, 1.0, 0.0]
    hinged = sorted(cal.hinge_residual_rad_s)
    moved = {s for j in hinged for s in JOINTS[j][:2]}
    rest = [s for s in cal.frames if s not in moved]
    if hinged:
        notes.append(
            "segment frames: long axes from the still pose; flexion axes of "
            f"{', '.join(hinged)} from the movement (the two sensors' relative rotation, "
            "Laidig et al. 2017's elbow model; RMS residual rad/s: "
            + ", ".join(f"{j} {cal.hinge_residual_rad_s[j]:.2f}" for j in hinged)
            + "), sign by anatomy (the larger excursion from the pose is flexion); the "
            "facing is not used for them"
        )
        provenance["flexion_axes"] = {j: "movement" for j in hinged}
    how = {
        "declared": "as declared ([calibration] facing)",
        "hinges": "estimated from the flexion axes fitted to the movement of " + ", ".join(hinged),
        "default": (
            f"north by default (the flexion axes of {', '.join(hinged)} gave no common one: see the "
            "facing note; declare [calibration] facing)"
            if hinged
            else "north by default (no elbow or knee moved enough to estimate it; declare "
            "[calibration] facing)"
        ),
    }.get(cal.facing_from, "as declared")
    turned = dict(getattr(cal, "limb_heading_deg", {}) or {})
    if turned and cal.facing_from == "default":
        how = f"the common 6-D heading of {cal_segs[0]}'s sensor (any facing serves: 6-D)"
    deg = float(np.degrees(np.arctan2(f[0], f[1])))
    notes.append(f"facing: {f} (world frame, {deg:.0f} deg from north towards east), {how}")
    provenance["facing"] = f
    provenance["facing_from"] = cal.facing_from or "declared"
    if rest:
        notes.append(
            f"segment frames of {', '.join(rest)}: anterior axis = the facing direction "
            "in the still pose; flexion axes follow from it"
        )
    if cal.world_heading_deg:
        notes.append(
            "heading: 6-D orientations (arbitrary heading per sensor) brought into the "
            f"heading of {cal_segs[0]} from the static pose, assuming all sensors face "
            "the same way on the body; applied (deg): "
            + ", ".join(f"{s} {v:.1f}" for s, v in cal.world_heading_deg.items())
        )
        provenance["heading"] = "static pose"
        _turn_notes(cal, notes, provenance)
    else:
        notes.append(
            "heading: orientations kept as estimated (shared, magnetometer-referenced north)"
            if not six_d
            else "heading: not aligned (heading = 'none')"
        )
        provenance["heading"] = "none"


def _each(d: Mapping) -> str:
    return ", ".join(f"{j} {v:.1f}" for j, v in d.items())


def _turn_notes(cal, notes: list[str], provenance: dict) -> None:
    """Notes and provenance of the sensors turned about the vertical by the movement (6-D):
    limbs by their hinges, feet by their ankles, the pelvis by its hips."""
    limbs, feet, pelvis = cal.limb_heading_deg, cal.foot_heading_deg, cal.pelvis_heading_deg
    found = []
    if limbs:
        found.append(("limb_heading_deg", {j: round(v, 2) for j, v in limbs.items()},
            f"heading: the limbs of {_each(limbs)} deg turned (included above) so that each "
            "flexion axis fitted to the movement is the body's medio-lateral axis in the pose, "
            "as the trunk's: their sensors need not face the same way on the body, and the "
            "shoulders and hips read zero in the pose"))  # fmt: skip
    if feet:
        found.append(("foot_heading_deg", {j: round(v, 2) for j, v in feet.items()},
            f"heading: the foot sensors turned relative to their shanks (included above) by "
            f"{_each(feet)} deg, fitted to each ankle's movement (flexion axis in the shank, "
            "axial rotation of the foot; Laidig et al. 2017's model): a foot sensor need not "
            "face as the shank's does"))  # fmt: skip
    if pelvis:
        found.append(("pelvis_heading_deg", round(float(pelvis["turn"]), 2),
            f"heading: the pelvis sensor turned by {pelvis['turn']:.1f} deg (included above), as "
            f"its hips' movement says: their angular rates (modulo 180 deg: "
            f"{_each(pelvis['rates'])}), their centres' accelerations choosing the half "
            f"({_each(pelvis['accelerations'])}); its frame turned with it, so the pose reads as "
            "before"))  # fmt: skip
    for key, value, text in found:
        notes.append(text)
        provenance[key] = value


def _sensor_orientations(recording, cal, t: np.ndarray, notes: list[str]) -> dict[str, np.ndarray]:
    """``q_world_from_sensor`` on ``t`` of every mapped IMU whose world frame the calibration
    puts in the common one (heading corrections applied); the others are named in ``notes``.

    Every IMU is in the common frame when no heading was estimated per sensor (the frames are
    shared); where headings were estimated (static ``heading="static"``, functional
    ``heading="estimate"``), only those the calibration turned are."""
    turned = set(cal.world_heading_deg)
    if getattr(cal, "heading", None) == "estimate":  # functional: the joint pairs' sensors
        turned |= {x for f in cal.joints.values() for x in (f.proximal, f.distal) if x}
    calibrated = set(cal.axes)
    out, left = {}, []
    for s, st in recording.imu.items():
        if s not in SEGMENTS or st.q_world_from_sensor is None:
            continue
        if turned and s not in turned and s not in calibrated:
            left.append(s)
            continue
        q = slerp_resample(st.t_s, st.q_world_from_sensor, t)  # NaN rows stay NaN
        out[s] = turn_heading(q, cal.world_heading_deg.get(s, 0.0))
    if left:
        notes.append(
            f"sensor orientations: {', '.join(left)} left out (their heading relative to the "
            "other sensors was not estimated by this calibration)"
        )
    return out


def _joint_angles(
    recording, cal, t: np.ndarray, notes: list[str], warnings: list[str] | None = None
) -> dict[str, np.ndarray]:
    """ISB joint angles (deg) from the calibrated segment frames, with a range check (a
    flexion beyond the anatomical range is a warning: in ``notes`` and ``warnings``, which the
    CLI prints)."""
    angles = joint_angles(segment_orientations(recording, cal, t))
    if angles:
        notes.append(
            "joint angles (deg, ISB: Wu et al. 2002/2005, Grood & Suntay 1983; zero in the "
            f"calibration pose): {', '.join(angles)}"
        )
    for j, a in angles.items():
        lo, hi = _HINGE_RANGE_DEG.get(j.rsplit("_", 1)[0], (-np.inf, np.inf))
        f = a[:, 0][np.isfinite(a[:, 0])]
        if f.size and (np.percentile(f, 1) < lo or np.percentile(f, 99) > hi):
            msg = (
                f"{j} flexion spans {f.min():.0f} to {f.max():.0f} deg, beyond the "
                f"anatomical {lo:.0f} to {hi:.0f} deg: the facing direction or the pose is "
                "probably wrong (the facing, the pose, or too little flexion to fit its axis: see "
                "the calibration warnings and the report's notes; [calibration] flexion_axes, "
                "facing)"
            )
            notes.append(f"warning: {msg}")
            if warnings is not None:
                warnings.append(msg)
    for msg in _pose_angle_check(angles, t, cal):
        notes.append(f"warning: {msg}")
        if warnings is not None:
            warnings.append(msg)
    return angles


#: A joint angle farther than this from zero in a static calibration's pose is a warning, deg.
POSE_ANGLE_WARN_DEG = 20.0


def _pose_angle_check(angles: Mapping[str, np.ndarray], t: np.ndarray, cal) -> list[str]:
    """Static calibration: every joint angle reads the pose's own in the pose by construction
    (each frame is built from it: zero, or a T-pose's shoulder abduction, ``pose_angles_deg``);
    one that does not says the frames disagree (e.g. a facing the hinges did not confirm, or
    sensors whose headings differ). The circular mean over the window, per angle."""
    if cal.still is None or not angles:
        return []
    win = (t >= cal.window_s[0]) & (t <= cal.window_s[1])
    out = []
    for j, a in angles.items():
        want = np.asarray(cal.pose_angles_deg.get(j, np.zeros(3)))
        rad = np.radians(a[win])
        ok = np.all(np.isfinite(rad), axis=-1)
        if not ok.any():
            continue
        mean = np.degrees(np.angle(np.mean(np.exp(1j * rad[ok]), axis=0)))
        off = (mean - want + 180.0) % 360.0 - 180.0
        if abs(abs(want[1]) - 90.0) < 1.0:  # a T-pose shoulder: flexion and rotation undefined
            off[[0, 2]] = 0.0
        names = angle_words(j)
        bad = [f"{c} {v:.0f}" for c, v, d in zip(names, mean, off, strict=True)
               if abs(d) > POSE_ANGLE_WARN_DEG]  # fmt: skip
        if bad:
            fix = _hinge_advice(cal, j, off[2]) or (  # heading = "static": where not applied
                "declare [calibration] facing, or check that each sensor sits on the segment "
                "it is mapped to (the headings were already aligned in the pose)"
                if cal.world_heading_deg
                else 'declare [calibration] facing, or heading = "static" for 6-D sensors'
            )
            if j.startswith(("elbow", "knee")) and abs(off[0]) > POSE_ANGLE_WARN_DEG:
                fix += (  # a bent hinge in the window, or an N-pose declared as a T-pose
                    "; or the limb was bent in the window, or the pose held was not the declared "
                    '[calibration] pose ("n": arms hanging, "t": arms out)'
                )
            pose = "zero"
            if np.any(np.abs(want) > 0.5):
                pose = ", ".join(f"{c} {v:.0f}" for c, v in zip(names, want, strict=True))
            out.append(
                f"{j} reads {', '.join(bad)} deg in the calibration pose ({cal.window_s[0]:.2f}-"
                f"{cal.window_s[1]:.2f} s), where it reads {pose} by construction: its "
                "segment frames disagree (the facing, or sensor headings that differ: see the "
                f"calibration warnings and the report's notes; {fix})"
            )
    return out


def _hinge_advice(cal, joint: str, rotation_deg: float) -> str:
    """What to do when a shoulder or hip reads a rotation in the pose because its distal
    segment's frame comes from a hinge fitted to the movement (elbow, knee) whose front
    disagrees with the trunk's; empty for other joints."""
    limb = JOINTS[joint][1]
    hinge = next((h for h in cal.hinge_residual_rad_s if JOINTS[h][0] == limb), None)
    if hinge is None or abs(rotation_deg) <= POSE_ANGLE_WARN_DEG:
        return ""
    dist = JOINTS[hinge][1]
    why = (
        f"{limb}'s frame comes from the flexion axis of {hinge} fitted to the movement, which "
        f"puts its front {abs(rotation_deg):.0f} deg from {JOINTS[joint][0]}'s"
    )
    if abs(rotation_deg) >= OPPOSITE_DEG:
        return (
            f"{why}, nearly backwards: are the sensors of {limb} and {dist} swapped in "
            "[imu.segments]? (a swapped pair reverses the fitted axis); otherwise the sensors' "
            'headings are not shared: heading = "static" turns each limb to its flexion axis'
        )
    return (
        f'{why}: the sensors\' headings are not shared (heading = "static" turns each limb to '
        f"its flexion axis), or a sensor is not on the segment it is mapped to"
    )
