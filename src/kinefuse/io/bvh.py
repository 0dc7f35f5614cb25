"""Reader for Biovision Hierarchy (BVH) motion capture files.

Format
------
``HIERARCHY`` with nested ``ROOT``/``JOINT``/``End Site`` blocks, each with an ``OFFSET`` (from
the parent joint, in the parent's frame) and ``CHANNELS`` (any of ``X/Y/Zposition``,
``X/Y/Zrotation``, in the order they appear in each frame line); then ``MOTION``, ``Frames: n``,
``Frame Time: dt`` and one line of channel values per frame (angles in degrees).

Forward kinematics: a joint's local rotation is the product of its rotation channels in the listed
order (``Zrotation Yrotation Xrotation`` -> ``Rz · Ry · Rx``, i.e. intrinsic); its global rotation
``R_j = R_parent · R_local``; its position ``p_j = p_parent + R_parent · offset_j`` (+ its
position channels, for the root). Positions are scaled by ``length_unit_m`` (the CMU BVH clips in
``cmu_mocap/bvh_131_scaled`` are in metres, the default) and y-up coordinates are rotated to ENU
with :data:`kinefuse.io.motion.R_ENU_FROM_YUP`.

Canonical mapping (the CMU "3ds Max friendly" BVH naming of cgspeed, default ``joint_map``)
    joints: pelvis / spine_base = Hips; spine_mid = Chest; spine_shoulder = Chest2; neck = Neck;
    head = Head; shoulder/elbow/wrist = Left|RightShoulder/Elbow/Wrist; hand = L|RFingers;
    hip/knee/ankle = Left|RightHip/Knee/Ankle; foot = Left|RightToe.
    segments carry the rotation of their proximal joint: pelvis = Hips, chest = Chest,
    upper_arm = Shoulder, forearm = Elbow, thigh = Hip, shank = Knee, foot = Ankle; the distal
    joint must be a direct child of the proximal one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io.motion import CANONICAL_SEGMENT_JOINTS, Motion, _build_motion
from kinefuse.io.recording import Recording

__all__ = ["CMU_BVH_JOINT_MAP", "load_motion_bvh", "read_bvh"]

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


def load_motion_bvh(
    path, *, length_unit_m: float = 1.0, joint_map: Mapping[str, str] | None = None
) -> Motion:
    """Read a BVH file and run forward kinematics: segment orientations and joint positions.

    Parameters
    ----------
    path : str or Path
        The ``.bvh`` file.
    length_unit_m : float
        Metres per BVH length unit (1.0 for the metre-scaled CMU clips; 0.01 for cm files).
    joint_map : mapping of str -> str, optional
        Canonical joint -> BVH joint name. Default :data:`CMU_BVH_JOINT_MAP`. Joints whose BVH
        name is absent are left out (a segment is exported only if both its joints are present
        and its distal joint is a direct child of the proximal one).

    Returns
    -------
    Motion
        ``t_s (T,)`` from ``Frame Time``; ``q_world_from_segment (T, S, 4)`` (y axis along each
        bone, proximal -> distal); ``position_m (T, J, 3)`` in metres, ENU.

    Raises
    ------
    FormatError
        Missing, truncated or malformed file; names file, line, expected and found.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "expected an existing BVH file, found none")
    if not np.isfinite(length_unit_m) or length_unit_m <= 0:
        raise InputError(f"expected length_unit_m finite and > 0, got {length_unit_m!r}")
    joints, _end_sites, values, dt = _parse_bvh(path)
    T = values.shape[0]
    rot: list[np.ndarray] = []
    pos: list[np.ndarray] = []
    for j in joints:
        ch = values[:, j.first_channel : j.first_channel + len(j.channels)]
        local_t = np.zeros((T, 3))
        rcols = [c for c, name in enumerate(j.channels) if name.endswith("rotation")]
        for c, name in enumerate(j.channels):
            if name.endswith("position"):
                local_t[:, "xyz".index(name[0])] = ch[:, c]
        if rcols:
            seq = "".join(j.channels[c][0].upper() for c in rcols)  # intrinsic, listed order
            R_local = Rotation.from_euler(seq, ch[:, rcols], degrees=True).as_matrix()
        else:
            R_local = np.broadcast_to(np.eye(3), (T, 3, 3))
        offset = j.offset * length_unit_m
        if j.parent < 0:
            p = offset + local_t * length_unit_m
            R = np.array(R_local)
        else:
            R_p, p_p = rot[j.parent], pos[j.parent]
            p = p_p + R_p @ offset + np.einsum("tij,tj->ti", R_p, local_t * length_unit_m)
            R = R_p @ R_local
        rot.append(R)
        pos.append(p)

    names = [j.name for j in joints]
    index = {n: i for i, n in enumerate(names)}
    jmap = dict(CMU_BVH_JOINT_MAP if joint_map is None else joint_map)
    joint_source = {c: b for c, b in jmap.items() if b in index}
    if not joint_source:
        raise FormatError(
            path,
            f"expected BVH joints named like {sorted(set(jmap.values()))[:6]}..., found {names[:8]}...; pass joint_map",
        )
    segment_source, bone_dir, bone_len = {}, {}, {}
    for seg, (prox, dist) in CANONICAL_SEGMENT_JOINTS.items():
        if prox not in joint_source or (dist is not None and dist not in joint_source):
            continue
        b = joint_source[prox]
        if dist is not None:
            child = index[joint_source[dist]]
            if joints[child].parent != index[b]:
                continue
            off = joints[child].offset * length_unit_m
            length = float(np.linalg.norm(off))
            if length == 0.0:
                continue
            bone_dir[b], bone_len[b] = off / length, length
        segment_source[seg] = b
    point = {n: pos[i] for n, i in index.items()}
    metadata = {
        "source": str(path),
        "format": "bvh",
        "subject": path.stem,
        "trial": path.stem,
        "rate_hz": 1.0 / dt,
        "frame_time_s": dt,
        "units_converted": f"length: BVH unit x {length_unit_m} -> m; angles: deg; y-up -> ENU",
        "bvh_joints": tuple(names),
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
    path, *, length_unit_m: float = 1.0, joint_map: Mapping[str, str] | None = None
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
