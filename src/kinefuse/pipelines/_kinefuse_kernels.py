"""Compiled kernels of the ``"kinefuse"`` fusion (:mod:`kinefuse.pipelines.kinefuse_fusion`).

The per-axis state-space model's forward Kalman filter (sequential scalar updates, NaN = not
measured, Joseph form), its RTS smoother (fixed-interval or fixed-lag, time-varying F, Q),
the lag-k moment sums of the noise fit (:mod:`kinefuse.pipelines.kinefuse_noise`) and the outage
bridge's prediction errors per horizon (:mod:`kinefuse.pipelines.offset_bridge`). Tested
against filterpy's ``KalmanFilter`` / ``rts_smoother`` and the closed-form joint Gaussian
(``tests/test_kinefuse_fusion_kf.py``).

Imported only by the fusion modules, themselves imported on first use, so that
:func:`kinefuse._compile.interpret_kernels` can switch to interpreted mode before this module
is imported.
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels_axis import load_filtered

__all__ = [
    "accumulate_moments",
    "bridge_scores",
    "ewma_hold",
    "horizon_sse",
    "kf_segment",
    "rts_smooth",
]


#: States per axis of the model, ``[p, v, b, c]`` (:mod:`kinefuse.pipelines.kinefuse_fusion`):
#: the kernels' matrix sizes, fixed so that the compiler unrolls their loops.
N_X = 4


@njit_inline
def _scalar_update(x, P, z, h, r, ph, n):
    """Scalar measurement update in place: ``x (n,)``, ``P (n, n)``; ``ph (n,)`` scratch."""
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


@njit_inline
def _predict(x, P, F, Q, b, w, W, n):
    """Prediction in place: ``x ← F x``, ``P ← F P Fᵀ + Q`` (symmetrised) with ``F[b], Q[b]``;
    ``w (n,)``, ``W (n, n)`` scratch. (Whole arrays and an index, no views: a view made per
    sample costs numba reference-count calls.)"""
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
    """Forward KF over one segment, batch (B, L), continuing from ``x (B, n)``, ``P (B, n, n)``
    (``n =`` :data:`N_X`).

    Each sample has two scalar measurements, either may be NaN (not measured). The first
    sample is predicted from ``(x, P)`` when ``predict_first`` (a continuation), else ``(x, P)``
    is the prior of the first sample. ``x`` and ``P`` are overwritten with the last posterior.
    No allocation and no array view per sample.
    """
    n = N_X  # a compile-time constant: the small matrix loops are unrolled
    if x.shape[1] != n:
        raise ValueError("kf_segment: expected x with shape (B, N_X)")
    B, L = z_cam.shape
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
                _predict(xb, Pb, F, Q, b, w, W, n)
            zc = z_cam[b, t]
            zi = z_imu[b, t]
            if np.isfinite(zc):
                _scalar_update(xb, Pb, zc, h_cam, r_cam[b], w, n)
            if np.isfinite(zi):
                _scalar_update(xb, Pb, zi, h_imu, r_imu[b], w, n)
            for i in range(n):
                x_out[b, t, i] = xb[i]
                for j in range(n):
                    P_out[b, t, i, j] = Pb[i, j]
        for i in range(n):
            x[b, i] = xb[i]
            for j in range(n):
                P[b, i, j] = Pb[i, j]


@njit_inline
def _solve_into(A, B, X, n):
    """``X = A⁻¹ B`` by Gaussian elimination with partial pivoting (as LAPACK's ``gesv``), in
    place: ``A`` is overwritten by its factors. No allocation."""
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


@njit_inline
def _rts_step(xf, Pf, F, Q, b, t, u, xs, Ps, FP, Pp, A, CT, d, n):
    """One RTS step back, in place on ``xs, Ps``: filtered ``(xf[b, t], Pf[b, t])``, smoothed
    ``(xs, Ps)`` at t+1 in, at t out; ``F[b, u], Q[b, u]``: t -> t+1 (u = t + 1, or 0 for a
    constant model). ``FP, Pp, A, CT (n, n)``, ``d (n,)`` scratch (no allocation, no view)."""
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
    _solve_into(A, FP, CT, n)  # Cᵀ = (P⁻)⁻¹ F P̂,  C = P̂ Fᵀ (P⁻)⁻¹
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


@njit_inline
def _store(x_out, P_out, b, t, xs, Ps, n):
    """``x_out[b, t] = xs`` and the leading ``k × k`` block of ``Ps`` into ``P_out (B, T, k, k)``."""
    k = P_out.shape[2]
    for i in range(n):
        x_out[b, t, i] = xs[i]
    for i in range(k):
        for j in range(k):
            P_out[b, t, i, j] = Ps[i, j]


@njit
def rts_smooth(xf, Pf, F, Q, lag, x_out, P_out):
    """RTS over a batch (B, T): fixed-interval (``lag < 0``) or fixed-lag with ``lag`` samples.

    ``F[b, t], Q[b, t]`` are the transition into sample t (from t − 1); time-varying, so the
    causal mode's piecewise-constant parameters are smoothed with the model that was filtered;
    ``F, Q`` of shape ``(B, 1, n, n)``: the same model at every t. No allocation and no array
    view per sample. ``P_out (B, T, k, k)``: the leading k×k block of each smoothed covariance
    (``k = n``: all of it; ``k = 1``: the position variance, when nothing else is read).
    """
    n = N_X  # a compile-time constant (as in kf_segment)
    if xf.shape[2] != n:
        raise ValueError("rts_smooth: expected xf with shape (B, T, N_X)")
    B, T = xf.shape[:2]
    step = 1 if F.shape[1] > 1 else 0
    xs = np.empty(n)
    Ps = np.empty((n, n))
    FP, Pp, A, CT = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    d = np.empty(n)
    for b in range(B):
        if lag < 0:
            load_filtered(xf, Pf, b, T - 1, xs, Ps, n)
            _store(x_out, P_out, b, T - 1, xs, Ps, n)
            for t in range(T - 2, -1, -1):
                _rts_step(xf, Pf, F, Q, b, t, (t + 1) * step, xs, Ps, FP, Pp, A, CT, d, n)
                _store(x_out, P_out, b, t, xs, Ps, n)
        else:
            for t in range(T):
                e = min(t + lag, T - 1)
                load_filtered(xf, Pf, b, e, xs, Ps, n)
                for s in range(e - 1, t - 1, -1):
                    _rts_step(xf, Pf, F, Q, b, s, (s + 1) * step, xs, Ps, FP, Pp, A, CT, d, n)
                _store(x_out, P_out, b, t, xs, Ps, n)


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


@njit
def horizon_sse(e, eb, w, lo, a, sse, n):
    """Squared prediction errors of an outage bridge per horizon (in place).

    For h = 1..H (``H = sse.shape[0]``) and the pairs ``(s, s + h)``, ``lo <= s``,
    ``s + h < a``: ``r = e[s + h] − w[h − 1] ē[s]``; pairs with a non-finite component of r
    are skipped. ``sse (H, 3)``: per axis Σ r²; ``n (H,)``: the pairs counted. ``e, eb (T, 3)``.
    """
    H = sse.shape[0]
    for k in range(H):
        h = k + 1
        wk = w[k]
        s0 = s1 = s2 = 0.0
        c = 0
        for s in range(lo, a - h):
            r0 = e[s + h, 0] - wk * eb[s, 0]
            r1 = e[s + h, 1] - wk * eb[s, 1]
            r2 = e[s + h, 2] - wk * eb[s, 2]
            if np.isfinite(r0) and np.isfinite(r1) and np.isfinite(r2):
                s0 += r0 * r0
                s1 += r1 * r1
                s2 += r2 * r2
                c += 1
        sse[k, 0], sse[k, 1], sse[k, 2] = s0, s1, s2
        n[k] = c


@njit
def bridge_scores(e0, eb0, okb, seen, H, phis, at, sse, n):
    """Cumulative scores of the bridge candidates of one smoothed offset (in place).

    ``e0, eb0 (T, 3)``: the camera-chain offset and its smoothed value, 0 where missing;
    ``okb (T,)`` where the smoothed value exists; ``seen (T,)`` camera-seen; ``phis (D,)`` the
    decay factors per sample. A pair ``(s, s + h)``, ``1 <= h <= H``, counts at ``t = s + h``
    when ``seen[t]`` and ``okb[s]``; its error is ``|e_t − φ^h ē_s|²``. At the times ``at (m,)``
    (increasing): ``sse (D + 1, m)`` the cumulative errors of the chain alone (row 0: the
    offset dropped) and of each decay, ``n (m,)`` the cumulative pair count.

    The lagged sums ``S_t = Σ_{h=1..H} φ^h x_{t−h}`` are updated in O(1) per sample,
    ``S_t = φ S_{t−1} + φ x_{t−1} − φ^{H+1} x_{t−1−H}``.
    """
    T = e0.shape[0]
    D = phis.shape[0]
    Sb = np.zeros((D, 3))
    Sc = np.zeros(D)
    tail = np.empty(D)
    tail2 = np.empty(D)
    for d in range(D):
        tail[d] = phis[d] ** (H + 1)
        tail2[d] = tail[d] * tail[d]
    acc = np.zeros(D + 1)
    cnt = 0.0
    n_acc = 0.0
    k = 0
    m = at.shape[0]
    for t in range(T):
        if t >= 1:
            x0, x1, x2 = eb0[t - 1, 0], eb0[t - 1, 1], eb0[t - 1, 2]
            xc = x0 * x0 + x1 * x1 + x2 * x2
            cnt += 1.0 if okb[t - 1] else 0.0
            o0 = o1 = o2 = oc = 0.0
            if t - 1 - H >= 0:
                o0, o1, o2 = eb0[t - 1 - H, 0], eb0[t - 1 - H, 1], eb0[t - 1 - H, 2]
                oc = o0 * o0 + o1 * o1 + o2 * o2
                cnt -= 1.0 if okb[t - 1 - H] else 0.0
            for d in range(D):
                p = phis[d]
                Sb[d, 0] = p * (Sb[d, 0] + x0) - tail[d] * o0
                Sb[d, 1] = p * (Sb[d, 1] + x1) - tail[d] * o1
                Sb[d, 2] = p * (Sb[d, 2] + x2) - tail[d] * o2
                Sc[d] = p * p * (Sc[d] + xc) - tail2[d] * oc
        e_0, e_1, e_2 = e0[t, 0], e0[t, 1], e0[t, 2]
        a_t = (e_0 * e_0 + e_1 * e_1 + e_2 * e_2) * cnt
        s_t = 1.0 if seen[t] else 0.0
        n_acc += s_t * cnt
        acc[0] += a_t
        for d in range(D):
            b = e_0 * Sb[d, 0] + e_1 * Sb[d, 1] + e_2 * Sb[d, 2]
            acc[d + 1] += a_t - 2.0 * b + s_t * Sc[d]
        while k < m and at[k] == t:
            for d in range(D + 1):
                sse[d, k] = acc[d]
            n[k] = n_acc
            k += 1


@njit
def ewma_hold(e, seen, a, out):
    """Causal EWMA over the ``seen`` rows of ``e (T, 3)``, held through the others (in place).

    ``m ← a x + (1 − a) m`` at each seen row x, ``m = x`` at the first; ``out (T, 3)`` keeps
    its values (NaN) before the first seen row.
    """
    T = e.shape[0]
    started = False
    m0 = m1 = m2 = 0.0
    for t in range(T):
        if seen[t]:
            if started:
                m0 = a * e[t, 0] + (1.0 - a) * m0
                m1 = a * e[t, 1] + (1.0 - a) * m1
                m2 = a * e[t, 2] + (1.0 - a) * m2
            else:
                m0, m1, m2 = e[t, 0], e[t, 1], e[t, 2]
                started = True
        if started:
            out[t, 0], out[t, 1], out[t, 2] = m0, m1, m2
