"""The one in-memory container for a recording: IMU streams, optional vision and reference."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from kinefuse.exceptions import InputError

__all__ = ["ImuStream", "JointStream", "Recording", "name_index"]


def _time_vector(t_s, where: str) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1:
        raise InputError(f"{where}: expected t_s with shape (T,), got {t.shape}")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"{where}: expected finite t_s, got {t[bad]} at sample {bad}")
    if t.size > 1:
        d = np.diff(t)
        if np.any(d <= 0):
            bad = int(np.flatnonzero(d <= 0)[0])
            raise InputError(
                f"{where}: expected strictly increasing t_s, got t[{bad}]={t[bad]!r} then "
                f"t[{bad + 1}]={t[bad + 1]!r}"
            )
    return t


def _signal(value, where: str, name: str, shape_tail: tuple[int, ...], T: int) -> np.ndarray | None:
    if value is None:
        return None
    a = np.asarray(value)
    if not np.issubdtype(a.dtype, np.floating):
        raise InputError(f"{where}: expected {name} as floats, got dtype {a.dtype}")
    expected = (T, *shape_tail)
    if a.shape != expected:
        exp = "(" + ", ".join(["T", *map(str, shape_tail)]) + ")"
        raise InputError(f"{where}: expected {name} with shape {exp} = {expected}, got {a.shape}")
    return np.asarray(a, dtype=np.float64)


def name_index(names: Sequence[str], name: str, what: str, owner: str) -> int:
    """Position of ``name`` in ``names``; an InputError lists the known names otherwise."""
    try:
        return list(names).index(name)
    except ValueError:
        raise InputError(f"unknown {what} {name!r}; {owner} has {list(names)}") from None


@dataclass(frozen=True, eq=False)
class ImuStream:
    """One body-worn IMU.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Sample times, s, strictly increasing.
    q_world_from_sensor : ndarray, shape (T, 4) or None
        Orientation, scalar-first ``wxyz``, sensor frame to world (ENU unless ``frame`` says
        otherwise). NaN rows = missing.
    acc_m_s2, gyr_rad_s, mag : ndarray, shape (T, 3) or None
        Specific force (m/s², gravity included), angular rate (rad/s), magnetic field (any
        consistent unit), in the sensor frame.
    name : str
        Sensor identifier in the source file.
    frame : str
        World frame of ``q_world_from_sensor`` (``"ENU"`` by default).
    """

    t_s: np.ndarray
    q_world_from_sensor: np.ndarray | None = None
    acc_m_s2: np.ndarray | None = None
    gyr_rad_s: np.ndarray | None = None
    mag: np.ndarray | None = None
    name: str = ""
    frame: str = "ENU"

    def __post_init__(self):
        where = f"IMU stream {self.name!r}" if self.name else "IMU stream"
        t = _time_vector(self.t_s, where)
        object.__setattr__(self, "t_s", t)
        for fname, tail in (
            ("q_world_from_sensor", (4,)),
            ("acc_m_s2", (3,)),
            ("gyr_rad_s", (3,)),
            ("mag", (3,)),
        ):
            object.__setattr__(
                self, fname, _signal(getattr(self, fname), where, fname, tail, t.size)
            )
        if self.q_world_from_sensor is None and (self.acc_m_s2 is None or self.gyr_rad_s is None):
            raise InputError(
                f"{where}: expected an orientation (q_world_from_sensor) or raw data (acc_m_s2 and "
                "gyr_rad_s), got neither"
            )

    @property
    def rate_hz(self) -> float:
        """Median sampling rate, Hz."""
        return float(1.0 / np.median(np.diff(self.t_s))) if self.t_s.size > 1 else float("nan")

    def __len__(self) -> int:
        return int(self.t_s.size)


@dataclass(frozen=True, eq=False)
class JointStream:
    """Joint positions from a camera/skeleton tracker or an optical reference.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Sample times, s, strictly increasing.
    position_m : ndarray, shape (T, J, 3)
        Joint positions in metres (frame given by ``frame``). NaN where not measured.
    available : ndarray of bool, shape (T, J)
        True where the joint was observed (e.g. Kinect TrackingState == Tracked and finite).
        Where False, ``position_m`` may hold the tracker's (untrusted) value.
    joints : tuple of str
        Joint names, canonical (:data:`kinefuse.conventions.JOINTS`) where known.
    frame : str
        Coordinate frame of the positions (``"ENU"``, ``"camera"``, ``"vicon"``...).
    """

    t_s: np.ndarray
    position_m: np.ndarray
    available: np.ndarray | None = None
    joints: tuple[str, ...] = ()
    frame: str = "ENU"

    def __post_init__(self):
        t = _time_vector(self.t_s, "joint stream")
        pos = np.asarray(self.position_m)
        if (
            not np.issubdtype(pos.dtype, np.floating)
            or pos.ndim != 3
            or pos.shape[0] != t.size
            or pos.shape[2] != 3
        ):
            raise InputError(
                f"joint stream: expected position_m as floats with shape (T, J, 3) = ({t.size}, J, 3), "
                f"got {pos.shape} {pos.dtype}"
            )
        joints = tuple(self.joints)
        if len(joints) != pos.shape[1]:
            raise InputError(
                f"joint stream: expected {pos.shape[1]} joint names, got {len(joints)}"
            )
        if len(set(joints)) != len(joints):
            raise InputError(f"joint stream: duplicate joint names in {joints}")
        finite = np.all(np.isfinite(pos), axis=-1)
        if self.available is None:
            avail = finite
        else:
            avail = np.asarray(self.available)
            if avail.shape != pos.shape[:2]:
                raise InputError(
                    f"joint stream: expected available with shape {pos.shape[:2]}, got {avail.shape}"
                )
            avail = avail.astype(bool) & finite
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "position_m", np.asarray(pos, dtype=np.float64))
        object.__setattr__(self, "available", avail)
        object.__setattr__(self, "joints", joints)

    def index(self, joint: str) -> int:
        """Column index of ``joint``; a clear error lists the known names."""
        return name_index(self.joints, joint, "joint", "this stream")

    def position(self, joint: str, *, masked: bool = True) -> np.ndarray:
        """Positions ``(T, 3)`` of one joint; NaN where unavailable when ``masked``."""
        j = self.index(joint)
        p = self.position_m[:, j]
        return np.where(self.available[:, j, None], p, np.nan) if masked else p.copy()

    def subset(self, joints: Sequence[str]) -> JointStream:
        """A stream with only ``joints`` (in that order)."""
        idx = [self.index(j) for j in joints]
        return replace(
            self,
            position_m=self.position_m[:, idx],
            available=self.available[:, idx],
            joints=tuple(joints),
        )

    def __len__(self) -> int:
        return int(self.t_s.size)


@dataclass(eq=False)
class Recording:
    """A recording: IMU streams keyed by segment, optional vision and reference joint streams.

    Attributes
    ----------
    imu : dict of str -> ImuStream
        Keyed by canonical segment name (``upper_arm_r``, ``shank_l`` ...).
    vision : JointStream or None
        Camera / skeleton-tracker joints (an input of the fusion).
    reference : JointStream or None
        Ground-truth joints (optical mocap, or the simulation truth); evaluation only.
    reference_orientation : dict of str -> ImuStream
        Optical reference orientations per segment (``q_world_from_sensor`` holds
        ``q_world_from_segment``/optical body), where the dataset has them.
    metadata : dict
        ``subject``, ``source`` (file path), ``format``, ``units_converted`` and reader notes.
    """

    imu: dict[str, ImuStream] = field(default_factory=dict)
    vision: JointStream | None = None
    reference: JointStream | None = None
    reference_orientation: dict[str, ImuStream] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.imu, Mapping):
            raise InputError(
                f"expected imu as a mapping segment -> ImuStream, got {type(self.imu).__name__}"
            )
        for k, v in self.imu.items():
            if not isinstance(v, ImuStream):
                raise InputError(f"imu[{k!r}]: expected ImuStream, got {type(v).__name__}")
        self.imu = dict(self.imu)

    @property
    def segments(self) -> tuple[str, ...]:
        return tuple(self.imu)

    def __repr__(self) -> str:
        parts = [f"imu={list(self.imu)}"]
        if self.vision is not None:
            parts.append(f"vision={len(self.vision)}x{len(self.vision.joints)}")
        if self.reference is not None:
            parts.append(f"reference={len(self.reference)}x{len(self.reference.joints)}")
        src = self.metadata.get("source")
        if src:
            parts.append(f"source={src!r}")
        return f"Recording({', '.join(parts)})"
