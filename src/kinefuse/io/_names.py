"""Source names -> canonical names: sensor labels to segments, marker/joint labels to joints.

Private module. Understands the spellings of the exporters kinefuse reads (``Right_Upper_Leg``,
``femur_r``, ``LUpLeg``, ``ShoulderLeft``, Plug-in-Gait ``RFEO``...).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence

from kinefuse.conventions import JOINTS, SEGMENTS
from kinefuse.exceptions import InputError

__all__ = [
    "KINECT_LIMB_JOINTS",
    "PLUG_IN_GAIT_JOINTS",
    "canonical_joint",
    "canonical_segment",
    "map_joints",
    "map_segments",
]

_SIDE = {"l": "l", "left": "l", "lt": "l", "r": "r", "right": "r", "rt": "r"}
_DROP = {"imu", "sensor", "udp", "body", "segment"}
_SEGMENT_PARTS = {
    "chest": "chest",
    "torso": "chest",
    "thorax": "chest",
    "sternum": "chest",
    "trunk": "chest",
    "upper_back": "chest",
    "upperback": "chest",
    "pelvis": "pelvis",
    "hip": "pelvis",
    "hips": "pelvis",
    "sacrum": "pelvis",
    "upper_arm": "upper_arm",
    "upperarm": "upper_arm",
    "humerus": "upper_arm",
    "forearm": "forearm",
    "fore_arm": "forearm",
    "lower_arm": "forearm",
    "lowerarm": "forearm",
    "radius": "forearm",
    "ulna": "forearm",
    "thigh": "thigh",
    "upper_leg": "thigh",
    "upperleg": "thigh",
    "up_leg": "thigh",
    "upleg": "thigh",
    "femur": "thigh",
    "shank": "shank",
    "lower_leg": "shank",
    "lowerleg": "shank",
    "tibia": "shank",
    "shin": "shank",
    "foot": "foot",
    "calcn": "foot",
    "hand": "hand",
}
_UNSIDED_SEGMENTS = {"chest", "pelvis"}


def _tokens(name: str) -> list[str]:
    out = []
    for part in re.split(r"[^A-Za-z0-9]+", str(name)):
        if not part or _is_device_id(part.lower()):
            continue
        part = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", part)
        out += [t for t in part.lower().split("_") if t]
    return out


def _is_device_id(tok: str) -> bool:
    return len(tok) >= 6 and bool(re.fullmatch(r"[0-9a-f]+", tok)) and any(c.isdigit() for c in tok)


def _side_and_rest(name: str, skip=None) -> tuple[str | None, list[str]] | None:
    """(side ``"l"``/``"r"``/None, the other tokens but those ``skip(tok)`` accepts); None if two sides."""
    side = None
    rest = []
    for tok in _tokens(name):
        if tok in _SIDE:
            if side is not None and side != _SIDE[tok]:
                return None
            side = _SIDE[tok]
        elif skip is None or not skip(tok):
            rest.append(tok)
    return side, rest


def canonical_segment(name: str) -> str | None:
    """Canonical segment name for a sensor/body label, or None when not recognised.

    Understands ``Right_Upper_Leg_64F61C2E``, ``upper_arm_left``, ``femur_r``, ``LUpLeg`` style
    labels; a trailing device id (hex) and the words ``imu``/``sensor`` are ignored.
    """
    if name in SEGMENTS:
        return name
    split = _side_and_rest(name, skip=lambda tok: tok in _DROP or _is_device_id(tok))
    if split is None or not split[1]:
        return None
    side, rest = split
    part = _SEGMENT_PARTS.get("_".join(rest))
    if part is None and len(rest) == 1 and len(rest[0]) > 1 and rest[0][0] in "lr" and side is None:
        # "lupleg" / "rthigh" style
        part = _SEGMENT_PARTS.get(rest[0][1:])
        side = rest[0][0] if part else None
    if part is None:
        return None
    if part in _UNSIDED_SEGMENTS:
        return part if side is None else None
    return f"{part}_{side}" if side else None


def map_segments(
    names: Iterable[str], overrides: Mapping[str, str] | None = None
) -> tuple[dict[str, str], list[str]]:
    """Map source sensor names to keys: canonical segment where recognised, else the own name.

    Parameters
    ----------
    names : iterable of str
        Source sensor names in file order.
    overrides : mapping or None
        Source name -> key, taking precedence (e.g. a user's ``sensor_map=``).

    Returns
    -------
    mapping : dict
        Source name -> key (unique keys).
    notes : list of str
        Human-readable notes (unrecognised names, clashes).
    """
    overrides = dict(overrides or {})
    mapping: dict[str, str] = {}
    notes: list[str] = []
    used: set[str] = set()
    for n in names:
        key = overrides.get(n) or canonical_segment(n)
        if key is None:
            key = n
            notes.append(f"sensor {n!r} not mapped to a canonical segment; kept under its own name")
        if key in used:
            notes.append(f"sensor {n!r} maps to {key!r}, already used; kept under its own name")
            key = n
        if key in used:
            raise InputError(f"two sensors are both named {n!r}")
        used.add(key)
        mapping[n] = key
    return mapping, notes


_JOINT_PARTS = {
    "shoulder": "shoulder",
    "elbow": "elbow",
    "wrist": "wrist",
    "hand": "hand",
    "hip": "hip",
    "knee": "knee",
    "ankle": "ankle",
    "foot": "foot",
    "foot_index": "foot",
}
_UNSIDED_JOINTS = {
    "head": "head",
    "neck": "neck",
    "spine_shoulder": "spine_shoulder",
    "shoulder_center": "spine_shoulder",
    "spine_mid": "spine_mid",
    "spine": "spine_mid",
    "spine_base": "spine_base",
    "hip_center": "spine_base",
    "pelvis": "pelvis",
}
#: Plug-in-Gait joint-centre labels (as in the gaittoolbox/Neura Vicon export).
PLUG_IN_GAIT_JOINTS = {
    "LFEP": "hip_l",
    "RFEP": "hip_r",
    "LFEO": "knee_l",
    "RFEO": "knee_r",
    "LTIO": "ankle_l",
    "RTIO": "ankle_r",
}


#: Shoulders to feet, left then right, in the order Kinect v1 and v2 both list them (their
#: skeleton tables differ only in the spine/head joints around this run).
KINECT_LIMB_JOINTS = (
    "shoulder_l", "elbow_l", "wrist_l", "hand_l", "shoulder_r", "elbow_r", "wrist_r", "hand_r",
    "hip_l", "knee_l", "ankle_l", "foot_l", "hip_r", "knee_r", "ankle_r", "foot_r",
)  # fmt: skip


def canonical_joint(label: str) -> str | None:
    """Canonical joint name for a label (``ShoulderLeft``, ``left_wrist``, ``RFEO``...) or None."""
    if label in JOINTS:
        return label
    if label.upper() in PLUG_IN_GAIT_JOINTS:
        return PLUG_IN_GAIT_JOINTS[label.upper()]
    split = _side_and_rest(label)
    if split is None:
        return None
    side, rest = split
    part = "_".join(rest)
    if side is None:
        return _UNSIDED_JOINTS.get(part)
    p = _JOINT_PARTS.get(part)
    return f"{p}_{side}" if p else None


def map_joints(labels: Sequence[str]) -> tuple[tuple[str, ...], dict[str, str]]:
    """Map labels to canonical joint names where they match, else keep the label (unique)."""
    out: list[str] = []
    mapping: dict[str, str] = {}
    for lab in labels:
        key = canonical_joint(lab) or lab
        if key in out:
            key = lab
        if key in out:
            key = f"{lab}#{len(out)}"
        out.append(key)
        mapping[lab] = key
    return tuple(out), mapping
