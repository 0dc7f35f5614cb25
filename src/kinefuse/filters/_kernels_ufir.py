"""Iterative UFIR kernels (numba): dense reference, per-axis form, precomputed taps.

Paper A §3.3 (Eqs. 24-28, Algorithm 3) as corrected by SPEC §6.2-§6.3. Textbook symbols, no
validation. Time-major ring buffers: the measurement of time ``t`` lives in slot ``t % N``; a
row holding any NaN is a missing sample (the whole row is stored as NaN).

Three ways to get the same horizon estimate:

* :func:`ufir_horizon` — the literal iterative UFIR on one horizon (batch or stored init,
  generalised batch init over the first K valid samples, missing samples predicted through).
  Called with the full ``(n_x, n_x)`` matrices it is the dense reference; called per axis with
  the 2×2 blocks (same K) it is the exact per-axis form (SPEC §1 "Per-axis decoupling").
* :func:`ufir_taps` — with no missing sample in the horizon, constant dt and batch init the
  estimate is a fixed linear function of the last N measurements (SPEC §6.3 "Fast exact forms"):
  ``x̂_k = Σ_i W_i z_{k-N+1+i}`` and ``P̂_k = P_full`` (data independent). The taps ``W`` and
  ``P_full`` are precomputed once by :func:`ufir_gains` running the same recursion on the
  linear map instead of on data.
* :func:`fir_estimate` — dispatcher used by the UFIR and the integrated filter.
"""

from __future__ import annotations

import numpy as np

# njit_inline: inlined at the numba IR level into its callers, so no per-call reference counting
# of the array arguments (see :mod:`._kernels_common`)
from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels import kf_predict, kf_update, symmetrize
from kinefuse.filters._kernels_blocks import _cov_step
from kinefuse.filters._kernels_linalg import chol_shifted

#: Relative pivot below which ``CᵀC`` is declared rank deficient (SPEC §6.3).
RANK_TOL = 1e-10


def ufir_gains(F, Finv, H, Q, R, N, K):
    """Precompute the FIR taps and covariance of a full, all-valid horizon (NumPy, once).

    Parameters
    ----------
    F, Finv : ndarray, shape (n_x, n_x)
        Transition matrix and its inverse.
    H : ndarray, shape (n_z, n_x)
    Q : ndarray, shape (n_x, n_x)
    R : ndarray, shape (n_z, n_z)
    N : int
        Horizon, samples.
    K : int
        Batch-initialisation length (``n_x``).

    Returns
    -------
    W : ndarray, shape (n_x, N, n_z)
        ``x̂_k = Σ_i W[:, i, :] @ z_{k-N+1+i}`` (exact linear map of the batch-initialised
        iterative UFIR, SPEC §6.3 "Fast exact forms").
    P_full : ndarray, shape (n_x, n_x)
        The (data-independent) Joseph covariance at the end of the horizon.
    """
    n_x, n_z = F.shape[0], H.shape[0]
    # SPEC §6.3 batch init on samples 0..K-1 of the horizon (s = K-1): C = [H F^-(K-1); ...; H]
    C = np.vstack([H @ np.linalg.matrix_power(Finv, K - 1 - i) for i in range(K)])
    Om = C.T @ C  # information form of G_s⁻¹ = CᵀC
    G = np.linalg.inv(Om)
    W = np.zeros((n_x, N * n_z))
    W[:, : K * n_z] = G @ C.T  # x̂_s = G_s Cᵀ Z
    P = G @ C.T @ np.kron(np.eye(K), R) @ C @ G  # P_s = G_s Cᵀ (I⊗R) C G_s
    P = 0.5 * (P + P.T)
    I = np.eye(n_x)
    for l in range(K, N):
        W = F @ W  # Eq. 24: x⁻ = F x
        P = F @ P @ F.T + Q  # Eq. 25
        Om = Finv.T @ Om @ Finv + H.T @ H  # G = inv(HᵀH + inv(F G Fᵀ)) (SPEC §6.2-1)
        Om = 0.5 * (Om + Om.T)
        Kg = np.linalg.solve(Om, H.T)  # Eq. 26 corrected: K = G Hᵀ
        E = np.zeros((n_z, N * n_z))
        E[:, l * n_z : (l + 1) * n_z] = np.eye(n_z)
        W = W + Kg @ (E - H @ W)  # Eq. 27
        A = I - Kg @ H
        P = A @ P @ A.T + Kg @ R @ Kg.T  # Eq. 28 (Joseph)
        P = 0.5 * (P + P.T)
    return W.reshape(n_x, N, n_z).copy(), P


@njit
def row_valid(z):
    """True when every component of the measurement row is finite."""
    for c in range(z.shape[0]):
        if not np.isfinite(z[c]):
            return False
    return True


@njit
def ufir_horizon(zr, k, N, K, F, Finv, H, Q, R, xs, Ps, stored, x_out, P_out):
    """Iterative UFIR estimate at time ``k`` from the horizon ``[k-N+1, k]`` (SPEC §6.3).

    Parameters
    ----------
    zr : ndarray, shape (N, n_z)
        Measurement ring buffer (slot ``t % N``); NaN rows are missing samples.
    k : int
        Time index of the estimate (``k >= N-1``).
    N, K : int
        Horizon and batch-initialisation length (``K = n_x`` of the full model, also when
        called per axis, so that per-axis and dense forms agree exactly).
    F, Finv, H, Q, R : ndarray
        Model (full or one axis block).
    xs, Ps : ndarray, shape (N, n_x) and (N, n_x, n_x)
        Stored posteriors ring (used when ``stored``).
    stored : bool
        ``init="stored"``: start from the stored estimate at ``s`` instead of the batch LS.
    x_out, P_out : ndarray
        Written with the estimate when the horizon is usable.

    Returns
    -------
    bool
        False when fewer than K valid samples or ``CᵀC`` is rank deficient (``fir_ready=False``).
    """
    n_x = F.shape[0]
    n_z = H.shape[0]
    m = k - N + 1
    idx = np.empty(N, np.int64)
    nv = 0
    for t in range(m, k + 1):
        if row_valid(zr[t % N]):
            idx[nv] = t
            nv += 1
    if nv < K:
        return False
    s = idx[K - 1]  # generalised batch init: s = i_K (SPEC §6.3)
    C = np.zeros((K * n_z, n_x))
    Zs = np.empty(K * n_z)
    Phi = np.eye(n_x)
    tcur = s
    for q in range(K - 1, -1, -1):
        t = idx[q]
        while tcur > t:
            Phi = Phi @ Finv  # F^{-(s-t)}
            tcur -= 1
        HPhi = H @ Phi
        for r in range(n_z):
            Zs[q * n_z + r] = zr[t % N, r]
            for c in range(n_x):
                C[q * n_z + r, c] = HPhi[r, c]  # C = [H F^-(s-i1); ...; H]
    Om = C.T @ C  # G_s⁻¹ = CᵀC
    L = np.zeros((n_x, n_x))
    if not chol_shifted(Om, L, n_x, 0.0):
        return False
    for i in range(n_x):
        if L[i, i] * L[i, i] < RANK_TOL * Om[i, i]:
            return False  # rank(C) < n_x
    G = np.linalg.inv(Om)  # G_s = (CᵀC)⁻¹  (once per horizon, off the fast path)
    x = G @ (C.T @ Zs)  # x̂_s = G_s Cᵀ Z
    CRC = np.zeros((n_x, n_x))
    for q in range(K):
        Cq = C[q * n_z : (q + 1) * n_z]
        CRC += Cq.T @ R @ Cq
    P = symmetrize(G @ CRC @ G)  # P_s = G_s Cᵀ (I⊗R) C G_s
    if stored and s < k:
        sl = s % N
        if np.isfinite(xs[sl, 0]):
            x = xs[sl].copy()  # init="stored": start from x̂_s, P̂_s (paper B)
            P = Ps[sl].copy()
    I = np.eye(n_x)
    HtH = H.T @ H
    for l in range(s + 1, k + 1):
        x = F @ x  # Eq. 24
        P = F @ P @ F.T + Q  # Eq. 25
        Om = Finv.T @ Om @ Finv  # inv(F G Fᵀ)
        zl = zr[l % N]
        if row_valid(zl):
            Om = 0.5 * (Om + HtH + (Om + HtH).T)  # G⁻¹ = HᵀH + inv(F G Fᵀ)
            Kg = np.linalg.solve(Om, H.T)  # K = G Hᵀ (Eq. 26 corrected)
            x = x + Kg @ (zl - H @ x)  # Eq. 27
            A = I - Kg @ H
            P = A @ P @ A.T + Kg @ R @ Kg.T  # Eq. 28, Joseph (Q, R only for P)
        P = symmetrize(P)
    x_out[:] = x
    P_out[:, :] = P
    return True


@njit
def ufir_horizon_axis(zr, a, k, N, K, Fa, Finva, Ha, Qa, Ra, xs, Ps, stored, idx):
    """Per-axis 2-state form of :func:`ufir_horizon` in scalar arithmetic (no allocation).

    Axis ``a`` reads column ``a`` of the ring and the 2×2 blocks ``Fa[a]``, ``Finva[a]``,
    ``Ha[a] (1, 2)``, ``Qa[a]``, ``Ra[a] (1, 1)``; the state block is ``[2a, 2a+1]``. Same K
    (``n_x`` of the full model) and the same recursion, hence the same estimate as the dense
    form up to rounding. ``idx`` is an int64 scratch of length ≥ K.

    Returns ``(ok, x0, x1, p00, p01, p11)``.
    """
    f00, f01, f10, f11 = Fa[a, 0, 0], Fa[a, 0, 1], Fa[a, 1, 0], Fa[a, 1, 1]
    i00, i01, i10, i11 = Finva[a, 0, 0], Finva[a, 0, 1], Finva[a, 1, 0], Finva[a, 1, 1]
    h0, h1 = Ha[a, 0, 0], Ha[a, 0, 1]
    q00, q01, q11 = Qa[a, 0, 0], Qa[a, 0, 1], Qa[a, 1, 1]
    r = Ra[a, 0, 0]
    m = k - N + 1
    nv = 0
    for t in range(m, k + 1):
        if not np.isnan(zr[t % N, a]):
            idx[nv] = t
            nv += 1
            if nv == K:
                break
    if nv < K:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    s = idx[K - 1]
    # CᵀC and Cᵀ Z with rows c = h F^{-(s-t)}, walking back from s (Φ = F^{-(s-t)})
    p00, p01, p10, p11 = 1.0, 0.0, 0.0, 1.0
    tcur = s
    o00 = 0.0
    o01 = 0.0
    o11 = 0.0
    y0 = 0.0
    y1 = 0.0
    for q in range(K - 1, -1, -1):
        t = idx[q]
        while tcur > t:
            n00 = p00 * i00 + p01 * i10
            n01 = p00 * i01 + p01 * i11
            n10 = p10 * i00 + p11 * i10
            n11 = p10 * i01 + p11 * i11
            p00, p01, p10, p11 = n00, n01, n10, n11
            tcur -= 1
        c0 = h0 * p00 + h1 * p10
        c1 = h0 * p01 + h1 * p11
        zv = zr[t % N, a]
        o00 += c0 * c0
        o01 += c0 * c1
        o11 += c1 * c1
        y0 += c0 * zv
        y1 += c1 * zv
    det = o00 * o11 - o01 * o01
    if not (o00 > 0.0) or not (det > RANK_TOL * o00 * o11):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0  # rank(C) < 2
    g00 = o11 / det
    g01 = -o01 / det
    g11 = o00 / det
    x0 = g00 * y0 + g01 * y1  # x̂_s = G_s Cᵀ Z
    x1 = g01 * y0 + g11 * y1
    P00 = r * g00  # P_s = G_s Cᵀ (I⊗r) C G_s = r G_s
    P01 = r * g01
    P11 = r * g11
    lo = 2 * a
    if stored and s < k:
        sl = s % N
        if np.isfinite(xs[sl, lo]):
            x0 = xs[sl, lo]
            x1 = xs[sl, lo + 1]
            P00 = Ps[sl, lo, lo]
            P01 = 0.5 * (Ps[sl, lo, lo + 1] + Ps[sl, lo + 1, lo])
            P11 = Ps[sl, lo + 1, lo + 1]
    for l in range(s + 1, k + 1):
        # Eqs. 24-25: x⁻ = F x, P⁻ = F P Fᵀ + Q
        n0 = f00 * x0 + f01 * x1
        n1 = f10 * x0 + f11 * x1
        x0, x1 = n0, n1
        a00 = f00 * P00 + f01 * P01
        a01 = f00 * P01 + f01 * P11
        a10 = f10 * P00 + f11 * P01
        a11 = f10 * P01 + f11 * P11
        P00 = a00 * f00 + a01 * f01 + q00
        P01 = a00 * f10 + a01 * f11 + q01
        P11 = a10 * f10 + a11 * f11 + q11
        # inv(F G Fᵀ) = F⁻ᵀ G⁻¹ F⁻¹
        b00 = i00 * o00 + i10 * o01
        b01 = i00 * o01 + i10 * o11
        b10 = i01 * o00 + i11 * o01
        b11 = i01 * o01 + i11 * o11
        o00 = b00 * i00 + b01 * i10
        o01 = b00 * i01 + b01 * i11
        o11 = b10 * i01 + b11 * i11
        zv = zr[l % N, a]
        if np.isnan(zv):
            continue
        o00 += h0 * h0  # G⁻¹ = HᵀH + inv(F G Fᵀ)
        o01 += h0 * h1
        o11 += h1 * h1
        det = o00 * o11 - o01 * o01
        k0 = (o11 * h0 - o01 * h1) / det  # K = G Hᵀ (Eq. 26 corrected)
        k1 = (o00 * h1 - o01 * h0) / det
        inn = zv - (h0 * x0 + h1 * x1)
        x0 += k0 * inn  # Eq. 27
        x1 += k1 * inn
        # Eq. 28 Joseph: A P Aᵀ + K r Kᵀ, A = I − K h
        m00 = 1.0 - k0 * h0
        m01 = -k0 * h1
        m10 = -k1 * h0
        m11 = 1.0 - k1 * h1
        a00 = m00 * P00 + m01 * P01
        a01 = m00 * P01 + m01 * P11
        a10 = m10 * P00 + m11 * P01
        a11 = m10 * P01 + m11 * P11
        P00 = a00 * m00 + a01 * m01 + r * k0 * k0
        P01 = a00 * m10 + a01 * m11 + r * k0 * k1
        P11 = a10 * m10 + a11 * m11 + r * k1 * k1
    return True, x0, x1, P00, P01, P11


@njit
def _same_blocks(Fa, Finva, Ha, Qa, Ra):
    """True when every axis has the same 2×2 model blocks as axis 0."""
    for a in range(1, Fa.shape[0]):
        for i in range(2):
            if Ha[a, 0, i] != Ha[0, 0, i]:
                return False
            for j in range(2):
                if Fa[a, i, j] != Fa[0, i, j] or Finva[a, i, j] != Finva[0, i, j]:
                    return False
                if Qa[a, i, j] != Qa[0, i, j]:
                    return False
        if Ra[a, 0, 0] != Ra[0, 0, 0]:
            return False
    return True


@njit_inline
def ufir_horizon_axes(zr, k, N, K, Fa, Finva, Ha, Qa, Ra, idx, xx, x_out, P_out):
    """:func:`ufir_horizon_axis` for all axes at once when they share blocks and missing samples.

    The covariance, ``G⁻¹`` and gain recursion depends only on the model blocks and on which
    samples are missing, not on the data; the ring stores a missing row as a whole, so with
    identical per-axis blocks (e.g. ``constant_velocity`` with ``R = r I``) every axis has the
    same gains. They are computed once and applied to each axis's state with the operations of
    :func:`ufir_horizon_axis` (same results, bit for bit). Batch init only. ``idx``: int64
    scratch of length ≥ K; ``xx``: float scratch of shape ``(2, n_axes)``.

    Returns 1 (estimate written to ``x_out``, ``P_out``), 2 (not ready: fewer than K valid
    samples or rank deficient, as every axis would report) or 0 (not applicable: blocks or
    missing patterns differ between axes; use the per-axis form).
    """
    n_ax = Fa.shape[0]
    m = k - N + 1
    if not _same_blocks(Fa, Finva, Ha, Qa, Ra):
        return 0
    for t in range(m, k + 1):
        miss = np.isnan(zr[t % N, 0])
        for a in range(1, n_ax):
            if np.isnan(zr[t % N, a]) != miss:
                return 0
    f00, f01, f10, f11 = Fa[0, 0, 0], Fa[0, 0, 1], Fa[0, 1, 0], Fa[0, 1, 1]
    i00, i01, i10, i11 = Finva[0, 0, 0], Finva[0, 0, 1], Finva[0, 1, 0], Finva[0, 1, 1]
    h0, h1 = Ha[0, 0, 0], Ha[0, 0, 1]
    q00, q01, q11 = Qa[0, 0, 0], Qa[0, 0, 1], Qa[0, 1, 1]
    r = Ra[0, 0, 0]
    nv = 0
    for t in range(m, k + 1):
        if not np.isnan(zr[t % N, 0]):
            idx[nv] = t
            nv += 1
            if nv == K:
                break
    if nv < K:
        return 2
    s = idx[K - 1]
    for a in range(n_ax):  # per-axis Cᵀ Z, then the state [position, velocity]
        xx[0, a] = 0.0
        xx[1, a] = 0.0
    p00, p01, p10, p11 = 1.0, 0.0, 0.0, 1.0
    tcur = s
    o00 = 0.0
    o01 = 0.0
    o11 = 0.0
    for q in range(K - 1, -1, -1):
        t = idx[q]
        while tcur > t:
            n00 = p00 * i00 + p01 * i10
            n01 = p00 * i01 + p01 * i11
            n10 = p10 * i00 + p11 * i10
            n11 = p10 * i01 + p11 * i11
            p00, p01, p10, p11 = n00, n01, n10, n11
            tcur -= 1
        c0 = h0 * p00 + h1 * p10
        c1 = h0 * p01 + h1 * p11
        o00 += c0 * c0
        o01 += c0 * c1
        o11 += c1 * c1
        for a in range(n_ax):
            zv = zr[t % N, a]
            xx[0, a] += c0 * zv
            xx[1, a] += c1 * zv
    det = o00 * o11 - o01 * o01
    if not (o00 > 0.0) or not (det > RANK_TOL * o00 * o11):
        return 2  # rank(C) < 2
    g00 = o11 / det
    g01 = -o01 / det
    g11 = o00 / det
    for a in range(n_ax):  # x̂_s = G_s Cᵀ Z
        y0 = xx[0, a]
        y1 = xx[1, a]
        xx[0, a] = g00 * y0 + g01 * y1
        xx[1, a] = g01 * y0 + g11 * y1
    P00 = r * g00  # P_s = r G_s
    P01 = r * g01
    P11 = r * g11
    for l in range(s + 1, k + 1):
        for a in range(n_ax):  # Eq. 24: x⁻ = F x
            x0 = xx[0, a]
            x1 = xx[1, a]
            xx[0, a] = f00 * x0 + f01 * x1
            xx[1, a] = f10 * x0 + f11 * x1
        a00 = f00 * P00 + f01 * P01  # Eq. 25: P⁻ = F P Fᵀ + Q
        a01 = f00 * P01 + f01 * P11
        a10 = f10 * P00 + f11 * P01
        a11 = f10 * P01 + f11 * P11
        P00 = a00 * f00 + a01 * f01 + q00
        P01 = a00 * f10 + a01 * f11 + q01
        P11 = a10 * f10 + a11 * f11 + q11
        b00 = i00 * o00 + i10 * o01  # inv(F G Fᵀ) = F⁻ᵀ G⁻¹ F⁻¹
        b01 = i00 * o01 + i10 * o11
        b10 = i01 * o00 + i11 * o01
        b11 = i01 * o01 + i11 * o11
        o00 = b00 * i00 + b01 * i10
        o01 = b00 * i01 + b01 * i11
        o11 = b10 * i01 + b11 * i11
        if np.isnan(zr[l % N, 0]):
            continue
        o00 += h0 * h0  # G⁻¹ = HᵀH + inv(F G Fᵀ)
        o01 += h0 * h1
        o11 += h1 * h1
        det = o00 * o11 - o01 * o01
        k0 = (o11 * h0 - o01 * h1) / det  # K = G Hᵀ (Eq. 26 corrected)
        k1 = (o00 * h1 - o01 * h0) / det
        for a in range(n_ax):  # Eq. 27
            inn = zr[l % N, a] - (h0 * xx[0, a] + h1 * xx[1, a])
            xx[0, a] += k0 * inn
            xx[1, a] += k1 * inn
        m00 = 1.0 - k0 * h0  # Eq. 28 Joseph: A P Aᵀ + K r Kᵀ, A = I − K h
        m01 = -k0 * h1
        m10 = -k1 * h0
        m11 = 1.0 - k1 * h1
        a00 = m00 * P00 + m01 * P01
        a01 = m00 * P01 + m01 * P11
        a10 = m10 * P00 + m11 * P01
        a11 = m10 * P01 + m11 * P11
        P00 = a00 * m00 + a01 * m01 + r * k0 * k0
        P01 = a00 * m10 + a01 * m11 + r * k0 * k1
        P11 = a10 * m10 + a11 * m11 + r * k1 * k1
    n_x = x_out.shape[0]
    for i in range(n_x):
        for j in range(n_x):
            P_out[i, j] = 0.0
    for a in range(n_ax):
        lo = 2 * a
        x_out[lo] = xx[0, a]
        x_out[lo + 1] = xx[1, a]
        P_out[lo, lo] = P00
        P_out[lo, lo + 1] = P01
        P_out[lo + 1, lo] = P01
        P_out[lo + 1, lo + 1] = P11
    return 1


@njit_inline
def ufir_taps(zr, k, N, W, axis_blocks, x_out):
    """All-valid horizon fast path: ``x̂_k = Σ_i W_i z_{k-N+1+i}`` (SPEC §6.3 "Fast exact forms").

    With ``axis_blocks`` only the per-axis taps are summed (state ``[p_a, v_a]`` reads axis a).
    Returns False (NaN in the sum) when the horizon holds a missing sample.
    """
    n_x = W.shape[0]
    n_z = W.shape[2]
    start = (k + 1) % N  # slot of time m = k-N+1
    ok = True
    if axis_blocks:
        for a in range(n_z):
            p = 0.0
            v = 0.0
            sl = start
            for i in range(N):
                za = zr[sl, a]
                p += W[2 * a, i, a] * za
                v += W[2 * a + 1, i, a] * za
                sl += 1
                if sl == N:
                    sl = 0
            x_out[2 * a] = p
            x_out[2 * a + 1] = v
            if not (np.isfinite(p) and np.isfinite(v)):
                ok = False
    else:
        for r in range(n_x):
            acc = 0.0
            sl = start
            for i in range(N):
                for c in range(n_z):
                    acc += W[r, i, c] * zr[sl, c]
                sl += 1
                if sl == N:
                    sl = 0
            x_out[r] = acc
            if not np.isfinite(acc):
                ok = False
    return ok


@njit
def fir_estimate(
    zr,
    k,
    N,
    K,
    fast,
    axis_blocks,
    W,
    P_full,
    F,
    Finv,
    H,
    Q,
    R,
    Fa,
    Finva,
    Ha,
    Qa,
    Ra,
    xs,
    Ps,
    stored,
    x_out,
    P_out,
):
    """UFIR estimate at ``k`` by the cheapest exact route; returns ``fir_ready``.

    ``fast``: precomputed taps when the horizon is complete (batch init only), else the per-axis
    iterative form when ``axis_blocks``; otherwise (``fast=False``) the dense reference.
    """
    n_x = F.shape[0]
    if fast and not stored:
        if ufir_taps(zr, k, N, W, axis_blocks, x_out):
            P_out[:, :] = P_full
            return True
    if fast and axis_blocks:
        n_ax = Fa.shape[0]
        idx = np.empty(K, np.int64)
        if not stored:  # shared gains across axes when possible (same result, ~n_ax× cheaper)
            xx = np.empty((2, n_ax))
            code = ufir_horizon_axes(zr, k, N, K, Fa, Finva, Ha, Qa, Ra, idx, xx, x_out, P_out)
            if code == 1:
                return True
            if code == 2:
                return False
        for i in range(n_x):
            for j in range(n_x):
                P_out[i, j] = 0.0
        for a in range(n_ax):
            ok, x0, x1, p00, p01, p11 = ufir_horizon_axis(
                zr, a, k, N, K, Fa, Finva, Ha, Qa, Ra, xs, Ps, stored, idx
            )
            if not ok:
                return False
            lo = 2 * a
            x_out[lo] = x0
            x_out[lo + 1] = x1
            P_out[lo, lo] = p00
            P_out[lo, lo + 1] = p01
            P_out[lo + 1, lo] = p01
            P_out[lo + 1, lo + 1] = p11
        return True
    return ufir_horizon(zr, k, N, K, F, Finv, H, Q, R, xs, Ps, stored, x_out, P_out)


@njit
def ufir_run(
    z,
    x,
    P,
    init,
    zring,
    xring,
    Pring,
    k0,
    N,
    K,
    stored,
    fast,
    axis_blocks,
    W,
    P_full,
    F,
    Finv,
    H,
    Q,
    R,
    Fa,
    Finva,
    Ha,
    Qa,
    Ra,
    Hpinv,
    P0,
    o_mean,
    o_cov,
    o_obs,
    o_nu,
    o_ready,
):
    """Run the UFIR (with dead-zone KF) over ``z (B, T, n_z)``; state arrays updated in place.

    Returns the number of KF updates skipped because ``S`` could not be factorised.
    """
    B, T, n_z = z.shape
    n_x = x.shape[1]
    xf = np.empty(n_x)
    Pf = np.empty((n_x, n_x))
    xb = np.empty(n_x)
    Pb = np.empty((n_x, n_x))
    zt = np.empty(n_z)
    HF = H @ F
    idx = np.empty(K, np.int64)
    xx = np.empty((2, Fa.shape[0]))
    n_fail = 0
    for b in range(B):
        zr = zring[b]
        xs = xring[b]
        Ps = Pring[b]
        for i in range(n_x):
            xb[i] = x[b, i]
            for j in range(n_x):
                Pb[i, j] = P[b, i, j]
        initialized = init[b]
        for t in range(T):
            k = k0 + t
            valid = True
            for c in range(n_z):
                zt[c] = z[b, t, c]
                if not np.isfinite(zt[c]):
                    valid = False
            sl = k % N
            for c in range(n_z):
                zr[sl, c] = zt[c] if valid else np.nan
            # innovation against the one-step prediction of the previous output: z − H F x̂_{k−1}
            for r in range(n_z):
                acc = zt[r]
                for c in range(n_x):
                    acc -= HF[r, c] * xb[c]
                o_nu[b, t, r] = acc if (valid and initialized) else np.nan
            ready = False
            if k >= N - 1 and fast and not stored and ufir_taps(zr, k, N, W, axis_blocks, xf):
                for i in range(n_x):  # complete horizon: taps inlined (as in fir_estimate)
                    for j in range(n_x):
                        Pf[i, j] = P_full[i, j]
                ready = True
            elif k >= N - 1:
                code = 0
                if fast and not stored and axis_blocks:  # missing samples: shared axis gains
                    code = ufir_horizon_axes(zr, k, N, K, Fa, Finva, Ha, Qa, Ra, idx, xx, xf, Pf)
                ready = code == 1
                if code == 0:
                    ready = fir_estimate(
                        zr, k, N, K, fast, axis_blocks, W, P_full, F, Finv, H, Q, R, Fa, Finva, Ha, Qa, Ra, xs,
                        Ps, stored, xf, Pf,
                    )  # fmt: skip
            if ready:
                for i in range(n_x):
                    xb[i] = xf[i]
                    for j in range(n_x):
                        Pb[i, j] = Pf[i, j]
                initialized = True
            elif not initialized:
                if valid:  # SPEC §4.2 initialisation: positions from z, zero velocity, P₀
                    xb[:] = Hpinv @ zt
                    Pb[:, :] = P0
                    initialized = True
            else:  # dead zone / fallback: KF step (SPEC §6.2-5, §6.3)
                xp, Pp = kf_predict(xb, Pb, F, Q)
                if valid:
                    xu, Pu, _nu, _S, ok = kf_update(xp, Pp, zt, H, R)
                    if not ok:
                        n_fail += 1
                    xb[:] = xu
                    Pb[:, :] = Pu
                else:
                    xb[:] = xp
                    Pb[:, :] = Pp
            if stored:
                xs[sl] = xb
                Ps[sl] = Pb
            for i in range(n_x):
                o_mean[b, t, i] = xb[i]
                for j in range(n_x):
                    o_cov[b, t, i, j] = Pb[i, j]
            o_obs[b, t] = valid and initialized
            o_ready[b, t] = ready
        for i in range(n_x):
            x[b, i] = xb[i]
            for j in range(n_x):
                P[b, i, j] = Pb[i, j]
        init[b] = initialized
    return n_fail


# --------------------------------------------------------------------------------------------
# O(1) per step for the constant-velocity model: the batch-initialised UFIR as sliding sums
# --------------------------------------------------------------------------------------------


@njit
def _suffix_sums(zr, j, N, n_a, Qs):
    """Suffix sums over block ``j - 1`` (times ``(j-1)N .. jN-1``) of the valid ring rows.

    ``Qs[i] (N + 1, 3 + 2 n_a)`` for local index ``i`` (time ``(j-1)N + i``) holds
    ``[n, Σu, Σu², Σz_a, Σu z_a]`` over valid ``t >= (j-1)N + i`` of the block, ``u`` the local
    index; row ``N`` is zero. Rows below the oldest time still in the ring are not needed and
    not filled. Accumulated from the block's end, so the numbers depend on the samples only
    (the same whether computed in one run or after a split).
    """
    W = Qs.shape[1]
    for c in range(W):
        Qs[N, c] = 0.0
    # a window ending in block j starts at local index >= 1 of block j - 1 (local 0 is never
    # needed); rows for times no longer in the ring come out wrong but are never read
    lo = 1 if j > 0 else N
    for i in range(N - 1, lo - 1, -1):
        for c in range(W):
            Qs[i, c] = Qs[i + 1, c]
        t = (j - 1) * N + i
        sl = t % N
        if not np.isnan(zr[sl, 0]):
            u = float(i)
            Qs[i, 0] += 1.0
            Qs[i, 1] += u
            Qs[i, 2] += u * u
            for a in range(n_a):
                zv = zr[sl, a]
                Qs[i, 3 + 2 * a] += zv
                Qs[i, 4 + 2 * a] += u * zv


@njit
def ufir_run_cv(
    z, x, P, init, zring, k0, N, K, dt, q00, q01, q11, r, p0, pfull, Fa, Finva, Ha, Qa, Ra,
    o_mean, o_covb, o_obs, o_nu, o_ready,
):  # fmt: skip
    """Batch-initialised UFIR for the constant-velocity model in O(1) per step (SPEC §6.3).

    Every axis has the block ``F = [[1, dt], [0, 1]]``, ``H = [1, 0]``, ``Q = [[q00, q01],
    [q01, q11]]``, ``R = r``; a missing row is missing on every axis. With batch
    initialisation the UFIR estimate at ``k`` is the least-squares line through the valid
    samples of the horizon (the recursion of :func:`ufir_horizon` is recursive least squares),
    so per axis ``x̂_k = (Σ c cᵀ)⁻¹ Σ c z`` with ``c_t = H F^{-(k-t)} = [1, −(k−t) dt]``: five
    window sums (``n, Σd, Σd², Σz, Σd z`` with ``d = k − t``). They are kept as a prefix over the
    current block of N samples plus a suffix over the previous block (recomputed every N steps
    and at the start of each call from the ring, so results do not depend on how the series is
    split); no sum is carried over more than 2N samples (no drift).

    Covariance: a complete horizon has the data-independent ``P_full``; with missing samples
    ``P̂_k`` depends on where they are and is computed by :func:`ufir_horizon_axes` (O(N)) only
    when wanted: for the ``o_covb`` output, at the last step (the state) and where the horizon
    holds exactly K valid samples (the next step may fall back to the KF, which needs it).
    Dead zone and fallback: the per-axis KF step (Joseph form). State ``x (B, 6)``, ``P``,
    ``init``, ``zring (B, N, n_z)`` updated in place; ``o_covb (B, T, 1, 3)`` (one block for all
    axes) may have a zero-length first axis (not wanted). Returns the count of KF updates with
    ``S`` not factorisable.
    """
    B, T, n_a = z.shape
    n_x = 2 * n_a
    w_cov = o_covb.shape[0] > 0
    Wd = 3 + 2 * n_a
    Qs = np.empty((N + 1, Wd))
    Ps_ = np.empty(Wd)  # prefix sums of the current block
    idx = np.empty(K, np.int64)
    xx = np.empty((2, n_a))
    xf = np.empty(n_x)
    Pf = np.empty((n_x, n_x))
    xs = np.empty((n_a, 2))
    n_fail = 0
    for b in range(B):
        zr = zring[b]
        for a in range(n_a):
            xs[a, 0] = x[b, 2 * a]
            xs[a, 1] = x[b, 2 * a + 1]
        p00 = P[b, 0, 0]
        p01 = 0.5 * (P[b, 0, 1] + P[b, 1, 0])
        p11 = P[b, 1, 1]
        ini = init[b]
        # sums for the block of k0 from the ring (samples k0-N .. k0-1 are there)
        j = k0 // N
        _suffix_sums(zr, j, N, n_a, Qs)
        for c in range(Wd):
            Ps_[c] = 0.0
        for t in range(j * N, k0):
            sl = t % N
            if not np.isnan(zr[sl, 0]):
                u = float(t - j * N)
                Ps_[0] += 1.0
                Ps_[1] += u
                Ps_[2] += u * u
                for a in range(n_a):
                    Ps_[3 + 2 * a] += zr[sl, a]
                    Ps_[4 + 2 * a] += u * zr[sl, a]
        for t in range(T):
            k = k0 + t
            valid = True
            for a in range(n_a):
                if not np.isfinite(z[b, t, a]):
                    valid = False
            sl = k % N
            for a in range(n_a):
                zr[sl, a] = z[b, t, a] if valid else np.nan
            if k % N == 0 and k > 0:  # new block: suffixes of the finished one, empty prefix
                j = k // N
                _suffix_sums(zr, j, N, n_a, Qs)
                for c in range(Wd):
                    Ps_[c] = 0.0
            u_k = float(k - j * N)
            if valid:
                Ps_[0] += 1.0
                Ps_[1] += u_k
                Ps_[2] += u_k * u_k
                for a in range(n_a):
                    Ps_[3 + 2 * a] += z[b, t, a]
                    Ps_[4 + 2 * a] += u_k * z[b, t, a]
            for a in range(n_a):  # innovation z − H F x̂_{k−1}
                o_nu[b, t, a] = (
                    z[b, t, a] - (xs[a, 0] + dt * xs[a, 1]) if (valid and ini) else np.nan
                )
            ready = False
            need_p = False
            if k >= N - 1:
                im = int(u_k) + 1  # local index of m = k−N+1 in block j−1 (N: empty suffix)
                e = u_k + N
                n = Qs[im, 0] + Ps_[0]
                if n >= K:
                    # Σd, Σd² with d = k − t: block j part d = u_k − u, block j−1 part e − u
                    D1 = u_k * Ps_[0] - Ps_[1] + e * Qs[im, 0] - Qs[im, 1]
                    D2 = (u_k * u_k * Ps_[0] - 2.0 * u_k * Ps_[1] + Ps_[2]
                          + e * e * Qs[im, 0] - 2.0 * e * Qs[im, 1] + Qs[im, 2])  # fmt: skip
                    # normal equations in (position p, change per sample β): z_t = p − β d
                    det = n * D2 - D1 * D1
                    if det > RANK_TOL * n * D2:
                        ready = True
                        for a in range(n_a):
                            Z0 = Ps_[3 + 2 * a] + Qs[im, 3 + 2 * a]
                            Z1 = (
                                u_k * Ps_[3 + 2 * a]
                                - Ps_[4 + 2 * a]
                                + e * Qs[im, 3 + 2 * a]
                                - Qs[im, 4 + 2 * a]
                            )
                            pos = (D2 * Z0 - D1 * Z1) / det  # x̂ = (CᵀC)⁻¹ Cᵀ Z
                            beta = (D1 * Z0 - n * Z1) / det
                            xs[a, 0] = pos
                            xs[a, 1] = beta / dt
                        if n == N:  # complete horizon: data-independent covariance
                            p00 = pfull[0]
                            p01 = pfull[1]
                            p11 = pfull[2]
                        else:
                            need_p = w_cov or n == K or t == T - 1
                            if need_p:
                                code = ufir_horizon_axes(
                                    zr, k, N, K, Fa, Finva, Ha, Qa, Ra, idx, xx, xf, Pf
                                )
                                if code == 1:
                                    p00 = Pf[0, 0]
                                    p01 = Pf[0, 1]
                                    p11 = Pf[1, 1]
                                else:
                                    p00 = p01 = p11 = np.nan
                            else:
                                p00 = p01 = p11 = np.nan  # not needed: not computed
                        ini = True
            if not ready:
                if not ini:
                    if valid:  # SPEC §4.2 initialisation: positions from z, zero velocity, P₀
                        for a in range(n_a):
                            xs[a, 0] = z[b, t, a]
                            xs[a, 1] = 0.0
                        p00 = p0[0]
                        p01 = p0[1]
                        p11 = p0[2]
                        ini = True
                else:  # dead zone / fallback: per-axis KF step (SPEC §6.2-5, §6.3)
                    p00, p01, p11, g0, g1, iS, upd = _cov_step(
                        p00, p01, p11, valid, True, 1.0, dt, 0.0, 1.0, q00, q01, q11, 1.0, 0.0, r
                    )
                    if valid and not upd:
                        n_fail += 1
                    for a in range(n_a):
                        xp0 = xs[a, 0] + dt * xs[a, 1]
                        xp1 = xs[a, 1]
                        if upd:
                            v = z[b, t, a] - xp0
                            xp0 += g0 * v
                            xp1 += g1 * v
                        xs[a, 0] = xp0
                        xs[a, 1] = xp1
            for a in range(n_a):
                o_mean[b, t, 2 * a] = xs[a, 0] if ini else np.nan
                o_mean[b, t, 2 * a + 1] = xs[a, 1] if ini else np.nan
            if w_cov:
                o_covb[b, t, 0, 0] = p00 if ini else np.nan
                o_covb[b, t, 0, 1] = p01 if ini else np.nan
                o_covb[b, t, 0, 2] = p11 if ini else np.nan
            o_obs[b, t] = valid and ini
            o_ready[b, t] = ready
        init[b] = ini
        if ini:
            P[b, :, :] = 0.0
            for a in range(n_a):
                i = 2 * a
                x[b, i] = xs[a, 0]
                x[b, i + 1] = xs[a, 1]
                P[b, i, i] = p00
                P[b, i, i + 1] = p01
                P[b, i + 1, i] = p01
                P[b, i + 1, i + 1] = p11
    return n_fail
