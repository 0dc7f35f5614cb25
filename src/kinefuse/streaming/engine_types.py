"""Configuration, status codes and output types of the online engine (:mod:`.engine`).

* :class:`EngineConfig`: skeleton, joints, rates, latency and staleness limits (immutable);
* ``IMU_*``: per-segment / per-joint IMU status of a frame; ``FLAG_*``: bits of
  :attr:`EngineOutput.flags`;
* :class:`EngineEvent` (a fault the engine noticed) and :class:`EngineOutput` (one fused frame).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from kinefuse._validation import positive_finite
from kinefuse.conventions import PAPER_B_JOINTS
from kinefuse.exceptions import InputError
from kinefuse.kinematics import Skeleton
from kinefuse.kinematics.angles import JOINTS as ANGLE_JOINTS

__all__ = [
    "FLAG_CAMERA_MISSING",
    "FLAG_FORCED",
    "FLAG_IMU_HELD",
    "FLAG_IMU_STALE",
    "FLAG_NO_CAMERA_JOINT",
    "IMU_FRESH",
    "IMU_HELD",
    "IMU_STALE",
    "EngineConfig",
    "EngineEvent",
    "EngineOutput",
    "SummaryMapping",
]

#: Per-segment / per-joint IMU status of a frame.
IMU_FRESH, IMU_HELD, IMU_STALE = 0, 1, 2

#: Bits of :attr:`EngineOutput.flags` (per joint).
FLAG_IMU_HELD = 1  #: an IMU orientation of the joint's chain was held (no sample after t yet)
FLAG_IMU_STALE = 2  #: an IMU stream of the chain is stale: no IMU measurement
FLAG_CAMERA_MISSING = 4  #: no camera frame at this time (synthesized frame)
FLAG_NO_CAMERA_JOINT = 8  #: the camera frame did not see this joint
FLAG_FORCED = 16  #: the frame was processed after ``max_latency_s`` without all live IMUs


@dataclass(frozen=True, eq=False)
class EngineConfig:
    """Configuration of :class:`~kinefuse.streaming.engine.Engine` (immutable).

    Attributes
    ----------
    skeleton : Skeleton
        Kinematic chain (lengths, axes in the sensor frames, offsets); e.g.
        :func:`kinefuse.kinematics.full_body` with calibrated axes.
    joints : tuple of str
        Output joints, in output order (default the eight of paper B).
    camera_joints : tuple of str or None
        Joint order of the camera frames given to :meth:`Engine.push_camera` (default
        ``joints`` plus the skeleton root if missing). None with ``camera=False``.
    camera : bool
        Whether a camera stream is expected (outputs per camera frame) or not (outputs on a
        regular grid at ``output_rate_hz`` anchored on the first IMU sample).
    camera_rate_hz : float
        Nominal camera rate, Hz (sets the expected frame period).
    output_rate_hz : float
        Output rate without a camera, Hz.
    imu_rate_hz : float or mapping of str -> float
        Nominal IMU rate(s), Hz (gap detection; VQF rate for raw samples).
    max_latency_s : float
        Longest wait for live IMU streams (or a camera frame) past a frame time, s.
    stale_after_s : float
        Silence after which an IMU stream is stale and a held orientation no longer used, s.
    gap_factor : float
        Consecutive samples more than ``gap_factor`` nominal periods apart form a gap.
    root_position_m : tuple of 3 floats
        Root joint position before the camera first sees it, m.
    R_world_from_camera : ndarray, shape (3, 3), or None
        Rotation from the camera frame to the IMU world frame (a
        :class:`~kinefuse.kinematics.Calibration`'s); outputs are in the camera frame.
    vqf_params : mapping or None
        VQF parameters for raw IMU samples.
    record : bool
        Keep every accepted sample in :attr:`Engine.accepted` (tests, benchmarks).
    segment_frames : mapping of str -> ndarray, shape (3, 3), or None
        ``R_sensor_from_segment`` (ISB segment frames) of calibrated segments, e.g. a
        ``chain.json``'s; the frames then carry the joint angles of :attr:`angle_joints`. A
        segment outside the skeleton (a foot calibrated for the ankle angles only) is an
        engine segment too: its IMU stream is read for the angles.
    angle_joints : tuple of str
        Derived: the joints of :data:`kinefuse.kinematics.angles.JOINTS` whose two segments
        are engine segments with a frame, in that table's order.
    offset_segments : mapping of str -> str, optional
        The IMU segment whose orientation carries each offset joint of the skeleton (default
        its ``root_segment``), e.g. the shoulders on the chest when the hips hang from the
        pelvis (``chain.json``'s ``offset_segments``).
    heading_pose_s : float or None
        Sensors of arbitrary headings (6-D): find each one's heading from a still pose of this
        length at the start (:mod:`kinefuse.streaming.heading`); every engine segment needs a
        frame in ``segment_frames``. None (default): the streams share one world frame.
    heading_reference : str, optional
        With ``heading_pose_s``: the segment whose sensor's heading the outputs keep (default
        the first engine segment; ``chain.json`` names the one its calibration kept).
    heading_pose_yaw_deg : mapping of str -> float, optional
        With ``heading_pose_s``: each segment frame's heading relative to the reference's in
        the calibration pose (default 0: the frames share one heading there).
    """

    skeleton: Skeleton
    joints: tuple[str, ...] = PAPER_B_JOINTS
    camera_joints: tuple[str, ...] | None = None
    camera: bool = True
    camera_rate_hz: float = 30.0
    output_rate_hz: float = 30.0
    imu_rate_hz: float | Mapping[str, float] = 100.0
    max_latency_s: float = 0.1
    stale_after_s: float = 0.25
    gap_factor: float = 2.5
    root_position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    R_world_from_camera: np.ndarray | None = None
    vqf_params: Mapping | None = None
    record: bool = False
    segment_frames: Mapping[str, np.ndarray] | None = None
    offset_segments: Mapping[str, str] | None = None
    heading_pose_s: float | None = None
    heading_reference: str | None = None
    heading_pose_yaw_deg: Mapping[str, float] | None = None
    segments: tuple[str, ...] = field(init=False)
    angle_joints: tuple[str, ...] = field(init=False)

    def __post_init__(self):
        if not isinstance(self.skeleton, Skeleton):
            raise InputError(f"expected skeleton as a Skeleton, got {type(self.skeleton).__name__}")
        joints = tuple(self.joints)
        if not joints or len(set(joints)) != len(joints):
            raise InputError(f"expected unique output joints, got {joints}")
        object.__setattr__(self, "joints", joints)
        segs = list(self.skeleton.segments)
        carriers = dict(self.offset_segments or {})
        unknown = sorted(set(carriers) - set(self.skeleton.offsets_m))
        if unknown:
            raise InputError(f"offset_segments: {unknown} are not offset joints of the skeleton")
        object.__setattr__(self, "offset_segments", carriers)
        if self.skeleton.root_segment is not None and self.skeleton.offsets_m:
            segs.insert(0, self.skeleton.root_segment)
        segs[:0] = [s for s in dict.fromkeys(carriers.values()) if s not in segs]
        frames = {}
        for s, F in (self.segment_frames or {}).items():
            R = np.array(F, dtype=float)
            if (R.shape != (3, 3) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
                    or np.linalg.det(R) < 0):  # fmt: skip
                raise InputError(f"segment_frames[{s!r}]: expected a (3, 3) rotation matrix")
            R.setflags(write=False)
            frames[s] = R
        object.__setattr__(self, "segment_frames", frames)
        object.__setattr__(self, "segments", tuple(dict.fromkeys([*segs, *frames])))
        have = set(frames)
        if self.heading_pose_s is not None:
            positive_finite(self.heading_pose_s, "heading_pose_s")
            lack = [s for s in self.segments if s not in have]
            if lack:
                raise InputError(
                    f"heading_pose_s: the headings come from the segment frames in the pose; "
                    f"no frame for {lack}"
                )
            if self.heading_reference not in (None, *self.segments):
                raise InputError(
                    f"heading_reference {self.heading_reference!r}: not an engine segment "
                    f"{list(self.segments)}"
                )
        angle_joints = tuple(j for j, (p, d, _) in ANGLE_JOINTS.items() if {p, d} <= have)
        object.__setattr__(self, "angle_joints", angle_joints)
        if self.camera:
            cj = self.camera_joints
            if cj is None:
                cj = joints + ((self.skeleton.root,) if self.skeleton.root not in joints else ())
            cj = tuple(cj)
            if len(set(cj)) != len(cj):
                raise InputError(f"expected unique camera_joints, got {cj}")
            object.__setattr__(self, "camera_joints", cj)
        else:
            object.__setattr__(self, "camera_joints", None)
        for name in ("camera_rate_hz", "output_rate_hz", "max_latency_s", "stale_after_s"):
            positive_finite(getattr(self, name), name)
        if not (isinstance(self.gap_factor, (int, float)) and self.gap_factor > 1):
            raise InputError(f"expected gap_factor > 1, got {self.gap_factor!r}")
        rates = self.imu_rate_hz
        if isinstance(rates, Mapping):
            missing = [s for s in self.segments if s not in rates]
            if missing:
                raise InputError(f"imu_rate_hz: no rate for segment(s) {missing}")
        elif not (isinstance(rates, (int, float)) and rates > 0):
            raise InputError(f"expected imu_rate_hz > 0 or a mapping segment -> Hz, got {rates!r}")
        root = np.asarray(self.root_position_m, dtype=float)
        if root.shape != (3,) or not np.all(np.isfinite(root)):
            raise InputError(
                f"expected root_position_m as 3 finite numbers, got {self.root_position_m!r}"
            )
        object.__setattr__(self, "root_position_m", tuple(float(v) for v in root))
        if self.R_world_from_camera is not None:
            R = np.asarray(self.R_world_from_camera, dtype=float)
            if R.shape != (3, 3) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6:
                raise InputError("expected R_world_from_camera as a (3, 3) rotation matrix")
            R.setflags(write=False)
            object.__setattr__(self, "R_world_from_camera", R)

    def imu_period_s(self, segment: str) -> float:
        """Nominal sample period of ``segment``'s IMU stream, s."""
        r = self.imu_rate_hz
        return 1.0 / float(r[segment] if isinstance(r, Mapping) else r)

    @property
    def frame_period_s(self) -> float:
        """Nominal output period, s."""
        return 1.0 / (self.camera_rate_hz if self.camera else self.output_rate_hz)


@dataclass(frozen=True)
class EngineEvent:
    """Something the engine noticed. ``kind`` in ``stream_stale``, ``camera_stale``,
    ``resumed``, ``time_jump``, ``late``, ``duplicate``, ``reordered``, ``forced``, ``heading``
    (6-D sensors: their headings found from the pose, or never found)."""

    t_s: float
    kind: str
    stream: str
    detail: str

    def __str__(self) -> str:
        return f"[{self.t_s:.3f} s] {self.kind} {self.stream}: {self.detail}"


@dataclass(frozen=True, eq=False)
class EngineOutput:
    """One fused frame.

    Attributes
    ----------
    t_s : float
        Time of the frame described (camera frame time), s.
    index : int
        Output index (0, 1, 2, ...).
    position_m : ndarray, shape (J, 3)
    cov_m2 : ndarray, shape (J, 3, 3)
        Position covariance.
    source : ndarray of int8, shape (J,)
        Processor source code (:data:`kinefuse.conventions.SOURCE_NAMES`, "predicted" when no
        input measured the joint; -1 no estimate).
    flags : ndarray of uint8, shape (J,)
        ``FLAG_*`` bits.
    imu_status : ndarray of int8, shape (J,)
        Worst ``IMU_*`` status over the segments carrying the joint.
    angles_deg : ndarray, shape (A, 3), or None
        ``[flexion, adduction, internal_rotation]`` of :attr:`EngineConfig.angle_joints`, deg
        (ISB, :func:`kinefuse.kinematics.joint_angles`); None without segment frames.
    """

    t_s: float
    index: int
    position_m: np.ndarray
    cov_m2: np.ndarray
    source: np.ndarray
    flags: np.ndarray
    imu_status: np.ndarray
    angles_deg: np.ndarray | None = None

    @property
    def std_m(self) -> np.ndarray:
        """Per-axis standard deviation, m, shape (J, 3)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov_m2, axis1=-2, axis2=-1), 0.0))


class SummaryMapping(Mapping):
    """Base of the streaming run summaries (dataclasses): also a read-only mapping of the
    fields, in order, without the optional ones that are None (:meth:`to_dict`), so that
    ``summary["outputs"]`` and ``summary.outputs`` both work and the CLI's JSON is the dict."""

    #: Fields left out of :meth:`to_dict` while None.
    _optional: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """The summary as a plain dict."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for k in self._optional:
            if d[k] is None:
                del d[k]
        return d

    def __getitem__(self, key):
        return self.to_dict()[key]

    def __iter__(self):
        return iter(self.to_dict())

    def __len__(self) -> int:
        return len(self.to_dict())
