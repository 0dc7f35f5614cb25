"""Compiled kernels of the ``"kinefuse"`` fusion (:mod:`kinefuse.pipelines.kinefuse_fusion`).

The per-axis state-space model's forward Kalman filter (sequential scalar updates, NaN = not
measured, Joseph form), its RTS smoother (fixed-interval or fixed-lag, time-varying F, Q) and
the lag-k moment sums of the noise fit (:mod:`kinefuse.pipelines.kinefuse_noise`). Tested
against filterpy's ``KalmanFilter`` / ``rts_smoother`` and the closed-form joint Gaussian
(``tests/test_kinefuse_fusion_kf.py``).

Imported only by the fusion modules, themselves imported on first use, so that
:func:`kinefuse._compile.interpret_kernels` can switch to interpreted mode before this module
is imported.
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit

__all__ = ["accumulate_moments", "kf_segment", "rts_smooth"]


@njit
def _scalar_update(x, P, z, h, r):
    """Scalar measurement update in place (no allocation): ``x (n,)``, ``P (n, n)``."""
    n = x.shape[0]
    ph = np.zeros(n)
    for i in range(n):
        for j in range(n):
            ph[i] += P[i, j] * h[j]  # P Hᵀ
    s = r  # S = H P Hᵀ + R   (scalar)
    nu = z  # ν = z − H x
    for i in range(n):
        s += h[i] * ph[i]
        nu -= h[i] * x[i]
    k = ph / s  # K = P Hᵀ S⁻¹
    for i in range(n):
        x[i] += k[i] * nu  # x⁺ = x⁻ + K ν
    # Joseph form (SPEC §1 numerical hygiene), expanded for a scalar update:
    # (I − K H) P (I − K H)ᵀ + K R Kᵀ = P − K (P Hᵀ)ᵀ − (P Hᵀ) Kᵀ + S K Kᵀ   (symmetric)
    for i in range(n):
        for j in range(i, n):
            v = P[i, j] - k[i] * ph[j] - ph[i] * k[j] + s * k[i] * k[j]
            P[i, j] = v
            P[j, i] = v


@njit
def _predict(x, P, F, Q):
    """Prediction in place: ``x ← F x``, ``P ← F P Fᵀ + Q`` (symmetrised)."""
    n = x.shape[0]
    xn = F @ x  # x⁻ = F x
    FP = F @ P
    for i in range(n):
        x[i] = xn[i]
        for j in range(i, n):
            v = Q[i, j]
            for m in range(n):
                v += FP[i, m] * F[j, m]  # P⁻ = F P Fᵀ + Q
            P[i, j] = v
            P[j, i] = v


@njit
def kf_segment(z_cam, z_imu, F, Q, r_cam, r_imu, x, P, predict_first, h_cam, h_imu, x_out, P_out):
    """Forward KF over one segment, batch (B, L), continuing from ``x (B, n)``, ``P (B, n, n)``.

    Each sample has two scalar measurements, either may be NaN (not measured). The first
    sample is predicted from ``(x, P)`` when ``predict_first`` (a continuation), else ``(x, P)``
    is the prior of the first sample. ``x`` and ``P`` are overwritten with the last posterior.
    """
    B, L = z_cam.shape
    for b in range(B):
        xb = x[b].copy()
        Pb = P[b].copy()
        for t in range(L):
            if t > 0 or predict_first:
                _predict(xb, Pb, F[b], Q[b])
            if np.isfinite(z_cam[b, t]):
                _scalar_update(xb, Pb, z_cam[b, t], h_cam, r_cam[b])
            if np.isfinite(z_imu[b, t]):
                _scalar_update(xb, Pb, z_imu[b, t], h_imu, r_imu[b])
            x_out[b, t] = xb
            P_out[b, t] = Pb
        x[b] = xb
        P[b] = Pb


@njit
def _rts_step(xf, Pf, F, Q, xs, Ps):
    """One RTS step back: filtered ``(xf, Pf)`` at t, smoothed ``(xs, Ps)`` at t+1, F, Q: t -> t+1."""
    Pp = F @ Pf @ F.T + Q  # P⁻_{t+1}
    C = np.linalg.solve(Pp + 1e-15 * np.eye(Pp.shape[0]), F @ Pf).T  # C = P̂ Fᵀ (P⁻)⁻¹
    xs = xf + C @ (xs - F @ xf)  # x̃_t = x̂_t + C (x̃_{t+1} − F x̂_t)
    Ps = Pf + C @ (Ps - Pp) @ C.T  # P̃_t = P̂_t + C (P̃_{t+1} − P⁻) Cᵀ
    return xs, 0.5 * (Ps + Ps.T)


@njit
def rts_smooth(xf, Pf, F, Q, lag, x_out, P_out):
    """RTS over a batch (B, T): fixed-interval (``lag < 0``) or fixed-lag with ``lag`` samples.

    ``F[b, t], Q[b, t]`` are the transition into sample t (from t − 1); time-varying, so the
    causal mode's piecewise-constant parameters are smoothed with the model that was filtered.
    """
    B, T = xf.shape[0], xf.shape[1]
    for b in range(B):
        if lag < 0:
            xs = xf[b, T - 1].copy()
            Ps = Pf[b, T - 1].copy()
            x_out[b, T - 1] = xs
            P_out[b, T - 1] = Ps
            for t in range(T - 2, -1, -1):
                xs, Ps = _rts_step(xf[b, t], Pf[b, t], F[b, t + 1], Q[b, t + 1], xs, Ps)
                x_out[b, t] = xs
                P_out[b, t] = Ps
        else:
            for t in range(T):
                e = min(t + lag, T - 1)
                xs = xf[b, e].copy()
                Ps = Pf[b, e].copy()
                for s in range(e - 1, t - 1, -1):
                    xs, Ps = _rts_step(xf[b, s], Pf[b, s], F[b, s + 1], Q[b, s + 1], xs, Ps)
                x_out[b, t] = xs
                P_out[b, t] = Ps


@njit
def accumulate_moments(zc, zi, ok, t0, t1, S, D):
    """Add the lag-k products of the pairs ``(t − k, t)``, t in [t0, t1), to S and D (in place).

    ``S (K, 4, 3)``: per lag k = 1..K and axis: number of pairs, Σ Δzc², Σ Δzc Δzi, Σ Δzi².
    ``D (3, 3)``: per axis: number of triples, Σ Δ²zc Δ²zi, Σ Δ²zi² (second differences).
    Only samples with ``ok`` enter; ``zc, zi (T, 3)``.
    """
    K = S.shape[0]
    for t in range(t0, t1):
        if not ok[t]:
            continue
        for k in range(1, K + 1):
            if t - k < 0:
                break
            if ok[t - k]:
                for a in range(3):
                    dc = zc[t, a] - zc[t - k, a]
                    di = zi[t, a] - zi[t - k, a]
                    S[k - 1, 0, a] += 1.0
                    S[k - 1, 1, a] += dc * dc
                    S[k - 1, 2, a] += dc * di
                    S[k - 1, 3, a] += di * di
        if t >= 2 and ok[t - 1] and ok[t - 2]:
            for a in range(3):
                d2c = zc[t, a] - 2.0 * zc[t - 1, a] + zc[t - 2, a]
                d2i = zi[t, a] - 2.0 * zi[t - 1, a] + zi[t - 2, a]
                D[0, a] += 1.0
                D[1, a] += d2c * d2i
                D[2, a] += d2i * d2i
