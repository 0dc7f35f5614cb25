"""Azure Kinect body-tracking JSON (Microsoft ``offline_processor`` layout): 32 joints.

Layout: ``{"joint_names": [32 names], "frames": [{"timestamp_usec": int, "bodies":
[{"body_id": int, "joint_positions": [[x, y, z] x 32] (mm), "joint_orientations":
[[w, x, y, z] x 32], "joint_confidence_levels": [32 ints] (optional)}]}]}``. Confidence levels
are ``K4ABT_JOINT_CONFIDENCE_NONE=0, LOW=1, MEDIUM=2, HIGH=3`` (MEDIUM is the highest level the
SDK reports; LOW = occluded, predicted).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import ZERO_RULE, finish_recording, make_metadata, zero_is_missing
from kinefuse.io._text import check_time, read_json
from kinefuse.io.recording import JointStream, Recording

__all__ = ["AZURE_JOINTS", "AZURE_TO_CANONICAL", "read_azure_kinect_json"]

#: Azure Kinect ``k4abt_joint_id_t`` names in index order 0..31.
AZURE_JOINTS = (
    "PELVIS",
    "SPINE_NAVEL",
    "SPINE_CHEST",
    "NECK",
    "CLAVICLE_LEFT",
    "SHOULDER_LEFT",
    "ELBOW_LEFT",
    "WRIST_LEFT",
    "HAND_LEFT",
    "HANDTIP_LEFT",
    "THUMB_LEFT",
    "CLAVICLE_RIGHT",
    "SHOULDER_RIGHT",
    "ELBOW_RIGHT",
    "WRIST_RIGHT",
    "HAND_RIGHT",
    "HANDTIP_RIGHT",
    "THUMB_RIGHT",
    "HIP_LEFT",
    "KNEE_LEFT",
    "ANKLE_LEFT",
    "FOOT_LEFT",
    "HIP_RIGHT",
    "KNEE_RIGHT",
    "ANKLE_RIGHT",
    "FOOT_RIGHT",
    "HEAD",
    "NOSE",
    "EYE_LEFT",
    "EAR_LEFT",
    "EYE_RIGHT",
    "EAR_RIGHT",
)
#: Canonical names of :data:`AZURE_JOINTS`. SPINE_CHEST sits lower than Kinect v2's SpineShoulder,
#: so it is kept as ``spine_chest``; NECK -> ``neck``, SPINE_NAVEL -> ``spine_mid``.
AZURE_TO_CANONICAL = (
    "pelvis",
    "spine_mid",
    "spine_chest",
    "neck",
    "clavicle_l",
    "shoulder_l",
    "elbow_l",
    "wrist_l",
    "hand_l",
    "hand_tip_l",
    "thumb_l",
    "clavicle_r",
    "shoulder_r",
    "elbow_r",
    "wrist_r",
    "hand_r",
    "hand_tip_r",
    "thumb_r",
    "hip_l",
    "knee_l",
    "ankle_l",
    "foot_l",
    "hip_r",
    "knee_r",
    "ankle_r",
    "foot_r",
    "head",
    "nose",
    "eye_l",
    "ear_l",
    "eye_r",
    "ear_r",
)

_CONF_KEYS = ("joint_confidence_levels", "confidence_levels", "joint_confidences", "confidence")


def read_azure_kinect_json(path, *, min_confidence: int | None = 2, body_id=None) -> Recording:
    """Read Azure Kinect body-tracking JSON (Microsoft ``offline_processor`` layout, see above).

    Parameters
    ----------
    path : str or Path
    min_confidence : {0, 1, 2, 3} or None
        A joint is available iff its confidence level >= this and its position is finite.
        Default 2 (MEDIUM), the analogue of Kinect v2 Tracked. Files without confidence levels
        (the stock offline_processor) fall back to finiteness (noted in metadata). ``None``:
        finiteness only.
    body_id : int or None
        Body to read; default the body present in the most frames.

    Returns
    -------
    Recording
        ``vision``: positions (T, 32, 3) in m (file mm) in the Azure Kinect depth-camera frame
        (x right, y down, z forward), canonical joint names (:data:`AZURE_TO_CANONICAL`),
        times ``(timestamp_usec - first) * 1e-6`` s; frames without the body are unavailable.
        ``metadata["confidence"]`` (T, 32), -1 where absent.

    Raises
    ------
    FormatError
        Invalid/truncated JSON, missing keys, wrong joint counts, non-monotonic timestamps.
    """
    path = Path(path)
    frames = _frames(path, read_json(path))
    body_id, notes = _choose_body(path, frames, body_id)
    t_us, pos, conf, has_conf = _body_samples(path, frames, body_id)
    t_us = check_time(path, t_us, None, "timestamp_usec")
    pos *= 1e-3
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero_is_missing(pos)
    rule = f"finite; {ZERO_RULE}"
    if min_confidence is not None:
        if has_conf:
            avail &= conf >= min_confidence
            rule = f"confidence level >= {min_confidence} and finite; {ZERO_RULE}"
        else:
            notes.append(
                "no joint confidence levels in the file; availability = body present and finite"
            )
    js = JointStream(
        t_s=(t_us - t_us[0]) * 1e-6,
        position_m=pos,
        available=avail,
        joints=AZURE_TO_CANONICAL,
        frame="azure_depth_camera",
    )
    md = make_metadata(
        path,
        "azure_kinect",
        units_converted=["positions mm -> m", "timestamp us -> s"],
        joint_map=dict(zip(AZURE_JOINTS, AZURE_TO_CANONICAL, strict=True)),
        availability_rule=rule,
        confidence=conf,
        body_id=body_id,
        t0_us=float(t_us[0]),
        frame_notes="Azure Kinect depth camera: x right, y down, z forward (m)",
        notes=notes,
    )
    return finish_recording(path, md, vision=js)


def _frames(path: Path, d) -> list:
    """The ``frames`` list, after checking the joint names and each frame's keys."""
    if not isinstance(d, dict) or not isinstance(d.get("frames"), list):
        raise FormatError(path, "expected a JSON object with a 'frames' list", field="frames")
    names = d.get("joint_names", list(AZURE_JOINTS))
    if list(names) != list(AZURE_JOINTS):
        raise FormatError(
            path,
            f"expected the 32 Azure Kinect joint names in k4abt order, found {names}",
            field="joint_names",
        )
    frames = d["frames"]
    if not frames:
        raise FormatError(path, "expected at least one frame, found none", field="frames")
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict) or "timestamp_usec" not in fr or "bodies" not in fr:
            raise FormatError(
                path,
                f"frame {k}: expected keys 'timestamp_usec' and 'bodies'",
                field=f"frames[{k}]",
            )
    return frames


def _choose_body(path: Path, frames: list, body_id) -> tuple[object, list[str]]:
    """The body to read (given, or the one in the most frames) and a note when there are several."""
    counts: Counter = Counter()
    for fr in frames:
        for b in fr["bodies"] or []:
            counts[b.get("body_id")] += 1
    notes = []
    if body_id is None:
        if not counts:
            raise FormatError(path, "no body in any frame", field="bodies")
        body_id = counts.most_common(1)[0][0]
        if len(counts) > 1:
            notes.append(
                f"{len(counts)} bodies; kept body_id {body_id} (most frames); pass body_id= to choose"
            )
    elif body_id not in counts:
        raise FormatError(
            path, f"body_id {body_id!r} not found; bodies: {sorted(counts)}", field="body_id"
        )
    return body_id, notes


def _body_samples(path: Path, frames: list, body_id):
    """Timestamps (us), positions (T, 32, 3) in mm, confidence (T, 32) and whether any was given."""
    T, J = len(frames), len(AZURE_JOINTS)
    ts = np.empty(T)
    pos = np.full((T, J, 3), np.nan)
    conf = np.full((T, J), -1.0)
    has_conf = False
    for k, fr in enumerate(frames):
        try:
            ts[k] = float(fr["timestamp_usec"])
        except (TypeError, ValueError):
            raise FormatError(
                path,
                f"frame {k}: expected a number, found {fr['timestamp_usec']!r}",
                field=f"frames[{k}].timestamp_usec",
            ) from None
        for b in fr["bodies"] or []:
            if b.get("body_id") != body_id:
                continue
            pos[k] = _frame_array(path, b, "joint_positions", (J, 3), k)
            ck = next((c for c in _CONF_KEYS if c in b), None)
            if ck is not None:
                conf[k] = _frame_array(path, b, ck, (J,), k)
                has_conf = True
    return ts, pos, conf, has_conf


def _frame_array(path: Path, body: dict, key: str, shape: tuple, k: int) -> np.ndarray:
    a = np.asarray(body.get(key, []), dtype=float)
    if a.shape != shape:
        want = "(32, 3)" if len(shape) == 2 else "(32,)"
        raise FormatError(
            path, f"frame {k}: expected {key} {want}, found {a.shape}", field=f"frames[{k}].{key}"
        )
    return a
