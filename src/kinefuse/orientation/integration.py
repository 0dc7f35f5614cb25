"""Exact strapdown integration of body-frame angular rate, and its inverse (virtual gyros)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse._validation import as_float_array
from kinefuse.exceptions import InputError

__all__ = ["integrate_gyro", "rate_from_orientation"]


def _dt_vector(dt_s, T: int) -> np.ndarray:
    dt = np.asarray(dt_s, dtype=float)
    if dt.ndim == 0:
        dt = np.full(T, float(dt))
    if dt.shape != (T,):
        raise InputError(f"expected dt_s as a scalar or with shape (T,) = ({T},), got {dt.shape}")
    if not np.all(np.isfinite(dt)) or np.any(dt <= 0):
        raise InputError(f"expected dt_s finite and > 0, got min {dt.min() if dt.size else 'n/a'}")
    return dt


def _unit_quat(q, name: str) -> np.ndarray:
    q = as_float_array(q, name, last_dim=4)
    n = np.linalg.norm(q, axis=-1)
    if not np.all(np.isfinite(q)) or np.any(np.abs(n - 1.0) > 1e-3):
        raise InputError(
            f"expected {name} as finite unit quaternions wxyz, got norms {np.unique(n)[:5]}"
        )
    return q / n[..., None]


def integrate_gyro(q0, gyr_rad_s, dt_s) -> np.ndarray:
    """Integrate body-frame angular rate exactly, one rotation vector per sample.

    Parameters
    ----------
    q0 : array_like, shape (4,)
        Initial orientation ``q_world_from_sensor``, ``wxyz`` unit quaternion.
    gyr_rad_s : array_like, shape (T, 3)
        Angular rate in the sensor (body) frame, rad/s, held constant over each step.
    dt_s : float or array_like, shape (T,)
        Step length(s), s; ``gyr_rad_s[k]`` acts over ``dt_s[k]``.

    Returns
    -------
    q_world_from_sensor : ndarray, shape (T + 1, 4)
        ``q[0] = q0`` and ``q[k + 1] = q[k] ⊗ exp(gyr[k] · dt[k])`` (``wxyz``).

    Notes
    -----
    With the rate constant over a step the update is exact (no small-angle approximation):
    ``R_{k+1} = R_k · Rotation.from_rotvec(ω_k Δt_k)``. :func:`rate_from_orientation` is its exact
    inverse, which makes it the oracle for virtual IMUs built from real motion.
    """
    q = _unit_quat(q0, "q0")
    if q.shape != (4,):
        raise InputError(f"expected q0 with shape (4,), got {q.shape}")
    w = as_float_array(gyr_rad_s, "gyr_rad_s")
    if w.ndim != 2 or w.shape[1] != 3:
        raise InputError(f"expected gyr_rad_s with shape (T, 3), got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise InputError("expected finite gyr_rad_s, got NaN/inf")
    dt = _dt_vector(dt_s, w.shape[0])
    steps = Rotation.from_rotvec(w * dt[:, None])
    out = np.empty((w.shape[0] + 1, 4))
    out[0] = q
    r = Rotation.from_quat(q, scalar_first=True)
    for k in range(w.shape[0]):
        r = r * steps[k]
        out[k + 1] = r.as_quat(scalar_first=True)
    return out


def rate_from_orientation(q_world_from_sensor, dt_s) -> np.ndarray:
    """Body-frame angular rate that takes each orientation to the next (inverse of :func:`integrate_gyro`).

    Parameters
    ----------
    q_world_from_sensor : array_like, shape (T + 1, 4)
        Orientations, ``wxyz``.
    dt_s : float or array_like, shape (T,)
        Step lengths, s.

    Returns
    -------
    gyr_rad_s : ndarray, shape (T, 3)
        ``ω_k = log(q_k⁻¹ ⊗ q_{k+1}) / Δt_k`` in the sensor frame, rad/s (rotation vector of the
        shortest rotation; exact for steps below 180°).
    """
    q = _unit_quat(q_world_from_sensor, "q_world_from_sensor")
    if q.ndim != 2 or q.shape[0] < 2:
        raise InputError(
            f"expected q_world_from_sensor with shape (T + 1, 4), T >= 1, got {q.shape}"
        )
    dt = _dt_vector(dt_s, q.shape[0] - 1)
    r = Rotation.from_quat(q, scalar_first=True)
    return (r[:-1].inv() * r[1:]).as_rotvec() / dt[:, None]
