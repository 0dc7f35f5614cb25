"""Publish a recording as live LSL streams (for tests, demos and latency measurements).

Streams: ``{prefix}_imu_{segment}`` (type ``IMU``: ``qw qx qy qz`` and, if present and
``include_raw``, ``acc_*`` m/s², ``gyr_*`` rad/s) and ``{prefix}_camera`` (type ``MoCap``: x,
y, z, available per joint); source ids ``{name}@kinefuse-replay``.

Sample k of a stream is pushed when ``local_clock() >= t_start + (t_k − t_0) / rate`` and
carries exactly that value as its LSL timestamp: the original timestamps, shifted to
``local_clock`` and compressed by ``rate``; nominal rates are multiplied by ``rate``. The
camera's NaN positions (unavailable joints) are sent as NaN with ``available = 0``. Ctrl-C
stops publishing before the next sample (every sample pushed is counted in the summary) and
closes the outlets after ``linger_s``, as at a normal end.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinefuse.data import demo_motion
from kinefuse.exceptions import InputError
from kinefuse.io import load
from kinefuse.io.recording import Recording
from kinefuse.sim import virtual_recording
from kinefuse.streaming.config import import_pylsl
from kinefuse.streaming.engine_types import SummaryMapping
from kinefuse.streaming.interrupt import sigint_as_flag
from kinefuse.streaming.lsl import (
    CAMERA_TYPE,
    IMU_CHANNELS,
    IMU_TYPE,
    RAW_CHANNELS,
    camera_channels,
    make_outlet,
)

__all__ = [
    "CONSUMER_GRACE_S",
    "ReplaySummary",
    "demo_recording",
    "load_recording",
    "run_replay",
    "wait_for_consumers",
]

log = logging.getLogger("kinefuse.streaming")


def demo_recording(stop_s: float | None = None, seed: int = 0) -> Recording:
    """The packaged CMU clip as a virtual recording: 9 IMUs at 100 Hz, a camera at 30 Hz with
    occlusions and dropouts (:func:`kinefuse.sim.virtual_recording`), first ``stop_s`` s."""
    return virtual_recording(demo_motion(None, stop_s), seed=seed)


def load_recording(recording, format: str | None = None) -> Recording:
    """A :class:`Recording`, a path readable by :func:`kinefuse.io.load` (as ``format`` if
    given), or ``"demo"``."""
    if isinstance(recording, Recording):
        return recording
    if isinstance(recording, str) and recording == "demo":
        return demo_recording()
    if isinstance(recording, (str, Path)):
        return load(Path(recording), format=format)
    raise InputError(f"expected a Recording, a path or 'demo', got {type(recording).__name__}")


def _streams(rec: Recording, prefix: str, include_raw: bool):
    """(name, type, channels, t (N,), values (N, C), rate_hz, desc) per stream."""
    out = []
    bare = [seg for seg, st in rec.imu.items() if st.q_world_from_sensor is None]
    if bare and not include_raw:
        raise InputError(
            f"--no-raw (include_raw=False): IMU {', '.join(map(repr, bare))} has no orientation, "
            "only acc/gyr: its stream would carry nothing; publish the raw channels, or estimate "
            "the orientations first (kinefuse.orientation.estimate)"
        )
    for seg, st in rec.imu.items():
        cols, chans = [], []
        if st.q_world_from_sensor is not None:
            cols.append(st.q_world_from_sensor)
            chans += list(IMU_CHANNELS)
        if (
            (include_raw or st.q_world_from_sensor is None)
            and st.acc_m_s2 is not None
            and st.gyr_rad_s is not None
        ):
            cols += [st.acc_m_s2, st.gyr_rad_s]
            chans += list(RAW_CHANNELS)
        out.append((f"{prefix}_imu_{seg}", IMU_TYPE, chans, st.t_s, np.hstack(cols), st.rate_hz,
                    {"segment": seg}))  # fmt: skip
    v = rec.vision
    if v is not None:
        vals = np.concatenate([v.position_m, v.available[..., None].astype(float)], axis=2)
        out.append((f"{prefix}_camera", CAMERA_TYPE, camera_channels(v.joints), v.t_s,
                    vals.reshape(len(v), -1), float(1.0 / np.median(np.diff(v.t_s))),
                    {"joints": list(v.joints), "frame": v.frame}))  # fmt: skip
    return out


@dataclass(frozen=True, eq=False)
class ReplaySummary(SummaryMapping):
    """Outcome of :func:`run_replay` (also a read-only mapping of its fields, in order)."""

    #: Stream names.
    streams: list
    #: Samples pushed per stream.
    samples: dict
    #: Wall time, s.
    duration_s: float
    #: Published recording time, s (up to the last sample pushed when stopped early).
    recording_s: float
    #: Ctrl-C stopped it.
    interrupted: bool


class _Publisher:
    """One merged, time-ordered schedule of every stream's samples, pushed at their due times."""

    def __init__(self, streams, rate: float, limit: float, stop_event):
        t_all = np.concatenate([s[3] for s in streams])
        which = np.concatenate([np.full(len(s[3]), k) for k, s in enumerate(streams)])
        row = np.concatenate([np.arange(len(s[3])) for s in streams])
        order = np.lexsort((which, t_all))
        self.t_all, self.which, self.row = t_all[order], which[order], row[order]
        self.t0 = float(self.t_all[0])
        self.span = float(self.t_all[-1] - self.t0) + float(np.median(np.diff(streams[0][3])))
        self.streams, self.rate, self.limit, self.stop_event = streams, rate, limit, stop_event
        self.sigint: list = []  # non-empty after Ctrl-C (streaming.interrupt.sigint_as_flag)
        self.pushed = [0] * len(streams)
        self.last_rt = 0.0  # recording time of the last sample pushed, s
        self.rep = 0

    def run(self, outlets, pylsl, loop: bool, quiet: bool) -> None:
        """Push every sample at ``start + (t_k − t_0) / rate``; raises :class:`_Stop` on the
        stop event or Ctrl-C, checked before each sample (never between a push and its
        count)."""
        start = pylsl.local_clock() + 0.05
        done = False
        while not done:
            base = self.rep * self.span
            for k in range(self.t_all.size):
                rt = float(self.t_all[k] - self.t0) + base
                if rt >= self.limit:
                    done = True
                    break
                due = start + rt / self.rate
                self._wait(pylsl, due)
                s = self.which[k]
                outlets[s].push_sample(self.streams[s][4][self.row[k]], due)
                self.pushed[s] += 1
                self.last_rt = rt
            self.rep += 1
            if not loop:
                done = True
            elif not quiet:
                log.info("replay: loop %d done", self.rep)

    def _wait(self, pylsl, due: float) -> None:
        while True:
            if self.sigint or (self.stop_event is not None and self.stop_event.is_set()):
                raise _Stop
            now = pylsl.local_clock()
            if now >= due:
                return
            time.sleep(min(due - now, 0.005))


def run_replay(
    recording,
    rate: float = 1.0,
    name_prefix: str = "kinefuse",
    loop: bool = False,
    duration_s: float | None = None,
    *,
    include_raw: bool = True,
    wait_for_consumers_s: float | None = None,
    stop_event=None,
    quiet: bool = True,
    linger_s: float = 0.5,
    format: str | None = None,
    on_ready: Callable[[], None] | None = None,
) -> ReplaySummary:
    """Publish a recording to LSL at its real rate (or ``rate`` times faster).

    Parameters
    ----------
    recording : Recording, path or "demo"
        What to publish (a path is read with :func:`kinefuse.io.load`; ``"demo"`` is
        :func:`demo_recording`).
    rate : float
        Speed-up factor (2 = twice real time).
    name_prefix : str
        Stream names ``{prefix}_imu_{segment}`` and ``{prefix}_camera`` (module docstring).
    loop : bool
        Start again at the end (timestamps keep increasing).
    duration_s : float, optional
        Stop after this much recording time, s (default: once, or forever with ``loop``).
    include_raw : bool
        Publish acc/gyr channels next to the orientation (an IMU without orientation publishes
        them anyway; with ``include_raw=False`` it is an error).
    wait_for_consumers_s : float, optional
        Before publishing, wait up to this long until every outlet has a consumer
        (:func:`wait_for_consumers`: once one has, at most :data:`CONSUMER_GRACE_S` more).
    stop_event : threading.Event, optional
        Set it to stop early (tests).
    quiet : bool
        No progress log lines.
    linger_s : float
        Keep the outlets open this long after the last sample (in-flight data), s; after a
        Ctrl-C too, so that a consumer gets every sample the summary counts (a second Ctrl-C
        closes them at once).
    format : str, optional
        A :data:`kinefuse.io.FORMATS` reader for a path (default: detected).
    on_ready : callable, optional
        Called once the recording is read and checked, before LSL is loaded (the CLI's
        "Publishing ..." line: not printed for a recording that is refused).

    Returns
    -------
    ReplaySummary
    """
    if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
        raise InputError(f"expected rate > 0, got {rate!r}")
    if duration_s is not None and not duration_s > 0:
        raise InputError(f"expected duration_s > 0, got {duration_s!r}")
    rec = load_recording(recording, format)
    streams = _streams(rec, name_prefix, include_raw)
    if not streams:
        raise InputError("the recording has no IMU or camera stream to publish")
    if on_ready is not None:
        on_ready()
    pylsl = import_pylsl()
    outlets = [make_outlet(name, stype, chans, rate_hz * rate, source_id=f"{name}@kinefuse-replay",
                           desc=desc, chunk_size=1)
               for name, stype, chans, _t, _v, rate_hz, desc in streams]  # fmt: skip
    limit = math.inf if duration_s is None else float(duration_s)
    start_wall = time.monotonic()
    pub = _Publisher(streams, rate, limit, stop_event)
    interrupted = stopped = False
    try:
        if wait_for_consumers_s:
            wait_for_consumers(outlets, wait_for_consumers_s)
        with sigint_as_flag() as pub.sigint:  # Ctrl-C between two samples: each push counted
            try:
                pub.run(outlets, pylsl, loop, quiet)
            except _Stop:
                stopped = True
            interrupted = bool(pub.sigint)
    except KeyboardInterrupt:  # while waiting for consumers, or outside the main thread
        interrupted = True
    finally:
        try:  # the samples pushed so far reach the inlets before the outlets close (Ctrl-C too)
            time.sleep(linger_s)
        except KeyboardInterrupt:  # a second Ctrl-C: close at once
            interrupted = True
        del outlets[:]
    done = min(limit, pub.rep * pub.span if loop else pub.span)
    published = pub.last_rt if interrupted or stopped else done
    return ReplaySummary(streams=[s[0] for s in streams],
                         samples=dict(zip([s[0] for s in streams], pub.pushed, strict=True)),
                         duration_s=time.monotonic() - start_wall, recording_s=published,
                         interrupted=interrupted)  # fmt: skip


class _Stop(Exception):
    pass


#: Once one stream has a reader, how long the others are waited for (s): a consumer opens all
#: the streams it reads at once, and one that reads only some (IMU-only capture: no camera)
#: must not hold the replay for the whole ``wait_for_consumers_s``.
CONSUMER_GRACE_S = 2.0


def wait_for_consumers(outlets, timeout_s: float, grace_s: float = CONSUMER_GRACE_S, *,
                       clock=time.monotonic, sleep=time.sleep) -> bool:  # fmt: skip
    """Wait until every outlet has a consumer, or ``grace_s`` after the first one got one, or
    ``timeout_s``; True if every outlet has one."""
    deadline = clock() + timeout_s
    first = None
    while True:
        have = [o.have_consumers() for o in outlets]
        now = clock()
        if all(have):
            return True
        if any(have) and first is None:
            first = now
        if now >= deadline or (first is not None and now - first >= grace_s):
            return False
        sleep(0.01)
