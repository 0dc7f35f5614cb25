"""Live sensors of arbitrary headings (6-D) brought into one world frame from a still pose.

A 6-D orientation (no magnetometer) has a heading of its own per sensor and per power-up, so
the heading offsets a calibration found offline do not carry to a live session. With
``chain.json``'s segment frames the engine finds them again: the subject stands in the
calibration pose for ``window_s`` at the start of streaming; in the earliest still window
(:func:`kinefuse.kinematics.static.pose_headings`) each sensor is turned about the vertical so
that the segment frames' headings relate as in the calibration pose (``pose_yaw_deg``, 0 where
the calibration's frames agreed there). Until then the engine outputs nothing;
the samples it buffered are then turned and processed like later ones. The batch form
(:func:`kinefuse.streaming.offline.offline_causal`) applies the same computation to the whole
recording: the earliest still window is the one the engine found (its candidate windows do
not depend on how much data followed).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from kinefuse.io.recording import ImuStream
from kinefuse.kinematics.static import pose_headings
from kinefuse.kinematics.still import MAX_ACC_STD_M_S2, MAX_RATE_RAD_S

__all__ = ["PoseHeading"]


def _yaw_quaternion(psi: float) -> np.ndarray:
    return np.array([np.cos(psi / 2.0), 0.0, 0.0, np.sin(psi / 2.0)])


def _turned(r: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``r q`` of a rotation about z, ``r = (c, 0, 0, s)``, and ``q`` (…, 4)."""
    c, s = r[0], r[3]
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w], axis=-1)


class PoseHeading:
    """Per-sensor heading offsets from the calibration pose (see the module docstring).

    Parameters
    ----------
    frames : mapping of str -> ndarray, shape (3, 3)
        ``R_sensor_from_segment`` of every engine segment (``chain.json``'s ``segment_frames``).
    window_s : float
        Still time needed, s (the calibration's window).
    segments : sequence of str
        The engine's segments.
    reference : str, optional
        The segment whose sensor keeps its heading (ψ = 0); default the first.
    pose_yaw_deg : mapping of str -> float, optional
        The segment frames' headings relative to the reference's in the calibration pose
        (``chain.json``'s ``heading.pose_yaw_deg``): kept.
    """

    def __init__(self, frames: Mapping, window_s: float, segments, reference=None,
                 pose_yaw_deg=None):  # fmt: skip
        self.pose_yaw_rad = {s: np.radians(v) for s, v in dict(pose_yaw_deg or {}).items()}
        self.segments = list(segments)
        if reference is not None:  # first: pose_headings turns the others onto it
            self.segments.remove(reference)
            self.segments.insert(0, reference)
        self.frames = {s: np.asarray(frames[s], dtype=float) for s in self.segments}
        self.window_s = float(window_s)
        self.rotation: dict[str, np.ndarray] | None = None  # per segment, wxyz, once found
        self.psi_deg: dict[str, float] = {}
        self.still = None
        self._next_try = -np.inf

    @property
    def aligned(self) -> bool:
        return self.rotation is not None

    def find(self, series: Mapping[str, tuple], force: bool = False) -> bool:
        """Look for the still pose in ``series`` (segment -> (t (N,), q (N, 4))) once every
        segment spans ``window_s``; True (and ``rotation`` set) when found. Between calls the
        search waits for a quarter window of new data (the candidates' spacing) unless
        ``force``."""
        spans = [series[s][0] for s in self.segments]
        if any(len(t) < 2 for t in spans):
            return False
        t0, t1 = max(t[0] for t in spans), min(t[-1] for t in spans)
        if t1 - t0 < self.window_s or (t1 < self._next_try and not force):
            return False
        self._next_try = t1 + 0.25 * self.window_s  # candidates start window_s / 4 apart
        imus = {
            s: ImuStream(t_s=np.asarray(series[s][0], float),
                         q_world_from_sensor=np.asarray(series[s][1], float), name=s)
            for s in self.segments
        }  # fmt: skip
        still, psi = pose_headings(
            imus, self.frames, self.window_s,
            max_rate_rad_s=MAX_RATE_RAD_S, max_acc_std_m_s2=MAX_ACC_STD_M_S2,
            pose_yaw_rad=self.pose_yaw_rad,
        )  # fmt: skip
        if psi is None:
            return False
        self.still = still
        self.psi_deg = {s: float(np.degrees(v)) for s, v in psi.items()}
        self.rotation = {s: _yaw_quaternion(v) for s, v in psi.items()}
        return True

    def turn(self, segment: str, q: np.ndarray) -> np.ndarray:
        """``q`` (…, 4) wxyz of ``segment`` in the common frame (after :meth:`find`)."""
        return _turned(self.rotation[segment], q)

    def apply(self, imu: Mapping[str, tuple]) -> dict[str, tuple] | None:
        """Batch form: the whole recording's samples turned (None: no still pose in it)."""
        series = {s: (np.asarray(t, float), np.asarray(q, float)) for s, (t, q) in imu.items()}
        if not self.find(
            {s: series.get(s, (np.zeros(0), np.zeros((0, 4)))) for s in self.segments}
        ):
            return None
        return {
            s: (t, self.turn(s, q)) if s in self.rotation else (t, q)
            for s, (t, q) in series.items()
        }
