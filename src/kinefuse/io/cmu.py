"""Reader for Acclaim ASF/AMC motion capture (CMU Graphics Lab Motion Capture Database).

Format (Acclaim, as used by CMU)
--------------------------------
ASF
    ``:units`` (``length`` = ASF length units per inch-based CMU unit, ``angle deg|rad``),
    ``:root`` (``order`` of the root channels, ``axis`` order, ``position``, ``orientation``),
    ``:bonedata`` (per bone: ``name``, unit ``direction`` in the global rest frame, ``length``,
    ``axis`` angles + order, ``dof``), ``:hierarchy`` (``parent child child ...``).
AMC
    ``:FULLY-SPECIFIED``, ``:DEGREES`` (or ``:RADIANS``), then per frame a frame number line
    followed by ``bone value value ...`` lines in the bone's ``dof`` order (root: ``order``).
    No timestamps: CMU captured at 120 Hz.

Units: CMU's ``:units length 0.45`` means one ASF unit is ``(1 / 0.45)`` inch, so
``metres = value / length * 0.0254`` (applied to bone lengths and root translation).

Forward kinematics (per frame): a bone's global rotation is ``R = R_parent · C · M · C⁻¹`` with
``C`` the bone's ``axis`` rotation and ``M`` the AMC rotation built from the dof angles applied in
their listed order (``rx ry rz``: X first, i.e. ``M = Rz Ry Rx``); the bone ends at
``start + length · R · direction``; it starts where its parent ends (the root at the root
translation). Mocap y-up coordinates are rotated to ENU with
:data:`kinefuse.io.motion.R_ENU_FROM_YUP`.

Canonical mapping (CMU bone names; "end of X" = the point where bone X ends)
    joints: pelvis / spine_base = root; spine_mid = end of upperback; spine_shoulder = end of
    thorax; neck = end of lowerneck; head = end of upperneck; shoulder = end of l/rclavicle;
    elbow = end of l/rhumerus; wrist = end of l/rradius; hand = end of l/rwrist; hip = end of
    l/rhipjoint; knee = end of l/rfemur; ankle = end of l/rtibia; foot = end of l/rfoot.
    segments: pelvis = root; chest = thorax; upper_arm = humerus; forearm = radius; hand =
    wrist (the short bone that carries pronation/supination, dof ``ry``); thigh = femur;
    shank = tibia; foot = foot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io.motion import CANONICAL_SEGMENT_JOINTS, Motion, _build_motion
from kinefuse.io.recording import Recording

__all__ = ["CMU_RATE_HZ", "load_motion_asf_amc", "read_asf_amc"]

#: CMU capture rate, Hz (the AMC files have no timestamps).
CMU_RATE_HZ = 120.0
_INCH_M = 0.0254

_CMU_JOINTS = {
    "pelvis": "root",
    "spine_base": "root",
    "spine_mid": "upperback",
    "spine_shoulder": "thorax",
    "neck": "lowerneck",
    "head": "upperneck",
    "shoulder_l": "lclavicle",
    "shoulder_r": "rclavicle",
    "elbow_l": "lhumerus",
    "elbow_r": "rhumerus",
    "wrist_l": "lradius",
    "wrist_r": "rradius",
    "hand_l": "lwrist",
    "hand_r": "rwrist",
    "hip_l": "lhipjoint",
    "hip_r": "rhipjoint",
    "knee_l": "lfemur",
    "knee_r": "rfemur",
    "ankle_l": "ltibia",
    "ankle_r": "rtibia",
    "foot_l": "lfoot",
    "foot_r": "rfoot",
}
_CMU_SEGMENTS = {
    "pelvis": "root",
    "chest": "thorax",
    "upper_arm_l": "lhumerus",
    "upper_arm_r": "rhumerus",
    "forearm_l": "lradius",
    "forearm_r": "rradius",
    "thigh_l": "lfemur",
    "thigh_r": "rfemur",
    "shank_l": "ltibia",
    "shank_r": "rtibia",
    "foot_l": "lfoot",
    "foot_r": "rfoot",
    "hand_l": "lwrist",
    "hand_r": "rwrist",
}
_ROT_DOFS = ("rx", "ry", "rz")


@dataclass
class _Bone:
    name: str
    line: int
    direction: np.ndarray = field(default_factory=lambda: np.zeros(3))
    length: float = 0.0
    axis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axis_order: str = "XYZ"
    dof: tuple[str, ...] = ()


@dataclass
class _Skeleton:
    path: Path
    length_unit: float
    angle_deg: bool
    root_order: tuple[str, ...]
    root_axis_order: str
    root_position: np.ndarray
    root_orientation: np.ndarray
    bones: dict[str, _Bone]
    children: dict[str, list[str]]
    name: str = ""


def _floats(path, line_no: int, tokens: list[str], n: int, what: str) -> np.ndarray:
    if len(tokens) < n:
        raise FormatError(
            path,
            f"expected {n} numbers for {what}, found {len(tokens)}: {' '.join(tokens)!r}",
            line=line_no,
        )
    try:
        return np.array([float(x) for x in tokens[:n]])
    except ValueError:
        raise FormatError(
            path, f"expected {n} numbers for {what}, found {' '.join(tokens[:n])!r}", line=line_no
        ) from None


def _parse_asf(path: Path) -> _Skeleton:
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise FormatError(path, f"cannot read the ASF file ({exc.strerror})") from None
    section = None
    length_unit, angle_deg, name = 1.0, True, ""
    root_order: tuple[str, ...] = ()
    root_axis, root_pos, root_ori = "XYZ", np.zeros(3), np.zeros(3)
    bones: dict[str, _Bone] = {}
    children: dict[str, list[str]] = {}
    current: _Bone | None = None
    seen_sections: set[str] = set()
    for i, raw in enumerate(lines, start=1):
        text = raw.split("#", 1)[0].strip()
        if not text:
            continue
        tok = text.split()
        key = tok[0].lower()
        if key.startswith(":"):
            section = key[1:]
            seen_sections.add(section)
            if section == "name" and len(tok) > 1:
                name = tok[1]
            if section in ("units", "root", "bonedata", "hierarchy") and len(tok) > 1:
                raise FormatError(
                    path,
                    f"expected nothing after ':{section}', found {' '.join(tok[1:])!r}",
                    line=i,
                )
            continue
        if section == "units":
            if key == "length":
                length_unit = float(_floats(path, i, tok[1:], 1, "units length")[0])
                if length_unit <= 0:
                    raise FormatError(
                        path, f"expected a positive length unit, found {tok[1]}", line=i
                    )
            elif key == "angle":
                if len(tok) < 2 or tok[1].lower() not in ("deg", "rad"):
                    raise FormatError(
                        path, f"expected 'angle deg' or 'angle rad', found {text!r}", line=i
                    )
                angle_deg = tok[1].lower() == "deg"
        elif section == "root":
            if key == "order":
                root_order = tuple(t.lower() for t in tok[1:])
                bad = [t for t in root_order if t not in ("tx", "ty", "tz", "rx", "ry", "rz")]
                if bad or not root_order:
                    raise FormatError(
                        path,
                        f"expected root order channels among TX TY TZ RX RY RZ, found {text!r}",
                        line=i,
                    )
            elif key == "axis":
                if len(tok) < 2 or sorted(tok[1].upper()) != ["X", "Y", "Z"]:
                    raise FormatError(
                        path, f"expected root axis order like XYZ, found {text!r}", line=i
                    )
                root_axis = tok[1].upper()
            elif key == "position":
                root_pos = _floats(path, i, tok[1:], 3, "root position")
            elif key == "orientation":
                root_ori = _floats(path, i, tok[1:], 3, "root orientation")
        elif section == "bonedata":
            if key == "begin":
                current = _Bone(name="", line=i)
            elif key == "end":
                if current is None:
                    raise FormatError(path, "expected 'begin' before 'end' in :bonedata", line=i)
                if not current.name:
                    raise FormatError(
                        path, "expected a 'name' in the bone block starting here", line=current.line
                    )
                norm = float(np.linalg.norm(current.direction))
                if not np.isfinite(norm) or norm == 0.0:
                    raise FormatError(
                        path,
                        f"expected a non-zero 'direction' for bone {current.name!r}",
                        line=current.line,
                    )
                current.direction = current.direction / norm
                bones[current.name] = current
                current = None
            elif current is None:
                raise FormatError(path, f"expected 'begin' in :bonedata, found {text!r}", line=i)
            elif key == "name":
                if len(tok) < 2:
                    raise FormatError(path, "expected a bone name after 'name'", line=i)
                current.name = tok[1]
            elif key == "direction":
                current.direction = _floats(path, i, tok[1:], 3, "bone direction")
            elif key == "length":
                current.length = float(_floats(path, i, tok[1:], 1, "bone length")[0])
                if current.length < 0:
                    raise FormatError(
                        path, f"expected a non-negative bone length, found {tok[1]}", line=i
                    )
            elif key == "axis":
                current.axis = _floats(path, i, tok[1:], 3, "bone axis angles")
                order = tok[4].upper() if len(tok) > 4 else "XYZ"
                if sorted(order) != ["X", "Y", "Z"]:
                    raise FormatError(
                        path, f"expected an axis order like XYZ, found {order!r}", line=i
                    )
                current.axis_order = order
            elif key == "dof":
                dof = tuple(t.lower() for t in tok[1:])
                bad = [d for d in dof if d not in _ROT_DOFS]
                if bad:
                    raise FormatError(
                        path,
                        f"expected rotational dofs among rx ry rz for bone {current.name!r}, found {bad} (translation/length dofs are not supported)",
                        line=i,
                    )
                current.dof = dof
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            children.setdefault(tok[0], []).extend(tok[1:])
    if current is not None:
        raise FormatError(
            path,
            f"expected 'end' closing the bone block of {current.name or '?'}, found end of file",
            line=current.line,
        )
    for sec in ("root", "bonedata", "hierarchy"):
        if sec not in seen_sections:
            raise FormatError(
                path,
                f"expected a ':{sec}' section, found none (truncated or not an ASF file?)",
                line=len(lines),
            )
    if not root_order:
        raise FormatError(
            path, "expected 'order' in the :root section, found none", field="root.order"
        )
    for parent, kids in children.items():
        for name_ in [parent, *kids]:
            if name_ != "root" and name_ not in bones:
                raise FormatError(
                    path,
                    f"expected hierarchy names to be defined bones, found {name_!r}",
                    field="hierarchy",
                )
    return _Skeleton(
        path=path,
        length_unit=length_unit,
        angle_deg=angle_deg,
        root_order=root_order,
        root_axis_order=root_axis,
        root_position=root_pos,
        root_orientation=root_ori,
        bones=bones,
        children=children,
        name=name,
    )


def _parse_amc(path: Path, skel: _Skeleton) -> tuple[np.ndarray, dict[str, np.ndarray], bool]:
    """Frame numbers (F,) and per-bone value arrays (F, n_dof); and whether angles are degrees."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise FormatError(path, f"cannot read the AMC file ({exc.strerror})") from None
    n_vals = {"root": len(skel.root_order)}
    n_vals.update({b.name: len(b.dof) for b in skel.bones.values() if b.dof})
    expected = set(n_vals)
    angle_deg = skel.angle_deg
    frames: list[int] = []
    values: dict[str, list[list[float]]] = {k: [] for k in n_vals}
    current: dict[str, list[float]] | None = None
    frame_line = 0

    def close_frame(end_line: int) -> None:
        if current is None:
            return
        missing = sorted(expected - set(current))
        if missing:
            raise FormatError(
                path,
                f"frame {frames[-1]} (starting line {frame_line}): expected values for all {len(expected)} bones, "
                f"missing {missing} (truncated file?)",
                line=end_line,
            )
        for k in n_vals:
            values[k].append(current[k])

    for i, raw in enumerate(lines, start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        if text.startswith(":"):
            if text.upper().startswith(":RADIANS"):
                angle_deg = False
            elif text.upper().startswith(":DEGREES"):
                angle_deg = True
            continue
        tok = text.split()
        if len(tok) == 1 and tok[0].isdigit():
            close_frame(i)
            number = int(tok[0])
            if frames and number != frames[-1] + 1:
                raise FormatError(
                    path, f"expected frame number {frames[-1] + 1}, found {number}", line=i
                )
            frames.append(number)
            current = {}
            frame_line = i
            continue
        if current is None:
            raise FormatError(
                path, f"expected a frame number before bone values, found {text[:40]!r}", line=i
            )
        bone = tok[0]
        if bone not in n_vals:
            raise FormatError(
                path,
                f"expected a bone with dofs from the ASF {skel.path.name}, found {bone!r}",
                line=i,
            )
        if bone in current:
            raise FormatError(path, f"frame {frames[-1]}: bone {bone!r} given twice", line=i)
        n = n_vals[bone]
        if len(tok) - 1 != n:
            dofs = skel.root_order if bone == "root" else skel.bones[bone].dof
            raise FormatError(
                path,
                f"expected {n} values ({' '.join(dofs)}) for {bone!r}, found {len(tok) - 1}",
                line=i,
            )
        try:
            current[bone] = [float(x) for x in tok[1:]]
        except ValueError:
            raise FormatError(
                path, f"expected numbers for {bone!r}, found {' '.join(tok[1:])!r}", line=i
            ) from None
    close_frame(len(lines))
    if len(frames) < 2:
        raise FormatError(path, f"expected at least 2 frames, found {len(frames)}", line=len(lines))
    arrays = {k: np.asarray(v, dtype=float) for k, v in values.items()}
    for k, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise FormatError(
                path, f"expected finite values, found non-finite values for bone {k!r}", field=k
            )
    return np.asarray(frames), arrays, angle_deg


def _euler_matrix(angles: np.ndarray, order: str, degrees: bool) -> np.ndarray:
    """Rotation for angles applied in ``order`` (first listed first): extrinsic SciPy sequence."""
    return Rotation.from_euler(order.lower(), angles, degrees=degrees).as_matrix()


def _find_asf(amc_path: Path) -> Path:
    subject = amc_path.stem.split("_")[0]
    candidate = amc_path.with_name(f"{subject}.asf")
    if candidate.is_file():
        return candidate
    found = sorted(amc_path.parent.glob("*.asf")) + sorted(amc_path.parent.glob("*.ASF"))
    if len(found) == 1:
        return found[0]
    raise FormatError(
        amc_path,
        f"expected the skeleton file {candidate.name} (or a single .asf) beside the AMC, found "
        f"{[p.name for p in found] or 'none'}; pass asf_path",
    )


def _forward_kinematics(skel, vals: dict, angle_deg: bool, scale: float, T: int):
    """Bone -> global rotation (T, 3, 3) and end point (T, 3) in m, from the root breadth-first."""
    # root
    order = skel.root_order
    root_vals = vals["root"]
    trans = np.zeros((T, 3))
    for c, name in enumerate(order):
        if name.startswith("t"):
            trans[:, "xyz".index(name[1])] = root_vals[:, c]
    rot_cols = [c for c, name in enumerate(order) if name.startswith("r")]
    C = _euler_matrix(skel.root_orientation, skel.root_axis_order, skel.angle_deg)
    if rot_cols:
        M = _euler_matrix(root_vals[:, rot_cols], "".join(order[c][1] for c in rot_cols), angle_deg)
    else:
        M = np.broadcast_to(np.eye(3), (T, 3, 3))
    rot = {"root": C @ M @ C.T}
    end = {"root": (skel.root_position + trans) * scale}

    # bones, breadth-first from the root
    queue = list(skel.children.get("root", []))
    parent = {k: "root" for k in queue}
    while queue:
        name = queue.pop(0)
        bone = skel.bones[name]
        C = _euler_matrix(bone.axis, bone.axis_order, skel.angle_deg)
        if bone.dof:
            M = _euler_matrix(vals[name], "".join(d[1] for d in bone.dof), angle_deg)
            local = C @ M @ C.T
            rot[name] = rot[parent[name]] @ local
        else:
            rot[name] = rot[parent[name]]
        end[name] = end[parent[name]] + (bone.length * scale) * (rot[name] @ bone.direction)
        for kid in skel.children.get(name, []):
            parent[kid] = name
            queue.append(kid)
    return rot, end


def load_motion_asf_amc(amc_path, asf_path=None, *, rate_hz: float = CMU_RATE_HZ) -> Motion:
    """Read an ASF/AMC pair and run forward kinematics: segment orientations and joint positions.

    Parameters
    ----------
    amc_path : str or Path
        The motion (``.amc``).
    asf_path : str or Path, optional
        The skeleton (``.asf``). Default: ``<subject>.asf`` beside the AMC (CMU naming
        ``02_05.amc`` -> ``02.asf``), or the only ``.asf`` in that folder.
    rate_hz : float
        Frame rate, Hz (AMC files carry none; CMU is 120 Hz). ``t_s = (frame - first) / rate_hz``.

    Returns
    -------
    Motion
        ``t_s (T,)``; ``q_world_from_segment (T, 12, 4)`` for the canonical segments (y axis
        along each bone); ``position_m (T, 22, 3)`` canonical joints in metres, ENU. See the
        module docstring for the mapping and :mod:`kinefuse.io.motion` for the frames.

    Raises
    ------
    FormatError
        Missing, truncated or malformed file; the message names file, line, expected and found.
    """
    amc_path = Path(amc_path)
    asf = _find_asf(amc_path) if asf_path is None else Path(asf_path)
    if not amc_path.is_file():
        raise FormatError(amc_path, "expected an existing AMC file, found none")
    if not asf.is_file():
        raise FormatError(asf, "expected an existing ASF file, found none")
    if not np.isfinite(rate_hz) or rate_hz <= 0:
        raise InputError(f"expected rate_hz finite and > 0, got {rate_hz!r}")
    skel = _parse_asf(asf)
    frames, vals, angle_deg = _parse_amc(amc_path, skel)
    scale = _INCH_M / skel.length_unit  # metres per ASF length unit
    T = frames.size

    rot, end = _forward_kinematics(skel, vals, angle_deg, scale, T)
    joint_source = {j: b for j, b in _CMU_JOINTS.items() if b in end}
    segment_source = {s: b for s, b in _CMU_SEGMENTS.items() if b in rot}
    # a segment needs both its joints
    segment_source = {
        s: b
        for s, b in segment_source.items()
        if all(j is None or j in joint_source for j in CANONICAL_SEGMENT_JOINTS[s])
    }
    metadata = {
        "source": str(amc_path),
        "skeleton": str(asf),
        "format": "cmu",
        "subject": amc_path.stem.split("_")[0],
        "trial": amc_path.stem,
        "rate_hz": float(rate_hz),
        "frames": (int(frames[0]), int(frames[-1])),
        "units_converted": f"length: ASF unit x 0.0254 / {skel.length_unit} -> m; angles: deg -> rotations; y-up -> ENU",
        "bone_lengths_m": {name: b.length * scale for name, b in skel.bones.items()},
    }
    return _build_motion(
        t_s=(frames - frames[0]) / float(rate_hz),
        rot_world_from_bone=rot,
        point_position=end,
        bone_direction={n: b.direction for n, b in skel.bones.items()},
        bone_length_m={n: b.length * scale for n, b in skel.bones.items()},
        segment_source=segment_source,
        joint_source=joint_source,
        metadata=metadata,
    )


def read_asf_amc(amc_path, asf_path=None, *, rate_hz: float = CMU_RATE_HZ) -> Recording:
    """Read an ASF/AMC pair as a :class:`~kinefuse.io.recording.Recording` (reference only).

    Parameters
    ----------
    amc_path, asf_path, rate_hz
        As in :func:`load_motion_asf_amc`.

    Returns
    -------
    Recording
        ``reference``: canonical joint positions (T, 22, 3), m, ENU, at 120 Hz;
        ``reference_orientation``: ``q_world_from_segment`` per canonical segment;
        ``metadata``: source, format ``"cmu"`` (the reader name), subject, rate, unit conversion, bone
        lengths, segment/joint maps. No IMU and no vision streams.
    """
    return load_motion_asf_amc(amc_path, asf_path, rate_hz=rate_hz).to_recording()
