"""The IMU chain: sensor orientations, the skeleton over the mapped segments, its roots.

:func:`build_chain` builds the :class:`~kinefuse.kinematics.Skeleton` over the limb segments
that carry an IMU (:data:`SEGMENT_JOINTS`); the private steps of
:func:`kinefuse.pipelines.run.process_recording` estimate missing orientations, resolve the
segment lengths and place the chain's root joints.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from kinefuse.exceptions import ConfigError, InputError
from kinefuse.kinematics import (
    ANTHROPOMETRIC_RATIOS,
    AXES,
    Skeleton,
    lengths_from_joints,
    segment_lengths,
    segment_orientations,
)
from kinefuse.kinematics.forward import as_rotation_matrices
from kinefuse.orientation import estimate
from kinefuse.orientation.resample import slerp_resample
from kinefuse.pipelines.run.timeline import sample_joint

__all__ = ["SEGMENT_JOINTS", "build_chain"]

#: Proximal and distal joint of every limb segment (segments with a length).
SEGMENT_JOINTS = {
    **{f"upper_arm_{s}": (f"shoulder_{s}", f"elbow_{s}") for s in "lr"},
    **{f"forearm_{s}": (f"elbow_{s}", f"wrist_{s}") for s in "lr"},
    **{f"thigh_{s}": (f"hip_{s}", f"knee_{s}") for s in "lr"},
    **{f"shank_{s}": (f"knee_{s}", f"ankle_{s}") for s in "lr"},
    **{f"foot_{s}": (f"ankle_{s}", f"foot_{s}") for s in "lr"},
    **{f"hand_{s}": (f"wrist_{s}", f"hand_{s}") for s in "lr"},
}


def _ensure_orientations(
    recording, params: Mapping, notes: list[str], warnings_out: list[str]
) -> set[str]:
    """Estimate ``q_world_from_sensor`` with VQF for the streams that have raw data only.

    The policy is ``estimate_orientation`` of ``[method.parameters]``: ``"auto"`` (default)
    estimates only when no mapped sensor has an orientation (a raw-only recording), ``true``
    for every sensor without one, ``false`` never. The substitution is always reported (a
    warning in the run summary and the report), never silent.

    Returns the segments whose orientation is 6-D (no magnetometer: arbitrary heading).
    """
    vqf_params = params.get("orientation_params")
    policy = params.get("estimate_orientation", "auto")
    if policy not in ("auto", True, False):
        raise ConfigError(
            f"[method.parameters] estimate_orientation: expected true, false or 'auto', got "
            f"{policy!r}"
        )
    lacking = [seg for seg, st in recording.imu.items() if st.q_world_from_sensor is None]
    having = [seg for seg in recording.imu if seg not in lacking]
    if lacking and (policy is False or (policy == "auto" and having)):
        why = (
            f"while {', '.join(having)} {'has' if len(having) == 1 else 'have'} one"
            if having
            else "and estimate_orientation = false"
        )
        raise InputError(
            f"no orientation for {', '.join(lacking)} in the IMU file (quaternion columns "
            f"missing or all empty) {why}; kinefuse does not substitute an estimate silently: "
            "set estimate_orientation = true in [method.parameters] to estimate it from acc + "
            "gyr with VQF, or fix the file"
        )
    six_d: set[str] = set()
    how: dict[str, list[str]] = {}  # the orientation notes, one line per kind
    for seg, st in list(recording.imu.items()):
        if st.q_world_from_sensor is not None:
            continue
        ok = np.all(np.isfinite(st.acc_m_s2), axis=1) & np.all(np.isfinite(st.gyr_rad_s), axis=1)
        acc, gyr = st.acc_m_s2, st.gyr_rad_s
        if not np.all(ok):  # hold the last valid sample across gaps (VQF needs finite input)
            idx = np.maximum.accumulate(np.where(ok, np.arange(ok.size), 0))
            first = int(np.flatnonzero(ok)[0])
            idx[:first] = first
            acc, gyr = acc[idx], gyr[idx]
        mag = None
        if st.mag is not None and np.all(np.isfinite(st.mag)):
            mag = st.mag
        try:
            q = estimate(acc, gyr, mag, rate_hz=st.rate_hz, params=vqf_params)
        except InputError as exc:
            raise InputError(f"IMU {seg!r}: orientation estimation failed: {exc}") from None
        q[~ok] = np.nan
        recording.imu[seg] = replace(st, q_world_from_sensor=q)
        how.setdefault(
            "9D, magnetometer" if mag is not None else "6D, arbitrary heading", []
        ).append(seg)
        if mag is None:
            six_d.add(seg)
    notes += [
        f"{', '.join(segs)}: orientation estimated from raw data with VQF ({kind})"
        for kind, segs in how.items()
    ]
    if lacking:
        msg = (
            f"the IMU file has no orientation for {', '.join(lacking)}: estimated from acc + "
            "gyr with VQF (policy estimate_orientation = "
            f"{'true' if policy is True else 'auto: no sensor has one'})"
        )
        notes.append(f"WARNING: {msg}")
        warnings_out.append(msg)
    return six_d


def build_chain(
    segments: Sequence[str],
    lengths: Mapping[str, float],
    axes: Mapping[str, object] | None = None,
):
    """A Skeleton over the given limb segments, rooted at the proximal joints of unparented ones.

    Parameters
    ----------
    segments : sequence of str
        Limb segments (:data:`SEGMENT_JOINTS` keys), e.g. ``("thigh_l", "shank_l")`` or
        ``("forearm_r",)``; a segment's parent is the segment whose distal joint is its
        proximal joint, if given.
    lengths : mapping of str -> float
        Length of every segment, m.
    axes : mapping, optional
        Segment axis in each sensor frame (default ``+e2``).

    Returns
    -------
    Skeleton
        Parents before children; the first root joint is ``root``, further roots are offset
        joints of unknown offset (to be given as root positions, e.g. from a camera).
    roots : tuple of str
        The root joints, whose positions must be supplied.
    """
    segs = [s for s in SEGMENT_JOINTS if s in set(segments)]
    unknown = sorted(set(segments) - set(SEGMENT_JOINTS))
    if unknown:
        raise InputError(f"segments {unknown} have no length; expected limb segments")
    order: list[str] = []
    pending = list(segs)
    distal = {SEGMENT_JOINTS[s][1]: s for s in segs}
    while pending:
        for s in list(pending):
            parent = distal.get(SEGMENT_JOINTS[s][0])
            if parent is None or parent in order:
                order.append(s)
                pending.remove(s)
    parents = []
    roots: list[str] = []
    for s in order:
        parent = distal.get(SEGMENT_JOINTS[s][0])
        parents.append(-1 if parent is None else order.index(parent))
        if parent is None and SEGMENT_JOINTS[s][0] not in roots:
            roots.append(SEGMENT_JOINTS[s][0])
    axes = dict(axes or {})
    sk = Skeleton(
        segments=tuple(order),
        parents=tuple(parents),
        proximal=tuple(SEGMENT_JOINTS[s][0] for s in order),
        distal=tuple(SEGMENT_JOINTS[s][1] for s in order),
        lengths_m=tuple(float(lengths[s]) for s in order),
        axes=np.array([axes.get(s, (0.0, 1.0, 0.0)) for s in order], dtype=float),
        root=roots[0],
        root_segment="pelvis" if len(roots) > 1 else None,
        offsets_m={j: (np.nan,) * 3 for j in roots[1:]},
    )
    return sk, tuple(roots)


def _declared_axes(value, segs) -> dict[str, tuple]:
    """``[skeleton.axes]``: segment -> sensor axis along it (names ``"+e1"``... or 3-vectors)."""
    out = {}
    for s, a in dict(value or {}).items():
        if s not in SEGMENT_JOINTS and s != "pelvis":
            raise ConfigError(f"[skeleton.axes] {s}: not a limb segment or 'pelvis'")
        if isinstance(a, str):
            if a not in AXES:
                raise ConfigError(
                    f"[skeleton.axes] {s}: unknown axis {a!r}; expected one of {sorted(AXES)}"
                )
            a = AXES[a]
        v = np.asarray(a, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
            raise ConfigError(f"[skeleton.axes] {s}: expected an axis name or [x, y, z], got {a!r}")
        out[s] = tuple(v / np.linalg.norm(v))
    return out


def hip_width_m(body_height_m) -> float:
    """Distance between the hip joint centres for hips placed from the pelvis IMU, m: 0.0928
    x body height (OpenSim gait2392, Delp et al. 1990; ``ANTHROPOMETRIC_RATIOS
    ["hip_joint_spacing"]``, which says why not Winter's hip breadth)."""
    if body_height_m is None:
        raise ConfigError(
            "the hips are placed from the pelvis IMU with the hip joint spacing 0.0928 x body "
            "height (OpenSim gait2392); give [skeleton] body_height_m"
        )
    return ANTHROPOMETRIC_RATIOS["hip_joint_spacing"] * float(body_height_m)


def pelvis_right_in_sensor(cal) -> np.ndarray:
    """The pelvis right axis (ISB Z) in the pelvis sensor's frame: the calibrated pelvis frame's,
    else the sensor's x (a right-front-up sensor: ISB X fwd = y, Y up = z, Z right = x)."""
    return trunk_frame_in_sensor(cal, "pelvis")[:, 2]


def trunk_frame_in_sensor(cal, segment: str) -> np.ndarray:
    """``R_sensor_from_segment (3, 3)`` of a trunk segment (``pelvis``, ``chest``): columns ISB
    X anterior, Y superior, Z right in the sensor's frame. The calibrated frame (static pose),
    else the sensor taken as right-front-up (X = sensor y, Y = sensor z, Z = sensor x)."""
    if cal is not None and segment in cal.frames:
        return np.asarray(cal.frames[segment], dtype=float)
    return np.eye(3)[:, [1, 2, 0]]


def shoulders_from_trunk(plan: Mapping) -> bool:
    """Whether a session plan places its shoulders from the trunk IMU: both arms, or arms and
    legs, without a root position per joint (``plan["shoulders"]``, set by the plan, which
    checked that a trunk IMU is mapped)."""
    return bool(plan.get("shoulders"))


def shoulder_trunk(imus) -> str | None:
    """The IMU the shoulders are placed from: the chest's, else the pelvis's, else None."""
    return next((s for s in ("chest", "pelvis") if s in imus), None)


def shoulder_offsets_m(body_height_m, above_hips: bool) -> dict[str, np.ndarray]:
    """Shoulder centres in the trunk's ISB frame (X anterior, Y up, Z right), m: ± half the
    shoulder joint spacing 0.189 H along Z (OpenSim full-body model; ``ANTHROPOMETRIC_RATIOS
    ["shoulder_joint_spacing"]``, which says why not Winter's shoulder breadth 0.259 H), and
    0.288 H up (the acromion, 0.818 H, above the greater trochanter, 0.530 H) when the origin is
    the mid-hip point (Winter 2009, Fig. 4.1)."""
    if body_height_m is None:
        raise ConfigError(
            "the shoulders are placed from the trunk IMU with the shoulder joint spacing 0.189 x "
            "body height (OpenSim full-body model); give [skeleton] body_height_m"
        )
    H = float(body_height_m)
    up = ANTHROPOMETRIC_RATIOS["chest_to_hip"] * H if above_hips else 0.0
    half = 0.5 * ANTHROPOMETRIC_RATIOS["shoulder_joint_spacing"] * H
    return {"shoulder_l": np.array([0.0, up, -half]), "shoulder_r": np.array([0.0, up, half])}


def _trunk_orientation(recording, cal, t, segment: str) -> tuple[np.ndarray, str]:
    """``R_world_from_segment (T, 3, 3)`` of a trunk segment on ``t`` (ISB columns, see
    :func:`trunk_frame_in_sensor`) and how it was found."""
    if cal is not None and segment in cal.frames:
        R = segment_orientations(recording, cal, t, [segment])[segment]
        how = {
            "static": "the static calibration (Z = right in the pose)",
            "reference": "the reference calibration (Z = right along its shoulders or hips)",
            "vision": "the camera calibration (Z = right along its shoulders or hips)",
        }.get(cal.method, f"the {cal.method} calibration")
        return R, f"the {segment} frame of {how}"
    st = recording.imu[segment]
    R = as_rotation_matrices(slerp_resample(st.t_s, st.q_world_from_sensor, t))
    how = f"the {segment} sensor frame taken as right-front-up (no calibrated {segment} frame)"
    return R @ trunk_frame_in_sensor(None, segment), how


#: Plausible distance between the two hip joint centres, m (adults: about 0.15-0.20 m); a
#: functional estimate outside it is not used.
HIP_WIDTH_RANGE_M = (0.10, 0.40)


def hip_offsets_in_pelvis_sensor(cal, body_height_m) -> tuple[dict[str, np.ndarray], str]:
    """The hip joint centres relative to the mid-hip point in the pelvis sensor's frame, m, and
    where they come from.

    A functional calibration that fitted both hips against the pelvis IMU gives them directly
    (each hip's sensor-to-centre vector ``r_proximal_m``, minus their mean), when their distance
    is plausible (:data:`HIP_WIDTH_RANGE_M`). Otherwise ± half the hip joint spacing 0.0928 x
    body height (:func:`hip_width_m`) along the pelvis right axis (:func:`pelvis_right_in_sensor`: the
    calibrated pelvis frame's, else the sensor taken as right-front-up).
    """
    fits = getattr(cal, "joints", None) or {}
    r = {h: getattr(fits.get(h), "r_proximal_m", None) for h in ("hip_l", "hip_r")}
    from_pelvis = all(fits.get(h) is not None and fits[h].proximal == "pelvis" for h in r)
    if from_pelvis and all(v is not None and np.all(np.isfinite(v)) for v in r.values()):
        mid = 0.5 * (r["hip_l"] + r["hip_r"])
        w = float(np.linalg.norm(r["hip_r"] - r["hip_l"]))
        lo, hi = HIP_WIDTH_RANGE_M
        if lo <= w <= hi:
            how = (
                f"the hip centres of the functional calibration in the pelvis sensor frame "
                f"(hip width {w:.3f} m)"
            )
            return {h: v - mid for h, v in r.items()}, how
        rejected = f"; the functional hip centres ({w:.3f} m apart) are outside {lo}-{hi} m"
    else:
        rejected = ""
    w = hip_width_m(body_height_m)
    right = pelvis_right_in_sensor(cal)
    frame = (
        "the calibrated pelvis frame"
        if cal is not None and "pelvis" in cal.frames
        else "the pelvis sensor frame taken as right-front-up (no calibrated pelvis frame)"
    )
    how = (
        f"± {w / 2:.3f} m along the pelvis right axis (hip joint spacing 0.0928 x "
        f"{float(body_height_m):g} m, OpenSim gait2392) of {frame}{rejected}"
    )
    return {"hip_l": -0.5 * w * right, "hip_r": 0.5 * w * right}, how


def _hip_roots(recording, cal, t, origin, body_height_m, notes) -> dict[str, np.ndarray]:
    """Hip joint centres from the pelvis IMU: origin (mid-hip) plus the offsets of
    :func:`hip_offsets_in_pelvis_sensor` turned by the pelvis sensor's orientation."""
    off, how = hip_offsets_in_pelvis_sensor(cal, body_height_m)
    st = recording.imu["pelvis"]
    R = as_rotation_matrices(slerp_resample(st.t_s, st.q_world_from_sensor, t))
    if cal is not None and getattr(cal, "world_heading_deg", None):
        R = cal.heading_matrix("pelvis") @ R
    notes.append(f"hips: pelvis origin (mid-hip) plus {how}")
    return {h: origin + R @ o for h, o in off.items()}


def _shoulder_roots(recording, cal, t, origin, above_hips, body_height_m, notes):
    """Shoulder centres from the trunk IMU (:func:`shoulder_trunk`) at the offsets of
    :func:`shoulder_offsets_m` from ``origin`` (the mid-hip point when ``above_hips``, else the
    mid-shoulder point)."""
    trunk = shoulder_trunk(recording.imu)
    R, how = _trunk_orientation(recording, cal, t, trunk)
    off = shoulder_offsets_m(body_height_m, above_hips)
    up, half = off["shoulder_r"][1], off["shoulder_r"][2]
    notes.append(
        "shoulders: "
        + (f"{up:.3f} m up the {trunk} axis from the mid-hip point, then " if above_hips else "")
        + f"± {half:.3f} m along the {trunk} right axis (shoulder joint spacing "
        + f"0.189 x {float(body_height_m):g} m, OpenSim full-body model"
        + (
            f"; acromion 0.288 x {float(body_height_m):g} m above the hip joint, Winter 2009"
            if above_hips
            else ""
        )
        + f"), from {how}"
        + (
            "; the trunk is taken as rigid with the pelvis (no chest IMU)"
            if trunk == "pelvis"
            else ""
        )
    )
    return {j: origin + R @ o for j, o in off.items()}


def _resolve_lengths(
    recording, segs, cal, calib, root_kind, use_stream_lengths, measured, body_height_m, notes
) -> tuple[dict[str, float], dict[str, str]]:
    """Segment lengths, m, and where each came from (measured, stream, functional, height)."""
    derived = {}
    if (
        use_stream_lengths
        and cal is not None
        and cal.lengths_m
        and calib in ("vision", "reference")
    ):
        src = "camera" if calib == "vision" else "REFERENCE"
        derived = {s: (v, f"{src} (calibration window)") for s, v in cal.lengths_m.items()}
    functional = dict(cal.lengths_m) if cal is not None and calib == "functional" else {}
    if root_kind == "vision" and use_stream_lengths:
        got = lengths_from_joints(
            recording.vision, [(s, *SEGMENT_JOINTS[s]) for s in segs], missing="skip"
        )
        for s, v in got.items():
            derived.setdefault(s, (v, "camera (median)"))
    try:
        seg_lengths, how = segment_lengths(
            segs,
            measured=measured,
            height_m=body_height_m,
            functional=functional,
            derived=derived,
        )
    except InputError as exc:
        raise ConfigError(str(exc)) from None
    notes.append(
        "segment lengths (m): " + ", ".join(f"{s} {seg_lengths[s]:.3f} ({how[s]})" for s in segs)
    )
    return seg_lengths, how


def _place_roots(recording, params, plan, roots, root_stream, t, cal, cal_segs, body_height_m,
                 notes):  # fmt: skip
    """Positions of the chain's root joints on ``t``, the output frame and their description.

    Returns
    -------
    root_pos : dict of str -> ndarray, shape (T, 3)
    frame : str
    root_desc : str
    """
    root_kind = plan["root"]
    root_name = {"vision": "camera", "reference": "reference"}.get(root_kind, root_kind)
    if root_stream is not None:
        lack = [j for j in roots if j not in root_stream.joints]
        if lack:
            raise InputError(
                f"the chain starts at {list(roots)}, but the {root_name} stream lacks {lack} "
                f"(it has {list(root_stream.joints)})"
            )
        root_pos = {j: sample_joint(root_stream, j, t, fill=True) for j in roots}
        return root_pos, root_stream.frame, f"{', '.join(roots)} from the {root_name}"
    rp = params.get("root_position_m", (0.0, 0.0, 0.0))
    if isinstance(rp, Mapping):
        root_pos = {j: np.tile(np.asarray(rp[j], dtype=float), (t.size, 1)) for j in roots}
        root_desc = "fixed " + ", ".join(f"{j} at {list(rp[j])} m" for j in roots)
    else:
        origin = np.tile(np.asarray(rp, dtype=float), (t.size, 1))
        hips = plan["hips"] and "pelvis" in recording.imu
        from_trunk = shoulders_from_trunk(plan)
        root_pos = {}
        if hips:
            placed = _hip_roots(recording, cal, t, origin, body_height_m, notes)
            root_pos.update({j: p for j, p in placed.items() if j in roots})  # a leg not mapped
            root_desc = f"pelvis (mid-hip) at {list(map(float, rp))} m, hips from the pelvis IMU"
        elif from_trunk:
            root_desc = f"mid-shoulder point at {list(map(float, rp))} m"
        else:
            root_desc = f"fixed {', '.join(roots)} at {list(map(float, rp))} m"
        if from_trunk:
            placed = _shoulder_roots(recording, cal, t, origin, hips, body_height_m, notes)
            root_pos.update({j: p for j, p in placed.items() if j in roots})  # an arm not mapped
            root_desc += f", shoulders from the {shoulder_trunk(recording.imu)} IMU"
        root_pos.update({j: origin for j in roots if j not in root_pos})
    # the IMUs' world frame when they declare one between them (e.g. a lab's 'vicon' frame)
    declared = {recording.imu[s].frame for s in cal_segs if s in recording.imu}
    frame = declared.pop() if len(declared) == 1 else "ENU"
    if cal is not None and cal.world_heading_deg:
        frame += f" (heading of the {cal_segs[0]} sensor)"
    zero = not isinstance(rp, Mapping) and not np.any(np.asarray(rp, dtype=float))
    if zero:
        if plan["hips"] and "pelvis" in recording.imu:
            frame += RELATIVE_TO["hips"]
        elif shoulders_from_trunk(plan):
            frame += RELATIVE_TO["shoulders"]
        else:
            frame += f", relative to {roots[0]}"
    return root_pos, frame, root_desc


#: The frame suffix of root-relative outputs whose origin is the midpoint of two joints.
RELATIVE_TO = {
    "hips": ", relative to the pelvis (mid-hip)",
    "shoulders": ", relative to the mid-shoulder point",
}


def relative_origin_joints(frame: str, world: str) -> tuple[str, ...] | None:
    """The joints whose mean is the origin of an output in ``frame`` when ``frame`` is
    ``world`` made relative to a point (:func:`_place_roots`' labels), else None."""
    if not frame.startswith(world + ", relative to "):
        return None
    rest = frame[len(world) :]
    if rest == RELATIVE_TO["hips"]:
        return ("hip_l", "hip_r")
    if rest == RELATIVE_TO["shoulders"]:
        return ("shoulder_l", "shoulder_r")
    joint = rest[len(", relative to ") :]
    return (joint,) if joint and " " not in joint else None
