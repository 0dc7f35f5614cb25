"""Time alignment of the online engine: per-segment sample buffers and the per-frame inputs.

One implementation for both forms of the engine's computation: :class:`~.engine.Engine` fills
the :class:`SegmentBuffer` s sample by sample as they arrive, :func:`~.offline.offline_causal`
fills them with a whole recording; both then call :meth:`FrameAssembler.assemble` once per
frame, which turns the buffered orientations and a camera frame into the processor's inputs
(IMU-chain and camera joint positions, availability, per-joint status and flags).

* orientation at t (:meth:`SegmentBuffer.orientation_at`): the sample at t, else SLERP between
  the samples around t unless they are a gap apart, else the last sample before t held while
  at most ``stale_after_s`` old (or the first sample when the stream starts less than a gap
  after t), else stale;
* IMU chain: forward kinematics from the root joint position (:class:`Chain`, compiled);
* joint angles (with ``segment_frames``): each segment's ``R_world_from_sensor(t)
  R_sensor_from_segment``, the orientation at t interpolated with the SLERP of
  :func:`kinefuse.orientation.resample.slerp_pairs` (the offline resampling's arithmetic), then
  :func:`kinefuse.kinematics.joint_angles`;
* camera frame slots (:func:`camera_frame_due`): the next camera frame is the next output frame
  unless it lies more than ``HOLE_TOL`` periods after the expected time.
"""

from __future__ import annotations

import bisect
import math
from typing import NamedTuple

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.kinematics.angles import JOINTS as ANGLE_JOINTS
from kinefuse.kinematics.angles import joint_angles
from kinefuse.kinematics.forward import as_rotation_matrices
from kinefuse.orientation.resample import slerp_pairs
from kinefuse.streaming._kernels import chain_positions, joint_flags
from kinefuse.streaming.engine_types import (
    FLAG_CAMERA_MISSING,
    FLAG_FORCED,
    FLAG_IMU_HELD,
    FLAG_IMU_STALE,
    FLAG_NO_CAMERA_JOINT,
    IMU_FRESH,
    IMU_HELD,
    IMU_STALE,
    EngineConfig,
)

__all__ = [
    "HOLE_TOL",
    "Chain",
    "FrameAssembler",
    "FrameInputs",
    "SegmentBuffer",
    "camera_frame_due",
    "unit_quaternion",
]

#: A camera frame more than this many periods after the expected next frame time leaves a
#: hole: the expected frames before it are synthesized (camera unavailable).
HOLE_TOL = 0.75


def camera_frame_due(t_camera: float, t_expected: float, period_s: float) -> bool:
    """Whether the camera frame at ``t_camera`` is the frame expected at ``t_expected`` (else the
    expected frames before it form a hole and are synthesized)."""
    return t_camera <= t_expected + HOLE_TOL * period_s


def unit_quaternion(q, where: str) -> np.ndarray:
    """``q`` (4,) wxyz normalised; InputError (naming ``where``) unless its norm is within 1 %
    of one."""
    q = np.array(q, dtype=float)
    n = math.sqrt(float(q @ q)) if q.shape == (4,) else float("nan")  # = np.linalg.norm
    if not (math.isfinite(n) and abs(n - 1.0) < 1e-2):
        raise InputError(f"{where}: expected a unit quaternion wxyz (4,), got {q}")
    q /= n
    return q


class Chain:
    """Precomputed forward kinematics of a skeleton for one frame at a time."""

    def __init__(self, config: EngineConfig):
        sk = config.skeleton
        self.segments = config.segments
        seg_index = {s: i for i, s in enumerate(self.segments)}
        self.root = sk.root
        carrier = config.offset_segments  # the segment each offset joint hangs from
        offsets = [(j, seg_index[carrier.get(j, sk.root_segment)], np.array(o))
                   for j, o in sk.offsets_m.items()]  # fmt: skip
        steps = [
            (sk.proximal[i], sk.distal[i], seg_index[s], sk.lengths_m[i] * np.array(sk.axes[i]))
            for i, s in enumerate(sk.segments)
        ]
        # segments each joint depends on
        deps: dict[str, set] = {sk.root: set()}
        for j, si, _ in offsets:
            deps[j] = {si}
        for prox, dist, si, _ in steps:
            deps[dist] = deps.get(prox, set()) | {si}
        self.deps = deps
        self.out_joints = config.joints
        self.out_deps = [sorted(deps.get(j, set())) for j in config.joints]
        # (J, S) mask of the segments each output joint depends on (vectorised worst status)
        self.dep_mask = np.zeros((len(config.joints), max(len(self.segments), 1)), bool)
        for j, d in enumerate(self.out_deps):
            self.dep_mask[j, d] = True
        self.computable = np.array([j in deps for j in config.joints])
        # the chain as arrays for the compiled kernel: node 0 = root, then every joint placed
        node = {sk.root: 0}
        dst, src, segs, vecs = [], [], [], []
        ops = [(sk.root, j, si, o) for j, si, o in offsets] + steps
        for a, b, si, v in ops:
            node.setdefault(b, len(node))
            dst.append(node[b])
            src.append(node[a])
            segs.append(si)
            vecs.append(np.asarray(v, dtype=float))
        self._dst = np.array(dst, np.int64)
        self._src = np.array(src, np.int64)
        self._seg = np.array(segs, np.int64)
        self._vec = np.array(vecs, dtype=float).reshape(-1, 3)
        self._out_node = np.array([node.get(j, -1) for j in config.joints], np.int64)
        self._kernel = chain_positions
        Rc = config.R_world_from_camera
        self._use_cam = Rc is not None
        self._Rc = np.eye(3) if Rc is None else np.ascontiguousarray(Rc, dtype=float)

    def positions(self, Q: np.ndarray, U: np.ndarray, root: np.ndarray) -> np.ndarray:
        """Joint positions (J_out, 3), m, from per-segment orientations ``slerp(Q[0], Q[1],
        U)`` (``Q`` (2, S, 4) unit wxyz, ``U`` (S,); NaN rows for stale segments -> NaN for
        the joints that depend on them)."""
        return self._kernel(Q, U, self._Rc, self._use_cam, np.asarray(root, dtype=float),
                            self._dst, self._src, self._seg, self._vec, self._out_node)  # fmt: skip


class SegmentBuffer:
    """Time-ordered recent orientation samples of one IMU stream."""

    def __init__(self, name: str, period_s: float, gap_s: float):
        self.name = name
        self.period_s = period_s
        self.gap_s = gap_s
        self.t: list[float] = []
        self.q: list[np.ndarray] = []
        self.last_t = -math.inf  # newest timestamp ever accepted
        self.stale = False
        self.n = 0
        self.estimator = None

    def fill(self, t_s: np.ndarray, q: np.ndarray) -> SegmentBuffer:
        """A whole recording at once (offline): samples sorted by time, a repeated timestamp
        dropped (the first received kept, as the engine drops duplicates), each ``q``
        normalised as :meth:`~.engine.Engine.push_imu` does; a row with a non-finite
        timestamp or quaternion is a sample not received."""
        t_s = np.asarray(t_s, dtype=float)
        q = np.asarray(q, dtype=float).reshape(-1, 4)
        ok = np.isfinite(t_s) & np.all(np.isfinite(q), axis=1)
        t_s, q = t_s[ok], q[ok]
        order = np.argsort(t_s, kind="stable")
        ts, first = np.unique(t_s[order], return_index=True)
        self.t = ts.tolist()
        self.q = [unit_quaternion(q[i], f"orientation {self.name}") for i in order[first]]
        self.last_t = self.t[-1] if self.t else -math.inf
        self.n = len(self.t)
        return self

    def orientation_at(self, t: float, stale_after_s: float):
        """``(q0, q1, u, status)``: the orientation at ``t`` is ``slerp(q0, q1, u)`` (q1 is
        q0 and u = 0 when no interpolation is needed; q0 None when stale)."""
        ts = self.t
        i = bisect.bisect_right(ts, t)
        if i > 0 and ts[i - 1] == t:
            return self.q[i - 1], self.q[i - 1], 0.0, IMU_FRESH
        if 0 < i < len(ts):
            a, b = ts[i - 1], ts[i]
            if b - a <= self.gap_s + 1e-12:
                return self.q[i - 1], self.q[i], (t - a) / (b - a), IMU_FRESH
        if i > 0 and t - ts[i - 1] <= stale_after_s:
            return self.q[i - 1], self.q[i - 1], 0.0, IMU_HELD
        if i == 0 and ts and ts[0] - t <= self.gap_s:
            q = self.q[0]  # stream starts just after t (clock offsets of inlets)
            return q, q, 0.0, IMU_HELD
        return None, None, 0.0, IMU_STALE

    def prune(self, t_done: float):
        """Drop samples no future frame (t > t_done) can need."""
        i = bisect.bisect_right(self.t, t_done) - 1
        if i > 0:
            del self.t[:i]
            del self.q[:i]


class FrameInputs(NamedTuple):
    """The processor's inputs of one frame and its per-joint diagnostics.

    ``z_imu, z_cam (J, 3)`` m (NaN = no measurement), ``available (J,)``, ``segment_status
    (S,)`` and ``imu_status (J,)`` ``IMU_*`` codes, ``flags (J,)`` ``FLAG_*`` bits, ``root (3,)``
    the chain root used (the camera's when it saw the root, else the one carried in).
    """

    z_imu: np.ndarray
    z_cam: np.ndarray
    available: np.ndarray
    segment_status: np.ndarray
    imu_status: np.ndarray
    flags: np.ndarray
    root: np.ndarray
    angles_deg: np.ndarray | None = None
    """``(A, 3)`` joint angles of ``config.angle_joints``, deg (NaN where a segment is stale)."""


class FrameAssembler:
    """Per frame: orientations from the buffers, camera joints, IMU chain, status and flags."""

    def __init__(self, config: EngineConfig):
        self.config = config
        self.chain = Chain(config)
        self._joint_flags = joint_flags
        if config.camera:
            cj = config.camera_joints
            cam_out = np.array([cj.index(j) if j in cj else -1 for j in config.joints])
            self._cam_seen = cam_out >= 0  # engine joints the camera tracks ...
            self._cam_idx = cam_out[self._cam_seen]  # ... and their camera indices
            self._cam_root = cj.index(config.skeleton.root) if config.skeleton.root in cj else -1
        used = {s for j in config.angle_joints for s in ANGLE_JOINTS[j][:2]}
        self._angle_segs = tuple(s for s in config.segments if s in used)
        self._angle_idx = np.array([config.segments.index(s) for s in self._angle_segs], int)
        self._angle_F = (
            np.stack([config.segment_frames[s] for s in self._angle_segs]) if used else None
        )

    def joint_angles(self, Q: np.ndarray, U: np.ndarray) -> np.ndarray:
        """``(A, 3)`` angles of ``config.angle_joints``, deg, from the orientations at t
        (``Q (2, S, 4)`` the samples around t, ``U (S,)`` the fractions, as in :meth:`assemble`)."""
        k = self._angle_idx
        R = as_rotation_matrices(slerp_pairs(Q[0, k], Q[1, k], U[k])) @ self._angle_F
        a = joint_angles({s: R[i][None] for i, s in enumerate(self._angle_segs)},
                         self.config.angle_joints)  # fmt: skip
        return np.stack([a[j][0] for j in self.config.angle_joints])

    def assemble(self, t, cam_pos, cam_avail, buffers, root, forced: bool) -> FrameInputs:
        """The inputs of the frame at ``t`` from ``buffers`` (one :class:`SegmentBuffer` per
        engine segment, in ``config.segments`` order) and the camera frame ``cam_pos (Jc, 3)``,
        ``cam_avail (Jc,)`` (None: no camera frame at t); ``root (3,)``: the chain root so far."""
        cfg = self.config
        S = len(buffers)
        Q = np.full((2, S, 4), np.nan)  # the two samples around t per segment ...
        U = np.zeros(S)  # ... and the interpolation fraction (slerp in the kernel)
        status = np.empty(S, np.int8)
        for k, buf in enumerate(buffers):
            q0, q1, u, st = buf.orientation_at(t, cfg.stale_after_s)
            status[k] = st
            if st != IMU_STALE:
                Q[0, k] = q0
                Q[1, k] = q1
                U[k] = u
        J = len(cfg.joints)
        z_cam = np.full((J, 3), np.nan)
        avail = np.zeros(J, bool)
        if cam_pos is not None:
            m, idx = self._cam_seen, self._cam_idx
            z_cam[m] = cam_pos[idx]
            avail[m] = cam_avail[idx]
            z_cam[~avail] = np.nan
            if self._cam_root >= 0 and cam_avail[self._cam_root]:
                root = cam_pos[self._cam_root].copy()
        z_imu = self.chain.positions(Q, U, root)  # camera frame if R_world_from_camera
        # flags: worst status over each joint's segments (IMU_FRESH = 0 without any)
        jstat, flags = self._joint_flags(status, self.chain.dep_mask[:, :S], self.chain.computable,
                                   avail, cfg.camera, cam_pos is None, forced, IMU_FRESH, IMU_HELD,
                                   IMU_STALE, FLAG_IMU_HELD, FLAG_IMU_STALE, FLAG_CAMERA_MISSING,
                                   FLAG_NO_CAMERA_JOINT, FLAG_FORCED)  # fmt: skip
        angles = self.joint_angles(Q, U) if self._angle_segs else None
        return FrameInputs(z_imu, z_cam, avail, status, jstat, flags, root, angles)
