"""Random processes of the virtual sensors: Gauss-Markov sequences, the per-axis sensor error
model, random matrices of bounded norm and magnetic disturbance episodes.

Every function draws from the generator it is given, in a fixed order (the draw order is part
of the simulation's reproducibility: the same seed gives the same recording).
"""

from __future__ import annotations

import math

import numpy as np

from kinefuse.sim.imu_config import ImuConfig

__all__ = [
    "disturbance_episodes",
    "gauss_markov",
    "norm_bounded_matrix",
    "sensor_errors",
    "window_weight",
]


def gauss_markov(
    rng: np.random.Generator, n: int, dim: int, std: float, tau_s: float, dt: float
) -> np.ndarray:
    """Stationary first-order Gauss-Markov sequences, shape (n, dim)."""
    w = rng.standard_normal((n, dim))
    if std == 0.0:
        return np.zeros((n, dim))
    phi = math.exp(-dt / tau_s) if tau_s > 0 else 0.0
    out = np.empty((n, dim))
    out[0] = std * w[0]
    c = std * math.sqrt(1.0 - phi * phi)
    for k in range(1, n):
        out[k] = phi * out[k - 1] + c * w[k]
    return out


def sensor_errors(rng, y_true, *, scale, cross, bias0, bias_gm, tau_s, rw, noise, dt):
    """Apply the per-sensor error model to ``y_true`` (n, 3); returns (y, parameters)."""
    n = y_true.shape[0]
    s = rng.uniform(-1.0, 1.0, 3) * scale
    X = rng.uniform(-1.0, 1.0, (3, 3)) * cross
    np.fill_diagonal(X, 0.0)
    M = (np.eye(3) + X) @ np.diag(1.0 + s)
    b0 = rng.uniform(-1.0, 1.0, 3) * bias0
    b_gm = gauss_markov(rng, n, 3, bias_gm, tau_s, dt)
    b_rw = np.cumsum(rng.standard_normal((n, 3)) * (rw * math.sqrt(dt)), axis=0)
    white = rng.standard_normal((n, 3)) * noise
    y = y_true @ M.T + b0 + b_gm + b_rw + white
    return y, {"sensitivity_matrix": M, "turn_on_bias": b0, "bias": b0 + b_gm + b_rw}


def norm_bounded_matrix(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Random ``rows x cols`` matrix with singular values uniform in [0.5, 1] (spectral norm <= 1)."""
    u, _, vt = np.linalg.svd(rng.standard_normal((rows, cols)), full_matrices=False)
    return (u * rng.uniform(0.5, 1.0, min(rows, cols))) @ vt


def disturbance_episodes(
    rng: np.random.Generator, t: np.ndarray, config: ImuConfig
) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """World-frame disturbance field (n, 3), µT, and the episodes ``(start_s, end_s)``."""
    n = t.size
    span_min = (t[-1] - t[0]) / 60.0
    k = int(rng.poisson(config.mag_disturbance_per_min * span_min))
    starts = np.sort(rng.uniform(t[0], t[-1], k))
    durations = config.mag_disturbance_duration_s * rng.uniform(0.5, 1.5, k)
    dirs = rng.standard_normal((k, 3))
    mags = config.mag_disturbance_ut * rng.uniform(0.25, 1.0, k)
    field = np.zeros((n, 3))
    episodes = []
    ramp = 1.0
    for t0, d, u, m in zip(starts, durations, dirs, mags, strict=True):
        t1 = t0 + d
        field += window_weight(t, t0, t1, ramp)[:, None] * (m * u / np.linalg.norm(u))
        episodes.append((float(t0), float(t1)))
    return field, episodes


def window_weight(t: np.ndarray, t0: float, t1: float, ramp: float = 1.0) -> np.ndarray:
    """Weight (n,) that is 1 inside ``[t0, t1]`` and 0 outside, with raised-cosine ramps of
    ``ramp`` seconds inside both ends (a disturbance that appears and goes by hand)."""
    w = np.clip(np.minimum(t - t0, t1 - t) / ramp, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * w)
