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

:func:`kinefuse.streaming.offline.offline_causal` is the same computation on a recording: it
fills the same :class:`~.alignment.SegmentBuffer` s and calls the same
:class:`~.alignment.FrameAssembler` per frame (:mod:`.alignment`), then the processor's ``run``.
"""

from __future__ import annotations

import bisect
import copy
import logging
import math
from collections import deque

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.orientation import OrientationEstimator
from kinefuse.streaming.alignment import (
    FrameAssembler,
    SegmentBuffer,
    camera_frame_due,
    unit_quaternion,
)
from kinefuse.streaming.engine_types import (
    IMU_HELD,
    IMU_STALE,
    EngineConfig,
    EngineEvent,
    EngineOutput,
)
from kinefuse.streaming.heading import PoseHeading
from kinefuse.streaming.processors import Processor

# the configuration and output types are part of the engine's interface: re-exported (their
# module, with the FLAG_* and IMU_* codes, is kinefuse.streaming.engine_types)
__all__ = ["Engine", "EngineConfig", "EngineEvent", "EngineOutput"]

log = logging.getLogger("kinefuse.streaming")

_CHECKPOINT_VERSION = 1


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
        self.config = config
        self.processor = processor
        self._frames = FrameAssembler(config)
        self._seg = {
            s: SegmentBuffer(s, config.imu_period_s(s), config.gap_factor * config.imu_period_s(s))
            for s in config.segments
        }
        self._seg_list = [self._seg[s] for s in config.segments]
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
        self.heading = (
            None
            if config.heading_pose_s is None
            else PoseHeading(
                config.segment_frames,
                config.heading_pose_s,
                config.segments,
                config.heading_reference,
                config.heading_pose_yaw_deg,
            )  # fmt: skip
        )

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
        i = self._imu_slot(buf, t)
        if i is None:
            return False
        if q is None:
            if acc is None or gyr is None:
                raise InputError(f"push_imu({segment!r}): give q (wxyz) or acc and gyr")
            if t < buf.last_t:
                self._event(t, "late", "imu:" + segment,
                            "raw sample out of order (VQF needs time order): dropped", logging.DEBUG)  # fmt: skip
                return False
            if buf.estimator is None:
                buf.estimator = OrientationEstimator(1.0 / buf.period_s, self.config.vqf_params)
            q = buf.estimator.update(acc, gyr, mag)
        q = unit_quaternion(q, f"push_imu({segment!r})")
        if self.config.record:  # as received: offline_causal turns them itself
            self.accepted["imu"][segment].append((t, q))
        if self.heading is not None and self.heading.aligned:
            q = self.heading.turn(segment, q)
        self._insert_imu(buf, i, t, q, now)
        self._data_arrived(t)
        return True

    def _imu_slot(self, buf: SegmentBuffer, t: float) -> int | None:
        """Where a sample at ``t`` goes in ``buf``; None (reported) for a duplicate or late one."""
        name = "imu:" + buf.name
        bt = buf.t
        if bt and t > bt[-1]:
            i = len(bt)  # in order (the usual case): newer than everything buffered
        else:
            i = bisect.bisect_left(bt, t)
            if i < len(bt) and bt[i] == t:
                self._event(t, "duplicate", name, "same timestamp as a buffered sample: dropped",
                            logging.DEBUG)  # fmt: skip
                return None
        if self._last_frame_t is not None and t <= self._last_frame_t:
            self._event(t, "late", name,
                        f"older than the last output ({self.last_output_t:.3f} s): dropped",
                        logging.DEBUG)  # fmt: skip
            return None
        return i

    def _insert_imu(self, buf: SegmentBuffer, i: int, t: float, q: np.ndarray, now) -> None:
        """Insert an accepted sample at index ``i``; report a gap, a resume or a reorder."""
        name = "imu:" + buf.name
        if t > buf.last_t:
            if buf.last_t > -math.inf and t - buf.last_t > buf.gap_s:
                silent = self._now(now) - buf.last_t
                if buf.stale:
                    self._event(t, "resumed", name, f"after {t - buf.last_t:.3f} s without samples",
                                logging.INFO)  # fmt: skip
                else:
                    self._event(t, "time_jump", name, f"step {t - buf.last_t:.3f} s > {buf.gap_s:.3f} s "
                                f"(expected {buf.period_s:.4f} s; silent {silent:.3f} s): gap, not interpolated")  # fmt: skip
            buf.last_t = t
            buf.t.append(t)
            buf.q.append(q)
        else:
            if buf.last_t - t > buf.gap_s:
                self._event(t, "time_jump", name,
                            f"{buf.last_t - t:.3f} s behind the newest sample: inserted in time order")  # fmt: skip
            else:
                self._event(t, "reordered", name, "out of order: inserted in time order",
                            logging.DEBUG)  # fmt: skip
            buf.t.insert(i, t)
            buf.q.insert(i, q)
        buf.stale = False
        buf.n += 1
        self.counters["imu_samples"] += 1

    def _data_arrived(self, t: float) -> None:
        if t > self._data_now:
            self._data_now = t
        if self._first_data_t is None:
            self._first_data_t = t

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
        pos, avail = self._camera_frame(position_m, available)
        times = [f[0] for f in self._pending]
        i = bisect.bisect_left(times, t)
        if (i < len(times) and times[i] == t) or t == self._last_frame_t:
            self._event(t, "duplicate", "camera", "same timestamp as a frame already received: dropped",
                        logging.DEBUG)  # fmt: skip
            return False
        if t <= self.last_output_t:
            self._event(t, "late", "camera",
                        f"older than the last output ({self.last_output_t:.3f} s): dropped",
                        logging.DEBUG)  # fmt: skip
            return False
        self._camera_sequence(t)
        self._cam_stale = False
        self._pending.insert(i, (t, pos, avail))
        self.counters["camera_frames"] += 1
        self._data_arrived(t)
        if self.config.record:
            self.accepted["camera"].append((t, pos, avail))
        return True

    def _camera_frame(self, position_m, available) -> tuple[np.ndarray, np.ndarray]:
        """Validated ``(position (Jc, 3), available (Jc,))`` of a camera frame."""
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
        return pos, avail

    def _camera_sequence(self, t: float) -> None:
        """Track the newest camera time; report a gap, a resume or a reorder."""
        period = 1.0 / self.config.camera_rate_hz
        gap = self.config.gap_factor * period
        if t > self._cam_last_t:
            if self._cam_last_t > -math.inf and t - self._cam_last_t > gap:
                if self._cam_stale:
                    self._event(t, "resumed", "camera",
                                f"after {t - self._cam_last_t:.3f} s without frames", logging.INFO)  # fmt: skip
                else:
                    self._event(t, "time_jump", "camera", f"step {t - self._cam_last_t:.3f} s > {gap:.3f} s "
                                f"(expected {period:.4f} s): gap, frames synthesized")  # fmt: skip
            self._cam_last_t = t
        else:
            self._event(t, "reordered", "camera", "out of order: inserted in time order",
                        logging.DEBUG)  # fmt: skip

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
            if camera_frame_due(f[0], t_exp, period):
                return f[0], f[1], f[2], False
        if cfg.camera and now < t_exp + cfg.max_latency_s:
            return None
        if not cfg.camera and now < t_exp:  # no frame ahead of the clock (all streams stale:
            return None  # else frames without end)
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
        if self.heading is not None and not self._find_heading():
            return outs  # no frame before the sensors share a heading
        while True:
            frame = self._next_frame(now_eff)
            if frame is None:
                break
            ready, forced = self._ready(frame[0], now_eff)
            if not ready:
                break
            self._process(frame, forced, outs)
        return outs

    def _find_heading(self, force: bool = False) -> bool:
        """6-D sensors: look for the still pose in the buffered samples; once found, turn
        them (and, in :meth:`push_imu`, every later sample) into the common heading."""
        h = self.heading
        if h.aligned:
            return True
        if not h.find({b.name: (b.t, b.q) for b in self._seg_list}, force=force):
            return False
        for b in self._seg_list:
            b.q = list(h.turn(b.name, np.array(b.q)))
        turns = ", ".join(f"{s} {v:+.1f}" for s, v in h.psi_deg.items())
        self._event(h.still.start_s, "heading", "imu",
                    f"sensor headings from the still pose {h.still.start_s:.2f}-"
                    f"{h.still.end_s:.2f} s (deg): {turns}", logging.INFO)  # fmt: skip
        return True

    def flush(self, now: float | None = None) -> list[EngineOutput]:
        """End of run: process all pending camera frames (holding orientations as needed)
        and emit the outputs a fixed-lag smoother still holds back."""
        outs: list[EngineOutput] = []
        if self.heading is not None and not self._find_heading(force=True):
            self._event(self._data_now, "heading", "imu",
                        "no still pose of the sensors: no output (6-D headings unknown)")  # fmt: skip
            return outs
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
                self._event(t, "camera_stale", "camera",
                            "no camera frame: synthesizing frames (camera unavailable)")  # fmt: skip
        if forced:
            self.counters["forced_frames"] += 1
        fr = self._frames.assemble(t, cam_pos, cam_avail, self._seg_list, self._root, forced)
        self._root = fr.root
        status = fr.segment_status
        for buf, st in zip(self._seg_list, status, strict=True):
            if st == IMU_STALE and not buf.stale:
                buf.stale = True
                self._event(t, "stream_stale", f"imu:{buf.name}",
                            f"no sample since {buf.last_t:.3f} s: joints predict-only")  # fmt: skip
        self.counters["held"] += int(np.count_nonzero(status == IMU_HELD))
        self.counters["stale"] += int(np.count_nonzero(status == IMU_STALE))
        self._last_frame_t = t
        for buf in self._seg_list:
            buf.prune(t)
        if cfg.record:
            self.accepted["frames"].append((t, bool(cam_pos is None and cfg.camera)))
        self.counters["frames"] += 1
        self._meta.append((t, fr.flags, fr.imu_status, fr.angles_deg))
        res = self.processor.step(t, fr.z_imu, fr.z_cam, fr.available)
        if res is not None:
            outs.append(self._emit(res))

    def _emit(self, res) -> EngineOutput:
        t, flags, jstat, angles = self._meta.popleft()
        pos, cov, src = res
        out = EngineOutput(float(t), self._n_out, np.asarray(pos), np.asarray(cov),
                           np.asarray(src, np.int8), flags, jstat, angles)  # fmt: skip
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
