"""Processing one recording: :func:`process_recording`, the shared core of ``kinefuse run``.

A sequence of steps, each in the module of its idea: the parameters and the plan
(:mod:`~kinefuse.pipelines.run.parameters`), the orientations, the skeleton and its roots
(:mod:`~kinefuse.pipelines.run.chain`), the output timeline and the coverage
(:mod:`~kinefuse.pipelines.run.timeline`), the calibration
(:mod:`~kinefuse.pipelines.run.calibration`); here the method runs on the chain (paper A's
filter or a :data:`kinefuse.pipelines.METHODS` fusion method), with the simple baselines beside
every camera method, and the scores are labelled with what the reference was used for.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from kinefuse import methods
from kinefuse.conventions import SOURCE_IMU
from kinefuse.exceptions import ConfigError, InputError
from kinefuse.kinematics import (
    chain_orientations,
    chain_positions,
    kabsch_rotation,
    segment_lengths,
)
from kinefuse.pipelines import METHODS as FUSION_METHODS
from kinefuse.pipelines import (
    VisionParams,
    upper_limb,
    vision_assisted,
    vision_assisted_from_recording,
)
from kinefuse.pipelines.features import moving_segments
from kinefuse.pipelines.run.calibration import (
    _joint_angles,
    _sensor_orientations,
    calibrate_session,
)
from kinefuse.pipelines.run.chain import (
    SEGMENT_JOINTS,
    _declared_axes,
    _ensure_orientations,
    _place_roots,
    _resolve_lengths,
    build_chain,
    relative_origin_joints,
    shoulder_trunk,
    shoulders_from_trunk,
)
from kinefuse.pipelines.run.chain_file import CHAIN_FILE, chain_description
from kinefuse.pipelines.run.output import SessionOutput
from kinefuse.pipelines.run.parameters import (
    _CAMERA_METHODS,
    _VISION_KEYS,
    _check_params,
    _number_or_table,
    _plan,
)
from kinefuse.pipelines.run.timeline import (
    _input_coverage,
    _output_timeline,
    _sample_joints,
    apply_coverage,
    nearest_samples,
    sample_joint,
)

__all__ = ["process_recording"]


def process_recording(
    recording,
    method: str,
    parameters: Mapping | None = None,
    *,
    lengths: Mapping[str, float] | None = None,
    body_height_m: float | None = None,
    tags: Sequence[str] = (),
) -> SessionOutput:
    """Run one method on a recording whose IMUs are keyed by canonical segment.

    Parameters
    ----------
    recording : Recording
        ``imu`` keyed by canonical segment (orientation or raw acc + gyr), optional ``vision``
        (camera) and ``reference``.
    method : str
        A :mod:`kinefuse.methods` name.
    parameters : mapping, optional
        ``[method.parameters]`` (see :mod:`kinefuse.pipelines.run`).
    lengths : mapping of str -> float, optional
        Measured segment lengths, m (win over everything else).
    body_height_m : float, optional
        Body height for anthropometric lengths (Winter 2009) and the hip joint spacing.
    tags : sequence of str
        Said first in the evaluated methods' label (``SessionOutput.tag``), before the tags
        of what the reference was used for, e.g. a calibration the caller chose.

    Returns
    -------
    SessionOutput

    Raises
    ------
    ConfigError
        Bad parameters, a method or calibration that needs a camera or reference without one,
        a root that cannot be placed, no limb segment, a segment without a length: all before
        any processing.
    InputError
        Problems found in the data (no still window, missing root joints...).

    Notes
    -----
    The IMU chain (SPEC §2.1) starts at the *root joints* (:mod:`kinefuse.pipelines.run`);
    nothing but the scores is taken from a reference unless asked (``calibration =
    "reference"``, ``measured_lengths = true``, ``align_to_reference = "rigid"``); tables of
    scores that used it are labelled.
    """
    if method not in methods.REGISTRY:
        known = methods.names()
        raise ConfigError(f"unknown method {method!r}; expected one of {', '.join(known)}")
    params = dict(parameters or {})
    _check_params(params, method)
    segs = [s for s in SEGMENT_JOINTS if s in recording.imu]
    if not segs:
        raise ConfigError(
            "no limb segment among the mapped sensors "
            f"{sorted(recording.imu)}; map at least one of {', '.join(SEGMENT_JOINTS)}"
        )
    plan = _plan(recording, method, params, segs)
    segs, beyond = _functional_segments(segs, plan, params)
    segs, angles_only = _feet_for_angles(segs, plan, params, lengths)
    out, recording, ctx = _chain_output(recording, method, params, segs, plan, lengths,
                                        body_height_m, angles_only)  # fmt: skip
    if angles_only:
        out.notes.append(
            f"{', '.join(angles_only)}: IMUs used for the ankle angles only (no measured length, "
            "so no toe position; [skeleton.lengths] foot_l / foot_r, ankle to toe, adds it)"
        )
    if beyond:
        kinds = (("foot_", "ankle"), ("hand_", "wrist"))
        centres = " and ".join(c for k, c in kinds if any(s.startswith(k) for s in beyond))
        out.notes.append(
            f"{', '.join(beyond)}: IMUs used for the {centres} centres only (functional "
            "calibration cannot locate a toe or fingertip without an IMU past it; declare "
            "[skeleton.axes] and [skeleton.lengths] for them to output those segments)"
        )
    _drop_unmatched_reference(out, recording)
    _run_method(out, recording, method, params, ctx)
    _label_and_align(out, recording, plan, tags)
    return out


def _drop_unmatched_reference(out: SessionOutput, recording) -> None:
    """A reference that has none of the output joints scores nothing: say so (one warning) and
    drop it, instead of a coverage of 0 % and advice about frames."""
    ref = recording.reference
    if out.reference is None or ref is None or any(j in ref.joints for j in out.joints):
        return
    msg = (
        f"not scored: the reference has none of the output joints ({', '.join(out.joints)}); "
        f"it has {list(ref.joints)}"
    )
    out.warnings.append(msg)
    out.notes.append(f"WARNING: {msg}")
    out.reference = None
    out.provenance["alignment"] = "none (the reference has none of the output joints)"


def _functional_segments(segs, plan: dict, params: Mapping) -> tuple[list, list]:
    """Functional calibration: the feet and hands without a declared axis serve the ankles' and
    wrists' joint centres only (nothing past the toe or fingers locates it), so they are not
    output segments. Returns the output segments and the feet and hands left out."""
    if plan["calibration"] != "functional":
        return segs, []
    declared = dict(params.get("axes") or {})
    beyond = [s for s in segs if s.startswith(("foot_", "hand_")) and s not in declared]
    return [s for s in segs if s not in beyond] or segs, beyond


def _feet_for_angles(segs, plan: dict, params: Mapping, lengths) -> tuple[list, list]:
    """Static calibration: a foot without a measured length or declared axis, whose shank is
    mapped, is calibrated for the ankle angles but not output (body height sizes no foot).
    Returns the output segments and those feet."""
    if plan["calibration"] != "static":
        return segs, []
    declared, measured = dict(params.get("axes") or {}), dict(lengths or {})
    feet = [s for s in segs if s.startswith("foot_") and s not in declared
            and s not in measured and f"shank_{s[-1]}" in segs]  # fmt: skip
    return [s for s in segs if s not in feet], feet


def _expected_lengths(segs, measured, body_height_m) -> dict[str, float]:
    """Measured or body-height lengths, m, 0 where neither is known (nothing to compare)."""
    out = {}
    for s in segs:
        try:
            out[s] = segment_lengths([s], measured=measured, height_m=body_height_m)[0][s]
        except InputError:
            out[s] = 0.0
    return out


def _chain_output(recording, method, params, segs, plan, lengths, body_height_m, angles_only=()):
    """Everything up to the method: the calibrated chain, the streams on the output timeline.

    Returns the :class:`SessionOutput` holding the unfiltered chain, the recording (headings
    aligned by a functional calibration) and what the later steps need.
    """
    calib, root_kind = plan["calibration"], plan["root"]
    notes: list[str] = []
    run_warnings: list[str] = []
    measured = dict(lengths or {})
    use_stream_lengths = bool(params.get("measured_lengths", calib == "vision"))
    if calib not in ("vision", "reference", "functional") or not use_stream_lengths:
        try:  # a missing length is refused before any work
            segment_lengths(segs, measured=measured, height_m=body_height_m)
        except InputError as exc:
            if calib != "functional":
                raise ConfigError(str(exc)) from None
    six_d = _ensure_orientations(recording, params, notes, run_warnings)
    t, root_stream = _output_timeline(recording, method, params, segs, root_kind)
    axes_decl = _declared_axes(params.get("axes"), segs)
    cal_segs = list(segs) + list(angles_only) + (["pelvis"] if root_kind == "pelvis" else [])
    trunk = shoulder_trunk(recording.imu) if shoulders_from_trunk(plan) else None
    if trunk is not None and trunk not in cal_segs and calib == "static":
        cal_segs.append(trunk)  # its frame in the pose places the shoulders
    if calib == "static" and {"pelvis", "chest"} <= set(recording.imu):
        cal_segs += [s for s in ("pelvis", "chest") if s not in cal_segs]  # the trunk angles
    # the functional calibration checks its lengths against these (measured, else body height)
    expected = _expected_lengths(segs, measured, body_height_m) if calib == "functional" else {}
    sk, roots = build_chain([*segs, *angles_only], {s: expected.get(s, 0.3) for s in cal_segs},
                            axes_decl)  # fmt: skip
    if root_kind == "pelvis":
        sk = replace(sk, root_segment="pelvis")
    provenance: dict = {"calibration": calib, "root": root_kind}
    # a functional calibration locates the shoulders from the chest IMU, whatever the root
    shoulders = [j for j in roots if j.startswith("shoulder_")]
    proximal = {j: "chest" for j in shoulders} if "chest" in recording.imu else None
    recording, cal = calibrate_session(recording, sk, params, calib, six_d, axes_decl, cal_segs,
                                       notes, provenance, proximal, run_warnings)  # fmt: skip
    if (root_kind in ("fixed", "pelvis") and "chest" in recording.imu and "chest" not in cal_segs
            and trunk != "chest" and not (calib == "functional" and proximal)):  # fmt: skip
        notes.append(
            "chest: mapped in [imu.segments] but not used: the chest IMU places the shoulders "
            "when both arms (or arms and legs) are mapped, and no joint angle reads it"
        )
    seg_lengths, how = _resolve_lengths(
        recording, segs, cal, calib, root_kind, use_stream_lengths, measured, body_height_m, notes
    )
    provenance["segment_lengths"] = {
        s: {"m": round(seg_lengths[s], 6), "source": how[s]} for s in segs
    }
    sk, roots = build_chain(segs, seg_lengths, axes_decl)
    if cal is not None:
        sk = cal.apply(sk, lengths=False)
    root_pos, frame, root_desc = _place_roots(
        recording, params, plan, roots, root_stream, t, cal, cal_segs, body_height_m, notes
    )
    provenance["root_position"] = root_desc
    source = "vision" if root_kind == "vision" else "reference"
    # sk holds the resolved lengths (measured > camera/reference > functional > body height):
    # the calibration's own length estimates must not override them again
    ori = chain_orientations(recording, sk, cal, t)  # resampled once: chain and "kinefuse"
    chain_st = chain_positions(recording, sk, cal, root=root_pos, source=source, t_s=t,
                               use_calibrated_lengths=False, orientations=ori)  # fmt: skip
    joints = tuple(s for s in sk.distal)
    chain = np.stack([chain_st.position(j, masked=False) for j in joints], axis=1)
    coverage, root_ok, inputs = _input_coverage(recording, sk, root_stream, t, joints)
    chain[~(coverage["imu"] & root_ok)] = np.nan  # no chain without its inputs
    notes.append(
        f"IMU chain from {root_desc}"
        f"{' (gaps interpolated)' if root_kind == 'vision' else ''} through "
        f"{', '.join(sk.segments)}; {t.size} samples at "
        f"{1.0 / float(np.median(np.diff(t))) if t.size > 1 else float('nan'):.1f} Hz; "
        f"frame: {frame}"
    )
    out = _new_output(recording, method, t, joints, chain, frame, sk, cal, root_kind)
    out.notes, out.warnings, out.root, out.provenance = notes, run_warnings, root_desc, provenance
    out.chain_description, why = chain_description(
        sk, root_kind, params, cal, body_height_m, trunk, recording
    )
    if why is not None:
        notes.append(f"no {CHAIN_FILE} for kinefuse stream --chain: {why}")
    out.chain_orientations = ori
    out.joint_segments = moving_segments(sk, joints, ori)
    if cal is not None:
        out.sensor_orientations = _sensor_orientations(recording, cal, t, notes)
    if cal is not None and cal.frames:
        out.angles = _joint_angles(recording, cal, t, notes, run_warnings)
    ctx = {"cal": cal, "calib": calib, "coverage": coverage, "root_ok": root_ok, "inputs": inputs,
           "root_name": {"vision": "camera", "reference": "reference"}.get(root_kind, root_kind),
           "joints": joints}  # fmt: skip
    return out, recording, ctx


def _new_output(recording, method, t, joints, chain, frame, sk, cal, root_kind) -> SessionOutput:
    """The output before the method: the chain, and the camera and reference on ``t``."""
    T, J = t.size, len(joints)
    camera = None
    if recording.vision is not None:
        camera = _sample_joints(recording.vision, joints, t)
        if cal is not None and cal.R_world_from_camera is not None and root_kind != "vision":
            camera = camera @ np.asarray(cal.R_world_from_camera).T
    reference = frames = None
    if recording.reference is not None:
        reference = _sample_joints(recording.reference, joints, t)
        frames = nearest_samples(t, recording.reference.t_s)
    return SessionOutput(
        t_s=t,
        joints=joints,
        position=chain.copy(),
        std_m=np.full((T, J, 3), np.nan),
        source=np.where(np.all(np.isfinite(chain), -1), SOURCE_IMU, -1).astype(np.int64),
        mode=np.full((T, J), -1, dtype=np.int64),
        frame=frame,
        method=method,
        label=methods.get(method).label,
        chain=chain,
        camera=camera,
        reference=reference,
        reference_frames=frames,
        edges=tuple((p, d) for p, d in zip(sk.proximal, sk.distal, strict=True) if p in joints),
    )


def _run_method(out: SessionOutput, recording, method: str, params: Mapping, ctx: dict) -> None:
    """The method on the chain (timed), then coverage and the baselines of camera methods."""
    T = out.t_s.size
    chain, camera = out.chain, out.camera
    dt = float(np.median(np.diff(out.t_s))) if T > 1 else 1.0 / 30.0
    t0 = time.perf_counter()
    flt = params.get("filter", "em-kf-fir" if method == "paper-a" else "none")
    if method in ("paper-a", "imu-only"):
        if flt != "none":
            t0 = _paper_a_filter(out, chain, dt, flt, params)
            out.label = methods.FILTERS[flt]
            if method == "imu-only":
                out.label = f"IMU only + {out.label}"
    else:
        _vision(out, recording, chain, camera, dt, method, params, ctx["cal"])
    # imu-only without a filter runs nothing beyond the chain: no run time to report
    out.run_time_s = time.perf_counter() - t0 if flt != "none" or method != "imu-only" else np.nan
    apply_coverage(
        out, ctx["coverage"], ctx["root_ok"], ctx["joints"], method, ctx["root_name"], ctx["inputs"]
    )
    if method in _CAMERA_METHODS and out.camera is not None and out.reference is not None:
        # only an evaluation reads them (SessionOutput.trajectories): none without a reference
        out.baselines = _baselines(out.chain, out.camera, dt, out.joints)


def _label_and_align(out: SessionOutput, recording, plan: dict, tags=()) -> None:
    """Tags saying what the reference was used for (after ``tags``); the rigid alignment, if
    asked."""
    notes, provenance = out.notes, out.provenance
    tags = list(tags)
    sources = [v["source"] for v in provenance["segment_lengths"].values()]
    if plan["calibration"] == "reference":
        tags.append("calibrated on reference")
    if any("REFERENCE" in s for s in sources):
        tags.append("lengths from reference")
    if plan["root"] == "reference":  # the chain starts at the reference's root joints: an input
        tags.append("root from reference")
    # a camera that is the reference's own data (e.g. UTD-MHAD's Kinect as both): what was
    # calibrated on it was calibrated on the reference (a distinct camera is an input: its use
    # is in the provenance, not a label)
    if _camera_is_reference(recording):
        if plan["calibration"] == "vision":
            tags.append("calibrated on camera = reference")
        if any(s.startswith("camera") for s in sources):
            tags.append("lengths from camera = reference")
        if plan["root"] == "vision":  # the chain starts at the camera's (= reference's) joints
            tags.append("root from camera = reference")
        if out.method in _CAMERA_METHODS or out.baselines:
            msg = (
                "the camera is the reference's own data: wherever the camera sees a joint, an "
                "estimate that follows it (camera only, gap-fill, the offset baselines, the "
                "camera fusions) scores about 0 there by construction, not by accuracy; only the "
                "IMU chain and samples inside camera outages say something"
            )
            out.warnings.append(msg)
            notes.append(f"WARNING: {msg}")
    if out.reference is not None and out.frame != "ENU chest-relative":
        ref_frame = recording.reference.frame
        # a root-relative output is scored against the reference made relative to its own
        # root joints (then aligned too, if asked): its origin moves, so no rigid alignment
        # maps it onto the reference's world positions
        relative = _score_relative(out, recording.reference)
        if relative:
            origin = relative_origin_joints(out.frame, ref_frame)
            tags.append(f"scored relative to the reference's {_origin_name(origin)}")
            notes.append(
                f"scored root-relative: the output ({out.frame}) against the reference minus "
                f"its own {' and '.join(origin)} (their mean) at "
                "each sample; no other use of the reference"
                + ("" if plan["align"] == "rigid" else " (no alignment)")
            )
            provenance["alignment"] = "none; scored relative to the reference's root joints"
        moving = "relative to" in out.frame
        if plan["align"] == "rigid" and (relative or not moving):
            _align_rigidly(out, out.reference, tags, notes, provenance, relative)
        elif not relative and ref_frame != out.frame:
            _not_scored(out, ref_frame, moving, plan["align"] == "rigid", notes, provenance)
        elif not relative:
            provenance["alignment"] = "none"
    out.tag = f" [{', '.join(tags)}]" if tags else ""
    provenance["labels"] = out.tag.strip() or "IMU/camera data only"


def _align_rigidly(out, reference, tags, notes, provenance, relative: bool) -> None:
    """The rigid (Kabsch) alignment asked for (``[reference] align = 'rigid'``), in place."""
    for name in ("position", "chain", "camera"):
        arr = getattr(out, name)
        if arr is not None and np.any(np.isfinite(arr)):
            setattr(out, name, _rigid_align(arr, reference)[0])
    out.baselines = {
        k: _rigid_align(v, reference)[0] if np.any(np.isfinite(v)) else v
        for k, v in out.baselines.items()
    }
    tags.append("aligned to reference")
    onto = "the root-relative reference" if relative else "the reference"
    notes.append(
        f"estimates rigidly aligned to {onto} (Kabsch rotation + translation over all samples, "
        "as asked: [reference] align = 'rigid') before evaluation"
    )
    provenance["alignment"] = f"rigid (Kabsch) to {onto}, as asked"


def _not_scored(out, ref_frame: str, moving: bool, rigid: bool, notes, provenance) -> None:
    """Drop the reference of an output whose frame differs from it, with a warning saying
    what would make them comparable."""
    if moving:  # a moving origin: no rigid alignment maps it
        fix = "set [skeleton] root = 'reference' (the chain starts at the reference joints)"
        if rigid:
            fix = (
                "a rigid alignment cannot map an output whose origin moves onto world "
                "positions, and the reference lacks that origin's joints to be made relative; "
                + fix
            )
    else:
        fix = (
            "set [reference] align = 'rigid' (a rigid alignment to the reference) or "
            "[skeleton] root = 'reference' (the chain starts at the reference joints)"
        )
    msg = (
        f"not scored: the output frame ({out.frame}) is not the reference frame "
        f"({ref_frame}); positions in different frames are not comparable. To score, "
        + fix
        + "; the scores are then labelled so"
    )
    out.warnings.append(msg)
    notes.append(f"WARNING: {msg}")
    out.reference = None
    provenance["alignment"] = "none (frames differ: not scored)"


def _origin_name(joints: Sequence[str]) -> str:
    """``("hip_l", "hip_r")`` -> ``"mid-hip"``; one joint: its name."""
    if len(joints) == 2:
        return "mid-" + joints[0].rsplit("_", 1)[0]
    return joints[0]


def _score_relative(out: SessionOutput, ref_stream) -> bool:
    """A root-relative output in the reference's world frame: make ``out.reference`` relative
    to the reference's own root joints (their mean, sampled on the output timeline) and say
    True; else leave it and say False."""
    joints = relative_origin_joints(out.frame, ref_stream.frame)
    if not joints or not all(j in ref_stream.joints for j in joints):
        return False
    origin = np.mean([sample_joint(ref_stream, j, out.t_s, fill=False) for j in joints], axis=0)
    out.reference = out.reference - origin[:, None, :]
    return True


def _camera_is_reference(recording) -> bool:
    """The camera and the reference hold the same samples (one file given as both)."""
    cam, ref = recording.vision, recording.reference
    if cam is None or ref is None or not np.array_equal(cam.t_s, ref.t_s):
        return False
    common = [j for j in cam.joints if j in ref.joints]
    return bool(common) and all(
        np.array_equal(cam.position(j), ref.position(j), equal_nan=True) for j in common
    )


def _rigid_align(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """Best rotation + translation of ``est (T, J, 3)`` onto ``ref``; aligned copy and RMS (m)."""
    P, Q = est.reshape(-1, 3), ref.reshape(-1, 3)
    ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(Q), axis=1)
    cp, cq = P[ok].mean(axis=0), Q[ok].mean(axis=0)
    R = kabsch_rotation(P[ok] - cp, Q[ok] - cq)
    out = (est - cp) @ R.T + cq
    return out, float(np.sqrt(np.nanmean(np.sum((out - ref) ** 2, axis=-1))))


def _paper_a_filter(out: SessionOutput, chain, dt, flt: str, params: Mapping) -> float:
    """Paper A's filter per joint, in place; returns the start time of the timed run."""
    kw = {k: params[k] for k in ("horizon", "threshold1", "threshold2", "n_em_iter") if k in params}
    q = _number_or_table(params.get("q", 0.1), out.joints, "q")
    r = _number_or_table(params.get("r", 0.01), out.joints, "r")
    ok = np.any(np.all(np.isfinite(chain), axis=-1), axis=0)
    if not np.all(ok):
        bad = [j for j, o in zip(out.joints, ok, strict=True) if not o]
        raise InputError(f"the IMU chain has no valid sample for {bad}")
    method = "em-kf-fir" if flt == "em-kf-fir" else flt
    try:
        # compile outside the timed run (numba compiles on the first call)
        z0 = chain[:, 0][np.all(np.isfinite(chain[:, 0]), axis=1)][:30]
        with warnings.catch_warnings():  # e.g. "horizon longer than the series": warm-up only
            warnings.simplefilter("ignore")
            upper_limb(z0, None, dt, method, q=q[0], r=r[0], **kw)
        t0 = time.perf_counter()
        for j, name in enumerate(out.joints):
            res = upper_limb(chain[:, j], None, dt, method, q=q[j], r=r[j], joints=(name,), **kw)
            out.position[:, j] = res.position[:, 0]
            out.std_m[:, j] = np.sqrt(np.diagonal(res.cov[:, 0], axis1=-2, axis2=-1))
            out.mode[:, j] = res.mode[:, 0]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[method.parameters]: {exc}") from None
    out.notes.append(
        f"filter {flt} (paper A) per joint, dt = {dt * 1e3:.1f} ms, q = {params.get('q', 0.1)}, "
        f"r = {params.get('r', 0.01)}"
    )
    return t0


def _vision(out: SessionOutput, recording, chain, camera, dt, method, params, cal) -> None:
    if method not in FUSION_METHODS:
        raise ConfigError(
            f"method {method!r} is not available in this installation (available: "
            f"{', '.join(sorted(FUSION_METHODS))})"
        )
    vp = {k: params[k] for k in _VISION_KEYS if k in params}
    try:
        vparams = VisionParams(**vp)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[method.parameters]: {exc}") from None
    causal = bool(params.get("causal", False))
    full = {"chest", "upper_arm_l", "upper_arm_r", "forearm_l", "forearm_r"} | {
        "thigh_l",
        "thigh_r",
        "shank_l",
        "shank_r",
    }
    cam = recording.vision
    if full <= set(recording.imu) and "spine_shoulder" in cam.joints:
        joints = tuple(j for j in out.joints if j in cam.joints)
        rate = 1.0 / dt
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fused = vision_assisted_from_recording(
                recording, None, cal, method, rate, joints=joints, causal=causal, params=vparams
            )
        if fused.t_s.size != out.t_s.size:
            raise InputError(
                f"camera timeline ({fused.t_s.size} samples) differs from the output timeline"
            )
        out.joints = joints
        out.position = fused.result.position
        out.chain = fused.z_imu
        out.chain_orientations = fused.orientations  # (the rig's chain, its frame)
        out.joint_segments = moving_segments(fused.skeleton, joints, fused.orientations)
        out.camera = fused.z_cam
        out.reference = fused.reference
        out.std_m = np.sqrt(np.diagonal(fused.result.cov, axis1=-2, axis2=-1))
        out.source = fused.result.source.astype(np.int64)
        out.mode = np.full(out.source.shape, -1, dtype=np.int64)
        out.frame = "ENU chest-relative"
        _method_notes(out, method, "from the chest IMU; positions relative to spine_shoulder")
        return
    avail = np.all(np.isfinite(camera), axis=-1)
    keep = [j for j in range(len(out.joints)) if np.any(avail[:, j]) or method != "camera-only"]
    rots = out.segment_rotations() if method == "kinefuse" else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = vision_assisted(
            chain[:, keep],
            camera[:, keep],
            avail[:, keep],
            dt,
            method,
            joints=[out.joints[j] for j in keep],
            causal=causal,
            params=vparams,
            segment_rotations=None if rots is None else rots[:, keep],
        )
    out.position = np.full_like(chain, np.nan)
    out.position[:, keep] = res.position
    out.std_m[:, keep] = np.sqrt(np.diagonal(res.cov, axis1=-2, axis2=-1))
    out.source[:, keep] = res.source
    _method_notes(out, method, "per joint on the IMU chain and the camera joints")


def _method_notes(out: SessionOutput, method: str, where: str) -> None:
    """What the camera method is (paper B's pipeline, or the registry's summary) and, for
    ``"kinefuse"``, the sensor frames its correction models the chain error in."""
    info = methods.get(method)
    what = f"paper B pipeline {method!r} (Xu 2023, SPEC §10.3)" if info.paper else info.summary
    out.notes.append(f"{what}, {where}")
    if method == "kinefuse":
        frames = "; ".join(f"{j}: {', '.join(out.joint_segments[j])}" for j in out.joints)
        out.notes.append(
            f"kinefuse: the chain error is also modelled in the frames of the sensors that move "
            f"each joint ({frames})"
        )


def _baselines(chain, camera, dt, joints) -> dict[str, np.ndarray]:
    """The simple baselines (offset interp / hold, camera gap-fill) on one chain and camera."""
    avail = np.all(np.isfinite(camera), axis=-1)
    keep = [j for j in range(len(joints)) if np.any(np.all(np.isfinite(chain[:, j]), axis=-1))]
    every = 0 < len(keep) == len(joints)  # (the common case: no copies of the joints kept)
    if keep and not every:
        chain, camera, avail = chain[:, keep], camera[:, keep], avail[:, keep]
    names = [joints[j] for j in keep]
    out = {}
    for m in methods.BASELINES:
        if every:
            pos = vision_assisted(chain, camera, avail, dt, m, joints=names).position
        else:
            pos = np.full((chain.shape[0], len(joints), 3), np.nan)
            if keep:
                res = vision_assisted(chain, camera, avail, dt, m, joints=names)
                pos[:, keep] = res.position
        out[methods.get(m).label] = pos
    return out
