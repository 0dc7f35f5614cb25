"""What every reader does before it returns: the metadata dict, the zero rule, unit checks.

Private module. :func:`finish_recording` is the last step of every reader: it builds the
:class:`~kinefuse.io.recording.Recording` and runs :func:`check_units` on it.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from kinefuse.conventions import GRAVITY_M_S2
from kinefuse.exceptions import UnitWarning
from kinefuse.io.recording import Recording

__all__ = [
    "DEG2RAD",
    "G",
    "ZERO_RULE",
    "check_units",
    "finish_recording",
    "make_metadata",
    "zero_is_missing",
    "zero_samples",
]

G = GRAVITY_M_S2
DEG2RAD = math.pi / 180.0


#: The one rule every position reader applies (documented in ``docs/formats.md``).
ZERO_RULE = "a point whose three coordinates are all exactly 0 is missing (not tracked)"


def zero_is_missing(position: np.ndarray) -> np.ndarray:
    """Mask of samples encoded as "not tracked" by all-zero coordinates.

    TRC and C3D writers (and Kinect v1, read by :mod:`kinefuse.io.utd_mhad`) write an untracked
    marker as ``0, 0, 0``; a real marker exactly at the origin to the file's resolution is
    unlikely enough that every kinefuse position reader treats an all-zero point as missing
    (:data:`ZERO_RULE`); readers take ``zero_is_missing=False`` to keep such samples.

    Parameters
    ----------
    position : ndarray, shape (..., 3)

    Returns
    -------
    ndarray of bool, shape (...)
        True where all three coordinates are exactly 0.
    """
    return np.all(np.asarray(position) == 0.0, axis=-1)


def zero_samples(position: np.ndarray, enabled: bool = True) -> tuple[np.ndarray, int]:
    """(:func:`zero_is_missing` mask, its count) when ``enabled``, else (all False, 0)."""
    if not enabled:
        return np.zeros(np.shape(position)[:-1], dtype=bool), 0
    zero = zero_is_missing(position)
    return zero, int(zero.sum())


def make_metadata(path, fmt: str, *, subject=None, units_converted=(), **extra) -> dict:
    """The standard metadata dict: subject, source, format, units_converted, plus reader notes."""
    md = {
        "subject": subject,
        "source": str(path),
        "format": fmt,
        "units_converted": list(units_converted),
    }
    md.update(extra)
    return md


def _finite_norm(a: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(a, axis=-1)
    return n[np.isfinite(n)]


def check_units(recording, *, where: str = "", stacklevel: int = 3) -> list[str]:
    """Warn (:class:`~kinefuse.exceptions.UnitWarning`) when magnitudes suggest wrong units.

    Rules (heuristics, documented in ``docs/formats.md``):

    * accelerometer: median ``|acc|`` between 0.5 and 2.0 -> looks like g, not m/s²;
    * gyroscope: 99th percentile of ``|gyr|`` above 35 rad/s (2000 deg/s) -> looks like deg/s;
    * joint positions: median distance of the joints from their per-frame centroid (0.2-0.6 m
      for a body) above 100 -> looks like millimetres, above 10 -> looks like centimetres (with
      one joint: median ``|p|`` above 100) -> looks like millimetres.

    Returns
    -------
    list of str
        The warning messages issued.
    """
    msgs = []
    prefix = f"{where}: " if where else ""
    for key, s in recording.imu.items():
        if s.acc_m_s2 is not None:
            n = _finite_norm(s.acc_m_s2)
            if n.size and 0.5 < float(np.median(n)) < 2.0:
                msgs.append(
                    f"{prefix}IMU {key!r}: median |acc| = {np.median(n):.3g}, which looks like g, not m/s^2 "
                    "(multiply by 9.80665 or declare the unit)"
                )
        if s.gyr_rad_s is not None:
            n = _finite_norm(s.gyr_rad_s)
            if n.size and float(np.percentile(n, 99)) > 35.0:
                msgs.append(
                    f"{prefix}IMU {key!r}: 99th percentile |gyr| = {np.percentile(n, 99):.3g} rad/s, which looks "
                    "like deg/s (multiply by pi/180 or declare the unit)"
                )
    for role in ("vision", "reference"):
        js = getattr(recording, role)
        if js is None or len(js) == 0:
            continue
        p = np.where(js.available[..., None], js.position_m, np.nan)
        if p.shape[1] >= 2:
            ok = np.isfinite(p)
            n = ok.sum(axis=1, keepdims=True)
            c = np.where(ok, p, 0.0).sum(axis=1, keepdims=True) / np.where(n > 0, n, 1)
            d = np.linalg.norm(p - c, axis=-1)
            d = d[np.isfinite(d)]
            if d.size and float(np.median(d)) > 10.0:
                unit, div = (
                    ("millimetres", 1000) if float(np.median(d)) > 100.0 else ("centimetres", 100)
                )
                msgs.append(
                    f"{prefix}{role} joints: median joint spread {np.median(d):.3g} 'm', which looks like "
                    f"{unit} (divide by {div} or declare the unit)"
                )
        else:
            n = _finite_norm(p.reshape(-1, 3))
            if n.size and float(np.median(n)) > 100.0:
                msgs.append(
                    f"{prefix}{role} position: median |p| = {np.median(n):.3g} 'm', which looks like millimetres"
                )
    for m in msgs:
        warnings.warn(m, UnitWarning, stacklevel=stacklevel)
    return msgs


def finish_recording(path, metadata: dict, **streams) -> Recording:
    """The reader's result: ``Recording(**streams, metadata=metadata)``, unit-checked.

    ``streams`` are the Recording's ``imu=``, ``vision=``, ``reference=`` (those the format has);
    :func:`check_units` warns, naming ``path``, when magnitudes suggest wrong units.
    """
    rec = Recording(**streams, metadata=metadata)
    check_units(rec, where=str(path), stacklevel=4)
    return rec
