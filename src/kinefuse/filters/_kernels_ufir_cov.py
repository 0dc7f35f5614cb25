"""The constant-velocity UFIR's covariance in O(1) per step on horizons with missing samples.

Paper A §3.3 (Eqs. 24-28) as corrected by SPEC §6.3, per axis: ``F = [[1, dt], [0, 1]]``,
``H = [1, 0]``, ``Q = [[q00, q01], [q01, q11]]``, ``R = r``, batch initialisation over the first
``K`` valid samples of the horizon ``[m, k]`` (``s`` = the K-th valid time). The iterative form
(:func:`~._kernels_ufir.ufir_horizon_axes`) runs the Joseph recursion from ``P_s = r G_s``
(``G_s = (C_sᵀ C_s)⁻¹``) over ``l = s+1 .. k``; its result is the error covariance of a linear
estimator, so it can be written out directly (derivation below). Textbook symbols, no
validation; all 2x2 blocks are scalars (``[a00, a01, a11]`` symmetric, ``[a00, a01, a10, a11]``
general).

Closed form
-----------
With batch initialisation the UFIR estimate at ``k`` is the least-squares line through the
horizon's valid samples, ``x̂_k = G Σ_t c_tᵀ z_t`` with ``c_t = H F^{t−k}`` and ``G = (Σ_t c_tᵀ
c_t)⁻¹``. Its error ``e_k`` is linear in the measurement noise of every valid sample and in the
process noise ``w_l`` of every ``l`` in ``(s, k]`` (the recursion adds ``Q`` only there), hence

    P_k = r G + G T G,   T = Σ_{l=s+1..k} S_l F^{k−l} Q F^{(k−l)ᵀ} S_l,   S_l = Σ_{t<l} c_tᵀ c_t

(sums over the valid times of the horizon): ``r G`` is ``Σ_t W_t r W_tᵀ`` with the estimator's
weights ``W_t = G c_tᵀ``, and the sensitivity of ``e_k`` to ``w_l`` is ``F^{k−l} − Σ_{t≥l} W_t H
F^{t−l} = G S_l F^{k−l}`` (the estimator reproduces any noise-free line: ``Σ_t W_t c_t = I``).

The sums are kept relative to a fixed reference ``ρ = jN``, the first time of the current block
of N samples (``c̃_t = H F^{t−ρ}``, ``M̃_l = F^{ρ−l} Q F^{(ρ−l)ᵀ}``; then ``T = Eᵀ T̃ E``, ``G =
E⁻¹ S̃⁻¹ E⁻ᵀ`` with ``E = F^{ρ−k}``), split at ``ρ`` as the mean's window sums are
(:func:`~._kernels_ufir_run.ufir_run_cv`):

* ``l`` in the previous block: ``S̃_l = Suf(m) − Suf(l)`` with ``Suf(i) = Σ_{i≤t<ρ} ã_t``; the
  suffix sums ``Σ_{l≥i} M̃_l``, ``Σ M̃_l Suf(l)`` and ``Σ Suf(l) M̃_l Suf(l)`` are computed once per
  block (O(N) every N steps).
* ``l`` in the current block: ``S̃_l = Suf(m) + Pre(l)`` with ``Pre(l) = Σ_{ρ≤t<l} ã_t``; the
  prefix sums ``Σ M̃_l``, ``Σ M̃_l Pre(l)``, ``Σ Pre(l) M̃_l Pre(l)`` grow by one row a step.

No sum runs over more than 2N samples, and all are rebuilt from the ring at the start of each
call, so results do not depend on how a series is split. Same numbers as the iterative form to
rounding (tested against it).
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline

#: Columns of the previous block's suffix table: Suf (3), ΣM̃ (3), ΣM̃ Suf (4), ΣSuf M̃ Suf (3).
N_PREV_COLS = 13
#: Columns of the current block's prefix table: ΣM̃ (3), ΣM̃ Pre (4), ΣPre M̃ Pre (3).
N_CUR_COLS = 10


@njit_inline
def _fsym(g, a00, a01, a11):
    """``Φ A Φᵀ`` of a symmetric block with ``Φ = [[1, g], [0, 1]]`` (``F^n``, ``g = n dt``)."""
    return a00 + 2.0 * g * a01 + g * g * a11, a01 + g * a11, a11


@njit_inline
def _sms(s00, s01, s11, m00, m01, m11):
    """``S M S`` of two symmetric blocks (symmetric)."""
    t00 = s00 * m00 + s01 * m01  # S M
    t01 = s00 * m01 + s01 * m11
    t10 = s01 * m00 + s11 * m01
    t11 = s01 * m01 + s11 * m11
    return t00 * s00 + t01 * s01, t00 * s01 + t01 * s11, t10 * s01 + t11 * s11


@njit_inline
def _ms(m00, m01, m11, s00, s01, s11):
    """``M S`` of two symmetric blocks (general)."""
    return (
        m00 * s00 + m01 * s01,
        m00 * s01 + m01 * s11,
        m01 * s00 + m11 * s01,
        m01 * s01 + m11 * s11,
    )


@njit_inline
def _sx_sym(s00, s01, s11, x00, x01, x10, x11):
    """``S X + (S X)ᵀ`` for symmetric ``S`` and general ``X`` (symmetric)."""
    y00 = s00 * x00 + s01 * x10
    y01 = s00 * x01 + s01 * x11
    y10 = s01 * x00 + s11 * x10
    y11 = s01 * x01 + s11 * x11
    return 2.0 * y00, y01 + y10, 2.0 * y11


@njit_inline
def _m_tilde(w, q00, q01, q11):
    """``M̃_l = F^{ρ−l} Q F^{(ρ−l)ᵀ}`` with ``w = (l − ρ) dt``."""
    return _fsym(-w, q00, q01, q11)


@njit
def cov_suffix_table(zr, j, N, dt, q00, q01, q11, prev):
    """The previous block's suffix table (``prev (N + 1, 13)``) for the block of reference ``jN``.

    Row ``i`` is time ``(j−1)N + i``; row ``N`` is zero. As in
    :func:`~._kernels_ufir_run._suffix_sums`, rows for times no longer in the ring come out wrong
    and are never read (a window ending in block ``j`` starts at row ≥ 1). Block ``j = 0`` has
    no previous block: the table is zero.
    """
    for c in range(N_PREV_COLS):
        prev[N, c] = 0.0
    lo = 1 if j > 0 else N
    for i in range(lo):
        for c in range(N_PREV_COLS):
            prev[i, c] = 0.0
    for i in range(N - 1, lo - 1, -1):  # time (j − 1) N + i, in ring slot i
        w = (i - N) * dt  # (t − ρ) dt
        s00, s01, s11 = prev[i + 1, 0], prev[i + 1, 1], prev[i + 1, 2]
        if not np.isnan(zr[i, 0]):  # Suf(i) includes time t
            s00 += 1.0
            s01 += w
            s11 += w * w
        m00, m01, m11 = _m_tilde(w, q00, q01, q11)
        x00, x01, x10, x11 = _ms(m00, m01, m11, s00, s01, s11)
        y00, y01, y11 = _sms(s00, s01, s11, m00, m01, m11)
        prev[i, 0], prev[i, 1], prev[i, 2] = s00, s01, s11
        prev[i, 3] = prev[i + 1, 3] + m00
        prev[i, 4] = prev[i + 1, 4] + m01
        prev[i, 5] = prev[i + 1, 5] + m11
        prev[i, 6] = prev[i + 1, 6] + x00
        prev[i, 7] = prev[i + 1, 7] + x01
        prev[i, 8] = prev[i + 1, 8] + x10
        prev[i, 9] = prev[i + 1, 9] + x11
        prev[i, 10] = prev[i + 1, 10] + y00
        prev[i, 11] = prev[i + 1, 11] + y01
        prev[i, 12] = prev[i + 1, 12] + y11


@njit_inline
def cov_prefix_add(cur, pre, i, valid, dt, q00, q01, q11):
    """Append time ``ρ + i`` to the current block's prefix table ``cur (N + 1, 10)`` (row
    ``i + 1``; row 0 is zero) and, when it is valid, to the running ``pre = Pre(ρ + i + 1)``."""
    w = i * dt
    p00, p01, p11 = pre[0], pre[1], pre[2]  # Pre(l): times before l
    m00, m01, m11 = _m_tilde(w, q00, q01, q11)
    x00, x01, x10, x11 = _ms(m00, m01, m11, p00, p01, p11)
    y00, y01, y11 = _sms(p00, p01, p11, m00, m01, m11)
    cur[i + 1, 0] = cur[i, 0] + m00
    cur[i + 1, 1] = cur[i, 1] + m01
    cur[i + 1, 2] = cur[i, 2] + m11
    cur[i + 1, 3] = cur[i, 3] + x00
    cur[i + 1, 4] = cur[i, 4] + x01
    cur[i + 1, 5] = cur[i, 5] + x10
    cur[i + 1, 6] = cur[i, 6] + x11
    cur[i + 1, 7] = cur[i, 7] + y00
    cur[i + 1, 8] = cur[i, 8] + y01
    cur[i + 1, 9] = cur[i, 9] + y11
    if valid:
        pre[0] = p00 + 1.0
        pre[1] = p01 + w
        pre[2] = p11 + w * w


@njit_inline
def next_valid(zr, s_t, s_sl, k):
    """The first valid time after ``s_t`` (ring slot ``s_sl``) up to ``k``, and its slot;
    ``(-1, 0)`` when there is none."""
    N = zr.shape[0]
    t = s_t + 1
    sl = s_sl + 1
    while t <= k:
        if sl == N:
            sl = 0
        if not np.isnan(zr[sl, 0]):
            return t, sl
        t += 1
        sl += 1
    return -1, 0


@njit_inline
def cov_at(prev, cur, pre, N, im, i_s, i_k, dt, r, idet):
    """``P_k`` (``(p00, p01, p11)``) of the horizon ending at index ``i_k`` of the current block,
    starting at row ``im`` of the previous block's table (``N``: empty), with the K-th valid
    time at ``i_s`` (index in the current block, negative in the previous one: ``i_s + N`` is
    its row there). ``pre`` is ``Pre`` through ``i_k`` inclusive; ``idet = 1 / det S̃`` (``det
    Σ c_tᵀ c_t``, the same in every frame of reference: the least-squares line's, reused)."""
    # Every table read is unconditional (no array read inside a branch: numba then keeps
    # reference-count calls in the caller's loop, ~15 ns each); the rows that do not apply are
    # the tables' zero rows (cur[0], prev[N]), which add exactly nothing.
    a00, a01, a11 = prev[im, 0], prev[im, 1], prev[im, 2]  # Suf(m)
    hi = i_k + 1
    lo = i_s + 1 if i_s + 1 > 0 else 0  # s in the current block: rows from s + 1
    i0 = i_s + 1 + N if i_s + 1 < 0 else N  # s in the previous block: l in (s, ρ) there
    # l in [max(ρ, s + 1), k]: (Suf(m) + Pre(l)) M̃ (Suf(m) + Pre(l)): rows lo .. u_k + 1;
    # l in (s, ρ): (Suf(m) − Suf(l)) M̃ (Suf(m) − Suf(l))
    m00 = cur[hi, 0] - cur[lo, 0] + prev[i0, 3]  # Σ M̃
    m01 = cur[hi, 1] - cur[lo, 1] + prev[i0, 4]
    m11 = cur[hi, 2] - cur[lo, 2] + prev[i0, 5]
    x00 = cur[hi, 3] - cur[lo, 3] - prev[i0, 6]  # ± Σ M̃ (Suf|Pre)
    x01 = cur[hi, 4] - cur[lo, 4] - prev[i0, 7]
    x10 = cur[hi, 5] - cur[lo, 5] - prev[i0, 8]
    x11 = cur[hi, 6] - cur[lo, 6] - prev[i0, 9]
    t00 = cur[hi, 7] - cur[lo, 7] + prev[i0, 10]  # Σ (Suf|Pre) M̃ (Suf|Pre)
    t01 = cur[hi, 8] - cur[lo, 8] + prev[i0, 11]
    t11 = cur[hi, 9] - cur[lo, 9] + prev[i0, 12]
    # T̃ = Suf(m) ΣM̃ Suf(m) + (Suf(m) X + (Suf(m) X)ᵀ) + Σ (Suf|Pre) M̃ (Suf|Pre)
    b00, b01, b11 = _sms(a00, a01, a11, m00, m01, m11)
    c00, c01, c11 = _sx_sym(a00, a01, a11, x00, x01, x10, x11)
    t00 += b00 + c00
    t01 += b01 + c01
    t11 += b11 + c11
    # S̃ = Suf(m) + Pre(k + 1); X = r S̃⁻¹ + S̃⁻¹ T̃ S̃⁻¹; P_k = F^{k−ρ} X F^{(k−ρ)ᵀ}
    s00, s01, s11 = a00 + pre[0], a01 + pre[1], a11 + pre[2]
    g00, g01, g11 = s11 * idet, -s01 * idet, s00 * idet
    x00, x01, x11 = _sms(g00, g01, g11, t00, t01, t11)
    return _fsym(i_k * dt, x00 + r * g00, x01 + r * g01, x11 + r * g11)
