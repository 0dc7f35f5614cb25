"""A mocap trial as kinematic truth: segment orientations and joint positions in ENU.

:class:`Motion` is what the mocap readers (:mod:`kinefuse.io.cmu`, :mod:`kinefuse.io.bvh`)
produce and what the virtual sensors (:mod:`kinefuse.sim`) consume.

Segment frames
--------------
For every canonical segment that is a bone (all but the pelvis), the exported
``q_world_from_segment`` has its **y axis (e2) along the bone, from the proximal to the distal
joint** (SPEC §2.2 default segment axis ``a = e2``), by construction, so that for every sample

``position(distal) == position(proximal) + segment_length_m[seg] * R(q_world_from_segment) @ e2``

holds to rounding error. The remaining twist is fixed in the mocap's rest pose (all joint angles
zero): z is the rest pose's forward direction made orthogonal to y (or its up direction when the
bone points nearly forward, as the foot does), and x = y × z. Bones that hang down in the rest pose
(legs) thus have x to the subject's right, z forward. The pelvis has no bone: its frame is the
mocap root frame, x left, y up, z forward in the rest pose; its ``segment_joints`` entry is
``("pelvis", None)``.

Mocap frame to ENU
------------------
Mocap data are y-up with the rest pose facing +z and +x to the subject's left. Positions and
orientations are rotated into ENU (z up) with :data:`R_ENU_FROM_YUP`: mocap +y -> up, +z ->
north, +x -> west; a proper rotation (180° about (0, 1, 1)/√2, det +1). The subject's heading in
the world is whatever the recording's root heading is.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.conventions import JOINTS, SEGMENTS
from kinefuse.exceptions import InputError
from kinefuse.io.recording import ImuStream, JointStream, Recording, name_index

__all__ = ["CANONICAL_SEGMENT_JOINTS", "R_ENU_FROM_YUP", "SEGMENT_AXIS", "Motion"]

#: Rotation taking y-up mocap coordinates (x left, y up, z forward in the rest pose) to ENU.
R_ENU_FROM_YUP = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])

#: Segment axis (proximal -> distal) in every exported segment frame: e2.
SEGMENT_AXIS = np.array([0.0, 1.0, 0.0])

#: Canonical segment -> (proximal joint, distal joint); ``None`` = no bone (pelvis).
CANONICAL_SEGMENT_JOINTS: dict[str, tuple[str, str | None]] = {
    "pelvis": ("pelvis", None),
    "chest": ("spine_mid", "spine_shoulder"),
    "upper_arm_l": ("shoulder_l", "elbow_l"),
    "upper_arm_r": ("shoulder_r", "elbow_r"),
    "forearm_l": ("elbow_l", "wrist_l"),
    "forearm_r": ("elbow_r", "wrist_r"),
    "thigh_l": ("hip_l", "knee_l"),
    "thigh_r": ("hip_r", "knee_r"),
    "shank_l": ("knee_l", "ankle_l"),
    "shank_r": ("knee_r", "ankle_r"),
    "foot_l": ("ankle_l", "foot_l"),
    "foot_r": ("ankle_r", "foot_r"),
    "hand_l": ("wrist_l", "hand_l"),
    "hand_r": ("wrist_r", "hand_r"),
}

_REST_FORWARD = np.array([0.0, 0.0, 1.0])  # mocap coordinates
_REST_UP = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True, eq=False)
class Motion:
    """Kinematic truth of one mocap trial in ENU (see the module docstring for the frames).

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Sample times, s, strictly increasing (120 Hz for CMU).
    q_world_from_segment : ndarray, shape (T, S, 4)
        Segment orientations, scalar-first ``wxyz``, segment frame to ENU; sign-continuous in
        time. The segment's y axis points along the bone from proximal to distal joint.
    segments : tuple of str, length S
        Canonical segment names (:data:`kinefuse.conventions.SEGMENTS`).
    position_m : ndarray, shape (T, J, 3)
        Joint positions, m, ENU.
    joints : tuple of str, length J
        Canonical joint names (:data:`kinefuse.conventions.JOINTS`).
    segment_joints : dict of str -> (str, str or None)
        Proximal and distal joint of each segment (``None`` distal for the bone-less pelvis).
    segment_length_m : dict of str -> float
        Bone length, m, of each segment with a distal joint (constant: rigid mocap bones).
    segment_source : dict of str -> str
        Canonical segment -> the mocap bone (ASF bone / BVH joint) whose rotation it carries.
    joint_source : dict of str -> str
        Canonical joint -> the mocap point (ASF: end of that bone, ``root``; BVH: that joint).
    metadata : dict
        ``source`` (file), ``format``, ``subject``, ``rate_hz``, ``R_enu_from_mocap`` and
        reader notes.
    """

    t_s: np.ndarray
    q_world_from_segment: np.ndarray
    segments: tuple[str, ...]
    position_m: np.ndarray
    joints: tuple[str, ...]
    segment_joints: Mapping[str, tuple[str, str | None]]
    segment_length_m: Mapping[str, float]
    segment_source: Mapping[str, str] = field(default_factory=dict)
    joint_source: Mapping[str, str] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        t = np.asarray(self.t_s, dtype=float)
        if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise InputError(
                f"Motion: expected finite, strictly increasing t_s with shape (T,), T >= 2, got shape {t.shape}"
            )
        q = np.asarray(self.q_world_from_segment, dtype=float)
        segs = tuple(self.segments)
        if q.shape != (t.size, len(segs), 4):
            raise InputError(
                f"Motion: expected q_world_from_segment with shape (T, S, 4) = ({t.size}, {len(segs)}, 4), got {q.shape}"
            )
        pos = np.asarray(self.position_m, dtype=float)
        joints = tuple(self.joints)
        if pos.shape != (t.size, len(joints), 3):
            raise InputError(
                f"Motion: expected position_m with shape (T, J, 3) = ({t.size}, {len(joints)}, 3), got {pos.shape}"
            )
        for name in segs:
            if name not in SEGMENTS:
                raise InputError(
                    f"Motion: expected canonical segment names {SEGMENTS}, got {name!r}"
                )
        for name in joints:
            if name not in JOINTS:
                raise InputError(f"Motion: expected canonical joint names {JOINTS}, got {name!r}")
        for seg in segs:
            if seg not in self.segment_joints:
                raise InputError(f"Motion: segment_joints has no entry for segment {seg!r}")
            prox, dist = self.segment_joints[seg]
            for j in (prox, dist):
                if j is not None and j not in joints:
                    raise InputError(
                        f"Motion: segment {seg!r} refers to joint {j!r}, not in {joints}"
                    )
            if dist is not None and seg not in self.segment_length_m:
                raise InputError(f"Motion: segment_length_m has no entry for segment {seg!r}")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "q_world_from_segment", q)
        object.__setattr__(self, "position_m", pos)
        object.__setattr__(self, "segments", segs)
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "segment_joints", dict(self.segment_joints))
        object.__setattr__(
            self, "segment_length_m", {k: float(v) for k, v in self.segment_length_m.items()}
        )
        object.__setattr__(self, "segment_source", dict(self.segment_source))
        object.__setattr__(self, "joint_source", dict(self.joint_source))

    # ---------------------------------------------------------------------------------- access
    @property
    def rate_hz(self) -> float:
        """Median sampling rate, Hz."""
        return float(1.0 / np.median(np.diff(self.t_s)))

    def __len__(self) -> int:
        return int(self.t_s.size)

    def segment_index(self, segment: str) -> int:
        """Index of ``segment`` along axis 1 of :attr:`q_world_from_segment`."""
        return name_index(self.segments, segment, "segment", "this motion")

    def joint_index(self, joint: str) -> int:
        """Index of ``joint`` along axis 1 of :attr:`position_m`."""
        return name_index(self.joints, joint, "joint", "this motion")

    def orientation(self, segment: str) -> np.ndarray:
        """``q_world_from_segment`` of one segment, shape (T, 4), ``wxyz``."""
        return self.q_world_from_segment[:, self.segment_index(segment)]

    def position(self, joint: str) -> np.ndarray:
        """Position of one joint, shape (T, 3), m, ENU."""
        return self.position_m[:, self.joint_index(joint)]

    def window(self, start_s: float, stop_s: float) -> Motion:
        """The samples with ``start_s <= t_s < stop_s`` (times kept, not shifted)."""
        keep = (self.t_s >= start_s) & (self.t_s < stop_s)
        if keep.sum() < 2:
            raise InputError(
                f"expected a window with at least 2 samples, got {int(keep.sum())} in [{start_s}, {stop_s}) "
                f"for t_s in [{self.t_s[0]}, {self.t_s[-1]}]"
            )
        return Motion(
            t_s=self.t_s[keep],
            q_world_from_segment=self.q_world_from_segment[keep],
            segments=self.segments,
            position_m=self.position_m[keep],
            joints=self.joints,
            segment_joints=self.segment_joints,
            segment_length_m=self.segment_length_m,
            segment_source=self.segment_source,
            joint_source=self.joint_source,
            metadata=dict(self.metadata),
        )

    def to_recording(self) -> Recording:
        """A :class:`~kinefuse.io.recording.Recording` holding this motion as reference.

        Returns
        -------
        Recording
            No IMU and no vision; ``reference`` = joint positions (``JointStream``, ENU, at the
            mocap rate); ``reference_orientation`` = one ``ImuStream`` per segment whose
            ``q_world_from_sensor`` holds ``q_world_from_segment``; ``metadata`` = this
            motion's metadata plus ``segment_joints``, ``segment_length_m`` and the name maps.
        """
        reference = JointStream(
            t_s=self.t_s, position_m=self.position_m, joints=self.joints, frame="ENU"
        )
        orient = {
            seg: ImuStream(
                t_s=self.t_s,
                q_world_from_sensor=self.q_world_from_segment[:, i],
                name=self.segment_source.get(seg, seg),
            )
            for i, seg in enumerate(self.segments)
        }
        meta = dict(self.metadata)
        meta.update(
            segment_joints=dict(self.segment_joints),
            segment_length_m=dict(self.segment_length_m),
            segment_source=dict(self.segment_source),
            joint_source=dict(self.joint_source),
            segment_axis="e2 (proximal -> distal)",
        )
        return Recording(reference=reference, reference_orientation=orient, metadata=meta)

    def __repr__(self) -> str:
        src = self.metadata.get("source", "")
        return (
            f"Motion(T={len(self)}, rate_hz={self.rate_hz:.4g}, segments={list(self.segments)}, "
            f"joints={len(self.joints)}, source={str(src)!r})"
        )


# ------------------------------------------------------------------------------------------
# shared construction used by the readers (private)
# ------------------------------------------------------------------------------------------
def _segment_from_bone(direction_rest: np.ndarray | None) -> np.ndarray:
    """Constant ``R_bone_from_segment`` (3, 3) for a bone with unit rest direction ``d``.

    The bone frame equals the mocap world frame in the rest pose. Columns are the segment axes
    in that frame: y = d, z = rest forward (or up if ``|d . forward| > 0.9``) made orthogonal to
    y, x = y × z. ``None`` (bone-less root) gives the identity.
    """
    if direction_rest is None:
        return np.eye(3)
    y = np.asarray(direction_rest, dtype=float)
    y = y / np.linalg.norm(y)
    ref = _REST_FORWARD if abs(float(y @ _REST_FORWARD)) <= 0.9 else _REST_UP
    z = ref - (ref @ y) * y
    z = z / np.linalg.norm(z)
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


def _continuous_quat(q: np.ndarray) -> np.ndarray:
    """Flip signs along axis 0 so consecutive quaternions have a non-negative dot product."""
    q = np.array(q, dtype=float)
    if q.shape[0] > 1:
        dots = np.einsum("...i,...i->...", q[1:], q[:-1])
        flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
        q[1:] *= flips[..., None]
    return q


def _build_motion(
    *,
    t_s: np.ndarray,
    rot_world_from_bone: Mapping[str, np.ndarray],
    point_position: Mapping[str, np.ndarray],
    bone_direction: Mapping[str, np.ndarray],
    bone_length_m: Mapping[str, float],
    segment_source: Mapping[str, str],
    joint_source: Mapping[str, str],
    metadata: dict,
) -> Motion:
    """Assemble a :class:`Motion` from mocap-frame forward-kinematics results.

    Parameters
    ----------
    t_s : ndarray, shape (T,)
    rot_world_from_bone : dict bone -> ndarray (T, 3, 3)
        Global bone rotations in mocap coordinates (identity in the rest pose).
    point_position : dict point -> ndarray (T, 3)
        Mocap point positions, m, mocap coordinates.
    bone_direction, bone_length_m : dict bone -> (3,) unit vector / float
        Rest direction (bone frame) and length of each segment bone; the readers computed
        ``distal = proximal + length * R_world_from_bone @ direction`` with the same numbers.
    segment_source, joint_source : dict
        Canonical segment -> bone; canonical joint -> point (only those present).
    """
    A = R_ENU_FROM_YUP
    joints = tuple(j for j in JOINTS if j in joint_source)
    pos = np.stack([point_position[joint_source[j]] for j in joints], axis=1) @ A.T
    segs = tuple(s for s in SEGMENTS if s in segment_source)
    quats, seg_joints, lengths = [], {}, {}
    for seg in segs:
        bone = segment_source[seg]
        prox, dist = CANONICAL_SEGMENT_JOINTS[seg]
        direction = None if dist is None else bone_direction[bone]
        R = A @ rot_world_from_bone[bone] @ _segment_from_bone(direction)
        quats.append(_continuous_quat(Rotation.from_matrix(R).as_quat(scalar_first=True)))
        seg_joints[seg] = (prox, dist)
        if dist is not None:
            lengths[seg] = float(bone_length_m[bone])
    meta = dict(metadata)
    meta.setdefault("R_enu_from_mocap", A.copy())
    return Motion(
        t_s=t_s,
        q_world_from_segment=np.stack(quats, axis=1),
        segments=segs,
        position_m=pos,
        joints=joints,
        segment_joints=seg_joints,
        segment_length_m=lengths,
        segment_source={s: segment_source[s] for s in segs},
        joint_source={j: joint_source[j] for j in joints},
        metadata=meta,
    )
