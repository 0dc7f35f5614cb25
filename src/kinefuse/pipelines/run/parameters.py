"""``[method.parameters]``: the allowed keys and values, and the processing plan.

:func:`_check_params` refuses unknown keys and values before any work; :func:`_plan` resolves
the calibration, the root and the alignment and refuses impossible combinations (a camera
method without a camera, a pelvis root without thighs...).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kinefuse import methods
from kinefuse._validation import did_you_mean
from kinefuse.exceptions import ConfigError
from kinefuse.kinematics import calibrate
from kinefuse.pipelines.run.chain import SEGMENT_JOINTS

#: ``filter`` values of ``paper-a`` / ``imu-only`` (:data:`kinefuse.methods.FILTERS`).
_FILTERS = ("none", *methods.FILTERS)
_CALIBRATIONS = ("static", "functional", "reference", "vision", "none")
_CAMERA_METHODS = methods.names(needs="camera")
#: Root kinds; "camera" is the old spelling of "vision".
_ROOTS = ("fixed", "pelvis", "vision", "camera", "reference")
_HEADINGS = ("auto", "none", "static")
_PAPER_A_KEYS = ("q", "r", "horizon", "threshold1", "threshold2", "n_em_iter")
_VISION_KEYS = (
    "q",
    "r_imu",
    "r_cam",
    "horizon",
    "transition",
    "mu_floor",
    "n_hidden",
    "alpha",
    "linear_skip",
    "train_window",
    "elm2_input",
    "clip_factor",
    "min_train",
    "fixed_lag",
    "seed",
)
_GENERAL_KEYS = (
    "calibration",
    "facing",
    "heading",
    "flexion_axes",
    "root_position_m",
    "axes",
    "align_to_reference",
    "max_rate_rad_s",
    "max_acc_std_m_s2",
    "calibration_window_s",
    "calibration_start_s",
    "pose",
    "align",
    "root",
    "rate_hz",
    "filter",
    "measured_lengths",
    "orientation_params",
    "strict_units",
    "causal",
    "estimate_orientation",
)


def _number_or_table(value, joints: Sequence[str], name: str) -> list[float]:
    if isinstance(value, Mapping):
        out = []
        for j in joints:
            v = value.get(j, value.get(j.rsplit("_", 1)[0]))
            if v is None:
                raise ConfigError(
                    f"[method.parameters] {name}: no value for joint {j!r} (give {j} or "
                    f"{j.rsplit('_', 1)[0]})"
                )
            out.append(v)
        return out
    return [value] * len(joints)


#: Parameters that are numbers (a number, or numbers per joint / per model).
_NUMERIC_KEYS = ("q", "r", "r_imu", "r_cam", "horizon", "threshold1", "threshold2", "n_em_iter",
                 "mu_floor", "n_hidden", "alpha", "train_window", "clip_factor", "min_train",
                 "fixed_lag", "seed")  # fmt: skip


def _numeric(v) -> bool:
    """A number (not a bool), or a table / list of them (nested)."""
    if isinstance(v, Mapping):
        return bool(v) and all(_numeric(x) for x in v.values())
    if isinstance(v, (list, tuple)):
        return bool(v) and all(_numeric(x) for x in v)
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_params(params: Mapping, method: str) -> None:
    allowed = set(_GENERAL_KEYS) | set(_PAPER_A_KEYS) | set(_VISION_KEYS)
    unknown = sorted(set(params) - allowed)
    if unknown:
        hint = did_you_mean(unknown[0], sorted(allowed), f"allowed: {', '.join(sorted(allowed))}")
        raise ConfigError(f"[method.parameters] {unknown[0]}: unknown parameter ({hint})")
    for key, choices in (
        ("calibration", _CALIBRATIONS),
        ("filter", _FILTERS),
        ("root", _ROOTS),
        ("heading", _HEADINGS),
        ("flexion_axes", ("auto", "movement", "pose")),
        ("pose", ("n", "t")),
        ("align_to_reference", ("none", "rigid")),
    ):
        if key in params and params[key] not in choices:
            raise ConfigError(
                f"[method.parameters] {key}: expected one of {', '.join(choices)}, got "
                f"{params[key]!r}"
            )
    for key in _NUMERIC_KEYS:  # used or not by this method: a number (or numbers) or an error
        if key in params and not _numeric(params[key]):
            raise ConfigError(
                f"[method.parameters] {key}: expected a number (or a table of numbers per "
                f"joint), got {params[key]!r}"
            )
    if "rate_hz" in params:
        v = params["rate_hz"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ConfigError(f"[method.parameters] rate_hz: expected a number > 0, got {v!r}")
    for key in ("root_position_m", "facing"):
        if key == "facing" and params.get(key) == "auto":
            continue
        if key in params and not isinstance(params[key], Mapping):
            v = np.asarray(params[key], dtype=object)
            if v.shape != (3,) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v
            ):
                what = "'auto' or [x, y, z]" if key == "facing" else "[x, y, z] in m"
                raise ConfigError(
                    f"[method.parameters] {key}: expected {what}, got {params[key]!r}"
                )


def _plan(recording, method: str, params: Mapping, segs: Sequence[str]) -> dict:
    """Resolve calibration, root and alignment; refuse impossible combinations before any work."""
    has_cam = recording.vision is not None
    has_ref = recording.reference is not None
    if method in _CAMERA_METHODS and not has_cam:
        raise ConfigError(
            f"method {method!r} needs a camera (it fuses the IMU chain with camera joints); add "
            "a [camera] section, or use 'paper-a' / 'imu-only' for IMUs alone"
        )
    calib = params.get("calibration", "vision" if has_cam else "static")
    if calib == "vision" and not has_cam:
        raise ConfigError(
            "calibration 'vision' needs a [camera]; use 'static' (a still pose) or 'functional'"
        )
    if calib == "reference" and not has_ref:
        raise ConfigError("calibration 'reference' needs a [reference] section")
    legs = any(s.startswith(("thigh_", "shank_", "foot_")) for s in segs)
    starts = {
        SEGMENT_JOINTS[s][0]
        for s in segs
        if SEGMENT_JOINTS[s][0] not in {SEGMENT_JOINTS[x][1] for x in segs}
    }
    hips = sorted(j for j in starts if j.startswith("hip_"))
    if "root" in params:
        root = "vision" if params["root"] == "camera" else params["root"]
    elif has_cam:
        root = "vision"
    elif hips and "pelvis" in recording.imu:
        root = "pelvis"
    else:
        root = "fixed"
    if root == "vision" and not has_cam:
        raise ConfigError("root 'vision' (camera joints) needs a [camera] section")
    if root == "reference" and not has_ref:
        raise ConfigError("root 'reference' needs a [reference] section")
    if root in ("fixed", "pelvis") and method in _CAMERA_METHODS:
        raise ConfigError(
            f"method {method!r} fuses with camera joints in the camera frame; it needs root "
            "'vision' (default with a camera), not {root!r}"
        )
    if root == "pelvis" and not (legs and hips):
        raise ConfigError(
            "root 'pelvis' places the hips from the pelvis IMU; it needs thigh segments (chains "
            f"starting at the hips), got chains starting at {sorted(starts)}; use root 'fixed'"
        )
    if root in ("fixed", "pelvis") and hips and "pelvis" not in recording.imu:
        # one chain start (a single leg from its hip, as paper A's arm from its shoulder): the
        # measured position is that hip's
        if not (root == "fixed" and (isinstance(params.get("root_position_m"), Mapping)
                                     or len(starts) == 1)):  # fmt: skip
            raise ConfigError(
                f"root {root!r}: the hips {hips} are placed from the pelvis IMU; map 'pelvis' in "
                "[imu.segments], or give each hip in root_position_m = {hip_l = [...], ...}"
            )
    shoulders = sorted(j for j in starts if j.startswith("shoulder_"))
    per_joint = isinstance(params.get("root_position_m"), Mapping)
    # both arms, or arms and legs, without a measured point each: the trunk IMU places them
    from_trunk = (
        root in ("fixed", "pelvis")
        and not per_joint
        and (len(shoulders) > 1 or bool(shoulders and hips))
    )
    if from_trunk:
        if not {"chest", "pelvis"} & set(recording.imu):
            raise ConfigError(
                f"root {root!r}: the shoulders {shoulders} are placed from the chest IMU (or the "
                "pelvis IMU); map 'chest' in [imu.segments], or give each shoulder in "
                "root_position_m = {shoulder_l = [...], shoulder_r = [...]}"
            )
    if root == "fixed" and per_joint:
        lack = sorted(starts - set(params["root_position_m"]))
        if lack:
            raise ConfigError(f"root_position_m: no position for the chain start(s) {lack}")
    align = params.get("align_to_reference", "none")
    if align != "none" and not has_ref:
        raise ConfigError("align_to_reference needs a [reference] section")
    if calib == "functional":
        if "functional" not in (calibrate.__doc__ or ""):
            raise ConfigError(
                "calibration 'functional' is not available in this version; use 'static'"
            )
    return {"calibration": calib, "root": root, "hips": hips, "align": align,
            "shoulders": shoulders if from_trunk else []}  # fmt: skip
