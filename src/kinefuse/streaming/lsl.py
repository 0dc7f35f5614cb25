"""Lab Streaming Layer adapters: stream layouts, inlets with clock correction, the fused outlet.

pylsl is only reached through :func:`kinefuse.streaming.config.import_pylsl` (machine-local
configuration first, see :mod:`kinefuse.streaming.config`).

Stream layouts (channel labels in ``desc/channels/channel/label``, units in ``unit``):

=============  ========  ===============================================================
stream         type      channels
=============  ========  ===============================================================
IMU segment    ``IMU``   ``qw qx qy qz`` (``q_world_from_sensor``, unit 1), optionally
                         ``acc_x acc_y acc_z`` (m/s^2) and ``gyr_x gyr_y gyr_z`` (rad/s);
                         ``desc/segment`` names the segment
camera         ``MoCap`` per joint ``{joint}_x {joint}_y {joint}_z`` (m) and
                         ``{joint}_available`` (0/1); ``desc/joints``
fused output   ``MoCap`` per joint ``{joint}_x _y _z`` (m), ``{joint}_std_x _y _z`` (m),
                         ``{joint}_source`` (code, ``desc/sources``), ``{joint}_flags``
                         (bit mask, ``desc/flags``); nominal rate = camera rate
joint angles   ``Angles`` with a calibrated chain (``--chain`` with segment frames): per joint
                         ``{joint}_flexion``, ``_adduction``, ``_internal_rotation`` (deg,
                         ISB; ``trunk_flexion``, ``_lateral_bending``,
                         ``_axial_rotation``); named ``{fused}-angles``, same
                         timestamps as the fused output
=============  ========  ===============================================================

Clocks: an inlet's timestamps are in the sender's ``local_clock``. With ``clock="manual"``
(default) :class:`Input` adds ``inlet.time_correction()`` (the estimated offset of the
sender's clock to ours, refreshed every ``refresh_s``); with ``clock="lsl"`` liblsl applies
``proc_clocksync | proc_dejitter | proc_monotonize`` itself (smoother timestamps, but
dejittering changes them, so they are no longer the sender's).
"""

from __future__ import annotations

import inspect
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from kinefuse.conventions import SOURCE_NAMES
from kinefuse.exceptions import InputError
from kinefuse.kinematics.angles import angle_components
from kinefuse.streaming import engine_types as _engine
from kinefuse.streaming.config import import_pylsl
from kinefuse.streaming.processors import SOURCE_NONE

__all__ = [
    "ANGLES_TYPE",
    "CAMERA_TYPE",
    "IMU_CHANNELS",
    "IMU_TYPE",
    "OUTPUT_TYPE",
    "FusedOutlet",
    "Input",
    "angle_channels",
    "camera_channels",
    "channel_labels",
    "make_outlet",
    "output_channels",
    "resolve",
    "resolve_many",
    "visible_streams",
]

log = logging.getLogger("kinefuse.streaming")

IMU_TYPE = "IMU"
CAMERA_TYPE = "MoCap"
OUTPUT_TYPE = "MoCap"
ANGLES_TYPE = "Angles"

#: IMU stream channels: (label, unit, type).
IMU_CHANNELS = (
    ("qw", "1", "Orientation"), ("qx", "1", "Orientation"), ("qy", "1", "Orientation"), ("qz", "1", "Orientation"),
)  # fmt: skip
RAW_CHANNELS = tuple((f"acc_{a}", "m/s^2", "Acceleration") for a in "xyz") + tuple(
    (f"gyr_{a}", "rad/s", "AngularVelocity") for a in "xyz"
)


def camera_channels(joints) -> list[tuple[str, str, str]]:
    """Camera stream channels ``(label, unit, type)``: x, y, z, available per joint."""
    out = []
    for j in joints:
        out += [(f"{j}_{a}", "m", "Position") for a in "xyz"] + [
            (f"{j}_available", "bool", "Availability")
        ]
    return out


def output_channels(joints) -> list[tuple[str, str, str]]:
    """Fused stream channels: x, y, z, std_x, std_y, std_z, source, flags per joint."""
    out = []
    for j in joints:
        out += [(f"{j}_{a}", "m", "Position") for a in "xyz"]
        out += [(f"{j}_std_{a}", "m", "PositionStd") for a in "xyz"]
        out += [(f"{j}_source", "code", "Source"), (f"{j}_flags", "bitmask", "Flags")]
    return out


def angle_channels(joints) -> list[tuple[str, str, str]]:
    """Joint-angle stream channels: flexion, adduction, internal rotation per joint (the
    trunk's: flexion, lateral bending, axial rotation), deg."""
    return [(f"{j}_{c}", "deg", "Angle") for j in joints for c in angle_components(j)]


def make_outlet(name, stype, channels, srate, *, source_id="", desc=None, chunk_size=1):
    """Create a ``double64`` outlet with channel labels/units/types in its description.

    Parameters
    ----------
    name, stype : str
        LSL name and type.
    channels : list of (label, unit, type)
    srate : float
        Nominal rate, Hz.
    source_id : str
        Unique source id (lets inlets recover the stream when it is re-created).
    desc : mapping of str -> str or list of str, optional
        Extra ``desc`` children (a list becomes repeated grandchildren).
    """
    pylsl = import_pylsl()
    info = pylsl.StreamInfo(name, stype, len(channels), float(srate), "double64", source_id)
    d = info.desc()
    chs = d.append_child("channels")
    for label, unit, ctype in channels:
        c = chs.append_child("channel")
        c.append_child_value("label", label)
        c.append_child_value("unit", unit)
        c.append_child_value("type", ctype)
    for key, value in (desc or {}).items():
        if isinstance(value, (list, tuple)):
            node = d.append_child(key)
            for item in value:
                if isinstance(item, tuple):
                    sub = node.append_child(item[0])
                    for k2, v2 in item[1].items():
                        sub.append_child_value(k2, str(v2))
                else:
                    node.append_child_value(key.rstrip("s") or "item", str(item))
        else:
            d.append_child_value(key, str(value))
    d.append_child_value("software", "kinefuse")
    return pylsl.StreamOutlet(info, chunk_size=chunk_size, max_buffered=60)


def channel_labels(info) -> list[str]:
    """Channel labels from a StreamInfo's ``desc/channels`` (empty strings where missing)."""
    labels = []
    ch = info.desc().child("channels").child("channel")
    while not ch.empty():
        labels.append(ch.child_value("label"))
        ch = ch.next_sibling("channel")
    n = info.channel_count()
    return (labels + [""] * n)[:n]


def resolve(name: str, stype: str | None = None, timeout_s: float = 5.0):
    """Resolve one stream by name (and type), waiting at most ``timeout_s``.

    Raises
    ------
    TimeoutError
        No such stream within the timeout (message names it).
    """
    pylsl = import_pylsl()
    deadline = time.monotonic() + timeout_s
    while True:
        left = max(0.0, deadline - time.monotonic())
        found = pylsl.resolve_byprop("name", name, 1, min(left, 1.0))
        found = [f for f in found if stype is None or f.type() == stype]
        if found:
            return found[0]
        if time.monotonic() >= deadline:
            raise TimeoutError(f"no LSL stream named {name!r}" + (f" of type {stype!r}" if stype else "") +
                               f" found within {timeout_s:g} s")  # fmt: skip


def resolve_many(names, timeout_s: float = 5.0) -> dict:
    """Resolve several streams by name in one query; returns ``{name: StreamInfo}`` for those
    found within ``timeout_s`` (the call returns as soon as all are found)."""
    pylsl = import_pylsl()
    names = list(dict.fromkeys(names))
    for n in names:
        if "'" in n or not n:
            raise InputError(f"expected LSL stream names without quotes, got {n!r}")
    if not names:
        return {}
    pred = " or ".join(f"name='{n}'" for n in names)
    found = {}
    deadline = time.monotonic() + timeout_s
    while True:
        left = max(0.0, deadline - time.monotonic())
        for info in pylsl.resolve_bypred(pred, len(names), min(left, 2.0)):
            found.setdefault(info.name(), info)
        if len(found) == len(names) or time.monotonic() >= deadline:
            return found


def visible_streams(timeout_s: float = 1.0) -> list[tuple[str, str]]:
    """``(name, type)`` of the streams LSL sees within ``timeout_s`` (sorted; for hints when a
    stream that was asked for is not found)."""
    pylsl = import_pylsl()
    return sorted({(i.name(), i.type()) for i in pylsl.resolve_streams(timeout_s)})


_EMPTY = (np.zeros((0, 0)), np.zeros(0))
_EMPTY[0].flags.writeable = _EMPTY[1].flags.writeable = False
#: ``as_numpy=True`` where pylsl has it (>= 1.18): one array instead of lists of floats
_AS_NUMPY: dict = {}


def _pull_options(pylsl) -> None:
    if "as_numpy" in inspect.signature(pylsl.StreamInlet.pull_chunk).parameters:
        _AS_NUMPY["as_numpy"] = True


@dataclass
class Input:
    """One input stream: an inlet, its layout and its clock correction.

    Attributes
    ----------
    kind : {"imu", "camera"}
    key : str
        Segment (IMU) or ``"camera"``.
    name : str
        LSL stream name.
    joints : tuple of str
        Camera joints (camera streams).
    """

    kind: str
    key: str
    name: str
    inlet: object = None
    info: object = None
    clock: str = "manual"
    refresh_s: float = 5.0
    joints: tuple = ()
    q_idx: list = field(default_factory=list)
    raw_idx: list | None = None
    offset_s: float = 0.0
    _next_refresh: float = 0.0
    _next_probe: float = 0.0
    lost: bool = False
    n_samples: int = 0
    n_reattached: int = 0

    @classmethod
    def open(
        cls,
        kind,
        key,
        name,
        *,
        stype=None,
        timeout_s=5.0,
        clock="manual",
        max_buflen_s=30,
        info=None,
    ):
        """Open an inlet on ``info`` or on the stream resolved by name (subscribed at once;
        data is buffered from then on)."""
        inp = cls(kind, key, name, clock=clock)
        inp._attach(info if info is not None else resolve(name, stype, timeout_s), max_buflen_s)
        return inp

    def _attach(self, info, max_buflen_s=30):
        pylsl = import_pylsl()
        _pull_options(pylsl)
        flags = 0
        if self.clock == "lsl":
            flags = pylsl.proc_clocksync | pylsl.proc_dejitter | pylsl.proc_monotonize
        self.inlet = pylsl.StreamInlet(
            info, max_buflen=max_buflen_s, recover=True, processing_flags=flags
        )
        self.info = self.inlet.info(timeout=5.0)
        self.inlet.open_stream(timeout=5.0)
        labels = channel_labels(self.info)
        if self.kind == "imu":
            if all(lab in labels for lab in ("qw", "qx", "qy", "qz")):
                self.q_idx = [labels.index(lab) for lab in ("qw", "qx", "qy", "qz")]
            elif self.info.channel_count() >= 4 and not any(labels):
                self.q_idx = [0, 1, 2, 3]  # unlabelled: first four channels are wxyz
            else:
                self.q_idx = []
            raw = [f"acc_{a}" for a in "xyz"] + [f"gyr_{a}" for a in "xyz"]
            self.raw_idx = [labels.index(r) for r in raw] if all(r in labels for r in raw) else None
            if not self.q_idx and self.raw_idx is None:
                raise InputError(
                    f"LSL stream {self.name!r}: expected channels qw qx qy qz or acc_x.. gyr_z, got {labels}"
                )
        else:
            joints = []
            for lab in labels:
                if lab.endswith("_x"):
                    joints.append(lab[:-2])
            self.joints = tuple(joints)
            self._cam_idx = np.array(
                [[labels.index(f"{j}_{a}") for a in "xyz"] for j in joints], int
            )
            self._av_idx = np.array(
                [
                    labels.index(f"{j}_available") if f"{j}_available" in labels else -1
                    for j in joints
                ]
            )
        self.offset_s = 0.0
        self._next_refresh = 0.0
        if self.clock == "manual":
            self._next_refresh = -1.0  # first estimate: refresh_clock(first=True) by the caller

    def refresh_clock(self, first: bool = False) -> None:
        """Update the clock offset (manual mode) at most every ``refresh_s``."""
        if self.clock != "manual":
            return
        now = time.monotonic()
        first = first or self._next_refresh < 0
        if not first and now < self._next_refresh:
            return
        pylsl = import_pylsl()
        try:
            self.offset_s = float(self.inlet.time_correction(timeout=2.0 if first else 0.05))
        except (pylsl.util.TimeoutError, TimeoutError):
            log.debug("time_correction of %s timed out; keeping %.6f s", self.name, self.offset_s)
        self._next_refresh = now + self.refresh_s

    def pull(self, max_samples: int = 1024):
        """Samples available now: ``(values (n, C) float64, timestamps (n,) corrected)``."""
        pylsl = import_pylsl()
        try:
            # a cheap query first (~1 us): most polls of a 100 Hz stream find nothing; a full
            # pull (which is what reports a lost stream) at least every 50 ms
            n = self.inlet.samples_available()
            if not n:
                now = time.monotonic()
                if now < self._next_probe:
                    return _EMPTY
                self._next_probe = now + 0.05
            elif n == 1:  # the live case: one sample per poll; pull_sample is the cheaper call
                row, t = self.inlet.pull_sample(timeout=0.0)
                if t is None:
                    return _EMPTY
                self.n_samples += 1
                return np.array([row], dtype=float), np.array([t + self.offset_s])
            data, ts = self.inlet.pull_chunk(timeout=0.0, max_samples=max_samples, **_AS_NUMPY)
        except pylsl.util.LostError:
            if not self.lost:
                log.warning("LSL stream %s lost; trying to reattach", self.name)
            self.lost = True
            return _EMPTY
        if not len(ts):
            return _EMPTY
        self.n_samples += len(ts)
        return np.asarray(data, dtype=float), np.asarray(ts, dtype=float) + self.offset_s

    def reattach(self, timeout_s: float = 0.2) -> bool:
        """Try to find the stream again by name (after :attr:`lost`); True when reattached."""
        try:
            info = resolve(self.name, None, timeout_s)
        except TimeoutError:
            return False
        self.close()
        self._attach(info)
        self.lost = False
        self.n_reattached += 1
        log.warning("LSL stream %s reattached (source_id %r)", self.name, info.source_id())
        return True

    def feed(self, engine, data: np.ndarray, ts: np.ndarray, now: float | None = None) -> int:
        """Push pulled samples into ``engine``; returns how many were accepted."""
        n = 0
        if self.kind == "imu":
            qi = self.q_idx
            if qi and qi == list(range(qi[0], qi[0] + 4)):
                qi = slice(qi[0], qi[0] + 4)  # a view, not a gather (push_imu copies it)
            for row, t in zip(data, ts, strict=True):
                if self.q_idx:
                    ok = engine.push_imu(self.key, t, row[qi], now=now)
                else:
                    r = row[self.raw_idx]
                    ok = engine.push_imu(self.key, t, acc=r[:3], gyr=r[3:], now=now)
                n += ok
        else:
            cols, av_cols, seen, always = self._camera_map(engine.config.camera_joints)
            for row, t in zip(data, ts, strict=True):
                pos = np.where(seen[:, None], row[cols], np.nan)  # (Jc, 3); unseen joints NaN
                avail = seen & (always | (row[av_cols] > 0.5))
                n += engine.push_camera(t, pos, avail, now=now)
        return n

    def _camera_map(self, camera_joints):
        """Column indices of the engine's camera joints in this stream's samples (cached):
        ``cols (Jc, 3)``, ``av_cols (Jc,)``, ``seen`` (the stream has the joint), ``always``
        (no availability channel: available whenever present)."""
        key = tuple(camera_joints)
        if getattr(self, "_cam_map_key", None) != key:
            src = np.array([self.joints.index(j) if j in self.joints else -1 for j in key], int)
            seen = src >= 0
            cols = np.where(seen[:, None], self._cam_idx[np.maximum(src, 0)], 0)
            av = np.where(seen, self._av_idx[np.maximum(src, 0)], -1)
            self._cam_map = (cols, np.maximum(av, 0), seen, av < 0)
            self._cam_map_key = key
        return self._cam_map

    def close(self) -> None:
        """Close the inlet."""
        if self.inlet is not None:
            try:
                self.inlet.close_stream()
            except Exception:
                pass
            self.inlet = None


class FusedOutlet:
    """The fused-joints outlet (layout in the module docstring).

    Parameters
    ----------
    name : str
    joints : sequence of str
    rate_hz : float
        Nominal rate (camera rate).
    processor : str
        Processor description stored in ``desc``.
    lag_frames : int
        Output delay of the processor, frames (``desc/lag_frames``).
    angle_joints : sequence of str
        Joints whose angles the outputs carry (:attr:`EngineConfig.angle_joints`): a second
        outlet ``{name}-angles`` publishes them (none: no angle outlet).
    """

    def __init__(
        self, name, joints, rate_hz, *, processor="", lag_frames=0, source_id=None, angle_joints=()
    ):
        self.joints = tuple(joints)
        self.channels = output_channels(self.joints)
        flags = [("flag", {"bit": b, "meaning": m}) for b, m in (
            (_engine.FLAG_IMU_HELD, "IMU orientation held (no sample after the frame yet)"),
            (_engine.FLAG_IMU_STALE, "IMU stream stale: no IMU measurement (predict only)"),
            (_engine.FLAG_CAMERA_MISSING, "no camera frame (synthesized frame)"),
            (_engine.FLAG_NO_CAMERA_JOINT, "camera did not see the joint"),
            (_engine.FLAG_FORCED, "frame processed after max latency"))]  # fmt: skip
        sources = [("source", {"code": c, "meaning": m}) for c, m in SOURCE_NAMES.items()]
        sources.append(("source", {"code": SOURCE_NONE, "meaning": "no estimate (NaN position)"}))
        self.outlet = make_outlet(
            name, OUTPUT_TYPE, self.channels, rate_hz,
            source_id=source_id or f"kinefuse-fused-{name}",
            desc={"joints": list(self.joints), "sources": sources, "flags": flags,
                  "processor": processor, "lag_frames": str(lag_frames),
                  "reference_frame": "camera frame of the inputs (ENU for kinefuse replays)"},
        )  # fmt: skip
        self._buf = np.empty(len(self.channels))
        self.angle_joints = tuple(angle_joints)
        self.angles_name = f"{name}-angles" if self.angle_joints else None
        self.angles_outlet = None
        if self.angle_joints:
            self.angles_outlet = make_outlet(
                self.angles_name, ANGLES_TYPE, angle_channels(self.angle_joints), rate_hz,
                source_id=f"{source_id or f'kinefuse-fused-{name}'}-angles",
                desc={"joints": list(self.angle_joints),
                      "convention": "ISB (Wu et al. 2002/2005), Grood & Suntay joint coordinate "
                                    "system; zero in the calibration pose; flexion positive",
                      "fused_stream": name},
            )  # fmt: skip

    def push(self, out) -> None:
        """Push one :class:`~kinefuse.streaming.engine.EngineOutput` (timestamp = frame time)."""
        J = len(self.joints)
        b = self._buf.reshape(J, 8)
        b[:, 0:3] = out.position_m
        b[:, 3:6] = out.std_m
        b[:, 6] = out.source
        b[:, 7] = out.flags
        # a one-sample chunk: pylsl hands the array's buffer to liblsl as is (push_sample
        # converts value by value); the chunk's timestamp is its only sample's
        self.outlet.push_chunk(self._buf.reshape(1, -1), out.t_s)
        if self.angles_outlet is not None and out.angles_deg is not None:
            self.angles_outlet.push_chunk(np.reshape(out.angles_deg, (1, -1)), out.t_s)

    def close(self) -> None:
        """Release the outlets."""
        self.outlet = self.angles_outlet = None
