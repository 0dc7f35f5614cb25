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
def _scalar_update(x, P, z, h, r, ph):
    """Scalar measurement update in place: ``x (n,)``, ``P (n, n)``; ``ph (n,)`` scratch."""
    n = x.shape[0]
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += P[i, j] * h[j]  # P Hᵀ
        ph[i] = acc
    s = r  # S = H P Hᵀ + R   (scalar)
    nu = z  # ν = z − H x
    for i in range(n):
        s += h[i] * ph[i]
        nu -= h[i] * x[i]
    for i in range(n):
        x[i] += (ph[i] / s) * nu  # x⁺ = x⁻ + K ν,  K = P Hᵀ S⁻¹
    # Joseph form (SPEC §1 numerical hygiene), expanded for a scalar update:
    # (I − K H) P (I − K H)ᵀ + K R Kᵀ = P − K (P Hᵀ)ᵀ − (P Hᵀ) Kᵀ + S K Kᵀ   (symmetric)
    for i in range(n):
        ki = ph[i] / s
        for j in range(i, n):
            kj = ph[j] / s
            v = P[i, j] - ki * ph[j] - ph[i] * kj + s * ki * kj
            P[i, j] = v
            P[j, i] = v


@njit
def _predict(x, P, F, Q, b, w, W):
    """Prediction in place: ``x ← F x``, ``P ← F P Fᵀ + Q`` (symmetrised) with ``F[b], Q[b]``;
    ``w (n,)``, ``W (n, n)`` scratch. (Whole arrays and an index, no views: a view made per
    sample costs numba reference-count calls.)"""
    n = x.shape[0]
    for i in range(n):
        acc = 0.0
        for m in range(n):
            acc += F[b, i, m] * x[m]  # x⁻ = F x
        w[i] = acc
        for j in range(n):
            acc = 0.0
            for m in range(n):
                acc += F[b, i, m] * P[m, j]  # F P
            W[i, j] = acc
    for i in range(n):
        x[i] = w[i]
        for j in range(i, n):
            v = Q[b, i, j]
            for m in range(n):
                v += W[i, m] * F[b, j, m]  # P⁻ = F P Fᵀ + Q
            P[i, j] = v
            P[j, i] = v


@njit
def kf_segment(z_cam, z_imu, F, Q, r_cam, r_imu, x, P, predict_first, h_cam, h_imu, x_out, P_out):
    """Forward KF over one segment, batch (B, L), continuing from ``x (B, n)``, ``P (B, n, n)``.

    Each sample has two scalar measurements, either may be NaN (not measured). The first
    sample is predicted from ``(x, P)`` when ``predict_first`` (a continuation), else ``(x, P)``
    is the prior of the first sample. ``x`` and ``P`` are overwritten with the last posterior.
    No allocation and no array view per sample.
    """
    B, L = z_cam.shape
    n = x.shape[1]
    xb = np.empty(n)
    Pb = np.empty((n, n))
    w = np.empty(n)
    W = np.empty((n, n))
    for b in range(B):
        for i in range(n):
            xb[i] = x[b, i]
            for j in range(n):
                Pb[i, j] = P[b, i, j]
        for t in range(L):
            if t > 0 or predict_first:
                _predict(xb, Pb, F, Q, b, w, W)
            zc = z_cam[b, t]
            zi = z_imu[b, t]
            if np.isfinite(zc):
                _scalar_update(xb, Pb, zc, h_cam, r_cam[b], w)
            if np.isfinite(zi):
                _scalar_update(xb, Pb, zi, h_imu, r_imu[b], w)
            for i in range(n):
                x_out[b, t, i] = xb[i]
                for j in range(n):
                    P_out[b, t, i, j] = Pb[i, j]
        for i in range(n):
            x[b, i] = xb[i]
            for j in range(n):
                P[b, i, j] = Pb[i, j]


@njit
def _solve_into(A, B, X):
    """``X = A⁻¹ B`` by Gaussian elimination with partial pivoting (as LAPACK's ``gesv``), in
    place: ``A`` is overwritten by its factors. No allocation."""
    n = A.shape[0]
    X[:, :] = B
    for k in range(n):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, n):
            a = abs(A[i, k])
            p = i if a > big else p
            big = a if a > big else big
        for j in range(n):  # (p == k: swaps a row with itself)
            A[k, j], A[p, j] = A[p, j], A[k, j]
            X[k, j], X[p, j] = X[p, j], X[k, j]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k + 1, n):
                A[i, j] -= f * A[k, j]
            for j in range(n):
                X[i, j] -= f * X[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(n):
            v = X[k, j]
            for m in range(k + 1, n):
                v -= A[k, m] * X[m, j]
            X[k, j] = v / A[k, k]


@njit
def _rts_step(xf, Pf, F, Q, b, t, xs, Ps, FP, Pp, A, CT, d):
    """One RTS step back, in place on ``xs, Ps``: filtered ``(xf[b, t], Pf[b, t])``, smoothed
    ``(xs, Ps)`` at t+1 in, at t out; ``F[b, t + 1], Q[b, t + 1]``: t -> t+1. ``FP, Pp, A, CT
    (n, n)``, ``d (n,)`` scratch (no allocation, no view)."""
    n = xs.shape[0]
    u = t + 1
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for m in range(n):
                acc += F[b, u, i, m] * Pf[b, t, m, j]
            FP[i, j] = acc  # M = F P̂
    for i in range(n):
        for j in range(n):
            v = Q[b, u, i, j]
            for m in range(n):
                v += FP[i, m] * F[b, u, j, m]
            Pp[i, j] = v  # P⁻_{t+1} = F P̂ Fᵀ + Q
            A[i, j] = v + (1e-15 if i == j else 0.0)
    _solve_into(A, FP, CT)  # Cᵀ = (P⁻)⁻¹ F P̂,  C = P̂ Fᵀ (P⁻)⁻¹
    for i in range(n):  # x̃_{t+1} − F x̂_t
        acc = 0.0
        for m in range(n):
            acc += F[b, u, i, m] * xf[b, t, m]
        d[i] = xs[i] - acc
    for i in range(n):  # x̃_t = x̂_t + C (x̃_{t+1} − F x̂_t)
        acc = 0.0
        for m in range(n):
            acc += CT[m, i] * d[m]
        xs[i] = xf[b, t, i] + acc
    for i in range(n):  # (P̃_{t+1} − P⁻) Cᵀ
        for j in range(n):
            acc = 0.0
            for m in range(n):
                acc += (Ps[i, m] - Pp[i, m]) * CT[m, j]
            A[i, j] = acc
    for i in range(n):  # P̂_t + C (P̃_{t+1} − P⁻) Cᵀ
        for j in range(n):
            acc = 0.0
            for m in range(n):
                acc += CT[m, i] * A[m, j]
            FP[i, j] = Pf[b, t, i, j] + acc
    for i in range(n):  # P̃_t, symmetrised
        for j in range(n):
            Ps[i, j] = 0.5 * (FP[i, j] + FP[j, i])


@njit
def _store(x_out, P_out, b, t, xs, Ps):
    n = xs.shape[0]
    for i in range(n):
        x_out[b, t, i] = xs[i]
        for j in range(n):
            P_out[b, t, i, j] = Ps[i, j]


@njit
def _load(xf, Pf, b, t, xs, Ps):
    n = xs.shape[0]
    for i in range(n):
        xs[i] = xf[b, t, i]
        for j in range(n):
            Ps[i, j] = Pf[b, t, i, j]


@njit
def rts_smooth(xf, Pf, F, Q, lag, x_out, P_out):
    """RTS over a batch (B, T): fixed-interval (``lag < 0``) or fixed-lag with ``lag`` samples.

    ``F[b, t], Q[b, t]`` are the transition into sample t (from t − 1); time-varying, so the
    causal mode's piecewise-constant parameters are smoothed with the model that was filtered.
    No allocation and no array view per sample.
    """
    B, T, n = xf.shape
    xs = np.empty(n)
    Ps = np.empty((n, n))
    FP, Pp, A, CT = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    d = np.empty(n)
    for b in range(B):
        if lag < 0:
            _load(xf, Pf, b, T - 1, xs, Ps)
            _store(x_out, P_out, b, T - 1, xs, Ps)
            for t in range(T - 2, -1, -1):
                _rts_step(xf, Pf, F, Q, b, t, xs, Ps, FP, Pp, A, CT, d)
                _store(x_out, P_out, b, t, xs, Ps)
        else:
            for t in range(T):
                e = min(t + lag, T - 1)
                _load(xf, Pf, b, e, xs, Ps)
                for s in range(e - 1, t - 1, -1):
                    _rts_step(xf, Pf, F, Q, b, s, xs, Ps, FP, Pp, A, CT, d)
                _store(x_out, P_out, b, t, xs, Ps)


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
