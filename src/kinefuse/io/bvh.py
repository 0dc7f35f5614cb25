"""Reader for Biovision Hierarchy (BVH) motion capture files.

Format
------
``HIERARCHY`` with nested ``ROOT``/``JOINT``/``End Site`` blocks, each with an ``OFFSET`` (from
the parent joint, in the parent's frame) and ``CHANNELS`` (any of ``X/Y/Zposition``,
``X/Y/Zrotation``, in the order they appear in each frame line); then ``MOTION``, ``Frames: n``,
``Frame Time: dt`` and one line of channel values per frame (angles in degrees).

Forward kinematics: a joint's local rotation is the product of its rotation channels in the listed
order (``Zrotation Yrotation Xrotation`` -> ``Rz · Ry · Rx``, i.e. intrinsic); its global rotation
``R_j = R_parent · R_local``; its position ``p_j = p_parent + R_parent · t_j`` with the local
translation ``t_j`` = its OFFSET, except that position channels **replace** the OFFSET components
they name on non-root joints (MotionBuilder/Bandai files carry position channels on every joint,
holding the bone vector) and are added to it on the root (the root's OFFSET is its rest
position). Positions are scaled by ``length_unit_m`` and y-up coordinates are rotated to ENU with
:data:`kinefuse.io.motion.R_ENU_FROM_YUP`.

Length unit
    BVH files carry no unit. ``length_unit_m=None`` (default) picks the one of
    :data:`BVH_LENGTH_UNITS` (m, cm, mm, inch, the CMU ASF unit 0.45 in) that makes the figure's
    size plausible: the median over frames of the largest side of the joints' bounding box must
    lie in 0.8-2.5 m (a standing or walking adult: ankle to head ~1.5 m). A given unit is checked
    the same way (:class:`~kinefuse.exceptions.UnitWarning` if implausible).

Canonical mapping (``joint_map``; default: of :data:`BVH_JOINT_MAPS` the naming that matches most
joints, a warning lists the limb joints it could not find)
    ``cgspeed`` (CMU "3ds Max friendly", :data:`CMU_BVH_JOINT_MAP`): pelvis / spine_base = Hips;
    spine_mid = Chest; spine_shoulder = Chest2; neck = Neck; head = Head; shoulder/elbow/wrist =
    Left|RightShoulder/Elbow/Wrist; hand = L|RFingers; hip/knee/ankle = Left|RightHip/Knee/Ankle;
    foot = Left|RightToe.
    ``motionbuilder`` (CMU MotionBuilder-friendly, fairmotion, PyMO, Mixamo without its
    ``mixamorig:`` prefix): Left|RightArm/ForeArm/Hand = shoulder/elbow/wrist (Left|RightShoulder
    is the clavicle, not mapped); Left|RightUpLeg/Leg/Foot/ToeBase = hip/knee/ankle/foot;
    spine_mid = Spine; spine_shoulder = Spine1 (Spine2 when present); neck = Neck1 or Neck.
    ``bandai`` (Bandai-Namco motion dataset): UpperArm/LowerArm/Hand_L|R = shoulder/elbow/wrist
    (Shoulder_L|R = clavicle); UpperLeg/LowerLeg/Foot/Toes_L|R = hip/knee/ankle/foot;
    spine_mid = Spine; spine_shoulder = Chest.
    Segments carry the rotation of their proximal joint (upper_arm = shoulder joint, thigh = hip
    joint ...); the distal joint must be a direct child of the proximal one.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError, InputError, UnitWarning
from kinefuse.io._names import KINECT_LIMB_JOINTS
from kinefuse.io.motion import CANONICAL_SEGMENT_JOINTS, Motion, _build_motion
from kinefuse.io.recording import Recording

__all__ = [
    "BVH_JOINT_MAPS",
    "BVH_LENGTH_UNITS",
    "CMU_BVH_JOINT_MAP",
    "load_motion_bvh",
    "read_bvh",
]

#: Canonical joint -> BVH joint name for the CMU BVH conversion (cgspeed, 3ds Max friendly).
CMU_BVH_JOINT_MAP: dict[str, str] = {
    "pelvis": "Hips",
    "spine_base": "Hips",
    "spine_mid": "Chest",
    "spine_shoulder": "Chest2",
    "neck": "Neck",
    "head": "Head",
    "shoulder_l": "LeftShoulder",
    "shoulder_r": "RightShoulder",
    "elbow_l": "LeftElbow",
    "elbow_r": "RightElbow",
    "wrist_l": "LeftWrist",
    "wrist_r": "RightWrist",
    "hand_l": "LFingers",
    "hand_r": "RFingers",
    "hip_l": "LeftHip",
    "hip_r": "RightHip",
    "knee_l": "LeftKnee",
    "knee_r": "RightKnee",
    "ankle_l": "LeftAnkle",
    "ankle_r": "RightAnkle",
    "foot_l": "LeftToe",
    "foot_r": "RightToe",
}


def _sided(left: str, right: str, pairs: dict[str, str]) -> dict[str, tuple[str, ...]]:
    out: dict[str, tuple[str, ...]] = {}
    for joint, pattern in pairs.items():
        for side, word in (("l", left), ("r", right)):
            out[f"{joint}_{side}"] = tuple(p.format(s=word) for p in pattern.split("|"))
    return out


#: Naming scheme -> canonical joint -> BVH joint names (first one present wins; matched
#: case-insensitively, a ``namespace:`` prefix ignored).
BVH_JOINT_MAPS: dict[str, dict[str, tuple[str, ...]]] = {
    "cgspeed": {k: (v,) for k, v in CMU_BVH_JOINT_MAP.items()},
    "motionbuilder": {
        "pelvis": ("Hips",),
        "spine_base": ("Hips",),
        "spine_mid": ("Spine",),
        "spine_shoulder": ("Spine2", "Spine1"),
        "neck": ("Neck1", "Neck"),
        "head": ("Head",),
        **_sided(
            "Left",
            "Right",
            {
                "shoulder": "{s}Arm",
                "elbow": "{s}ForeArm",
                "wrist": "{s}Hand",
                "hip": "{s}UpLeg",
                "knee": "{s}Leg",
                "ankle": "{s}Foot",
                "foot": "{s}ToeBase|{s}Toe",
            },
        ),
        "hand_l": ("LFingers", "LeftHandMiddle1", "LeftHandIndex1"),
        "hand_r": ("RFingers", "RightHandMiddle1", "RightHandIndex1"),
    },
    "bandai": {
        "pelvis": ("Hips",),
        "spine_base": ("Hips",),
        "spine_mid": ("Spine",),
        "spine_shoulder": ("Chest",),
        "neck": ("Neck",),
        "head": ("Head",),
        **_sided(
            "L",
            "R",
            {
                "shoulder": "UpperArm_{s}",
                "elbow": "LowerArm_{s}",
                "wrist": "Hand_{s}",
                "hip": "UpperLeg_{s}",
                "knee": "LowerLeg_{s}",
                "ankle": "Foot_{s}",
                "foot": "Toes_{s}",
            },
        ),
    },
}

#: Candidate BVH length units, metres per unit.
BVH_LENGTH_UNITS: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": 0.0254,
    "CMU ASF unit (1/0.45 inch)": 0.0254 / 0.45,
}
_FIGURE_SIZE_M = (0.8, 2.5)

_CHANNELS = ("xposition", "yposition", "zposition", "xrotation", "yrotation", "zrotation")


@dataclass
class _Joint:
    name: str
    parent: int
    line: int
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    channels: tuple[str, ...] = ()
    first_channel: int = 0
    children: list[int] = field(default_factory=list)


class _Tokens:
    """Whitespace tokens with their line numbers, for error messages."""

    def __init__(self, path: Path, lines: list[str]):
        self.path = path
        self.items = [(tok, i) for i, line in enumerate(lines, start=1) for tok in line.split()]
        self.pos = 0
        self.last_line = len(lines)

    def next(self, expected: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            raise FormatError(
                self.path,
                f"expected {expected}, found end of file (truncated?)",
                line=self.last_line,
            )
        item = self.items[self.pos]
        self.pos += 1
        return item

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok.upper() != word.upper():
            raise FormatError(self.path, f"expected {word!r}, found {tok!r}", line=line)
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            return float(tok)
        except ValueError:
            raise FormatError(
                self.path, f"expected a number ({what}), found {tok!r}", line=line
            ) from None


def _parse_hierarchy(tokens: _Tokens) -> tuple[list[_Joint], dict[int, np.ndarray]]:
    """Joints in file order and End Site offsets keyed by the owning joint."""
    path = tokens.path
    tokens.expect("HIERARCHY")
    joints: list[_Joint] = []
    end_sites: dict[int, np.ndarray] = {}
    n_channels = 0

    def parse_block(parent: int, kind: str, kind_line: int) -> None:
        nonlocal n_channels
        if kind == "End":
            tokens.expect("Site")
            tokens.expect("{")
            tokens.expect("OFFSET")
            off = np.array(
                [
                    tokens.number("End Site OFFSET x"),
                    tokens.number("OFFSET y"),
                    tokens.number("OFFSET z"),
                ]
            )
            tokens.expect("}")
            end_sites[parent] = off
            return
        name, _ = tokens.next("a joint name")
        idx = len(joints)
        joint = _Joint(name=name, parent=parent, line=kind_line)
        joints.append(joint)
        if parent >= 0:
            joints[parent].children.append(idx)
        tokens.expect("{")
        tokens.expect("OFFSET")
        joint.offset = np.array(
            [
                tokens.number(f"OFFSET x of {name}"),
                tokens.number("OFFSET y"),
                tokens.number("OFFSET z"),
            ]
        )
        line = tokens.expect("CHANNELS")
        count_f = tokens.number(f"channel count of {name}")
        if count_f != int(count_f) or count_f < 0:
            raise FormatError(
                path, f"expected a channel count for {name!r}, found {count_f}", line=line
            )
        chans = []
        for _ in range(int(count_f)):
            tok, tline = tokens.next(f"a channel name of {name}")
            if tok.lower() not in _CHANNELS:
                raise FormatError(
                    path,
                    f"expected a channel among {[c.capitalize() for c in _CHANNELS]}, found {tok!r}",
                    line=tline,
                )
            chans.append(tok.lower())
        joint.channels = tuple(chans)
        joint.first_channel = n_channels
        n_channels += len(chans)
        while True:
            tok, tline = tokens.next(f"JOINT, End Site or '}}' in {name}")
            if tok == "}":
                return
            if tok.upper() == "JOINT":
                parse_block(idx, "JOINT", tline)
            elif tok == "End":
                parse_block(idx, "End", tline)
            else:
                raise FormatError(
                    path, f"expected JOINT, End Site or '}}' in {name!r}, found {tok!r}", line=tline
                )

    tok, line = tokens.next("ROOT")
    if tok.upper() != "ROOT":
        raise FormatError(path, f"expected 'ROOT', found {tok!r}", line=line)
    parse_block(-1, "ROOT", line)
    return joints, end_sites


def _parse_bvh(path: Path) -> tuple[list[_Joint], dict[int, np.ndarray], np.ndarray, float]:
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise FormatError(path, f"cannot read the BVH file ({exc.strerror})") from None
    motion_line = next(
        (i for i, line in enumerate(lines) if line.strip().upper() == "MOTION"), None
    )
    if motion_line is None:
        raise FormatError(
            path,
            "expected a 'MOTION' section, found none (truncated or not a BVH file?)",
            line=len(lines),
        )
    tokens = _Tokens(path, lines[:motion_line])
    joints, end_sites = _parse_hierarchy(tokens)
    if tokens.pos != len(tokens.items):
        tok, line = tokens.items[tokens.pos]
        raise FormatError(path, f"expected 'MOTION' after the hierarchy, found {tok!r}", line=line)
    n_channels = sum(len(j.channels) for j in joints)

    def header(k: int, key: str) -> str:
        if k >= len(lines):
            raise FormatError(path, f"expected '{key}', found end of file", line=len(lines))
        text = lines[k].strip()
        if not text.lower().startswith(key.lower()):
            raise FormatError(path, f"expected '{key} ...', found {text[:40]!r}", line=k + 1)
        return text[len(key) :].strip()

    n_text = header(motion_line + 1, "Frames:")
    dt_text = header(motion_line + 2, "Frame Time:")
    try:
        n_frames = int(n_text)
        dt = float(dt_text)
    except ValueError:
        raise FormatError(
            path,
            f"expected an integer frame count and a frame time, found {n_text!r}, {dt_text!r}",
            line=motion_line + 2,
        ) from None
    if n_frames < 2 or not np.isfinite(dt) or dt <= 0:
        raise FormatError(
            path,
            f"expected Frames >= 2 and Frame Time > 0, found {n_frames}, {dt}",
            line=motion_line + 2,
        )
    first = motion_line + 3
    data_lines = [(k + 1, lines[k]) for k in range(first, len(lines)) if lines[k].strip()]
    if len(data_lines) < n_frames:
        last = data_lines[-1][0] if data_lines else first
        raise FormatError(
            path,
            f"expected {n_frames} frame lines (Frames:), found {len(data_lines)} (truncated file?)",
            line=last,
        )
    if len(data_lines) > n_frames:
        raise FormatError(
            path,
            f"expected {n_frames} frame lines (Frames:), found {len(data_lines)}",
            line=data_lines[n_frames][0],
        )
    values = np.empty((n_frames, n_channels))
    for f, (line_no, text) in enumerate(data_lines):
        tok = text.split()
        if len(tok) != n_channels:
            raise FormatError(
                path,
                f"frame {f}: expected {n_channels} channel values, found {len(tok)}",
                line=line_no,
            )
        try:
            values[f] = [float(x) for x in tok]
        except ValueError:
            raise FormatError(
                path, f"frame {f}: expected {n_channels} numbers, found a non-number", line=line_no
            ) from None
    if not np.all(np.isfinite(values)):
        f = int(np.flatnonzero(~np.all(np.isfinite(values), axis=1))[0])
        raise FormatError(
            path, f"frame {f}: expected finite values, found NaN/inf", line=data_lines[f][0]
        )
    return joints, end_sites, values, dt


def _bare(name: str) -> str:
    return name.rsplit(":", 1)[-1].lower()


def _pick_joint_map(path: Path, names: list[str], joint_map) -> tuple[dict[str, str], str]:
    """Canonical joint -> BVH joint name actually present, and the naming used."""
    present = {_bare(n): n for n in names}
    if joint_map is not None:
        jm = {c: b for c, b in dict(joint_map).items() if b in names or _bare(b) in present}
        return {c: (b if b in names else present[_bare(b)]) for c, b in jm.items()}, "given"
    best, best_name = {}, ""
    for scheme, table in BVH_JOINT_MAPS.items():
        found = {}
        for canon, cands in table.items():
            hit = next((present[_bare(c)] for c in cands if _bare(c) in present), None)
            if hit is not None:
                found[canon] = hit
        if len(found) > len(best):
            best, best_name = found, scheme
    if not best:
        raise FormatError(
            path,
            f"expected BVH joints in one of the namings {sorted(BVH_JOINT_MAPS)} (e.g. Hips, LeftUpLeg, "
            f"LeftArm), found {names[:8]}...; pass joint_map",
        )
    return best, best_name


def _figure_size(pos: list[np.ndarray]) -> float:
    """Median over frames of the largest side of the joints' bounding box (file units)."""
    p = np.stack(pos, axis=1)  # (T, J, 3)
    return float(np.median((p.max(axis=1) - p.min(axis=1)).max(axis=1)))


def _length_unit(path: Path, size: float, given: float | None) -> tuple[float, str]:
    lo, hi = _FIGURE_SIZE_M
    if given is not None:
        if not lo <= size * given <= hi:
            warnings.warn(
                f"{path}: with length_unit_m={given} the figure is {size * given:.3g} m tall/wide "
                f"(expected {lo}-{hi} m for a person); check the unit",
                UnitWarning,
                stacklevel=4,
            )
        return given, f"length_unit_m={given} given"
    fits = {k: u for k, u in BVH_LENGTH_UNITS.items() if lo <= size * u <= hi}
    # the candidate nearest (in ratio) to a 1.5 m figure; warn unless it is the only plausible one
    name, unit = min(
        (fits or BVH_LENGTH_UNITS).items(), key=lambda kv: abs(np.log(size * kv[1] / 1.5))
    )
    if len(fits) != 1:
        which = (
            f"several units fit ({', '.join(fits)})"
            if fits
            else f"none of {', '.join(BVH_LENGTH_UNITS)} makes it {lo}-{hi} m"
        )
        warnings.warn(
            f"{path}: cannot tell the length unit: the figure measures {size:.4g} BVH units and "
            f"{which}; assumed {name} ({size * unit:.3g} m); pass length_unit_m= to say",
            UnitWarning,
            stacklevel=4,
        )
    return unit, f"detected {name} (figure {size:.4g} units = {size * unit:.3g} m)"


def _forward_kinematics(joints, values: np.ndarray):
    """Per joint: global rotation (T, 3, 3), position (T, 3) and local translation (T, 3), file units."""
    T = values.shape[0]
    rot: list[np.ndarray] = []
    pos: list[np.ndarray] = []  # file units
    trans: list[np.ndarray] = []  # local translation (T, 3), file units
    for j in joints:
        ch = values[:, j.first_channel : j.first_channel + len(j.channels)]
        local_t = np.broadcast_to(j.offset, (T, 3)).copy()
        rcols = [c for c, name in enumerate(j.channels) if name.endswith("rotation")]
        for c, name in enumerate(j.channels):
            if name.endswith("position"):
                a = "xyz".index(name[0])
                local_t[:, a] = ch[:, c] + (j.offset[a] if j.parent < 0 else 0.0)
        if rcols:
            seq = "".join(j.channels[c][0].upper() for c in rcols)  # intrinsic, listed order
            R_local = Rotation.from_euler(seq, ch[:, rcols], degrees=True).as_matrix()
        else:
            R_local = np.broadcast_to(np.eye(3), (T, 3, 3))
        if j.parent < 0:
            p = local_t
            R = np.array(R_local)
        else:
            R_p, p_p = rot[j.parent], pos[j.parent]
            p = p_p + np.einsum("tij,tj->ti", R_p, local_t)
            R = R_p @ R_local
        rot.append(R)
        pos.append(p)
        trans.append(local_t)

    return rot, pos, trans


def _segments(joints, index: dict, joint_source: dict, trans: list, unit: float):
    """Canonical segment -> BVH joint carrying it, with each bone's direction and length (m)."""
    segment_source, bone_dir, bone_len = {}, {}, {}
    for seg, (prox, dist) in CANONICAL_SEGMENT_JOINTS.items():
        if prox not in joint_source or (dist is not None and dist not in joint_source):
            continue
        b = joint_source[prox]
        if dist is not None:
            child = index[joint_source[dist]]
            if joints[child].parent != index[b]:
                continue
            off = np.median(trans[child], axis=0) * unit
            length = float(np.linalg.norm(off))
            if length == 0.0:
                continue
            bone_dir[b], bone_len[b] = off / length, length
        segment_source[seg] = b
    return segment_source, bone_dir, bone_len


def load_motion_bvh(
    path, *, length_unit_m: float | None = None, joint_map: Mapping[str, str] | None = None
) -> Motion:
    """Read a BVH file and run forward kinematics: segment orientations and joint positions.

    Parameters
    ----------
    path : str or Path
        The ``.bvh`` file.
    length_unit_m : float or None
        Metres per BVH length unit (1.0 for the metre-scaled CMU clips; 0.01 for cm files).
        None: detected from the figure's size (module docstring), ``metadata["length_unit"]``
        says what was found; a given unit is checked the same way (a UnitWarning if the figure
        is implausibly small or large).
    joint_map : mapping of str -> str, optional
        Canonical joint -> BVH joint name. Default: the naming of :data:`BVH_JOINT_MAPS` that
        matches most joints (``metadata["joint_naming"]``). Joints whose BVH name is absent are
        left out with a warning for the limb joints (a segment is exported only if both its joints
        are present and its distal joint is a direct child of the proximal one).

    Returns
    -------
    Motion
        ``t_s (T,)`` from ``Frame Time``; ``q_world_from_segment (T, S, 4)`` (y axis along each
        bone, proximal -> distal); ``position_m (T, J, 3)`` in metres, ENU.

    Raises
    ------
    FormatError
        Missing, truncated or malformed file; no known naming; undecidable length unit. Names
        file, line, expected and found.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "expected an existing BVH file, found none")
    if length_unit_m is not None and (not np.isfinite(length_unit_m) or length_unit_m <= 0):
        raise InputError(f"expected length_unit_m finite and > 0, got {length_unit_m!r}")
    joints, _end_sites, values, dt = _parse_bvh(path)
    T = values.shape[0]
    rot, pos, trans = _forward_kinematics(joints, values)
    names = [j.name for j in joints]
    index = {n: i for i, n in enumerate(names)}
    joint_source, naming = _pick_joint_map(path, names, joint_map)
    notes = []
    missing = [c for c in KINECT_LIMB_JOINTS if c not in joint_source]
    if missing:
        msg = f"{path}: BVH naming {naming!r}: no joint found for {missing}; they are left out"
        warnings.warn(msg, UserWarning, stacklevel=3)
        notes.append(msg)
    size = _figure_size([pos[index[b]] for b in set(joint_source.values())] or pos)
    unit, unit_note = _length_unit(path, size, length_unit_m)
    segment_source, bone_dir, bone_len = _segments(joints, index, joint_source, trans, unit)
    point = {n: pos[i] * unit for n, i in index.items()}
    metadata = {
        "source": str(path),
        "format": "bvh",
        "subject": path.stem,
        "trial": path.stem,
        "rate_hz": 1.0 / dt,
        "frame_time_s": dt,
        "units_converted": f"length: BVH unit x {unit:.6g} -> m; angles: deg; y-up -> ENU",
        "length_unit": unit_note,
        "length_unit_m": unit,
        "joint_naming": naming,
        "bvh_joints": tuple(names),
        "notes": notes,
    }
    return _build_motion(
        t_s=np.arange(T) * dt,
        rot_world_from_bone={n: rot[i] for n, i in index.items()},
        point_position=point,
        bone_direction=bone_dir,
        bone_length_m=bone_len,
        segment_source=segment_source,
        joint_source=joint_source,
        metadata=metadata,
    )


def read_bvh(
    path, *, length_unit_m: float | None = None, joint_map: Mapping[str, str] | None = None
) -> Recording:
    """Read a BVH file as a :class:`~kinefuse.io.recording.Recording` (reference only).

    Parameters
    ----------
    path, length_unit_m, joint_map
        As in :func:`load_motion_bvh`.

    Returns
    -------
    Recording
        ``reference``: canonical joint positions (T, J, 3), m, ENU, at the file's frame rate;
        ``reference_orientation``: ``q_world_from_segment`` per canonical segment; ``metadata``:
        source, format ``"bvh"``, rate, unit conversion, segment/joint maps.
    """
    return load_motion_bvh(path, length_unit_m=length_unit_m, joint_map=joint_map).to_recording()
