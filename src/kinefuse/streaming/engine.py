"""The online engine: asynchronous IMU and camera samples in, one fused output per frame out.

:class:`Engine` is fed one sample at a time from several streams, each with its own
timestamps (seconds, one clock for all streams, e.g. LSL ``local_clock`` after time
correction):

* per-segment IMU orientations ``q_world_from_sensor`` (``wxyz``), or raw acc/gyr(/mag) that a
  per-segment :class:`~kinefuse.orientation.OrientationEstimator` (VQF) turns into
  orientations;
* camera skeleton frames: joint positions with per-joint availability.

It emits one :class:`EngineOutput` per camera frame (without a camera: per tick of a regular
grid at ``output_rate_hz``), after the :class:`~kinefuse.streaming.processors.Processor` has
run on that frame.

Per frame at time t (all causal):

1. **Wait** until every *live* IMU stream (one whose last sample is less than
   ``stale_after_s`` old; a stream not seen yet counts as live until ``stale_after_s`` after
   the first sample of any stream) has a sample at or after t, or until ``now >= t + max_latency_s``;
   in the latter case the frame is *forced* and flagged.
2. **Orientation at t** per segment: the sample at t, else SLERP between the samples around t
   unless they are more than ``gap_factor`` nominal periods apart (a gap is never
   interpolated); else *hold* the last sample before t if it is at most ``stale_after_s`` old
   (or, before a stream's first sample, that sample if it is less than a gap after t) (flag
   ``IMU_HELD``); else the segment is *stale* (``IMU_STALE``): the joints it carries get
   no IMU measurement (NaN) and the processor predicts only for them.
3. **IMU chain**: forward kinematics (:mod:`kinefuse.kinematics`, SPEC §2.2) from the root
   joint position, taken from the camera frame (the last seen value while the camera does not
   see it; ``root_position_m`` before that).
4. **Processor** ``step(t, z_imu, z_cam, available)`` -> position, covariance, source.

With a fixed-lag smoother (processor ``lag_frames = L``) the output of frame k is produced
when frame k + L has been processed: outputs are delayed by L frames (L / camera rate
seconds), carry the time stamp of the frame they describe, and :meth:`Engine.flush` emits the
last L at the end of a run.

Faults, each counted in :attr:`Engine.counters`, recorded in :attr:`Engine.events` and logged
on the ``kinefuse.streaming`` logger:

* **stopped stream**: after ``stale_after_s`` without samples an IMU stream is no longer
  waited for and its joints go predict-only (``stream_stale``); a silent camera is replaced by
  synthesized frames on the expected grid after ``max_latency_s`` (``camera_stale``), so
  outputs continue at the camera rate;
* **restart / resume**: samples after a silence are accepted again (``resumed``); the LSL
  adapter reattaches a re-created stream of the same name/source id;
* **late / out of order**: a sample newer than the last output is inserted in time order
  (``reordered``); one at or before the last output time is dropped (``late``);
* **duplicate** timestamps are dropped (``duplicate``);
* **time jump**: a step between consecutive samples larger than ``gap_factor`` × the nominal
  period is a gap (``time_jump``): never interpolated across. Timestamps are trusted: after a
  jump of one clock its samples are aligned by their new stamps (reported, not corrected).
* **missing camera frames**: when the next camera frame is more than 0.75 periods after the
  expected time, the expected frames before it are synthesized (camera unavailable), so the
  output grid stays one output per camera period.

:func:`offline_causal` is the batch computation the engine must equal (same resampling rules,
forward kinematics by :func:`kinefuse.kinematics.forward_kinematics`, processor ``run``).
"""

from __future__ import annotations

import bisect
import copy
import logging
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from kinefuse.conventions import PAPER_B_JOINTS
from kinefuse.exceptions import InputError
from kinefuse.kinematics import Skeleton, forward_kinematics
from kinefuse.orientation.resample import slerp_resample
from kinefuse.streaming.processors import Processor

__all__ = [
    "FLAG_CAMERA_MISSING",
    "FLAG_FORCED",
    "FLAG_IMU_HELD",
    "FLAG_IMU_STALE",
    "FLAG_NO_CAMERA_JOINT",
    "IMU_FRESH",
    "IMU_HELD",
    "IMU_STALE",
    "Engine",
    "EngineConfig",
    "EngineEvent",
    "EngineOutput",
    "offline_causal",
]

log = logging.getLogger("kinefuse.streaming")

#: Per-segment / per-joint IMU status of a frame.
IMU_FRESH, IMU_HELD, IMU_STALE = 0, 1, 2

#: Bits of :attr:`EngineOutput.flags` (per joint).
FLAG_IMU_HELD = 1  #: an IMU orientation of the joint's chain was held (no sample after t yet)
FLAG_IMU_STALE = 2  #: an IMU stream of the chain is stale: no IMU measurement
FLAG_CAMERA_MISSING = 4  #: no camera frame at this time (synthesized frame)
FLAG_NO_CAMERA_JOINT = 8  #: the camera frame did not see this joint
FLAG_FORCED = 16  #: the frame was processed after ``max_latency_s`` without all live IMUs

_CHECKPOINT_VERSION = 1
#: A camera frame more than this many periods after the expected next frame time leaves a
#: hole: the expected frames before it are synthesized (camera unavailable).
_HOLE_TOL = 0.75


@dataclass(frozen=True, eq=False)
class EngineConfig:
    """Configuration of :class:`Engine` (immutable).

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
    segments: tuple[str, ...] = field(init=False)

    def __post_init__(self):
        if not isinstance(self.skeleton, Skeleton):
            raise InputError(f"expected skeleton as a Skeleton, got {type(self.skeleton).__name__}")
        joints = tuple(self.joints)
        if not joints or len(set(joints)) != len(joints):
            raise InputError(f"expected unique output joints, got {joints}")
        object.__setattr__(self, "joints", joints)
        segs = list(self.skeleton.segments)
        if self.skeleton.root_segment is not None and self.skeleton.offsets_m:
            segs.insert(0, self.skeleton.root_segment)
        object.__setattr__(self, "segments", tuple(dict.fromkeys(segs)))
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
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float))
                or not math.isfinite(v)
                or v <= 0
            ):
                raise InputError(f"expected {name} finite and > 0, got {v!r}")
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
    ``resumed``, ``time_jump``, ``late``, ``duplicate``, ``reordered``, ``forced``."""

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
        Processor source code (:data:`kinefuse.conventions.SOURCE_NAMES`, -1 predict only).
    flags : ndarray of uint8, shape (J,)
        ``FLAG_*`` bits.
    imu_status : ndarray of int8, shape (J,)
        Worst ``IMU_*`` status over the segments carrying the joint.
    """

    t_s: float
    index: int
    position_m: np.ndarray
    cov_m2: np.ndarray
    source: np.ndarray
    flags: np.ndarray
    imu_status: np.ndarray

    @property
    def std_m(self) -> np.ndarray:
        """Per-axis standard deviation, m, shape (J, 3)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov_m2, axis1=-2, axis2=-1), 0.0))


# ------------------------------------------------------------------------------ small math
class _Chain:
    """Precomputed forward kinematics of a skeleton for one frame at a time."""

    def __init__(self, config: EngineConfig):
        sk = config.skeleton
        self.segments = config.segments
        seg_index = {s: i for i, s in enumerate(self.segments)}
        self.root = sk.root
        self.offsets = [
            (j, seg_index[sk.root_segment], np.array(o)) for j, o in sk.offsets_m.items()
        ]
        self.steps = [
            (sk.proximal[i], sk.distal[i], seg_index[s], sk.lengths_m[i] * np.array(sk.axes[i]))
            for i, s in enumerate(sk.segments)
        ]
        # segments each joint depends on
        deps: dict[str, set] = {sk.root: set()}
        for j, si, _ in self.offsets:
            deps[j] = {si}
        for prox, dist, si, _ in self.steps:
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
        ops = [(sk.root, j, si, o) for j, si, o in self.offsets]
        ops += [(prox, dist, si, vec) for prox, dist, si, vec in self.steps]
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
        from kinefuse.streaming._kernels import chain_positions  # compiled: imported on use

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


class _SegmentBuffer:
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


class Engine:
    """Online, causal fusion engine (see the module docstring for the processing).

    Parameters
    ----------
    config : EngineConfig
    processor : Processor
        Per-frame processor, e.g. :class:`~kinefuse.streaming.processors.KalmanFusionProcessor`
        or :class:`~kinefuse.streaming.processors.IntegratedProcessor`.

    Notes
    -----
    ``now`` arguments are the current time on the samples' clock (LSL: ``local_clock()``).
    When omitted, the newest timestamp seen on any stream stands in for it (deterministic
    replay of recorded data). :meth:`checkpoint` returns a pickle-able dict; an engine of the
    same configuration given it with :meth:`restore` continues identically.

    Examples
    --------
    >>> from kinefuse.kinematics import full_body
    >>> from kinefuse.streaming.processors import KalmanFusionProcessor
    >>> eng = Engine(EngineConfig(full_body(height_m=1.75)), KalmanFusionProcessor(1 / 30))
    >>> eng.push_imu("chest", 0.0, [1.0, 0.0, 0.0, 0.0])
    True
    >>> eng.poll()
    []
    """

    def __init__(self, config: EngineConfig, processor: Processor):
        if not isinstance(config, EngineConfig):
            raise InputError(f"expected config as an EngineConfig, got {type(config).__name__}")
        for attr in ("step", "flush", "checkpoint", "restore", "lag_frames"):
            if not hasattr(processor, attr):
                raise InputError(
                    f"expected a Processor (step, flush, checkpoint, restore, lag_frames), got {type(processor).__name__} without .{attr}"
                )
        from kinefuse.streaming._kernels import joint_flags  # compiled: imported on first use

        self.config = config
        self.processor = processor
        self._joint_flags = joint_flags
        self._chain = _Chain(config)
        self._seg = {
            s: _SegmentBuffer(s, config.imu_period_s(s), config.gap_factor * config.imu_period_s(s))
            for s in config.segments
        }
        self._seg_list = [self._seg[s] for s in config.segments]
        if config.camera:
            cj = config.camera_joints
            self._cam_out = np.array([cj.index(j) if j in cj else -1 for j in config.joints])
            self._cam_root = cj.index(config.skeleton.root) if config.skeleton.root in cj else -1
        self.events: deque[EngineEvent] = deque(maxlen=2000)
        self.counters = dict.fromkeys(
            ("imu_samples", "camera_frames", "outputs", "frames", "forced_frames",
             "synthesized_frames", "held", "stale", "late", "duplicate", "reordered",
             "time_jump", "resumed", "stream_stale", "camera_stale"), 0)  # fmt: skip
        self._pending: list[tuple] = []  # camera frames (t, pos, avail), sorted
        self._cam_last_t = -math.inf
        self._cam_stale = False
        self._last_frame_t: float | None = None  # last processed frame time
        self._first_data_t: float | None = None
        self._data_now = -math.inf
        self._root = np.array(config.root_position_m)
        self._meta: deque = deque()  # metadata of frames waiting for lagged outputs
        self._n_out = 0
        self.accepted = {"imu": {s: [] for s in config.segments}, "camera": [], "frames": []}

    # ------------------------------------------------------------------ helpers
    def _event(self, t, kind, stream, detail, level=logging.WARNING):
        ev = EngineEvent(float(t), kind, stream, detail)
        self.events.append(ev)
        self.counters[kind] = self.counters.get(kind, 0) + 1
        log.log(level, "%s", ev)

    def _now(self, now):
        return self._data_now if now is None else float(now)

    @property
    def last_output_t(self) -> float:
        """Time of the last processed frame (-inf before the first)."""
        return -math.inf if self._last_frame_t is None else self._last_frame_t

    # ------------------------------------------------------------------ input
    def push_imu(
        self, segment: str, t_s: float, q=None, *, acc=None, gyr=None, mag=None, now=None
    ) -> bool:
        """Add one IMU sample.

        Parameters
        ----------
        segment : str
            Segment carrying the IMU (one of ``config.segments``).
        t_s : float
            Sample time, s.
        q : array_like, shape (4,), optional
            ``q_world_from_sensor`` wxyz. Without it ``acc`` (m/s²) and ``gyr`` (rad/s)
            (optionally ``mag``) are required and fed, in time order, to the segment's VQF.
        now : float, optional
            Current time (see class notes).

        Returns
        -------
        bool
            True if accepted; False if dropped (duplicate, late; counted and reported).
        """
        buf = self._seg.get(segment)
        if buf is None:
            raise InputError(f"unknown segment {segment!r}; the engine expects {list(self._seg)}")
        t = float(t_s)
        if not math.isfinite(t):
            raise InputError(f"expected a finite timestamp, got {t_s!r}")
        name = "imu:" + segment
        bt = buf.t
        if bt and t > bt[-1]:
            i = len(bt)  # in order (the usual case): newer than everything buffered
        else:
            i = bisect.bisect_left(bt, t)
            if i < len(bt) and bt[i] == t:
                self._event(
                    t,
                    "duplicate",
                    name,
                    "same timestamp as a buffered sample: dropped",
                    logging.DEBUG,
                )
                return False
        if self._last_frame_t is not None and t <= self._last_frame_t:
            self._event(
                t,
                "late",
                name,
                f"older than the last output ({self.last_output_t:.3f} s): dropped",
                logging.DEBUG,
            )
            return False
        if q is None:
            if acc is None or gyr is None:
                raise InputError(f"push_imu({segment!r}): give q (wxyz) or acc and gyr")
            if t < buf.last_t:
                self._event(
                    t,
                    "late",
                    name,
                    "raw sample out of order (VQF needs time order): dropped",
                    logging.DEBUG,
                )
                return False
            if buf.estimator is None:
                from kinefuse.orientation import OrientationEstimator

                buf.estimator = OrientationEstimator(1.0 / buf.period_s, self.config.vqf_params)
            q = buf.estimator.update(acc, gyr, mag)
        q = np.array(q, dtype=float)
        n = math.sqrt(float(q @ q)) if q.shape == (4,) else float("nan")  # = np.linalg.norm
        if not (math.isfinite(n) and abs(n - 1.0) < 1e-2):
            raise InputError(
                f"push_imu({segment!r}): expected a unit quaternion wxyz (4,), got {q}"
            )
        q /= n
        if t > buf.last_t:
            if buf.last_t > -math.inf and t - buf.last_t > buf.gap_s:
                silent = self._now(now) - buf.last_t
                if buf.stale:
                    self._event(
                        t,
                        "resumed",
                        name,
                        f"after {t - buf.last_t:.3f} s without samples",
                        logging.INFO,
                    )
                else:
                    self._event(t, "time_jump", name, f"step {t - buf.last_t:.3f} s > {buf.gap_s:.3f} s "
                                f"(expected {buf.period_s:.4f} s; silent {silent:.3f} s): gap, not interpolated")  # fmt: skip
            buf.last_t = t
            buf.t.append(t)
            buf.q.append(q)
        else:
            if buf.last_t - t > buf.gap_s:
                self._event(
                    t,
                    "time_jump",
                    name,
                    f"{buf.last_t - t:.3f} s behind the newest sample: inserted in time order",
                )
            else:
                self._event(
                    t, "reordered", name, "out of order: inserted in time order", logging.DEBUG
                )
            buf.t.insert(i, t)
            buf.q.insert(i, q)
        buf.stale = False
        buf.n += 1
        self.counters["imu_samples"] += 1
        if t > self._data_now:
            self._data_now = t
        if self._first_data_t is None:
            self._first_data_t = t
        if self.config.record:
            self.accepted["imu"][segment].append((t, q))
        return True

    def push_camera(self, t_s: float, position_m, available=None, *, now=None) -> bool:
        """Add one camera frame.

        Parameters
        ----------
        t_s : float
            Frame time, s.
        position_m : array_like, shape (Jc, 3)
            Joint positions in ``config.camera_joints`` order, m (camera frame).
        available : array_like of bool, shape (Jc,), optional
            Per-joint availability (default: finite rows).
        now : float, optional

        Returns
        -------
        bool
            True if accepted, False if dropped (duplicate or late; counted and reported).
        """
        if not self.config.camera:
            raise InputError("push_camera: the engine was configured with camera=False")
        t = float(t_s)
        pos = np.array(position_m, dtype=float)
        Jc = len(self.config.camera_joints)
        if pos.shape != (Jc, 3):
            raise InputError(
                f"expected position_m with shape ({Jc}, 3) (camera_joints), got {pos.shape}"
            )
        avail = np.all(np.isfinite(pos), axis=1)
        if available is not None:
            a = np.asarray(available)
            if a.shape != (Jc,):
                raise InputError(f"expected available with shape ({Jc},), got {a.shape}")
            avail &= a.astype(bool)
        times = [f[0] for f in self._pending]
        i = bisect.bisect_left(times, t)
        if (i < len(times) and times[i] == t) or t == self._last_frame_t:
            self._event(
                t,
                "duplicate",
                "camera",
                "same timestamp as a frame already received: dropped",
                logging.DEBUG,
            )
            return False
        if t <= self.last_output_t:
            self._event(
                t,
                "late",
                "camera",
                f"older than the last output ({self.last_output_t:.3f} s): dropped",
                logging.DEBUG,
            )
            return False
        period = 1.0 / self.config.camera_rate_hz
        gap = self.config.gap_factor * period
        if t > self._cam_last_t:
            if self._cam_last_t > -math.inf and t - self._cam_last_t > gap:
                if self._cam_stale:
                    self._event(
                        t,
                        "resumed",
                        "camera",
                        f"after {t - self._cam_last_t:.3f} s without frames",
                        logging.INFO,
                    )
                else:
                    self._event(t, "time_jump", "camera", f"step {t - self._cam_last_t:.3f} s > {gap:.3f} s "
                                f"(expected {period:.4f} s): gap, frames synthesized")  # fmt: skip
            self._cam_last_t = t
        else:
            self._event(
                t, "reordered", "camera", "out of order: inserted in time order", logging.DEBUG
            )
        self._cam_stale = False
        self._pending.insert(i, (t, pos, avail))
        self.counters["camera_frames"] += 1
        self._data_now = max(self._data_now, t)
        if self._first_data_t is None:
            self._first_data_t = t
        if self.config.record:
            self.accepted["camera"].append((t, pos, avail))
        return True

    # ------------------------------------------------------------------ scheduling
    def _next_frame(self, now: float):
        """The next frame to process: (t, pos, avail, synthesized) or None (not known yet)."""
        cfg = self.config
        period = cfg.frame_period_s
        if self._last_frame_t is None:
            if cfg.camera and self._pending:
                f = self._pending[0]
                return f[0], f[1], f[2], False
            if self._first_data_t is None:
                return None
            if cfg.camera and now < self._first_data_t + max(cfg.stale_after_s, cfg.max_latency_s):
                return None  # give the camera a chance to anchor the grid
            return self._first_data_t, None, None, cfg.camera
        t_exp = self._last_frame_t + period
        if cfg.camera and self._pending:
            f = self._pending[0]
            if f[0] <= t_exp + _HOLE_TOL * period:
                return f[0], f[1], f[2], False
        if cfg.camera and now < t_exp + cfg.max_latency_s:
            return None
        return t_exp, None, None, cfg.camera

    def _ready(self, t: float, now: float) -> tuple[bool, bool]:
        waiting = False
        for buf in self._seg_list:
            if buf.last_t >= t:
                continue
            seen = buf.last_t if buf.last_t > -math.inf else self._first_data_t
            if seen is None or now - seen > self.config.stale_after_s:
                continue  # not live (or never appeared since the data started): not waited for
            waiting = True
            break
        if not waiting:
            return True, False
        if now >= t + self.config.max_latency_s:
            return True, True
        return False, False

    def poll(self, now: float | None = None) -> list[EngineOutput]:
        """Process every frame that is ready; return the outputs produced (oldest first)."""
        now_eff = self._now(now)
        outs: list[EngineOutput] = []
        while True:
            frame = self._next_frame(now_eff)
            if frame is None:
                break
            ready, forced = self._ready(frame[0], now_eff)
            if not ready:
                break
            self._process(frame, forced, outs)
        return outs

    def flush(self, now: float | None = None) -> list[EngineOutput]:
        """End of run: process all pending camera frames (holding orientations as needed)
        and emit the outputs a fixed-lag smoother still holds back."""
        outs: list[EngineOutput] = []
        while self._pending:
            frame = self._next_frame(math.inf)  # the next real frame, or a slot of a gap before it
            forced = any(b.last_t < frame[0] for b in self._seg_list)
            self._process(frame, forced, outs)
        for res in self.processor.flush():
            outs.append(self._emit(res))
        return outs

    # ------------------------------------------------------------------ processing
    def _process(self, frame, forced: bool, outs: list) -> None:
        t, cam_pos, cam_avail, synthesized = frame
        cfg = self.config
        if not synthesized and cam_pos is not None:
            self._pending.pop(0)
        elif cfg.camera:
            self.counters["synthesized_frames"] += 1
            if not self._cam_stale and t > self._cam_last_t:  # silent, not a hole already reported
                self._cam_stale = True
                self._event(
                    t,
                    "camera_stale",
                    "camera",
                    "no camera frame: synthesizing frames (camera unavailable)",
                )
        if forced:
            self.counters["forced_frames"] += 1
        # orientations
        S = len(self._seg_list)
        Q = np.full((2, S, 4), np.nan)  # the two samples around t per segment ...
        U = np.zeros(S)  # ... and the interpolation fraction (slerp in the kernel)
        status = np.empty(S, np.int8)
        for k, buf in enumerate(self._seg_list):
            q0, q1, u, st = buf.orientation_at(t, cfg.stale_after_s)
            status[k] = st
            if st == IMU_STALE:
                if not buf.stale:
                    buf.stale = True
                    self._event(t, "stream_stale", f"imu:{buf.name}",
                                f"no sample since {buf.last_t:.3f} s: joints predict-only")  # fmt: skip
            else:
                Q[0, k] = q0
                Q[1, k] = q1
                U[k] = u
        self.counters["held"] += int(np.sum(status == IMU_HELD))
        self.counters["stale"] += int(np.sum(status == IMU_STALE))
        # camera
        J = len(cfg.joints)
        z_cam = np.full((J, 3), np.nan)
        avail = np.zeros(J, bool)
        if cam_pos is not None:
            m = self._cam_out >= 0
            idx = self._cam_out[m]
            z_cam[m] = cam_pos[idx]
            avail[m] = cam_avail[idx]
            z_cam[~avail] = np.nan
            if self._cam_root >= 0 and cam_avail[self._cam_root]:
                self._root = cam_pos[self._cam_root].copy()
        z_imu = self._chain.positions(Q, U, self._root)  # camera frame if R_world_from_camera
        # flags: worst status over each joint's segments (IMU_FRESH = 0 without any)
        jstat, flags = self._joint_flags(status, self._chain.dep_mask[:, :S], self._chain.computable,
                                   avail, cfg.camera, cam_pos is None, forced, IMU_FRESH, IMU_HELD,
                                   IMU_STALE, FLAG_IMU_HELD, FLAG_IMU_STALE, FLAG_CAMERA_MISSING,
                                   FLAG_NO_CAMERA_JOINT, FLAG_FORCED)  # fmt: skip
        self._last_frame_t = t
        for buf in self._seg_list:
            buf.prune(t)
        if cfg.record:
            self.accepted["frames"].append((t, bool(cam_pos is None and cfg.camera)))
        self.counters["frames"] += 1
        self._meta.append((t, flags, jstat))
        res = self.processor.step(t, z_imu, z_cam, avail)
        if res is not None:
            outs.append(self._emit(res))

    def _emit(self, res) -> EngineOutput:
        t, flags, jstat = self._meta.popleft()
        pos, cov, src = res
        out = EngineOutput(float(t), self._n_out, np.asarray(pos), np.asarray(cov),
                           np.asarray(src, np.int8), flags, jstat)  # fmt: skip
        self._n_out += 1
        self.counters["outputs"] += 1
        return out

    # ------------------------------------------------------------------ status / state
    def stream_status(self, now: float | None = None) -> dict:
        """Per stream: samples received, newest timestamp, age (s) and stale flag."""
        now_eff = self._now(now)
        out = {
            f"imu:{b.name}": {
                "samples": b.n,
                "last_t": b.last_t,
                "age_s": now_eff - b.last_t,
                "stale": b.stale,
            }
            for b in self._seg_list
        }
        if self.config.camera:
            out["camera"] = {"samples": self.counters["camera_frames"], "last_t": self._cam_last_t,
                             "age_s": now_eff - self._cam_last_t, "stale": self._cam_stale}  # fmt: skip
        return out

    def checkpoint(self) -> dict:
        """Pickle-able snapshot of all mutable state (buffers, pending frames, processor)."""
        segs = {}
        for b in self._seg_list:
            segs[b.name] = {
                "t": list(b.t), "q": [q.copy() for q in b.q], "last_t": b.last_t, "stale": b.stale,
                "n": b.n, "vqf": None if b.estimator is None else copy.deepcopy(b.estimator.state),
                "vqf_mag": None if b.estimator is None else b.estimator._used_mag,
            }  # fmt: skip
        return {
            "version": _CHECKPOINT_VERSION,
            "segments": segs,
            "pending": copy.deepcopy(self._pending),
            "cam_last_t": self._cam_last_t,
            "cam_stale": self._cam_stale,
            "last_frame_t": self._last_frame_t,
            "first_data_t": self._first_data_t,
            "data_now": self._data_now,
            "root": self._root.copy(),
            "meta": copy.deepcopy(list(self._meta)),
            "n_out": self._n_out,
            "counters": dict(self.counters),
            "processor": self.processor.checkpoint(),
        }

    def restore(self, checkpoint: dict) -> None:
        """Continue from a :meth:`checkpoint` (same configuration and processor type)."""
        if not isinstance(checkpoint, dict) or checkpoint.get("version") != _CHECKPOINT_VERSION:
            raise InputError("expected a checkpoint dict from Engine.checkpoint()")
        if set(checkpoint["segments"]) != set(self._seg):
            raise InputError(
                f"checkpoint segments {sorted(checkpoint['segments'])} differ from {sorted(self._seg)}"
            )
        for name, s in checkpoint["segments"].items():
            b = self._seg[name]
            b.t, b.q = list(s["t"]), [np.array(q) for q in s["q"]]
            b.last_t, b.stale, b.n = s["last_t"], s["stale"], s["n"]
            if s["vqf"] is not None:
                from kinefuse.orientation import OrientationEstimator

                b.estimator = OrientationEstimator(1.0 / b.period_s, self.config.vqf_params)
                b.estimator.state = copy.deepcopy(s["vqf"])
                b.estimator._used_mag = s["vqf_mag"]
        self._pending = copy.deepcopy(checkpoint["pending"])
        self._cam_last_t = checkpoint["cam_last_t"]
        self._cam_stale = checkpoint["cam_stale"]
        self._last_frame_t = checkpoint["last_frame_t"]
        self._first_data_t = checkpoint["first_data_t"]
        self._data_now = checkpoint["data_now"]
        self._root = np.array(checkpoint["root"])
        self._meta = deque(copy.deepcopy(checkpoint["meta"]))
        self._n_out = checkpoint["n_out"]
        self.counters = dict(checkpoint["counters"])
        self.processor.restore(checkpoint["processor"])


# ------------------------------------------------------------------------------ offline
def _offline_orientations(t_src, q_src, t_frames, gap_s, stale_after_s):
    """Batch version of the engine's orientation rule: SLERP, else hold, else NaN."""
    T = t_frames.size
    if t_src.size == 0:
        return np.full((T, 4), np.nan), np.full(T, IMU_STALE, np.int8)
    if t_src.size == 1:
        q = np.full((T, 4), np.nan)
        exact = t_frames == t_src[0]
        q[exact] = q_src[0]
    else:
        q = slerp_resample(t_src, q_src, t_frames, max_gap_s=gap_s)
    status = np.where(np.all(np.isfinite(q), axis=1), IMU_FRESH, IMU_STALE).astype(np.int8)
    i = np.searchsorted(t_src, t_frames, side="right") - 1
    hold = (status == IMU_STALE) & (i >= 0)
    hold &= t_frames - t_src[np.clip(i, 0, None)] <= stale_after_s
    q[hold] = q_src[i[hold]]
    status[hold] = IMU_HELD
    first = (status == IMU_STALE) & (i < 0) & (t_src[0] - t_frames <= gap_s)
    q[first] = q_src[0]
    status[first] = IMU_HELD
    return q, status


def offline_causal(
    config: EngineConfig,
    processor: Processor,
    imu: Mapping[str, tuple],
    camera: tuple | None,
    frame_times: Sequence[float] | None = None,
) -> dict:
    """The engine's computation done offline (causal, batch) on recorded samples.

    Parameters
    ----------
    config : EngineConfig
    processor : Processor
        A processor of the same configuration as the engine's; its :meth:`run` is used (its
        online state is not touched).
    imu : mapping of str -> (t (N,), q (N, 4))
        Accepted orientation samples per segment (any order; sorted here).
    camera : (t (M,), position (M, Jc, 3), available (M, Jc)) or None
        Accepted camera frames.
    frame_times : sequence of float, optional
        Frame times. Default: the camera frames plus the frames the engine synthesizes in
        camera holes (``t_prev + period`` while the next frame is more than 0.75 periods
        beyond); required without a camera.

    Returns
    -------
    dict
        ``t_s (T,)``, ``position_m (T, J, 3)``, ``cov_m2 (T, J, 3, 3)``, ``source (T, J)``,
        ``imu_status (T, J)``, ``synthesized (T,)``, ``z_imu``, ``z_cam``, ``available``.

    Notes
    -----
    Orientation at frame time: :func:`kinefuse.orientation.slerp_resample` with
    ``max_gap_s = gap_factor × period``, else hold of the last sample at most
    ``stale_after_s`` old, else NaN; positions by :func:`kinefuse.kinematics.forward_kinematics`
    with the root from the camera (forward-filled). Equals the engine's outputs whenever the
    engine never forced a frame (every live IMU sample at or after a frame time had arrived
    when it was processed) and was given ``frame_times`` equal to its frames.
    """
    cfg = config
    period = cfg.frame_period_s
    if camera is not None:
        ct, cpos, cav = (np.asarray(a) for a in camera)
        order = np.argsort(ct, kind="stable")
        ct, cpos, cav = ct[order].astype(float), cpos[order].astype(float), cav[order].astype(bool)
        cav = cav & np.all(np.isfinite(cpos), axis=-1)
    else:
        ct = np.zeros(0)
    if frame_times is None:
        if camera is None:
            raise InputError("offline_causal: frame_times is required without a camera")
        ft = []
        tol = _HOLE_TOL * period
        for k, tc in enumerate(ct):
            if k:
                t_exp = ft[-1] + period
                while tc > t_exp + tol:
                    ft.append(t_exp)
                    t_exp += period
            ft.append(float(tc))
        t = np.asarray(ft)
    else:
        t = np.asarray(frame_times, dtype=float)
    T, J = t.size, len(cfg.joints)
    # camera per frame
    z_cam = np.full((T, J, 3), np.nan)
    avail = np.zeros((T, J), bool)
    synthesized = np.ones(T, bool) if cfg.camera else np.zeros(T, bool)
    root = np.empty((T, 3))
    last_root = np.array(cfg.root_position_m)
    ci = {float(v): k for k, v in enumerate(ct)}
    cj = cfg.camera_joints or ()
    rj = cj.index(cfg.skeleton.root) if cfg.skeleton.root in cj else -1
    for k, tk in enumerate(t):
        c = ci.get(float(tk))
        if c is not None:
            synthesized[k] = False
            for j, name in enumerate(cfg.joints):
                if name in cj:
                    m = cj.index(name)
                    avail[k, j] = cav[c, m]
                    if cav[c, m]:
                        z_cam[k, j] = cpos[c, m]
            if rj >= 0 and cav[c, rj]:
                last_root = cpos[c, rj]
        root[k] = last_root
    # orientations per segment
    ori, stat = {}, {}
    Rc = cfg.R_world_from_camera
    for s in cfg.segments:
        ts, qs = imu.get(s, (np.zeros(0), np.zeros((0, 4))))
        ts, qs = np.asarray(ts, float), np.asarray(qs, float).reshape(-1, 4)
        o = np.argsort(ts, kind="stable")
        q, st = _offline_orientations(
            ts[o], qs[o], t, cfg.gap_factor * cfg.imu_period_s(s), cfg.stale_after_s
        )
        from kinefuse.kinematics import as_rotation_matrices

        Rm = as_rotation_matrices(q, f"orientation {s}")
        ori[s] = Rm if Rc is None else np.einsum("ji,kjl->kil", Rc, Rm)
        stat[s] = st
    pos = forward_kinematics(cfg.skeleton, ori, root)
    z_imu = np.stack([pos.get(j, np.full((T, 3), np.nan)) for j in cfg.joints], axis=1)
    chain = _Chain(cfg)
    S = np.stack([stat[s] for s in cfg.segments], axis=1)  # (T, S)
    jstat = np.zeros((T, J), np.int8)
    for j, d in enumerate(chain.out_deps):
        if d:
            jstat[:, j] = S[:, d].max(axis=1)
    jstat[:, ~chain.computable] = IMU_STALE
    position, cov, source = processor.run(t, z_imu, z_cam, avail)
    return {
        "t_s": t, "position_m": position, "cov_m2": cov, "source": source, "imu_status": jstat,
        "synthesized": synthesized, "z_imu": z_imu, "z_cam": z_cam, "available": avail,
    }  # fmt: skip
