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

The UFIR filter's run loops (:func:`~._kernels_ufir_run.ufir_run`, the O(1)-per-step
constant-velocity :func:`~._kernels_ufir_run.ufir_run_cv`) are in :mod:`._kernels_ufir_run`.
"""

from __future__ import annotations

import numpy as np

# njit_inline: inlined at the numba IR level into its callers, so no per-call reference counting
# of the array arguments (see :mod:`._kernels_common`)
from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels import symmetrize
from kinefuse.filters._kernels_block2 import cov2_predict, info2_back, joseph2, mat2_finv
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


@njit_inline
def _axis_params(Fa, Finva, Ha, Qa, Ra, a):
    """The 2×2 model blocks of axis ``a`` as scalars: ``F``, ``F⁻¹``, ``h``, ``Q``, ``r``."""
    return (
        Fa[a, 0, 0], Fa[a, 0, 1], Fa[a, 1, 0], Fa[a, 1, 1],
        Finva[a, 0, 0], Finva[a, 0, 1], Finva[a, 1, 0], Finva[a, 1, 1],
        Ha[a, 0, 0], Ha[a, 0, 1], Qa[a, 0, 0], Qa[a, 0, 1], Qa[a, 1, 1], Ra[a, 0, 0],
    )  # fmt: skip


@njit_inline
def _first_valid(zr, col, m, k, N, K, idx):
    """The first ``K`` valid times of ``[m, k]`` (column ``col`` of the ring) into ``idx``;
    returns how many were found (``< K``: the horizon is not usable)."""
    nv = 0
    for t in range(m, k + 1):
        if not np.isnan(zr[t % N, col]):
            idx[nv] = t
            nv += 1
            if nv == K:
                break
    return nv


@njit_inline
def _c_row(t, tcur, p00, p01, p10, p11, o00, o01, o11, i00, i01, i10, i11, h0, h1):
    """Batch init (SPEC §6.3): the row ``c = h F^{-(s-t)}`` of ``C`` for valid time ``t``.

    ``Φ = [p]`` is ``F^{-(s-tcur)}``, stepped back to ``t`` (rows come newest first); ``c cᵀ``
    is added to ``CᵀC = [o]``. Returns ``(t, Φ, CᵀC, c0, c1)``.
    """
    while tcur > t:
        p00, p01, p10, p11 = mat2_finv(p00, p01, p10, p11, i00, i01, i10, i11)
        tcur -= 1
    c0 = h0 * p00 + h1 * p10
    c1 = h0 * p01 + h1 * p11
    return tcur, p00, p01, p10, p11, o00 + c0 * c0, o01 + c0 * c1, o11 + c1 * c1, c0, c1


@njit_inline
def _info_gain(o00, o01, o11, h0, h1):
    """``G⁻¹ = hᵀh + inv(F G Fᵀ)`` and the UFIR gain ``k = G hᵀ`` (Eq. 26 corrected).

    Returns ``(o00, o01, o11, k0, k1)``.
    """
    o00 += h0 * h0
    o01 += h0 * h1
    o11 += h1 * h1
    det = o00 * o11 - o01 * o01
    k0 = (o11 * h0 - o01 * h1) / det
    k1 = (o00 * h1 - o01 * h0) / det
    return o00, o01, o11, k0, k1


@njit
def ufir_horizon_axis(zr, a, k, N, K, Fa, Finva, Ha, Qa, Ra, xs, Ps, stored, idx):
    """Per-axis 2-state form of :func:`ufir_horizon` in scalar arithmetic (no allocation).

    Axis ``a`` reads column ``a`` of the ring and the 2×2 blocks ``Fa[a]``, ``Finva[a]``,
    ``Ha[a] (1, 2)``, ``Qa[a]``, ``Ra[a] (1, 1)``; the state block is ``[2a, 2a+1]``. Same K
    (``n_x`` of the full model) and the same recursion, hence the same estimate as the dense
    form up to rounding. ``idx`` is an int64 scratch of length ≥ K.

    Returns ``(ok, x0, x1, p00, p01, p11)``.
    """
    f00, f01, f10, f11, i00, i01, i10, i11, h0, h1, q00, q01, q11, r = _axis_params(
        Fa, Finva, Ha, Qa, Ra, a
    )
    if _first_valid(zr, a, k - N + 1, k, N, K, idx) < K:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    s = idx[K - 1]
    # CᵀC and Cᵀ Z with rows c = h F^{-(s-t)}, walking back from s (Φ = F^{-(s-t)})
    p00, p01, p10, p11 = 1.0, 0.0, 0.0, 1.0
    tcur = s
    o00 = o01 = o11 = y0 = y1 = 0.0
    for q in range(K - 1, -1, -1):
        t = idx[q]
        tcur, p00, p01, p10, p11, o00, o01, o11, c0, c1 = _c_row(
            t, tcur, p00, p01, p10, p11, o00, o01, o11, i00, i01, i10, i11, h0, h1
        )
        zv = zr[t % N, a]
        y0 += c0 * zv
        y1 += c1 * zv
    det = o00 * o11 - o01 * o01
    if not (o00 > 0.0) or not (det > RANK_TOL * o00 * o11):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0  # rank(C) < 2
    g00, g01, g11 = o11 / det, -o01 / det, o00 / det
    x0 = g00 * y0 + g01 * y1  # x̂_s = G_s Cᵀ Z
    x1 = g01 * y0 + g11 * y1
    P00, P01, P11 = r * g00, r * g01, r * g11  # P_s = G_s Cᵀ (I⊗r) C G_s = r G_s
    lo = 2 * a
    if stored and s < k and np.isfinite(xs[s % N, lo]):  # init="stored": x̂_s, P̂_s
        sl = s % N
        x0, x1 = xs[sl, lo], xs[sl, lo + 1]
        P00, P01 = Ps[sl, lo, lo], 0.5 * (Ps[sl, lo, lo + 1] + Ps[sl, lo + 1, lo])
        P11 = Ps[sl, lo + 1, lo + 1]
    for l in range(s + 1, k + 1):
        x0, x1 = f00 * x0 + f01 * x1, f10 * x0 + f11 * x1  # Eq. 24: x⁻ = F x
        P00, P01, P11, _, _, _, _ = cov2_predict(P00, P01, P11, f00, f01, f10, f11, q00, q01, q11)
        o00, o01, o11 = info2_back(o00, o01, o11, i00, i01, i10, i11)  # inv(F G Fᵀ)
        zv = zr[l % N, a]
        if np.isnan(zv):
            continue
        o00, o01, o11, k0, k1 = _info_gain(o00, o01, o11, h0, h1)
        inn = zv - (h0 * x0 + h1 * x1)
        x0 += k0 * inn  # Eq. 27
        x1 += k1 * inn
        P00, P01, P11 = joseph2(P00, P01, P11, k0, k1, h0, h1, r)  # Eq. 28
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
def _same_missing(zr, m, k, N):
    """True when every row of the horizon ``[m, k]`` is missing on all axes or on none."""
    for t in range(m, k + 1):
        miss = np.isnan(zr[t % N, 0])
        for a in range(1, zr.shape[1]):
            if np.isnan(zr[t % N, a]) != miss:
                return False
    return True


@njit_inline
def _put_axes(xx, P00, P01, P11, x_out, P_out):
    """Write the per-axis states ``xx (2, n_axes)`` and the shared block into ``x_out, P_out``."""
    P_out[:, :] = 0.0
    for a in range(xx.shape[1]):
        lo = 2 * a
        x_out[lo] = xx[0, a]
        x_out[lo + 1] = xx[1, a]
        P_out[lo, lo] = P00
        P_out[lo, lo + 1] = P01
        P_out[lo + 1, lo] = P01
        P_out[lo + 1, lo + 1] = P11


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
    if not _same_blocks(Fa, Finva, Ha, Qa, Ra) or not _same_missing(zr, m, k, N):
        return 0
    f00, f01, f10, f11, i00, i01, i10, i11, h0, h1, q00, q01, q11, r = _axis_params(
        Fa, Finva, Ha, Qa, Ra, 0
    )
    if _first_valid(zr, 0, m, k, N, K, idx) < K:
        return 2
    s = idx[K - 1]
    xx[:, :] = 0.0  # per-axis Cᵀ Z, then the state [position, velocity]
    p00, p01, p10, p11 = 1.0, 0.0, 0.0, 1.0
    tcur = s
    o00 = o01 = o11 = 0.0
    for q in range(K - 1, -1, -1):
        t = idx[q]
        tcur, p00, p01, p10, p11, o00, o01, o11, c0, c1 = _c_row(
            t, tcur, p00, p01, p10, p11, o00, o01, o11, i00, i01, i10, i11, h0, h1
        )
        for a in range(n_ax):
            zv = zr[t % N, a]
            xx[0, a] += c0 * zv
            xx[1, a] += c1 * zv
    det = o00 * o11 - o01 * o01
    if not (o00 > 0.0) or not (det > RANK_TOL * o00 * o11):
        return 2  # rank(C) < 2
    g00, g01, g11 = o11 / det, -o01 / det, o00 / det
    for a in range(n_ax):  # x̂_s = G_s Cᵀ Z
        y0, y1 = xx[0, a], xx[1, a]
        xx[0, a] = g00 * y0 + g01 * y1
        xx[1, a] = g01 * y0 + g11 * y1
    P00, P01, P11 = r * g00, r * g01, r * g11  # P_s = r G_s
    for l in range(s + 1, k + 1):
        for a in range(n_ax):  # Eq. 24: x⁻ = F x
            x0, x1 = xx[0, a], xx[1, a]
            xx[0, a] = f00 * x0 + f01 * x1
            xx[1, a] = f10 * x0 + f11 * x1
        P00, P01, P11, _, _, _, _ = cov2_predict(P00, P01, P11, f00, f01, f10, f11, q00, q01, q11)
        o00, o01, o11 = info2_back(o00, o01, o11, i00, i01, i10, i11)  # inv(F G Fᵀ)
        if np.isnan(zr[l % N, 0]):
            continue
        o00, o01, o11, k0, k1 = _info_gain(o00, o01, o11, h0, h1)
        for a in range(n_ax):  # Eq. 27
            inn = zr[l % N, a] - (h0 * xx[0, a] + h1 * xx[1, a])
            xx[0, a] += k0 * inn
            xx[1, a] += k1 * inn
        P00, P01, P11 = joseph2(P00, P01, P11, k0, k1, h0, h1, r)  # Eq. 28
    _put_axes(xx, P00, P01, P11, x_out, P_out)
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
