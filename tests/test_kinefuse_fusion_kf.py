"""The ``"kinefuse"`` fusion's own KF/RTS against independent oracles.

filterpy's ``KalmanFilter`` (joint update of both sensors, Joseph form) and ``rts_smoother``;
the closed-form joint Gaussian (smoothed mean and covariance = conditional moments of all states
given all measurements); split-and-resume of the forward filter.
"""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.pipelines._kinefuse_kernels import N_X, kf_segment, rts_smooth
from kinefuse.pipelines.kinefuse_fusion import (
    _H_CAM,
    _H_IMU,
    NoiseParameters,
    _model_matrices,
    _prior,
    _run,
)

filterpy_kalman = pytest.importorskip("filterpy.kalman")

TOL = 1e-9
DT = 1 / 30


def _params(scale=1.0):
    """Per-axis parameters, all error states non-degenerate (σ² > 0: the oracles invert the
    predicted covariance, which the kernel regularises by 1e-15 I for σ² = 0)."""
    a = lambda *v: scale * np.array(v, dtype=float)  # noqa: E731
    return NoiseParameters(q=a(0.1, 0.3, 0.05), r_cam=a(1e-3, 2e-3, 5e-4),
                           r_imu=a(1e-4, 3e-4, 2e-4), var_b=a(2.5e-3, 1e-3, 4e-3),
                           phi_b=a(0.98, 0.9, 0.995) ** (1 / scale), var_c=a(1e-4, 2e-4, 3e-4),
                           phi_c=a(0.8, 0.3, 0.5) ** (1 / scale), motion_gain=a(0, 0, 0))  # fmt: skip


def _series(T=60, seed=0):
    """One joint: camera and chain positions (T, 3) with a camera outage and missing chain rows."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    p = np.stack([np.sin(2 * t), 0.3 * np.cos(3 * t), 0.1 * t], axis=1)
    zc = p + 0.02 * rng.standard_normal((T, 3))
    zi = p + 0.05 + 0.01 * rng.standard_normal((T, 3))
    zc[T // 3 : T // 2] = np.nan  # outage
    zi[[5, T - 9, T - 8]] = np.nan  # chain samples missing
    zc[T - 3, 1] = np.nan  # one axis only
    return zc, zi


def _filterpy_axis(zc, zi, F, Q, r_cam, r_imu, x0, P0):
    """filterpy forward filter + RTS of one axis (first sample: prior, not predicted)."""
    kf = filterpy_kalman.KalmanFilter(dim_x=N_X, dim_z=2)
    kf.x = x0.reshape(-1, 1).copy()
    kf.P = P0.copy()
    kf.F, kf.Q = F, Q
    xs, Ps = [], []
    for t in range(zc.size):
        if t > 0:
            kf.predict()
        rows = [(z, h, r) for z, h, r in ((zc[t], _H_CAM, r_cam), (zi[t], _H_IMU, r_imu))
                if np.isfinite(z)]  # fmt: skip
        if rows:
            z = np.array([[v[0]] for v in rows])
            H = np.array([v[1] for v in rows])
            R = np.diag([v[2] for v in rows])
            kf.update(z, R=R, H=H)
        xs.append(kf.x[:, 0].copy())
        Ps.append(kf.P.copy())
    xs, Ps = np.array(xs), np.array(Ps)
    T = zc.size
    xsm, Psm, _, _ = filterpy_kalman.rts_smoother(xs, Ps, np.broadcast_to(F, (T, 4, 4)),
                                                  np.broadcast_to(Q, (T, 4, 4)))  # fmt: skip
    return xs, Ps, xsm, Psm


def _kernel_filter(zc, zi, F, Q, p, x, P):
    T = zc.shape[0]
    xf = np.empty((3, T, N_X))
    Pf = np.empty((3, T, N_X, N_X))
    kf_segment(np.ascontiguousarray(zc.T), np.ascontiguousarray(zi.T), F, Q, p.r_cam, p.r_imu,
               x, P, False, _H_CAM, _H_IMU, xf, Pf)  # fmt: skip
    return xf, Pf


def _smooth_full(zc, zi, F, Q, p, x, P):
    """The offline path's filter and fixed-interval RTS with the full smoothed covariances
    (``_run`` keeps the position variances only)."""
    xf, Pf = _kernel_filter(zc, zi, F, Q, p, x, P)
    xs, Ps = np.empty_like(xf), np.empty_like(Pf)
    rts_smooth(xf, Pf, F[:, None], Q[:, None], -1, xs, Ps)
    return xs, Ps


def test_filter_and_fixed_interval_rts_equal_filterpy():
    zc, zi = _series()
    p = _params()
    F, Q = _model_matrices(p, DT)
    x0, P0 = _prior(zc[0], zi[0], p)
    xf, Pf = _kernel_filter(zc, zi, F, Q, p, x0.copy(), P0.copy())
    xs, Ps = _smooth_full(zc, zi, F, Q, p, x0.copy(), P0.copy())
    xr, var = _run(zc, zi, p, DT)  # the offline path: filter + fixed-interval RTS
    assert var.shape == (3, zc.shape[0], 1, 1)
    for a in range(3):
        fx, fP, sx, sP = _filterpy_axis(zc[:, a], zi[:, a], F[a], Q[a], p.r_cam[a], p.r_imu[a],
                                        x0[a], P0[a])  # fmt: skip
        np.testing.assert_allclose(xf[a], fx, atol=TOL, rtol=0)
        np.testing.assert_allclose(Pf[a], fP, atol=TOL, rtol=0)
        np.testing.assert_allclose(xs[a], sx, atol=TOL, rtol=0)
        np.testing.assert_allclose(Ps[a], sP, atol=TOL, rtol=0)
        np.testing.assert_allclose(xr[a], sx, atol=TOL, rtol=0)
        np.testing.assert_allclose(var[a, :, 0, 0], sP[:, 0, 0], atol=TOL, rtol=0)


def test_fixed_lag_time_varying_rts_equals_filterpy_on_truncated_series():
    """Fixed-lag L at t = the RTS of the filtered series up to t + L, with time-varying F, Q."""
    zc, zi = _series(T=40, seed=1)
    T, lag = 40, 4
    p1, p2 = _params(), _params(scale=2.0)  # a refit: other parameters from t = 25
    F1, Q1 = _model_matrices(p1, DT)
    F2, Q2 = _model_matrices(p2, DT)
    Fs = np.empty((3, T, 4, 4))
    Qs = np.empty((3, T, 4, 4))
    Fs[:, :25], Qs[:, :25] = F1[:, None], Q1[:, None]
    Fs[:, 25:], Qs[:, 25:] = F2[:, None], Q2[:, None]
    x0, P0 = _prior(zc[0], zi[0], p1)
    xf, Pf = _kernel_filter(zc, zi, F1, Q1, p1, x0, P0)  # the filter itself is tested above
    xs, Ps = np.empty_like(xf), np.empty_like(Pf)
    rts_smooth(xf, Pf, Fs, Qs, lag, xs, Ps)
    for a in range(3):
        for t in range(T):
            e = min(t + lag, T - 1)
            # filterpy's Fs[k] is the transition k -> k + 1, the kernel's F[k] the one into k
            sx, sP, _, _ = filterpy_kalman.rts_smoother(xf[a, : e + 1].copy(), Pf[a, : e + 1].copy(),
                                                        Fs[a, 1 : e + 1], Qs[a, 1 : e + 1])  # fmt: skip
            # the first samples' velocity (m/s) and its variance (tens of (m/s)², from the 1 m²
            # prior) are large: relative 1e-9 there
            np.testing.assert_allclose(xs[a, t], sx[t], atol=TOL, rtol=1e-9)
            np.testing.assert_allclose(Ps[a, t], sP[t], atol=TOL, rtol=1e-9)


def test_rts_equals_closed_form_joint_gaussian():
    """Smoothed mean/cov = E[x_t | all z], Cov[x_t | all z] of the stacked linear-Gaussian model."""
    T = 12
    zc, zi = _series(T=T, seed=2)
    zc[4:7] = np.nan
    p = _params()
    F, Q = _model_matrices(p, DT)
    x0, P0 = _prior(zc[0], zi[0], p)
    xs, Ps = _smooth_full(zc, zi, F, Q, p, x0.copy(), P0.copy())
    n = N_X
    for a in range(3):
        # states x_t = Φ_t x_0 + Σ_{s<=t} Φ_{t-s} w_s: mean and covariance of the stacked (T n,)
        mean = np.concatenate([np.linalg.matrix_power(F[a], t) @ x0[a] for t in range(T)])
        A = np.zeros((T * n, T * n))  # x = A [x_0; w_1; ...; w_{T-1}]
        for t in range(T):
            for s in range(t + 1):
                A[t * n : (t + 1) * n, s * n : (s + 1) * n] = np.linalg.matrix_power(F[a], t - s)
        noise = np.zeros((T * n, T * n))
        noise[:n, :n] = P0[a]
        for s in range(1, T):
            noise[s * n : (s + 1) * n, s * n : (s + 1) * n] = Q[a]
        Sxx = A @ noise @ A.T
        H, z, r = [], [], []
        for t in range(T):
            for zz, h, rr in ((zc[t, a], _H_CAM, p.r_cam[a]), (zi[t, a], _H_IMU, p.r_imu[a])):
                if np.isfinite(zz):
                    row = np.zeros(T * n)
                    row[t * n : (t + 1) * n] = h
                    H.append(row)
                    z.append(zz)
                    r.append(rr)
        H, z = np.array(H), np.array(z)
        Syy = H @ Sxx @ H.T + np.diag(r)
        G = np.linalg.solve(Syy, H @ Sxx).T  # Σ_xy Σ_yy⁻¹
        m_post = mean + G @ (z - H @ mean)
        S_post = Sxx - G @ H @ Sxx
        for t in range(T):
            sl = slice(t * n, (t + 1) * n)
            np.testing.assert_allclose(xs[a, t], m_post[sl], atol=TOL, rtol=0)
            np.testing.assert_allclose(Ps[a, t], S_post[sl, sl], atol=TOL, rtol=0)


def test_filter_split_and_resume_equals_one_run():
    zc, zi = _series(T=50, seed=3)
    p = _params()
    F, Q = _model_matrices(p, DT)
    x0, P0 = _prior(zc[0], zi[0], p)
    xf, Pf = _kernel_filter(zc, zi, F, Q, p, x0.copy(), P0.copy())
    x, P = x0.copy(), P0.copy()
    parts = []
    for t0, t1 in ((0, 17), (17, 18), (18, 50)):
        xo = np.empty((3, t1 - t0, N_X))
        Po = np.empty((3, t1 - t0, N_X, N_X))
        kf_segment(np.ascontiguousarray(zc[t0:t1].T), np.ascontiguousarray(zi[t0:t1].T), F, Q,
                   p.r_cam, p.r_imu, x, P, t0 > 0, _H_CAM, _H_IMU, xo, Po)  # fmt: skip
        parts.append((xo, Po))
    np.testing.assert_array_equal(np.concatenate([q[0] for q in parts], axis=1), xf)
    np.testing.assert_array_equal(np.concatenate([q[1] for q in parts], axis=1), Pf)
    # the last posterior is left in (x, P)
    np.testing.assert_array_equal(x, xf[:, -1])
    np.testing.assert_array_equal(P, Pf[:, -1])
