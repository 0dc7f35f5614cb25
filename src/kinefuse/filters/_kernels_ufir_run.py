"""UFIR filter run loops (numba): the general form and the O(1)-per-step constant-velocity form.

Paper A §3.3 (Eqs. 24-28, Algorithm 3) as corrected by SPEC §6.2-§6.3. Textbook symbols, no
validation. Both loops keep the time-major measurement ring of :mod:`._kernels_ufir` (slot
``t % N``; a row holding any NaN is a missing sample) and get each horizon estimate from it:

* :func:`ufir_run` — any model: :func:`~._kernels_ufir.fir_estimate` per step (precomputed
  taps on a complete horizon, the per-axis or dense iterative UFIR otherwise), the KF in the
  dead zone and as the fallback when the horizon is not usable.
* :func:`ufir_run_cv` — the constant-velocity model with batch initialisation: the estimate is
  the least-squares line through the valid samples of the horizon, kept as window sums (O(1)
  per step for any horizon, the same numbers as the iterative form to rounding).
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels import kf_predict, kf_update
from kinefuse.filters._kernels_blocks import _cov_step
from kinefuse.filters._kernels_ufir import (
    RANK_TOL,
    _first_valid,
    fir_estimate,
    ufir_horizon_axes,
    ufir_taps,
)
from kinefuse.filters._kernels_ufir_cov import (
    N_CUR_COLS,
    N_PREV_COLS,
    cov_at,
    cov_prefix_add,
    cov_suffix_table,
    next_valid,
)


@njit
def ufir_run(
    z, x, P, init, zring, xring, Pring, k0, N, K, stored, fast, axis_blocks, W, P_full,
    F, Finv, H, Q, R, Fa, Finva, Ha, Qa, Ra, Hpinv, P0, o_mean, o_cov, o_obs, o_nu, o_ready,
):  # fmt: skip
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
        xb[:] = x[b]
        Pb[:, :] = P[b]
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
                Pf[:, :] = P_full  # complete horizon: taps inlined (as in fir_estimate)
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
                xb[:] = xf
                Pb[:, :] = Pf
                initialized = True
            elif not initialized:
                if valid:  # SPEC §4.2 initialisation: positions from z, zero velocity, P₀
                    xb[:] = Hpinv @ zt
                    Pb[:, :] = P0
                    initialized = True
            elif not _kf_step_dense(xb, Pb, zt, valid, F, Q, H, R):  # dead zone / fallback
                n_fail += 1
            if stored:
                xs[sl] = xb
                Ps[sl] = Pb
            o_mean[b, t, :] = xb
            o_cov[b, t, :, :] = Pb
            o_obs[b, t] = valid and initialized
            o_ready[b, t] = ready
        x[b, :] = xb
        P[b, :, :] = Pb
        init[b] = initialized
    return n_fail


@njit_inline
def _kf_step_dense(xb, Pb, zt, valid, F, Q, H, R):
    """KF step in place on ``xb, Pb`` (dead zone and fallback, SPEC §6.2-5, §6.3); returns
    False when ``S`` could not be factorised (predict only)."""
    xp, Pp = kf_predict(xb, Pb, F, Q)
    ok = True
    if valid:
        xu, Pu, _nu, _S, ok = kf_update(xp, Pp, zt, H, R)
        xb[:] = xu
        Pb[:, :] = Pu
    else:
        xb[:] = xp
        Pb[:, :] = Pp
    return ok


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
        if not np.isnan(zr[i, 0]):  # time (j - 1) N + i, in ring slot i
            u = float(i)
            Qs[i, 0] += 1.0
            Qs[i, 1] += u
            Qs[i, 2] += u * u
            for a in range(n_a):
                zv = zr[i, a]
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
    ``P̂_k`` depends on where they are. The state's covariance comes from the iterative form
    (:func:`ufir_horizon_axes`, O(N)) at the last step and where the horizon holds exactly K
    valid samples (the next step may fall back to the KF, which needs it): with or without the
    ``o_covb`` output, so that asking for it changes no estimate, bit for bit. Everywhere else
    the ``o_covb`` output comes in O(1) per step from the closed form of
    :mod:`._kernels_ufir_cov` (window tables kept like the sums above; the same numbers to
    rounding); without that output it is not computed. It depends on nothing but which samples
    are valid, so an element with the previous element's pattern (a camera frame lost for every
    joint) copies that element's blocks instead (the same numbers, bit for bit).
    Dead zone and fallback: the per-axis KF step (Joseph form). State ``x (B, 6)``, ``P``,
    ``init``, ``zring (B, N, n_z)`` updated in place; ``o_covb (B, T, 1, 3)`` (one block for all
    axes) may have a zero-length first axis (not wanted). Returns the count of KF updates with
    ``S`` not factorisable.

    Notes
    -----
    The outputs and the start of a new block are written in the loop itself: an inlined helper
    taking the output arrays, or the block's tables, made numba (0.68) keep reference-count
    calls on them (~25 ns a step for the outputs; ~80 ns a block, 8 ns a step at N = 10).
    """
    B, T, n_a = z.shape
    w_cov = o_covb.shape[0] > 0
    Wd = 3 + 2 * n_a
    Qs = np.empty((N + 1, Wd))
    Ps_ = np.empty(Wd)  # prefix sums of the current block
    xs = np.empty((n_a, 2))
    c_prev, c_cur, c_pre = _cov_tables(N if w_cov else -1)  # closed form, for o_covb only
    idt2 = 1.0 / (dt * dt)  # det CᵀC in (position, velocity) = det in (p, β) / dt²
    n_fail = 0
    shared = _shared_patterns(z, zring, w_cov)  # before the loop updates the rings
    for b in range(B):
        zr, ini = zring[b], init[b]
        p00, p01, p11 = _load_axes(x, P, b, xs)
        tab = w_cov and not shared[b]  # keep the closed form's tables (else: copied)
        # block j's sums from the ring (k0-N .. k0-1); a time's ring slot is its index in its block
        j, i_k = k0 // N, k0 % N
        _start_block(zr, j, i_k, Qs, Ps_, tab, c_prev, c_cur, c_pre, dt, q00, q01, q11)
        s_t, s_sl = -1, 0  # the horizon's K-th valid time (-1: not known), and its ring slot
        for t in range(T):
            k = k0 + t
            if i_k == N:  # new block
                j, i_k = j + 1, 0
            left = s_t >= 0 and not np.isnan(zr[i_k, 0])  # time k − N leaves: was it valid?
            valid = _push_row(z, b, t, zr, i_k)
            u_k = float(i_k)
            if i_k == 0 and t > 0:  # new block: suffixes of the finished one, empty prefix
                _suffix_sums(zr, j, N, n_a, Qs)  # (_start_block written out: see Notes)
                for c in range(Wd):
                    Ps_[c] = 0.0
                if tab:
                    cov_suffix_table(zr, j, N, dt, q00, q01, q11, c_prev)
                    c_pre[0] = c_pre[1] = c_pre[2] = 0.0
            if valid:
                _sums_add(Ps_, u_k, zr, i_k)
            if tab:
                cov_prefix_add(c_cur, c_pre, i_k, valid, dt, q00, q01, q11)
                if left:
                    s_t, s_sl = next_valid(zr, s_t, s_sl, k)
            _innovation(o_nu, z, b, t, xs, dt, valid and ini)
            ready = False
            if k >= N - 1:
                im = i_k + 1  # local index of m = k−N+1 in block j−1 (N: empty suffix)
                n = Qs[im, 0] + Ps_[0]
                idet = _ls_line(Ps_, Qs, im, u_k, u_k + N, n, dt, xs) if n >= K else 0.0
                if idet > 0.0:
                    ready = ini = True
                    if n == N:  # complete horizon: data-independent covariance
                        p00, p01, p11 = pfull[0], pfull[1], pfull[2]
                    elif n == K or t == T - 1:  # the state's: iterative, O(N) (Notes)
                        p00, p01, p11 = _iterative_cov(zr, k, N, K, Fa, Finva, Ha, Qa, Ra)
                    elif shared[b]:  # the previous element's block (the same pattern)
                        p00, p01, p11 = o_covb[b - 1, t, 0, 0], o_covb[b - 1, t, 0, 1], o_covb[b - 1, t, 0, 2]  # fmt: skip
                    elif w_cov:  # closed form, O(1) (the K-th valid time tracked as it slides)
                        if s_t < 0:  # not tracked yet: scan the horizon once
                            s_t, s_sl = _kth_valid(zr, k, N, K)
                        p00, p01, p11 = cov_at(
                            c_prev, c_cur, c_pre, N, im, s_t - j * N, i_k, dt, r, idet * idt2
                        )
                    else:
                        p00, p01, p11 = _NAN3  # not needed: not computed
            if not ready:  # initialisation, dead zone or fallback
                p00, p01, p11, ini, fail = _not_ready(
                    z, b, t, valid, ini, xs, p0, p00, p01, p11, dt, q00, q01, q11, r
                )
                n_fail += fail
            for a in range(n_a):  # the outputs (here, not in a helper: see Notes)
                o_mean[b, t, 2 * a] = xs[a, 0] if ini else np.nan
                o_mean[b, t, 2 * a + 1] = xs[a, 1] if ini else np.nan
            if w_cov:
                o_covb[b, t, 0, 0], o_covb[b, t, 0, 1], o_covb[b, t, 0, 2] = (p00, p01, p11) if ini else _NAN3  # fmt: skip
            o_obs[b, t], o_ready[b, t] = valid and ini, ready
            i_k += 1
        init[b] = ini
        if ini:
            _store_axes(x, P, b, xs, p00, p01, p11)
    return n_fail


_NAN3 = (np.nan, np.nan, np.nan)


@njit_inline
def _shared_patterns(z, zring, w_cov):
    """Per element, whether it may copy the previous element's closed-form blocks: the closed
    form depends on nothing but which samples are valid (:func:`_same_pattern`). All False
    without the covariance output."""
    B = z.shape[0]
    shared = np.zeros(B, np.bool_)
    if w_cov:
        for b in range(1, B):
            shared[b] = _same_pattern(z, zring, b)
    return shared


@njit_inline
def _same_pattern(z, zring, b):
    """Whether element ``b`` has element ``b − 1``'s valid samples, in the ring and in ``z``:
    then both take the same branches at every step, and the closed form's covariance (a
    function of the horizon's valid times alone) is the same, bit for bit."""
    N = zring.shape[1]
    for sl in range(N):
        if np.isnan(zring[b, sl, 0]) != np.isnan(zring[b - 1, sl, 0]):
            return False
    T, n_a = z.shape[1], z.shape[2]
    for t in range(T):
        va = True
        vb = True
        for a in range(n_a):
            va = va and np.isfinite(z[b, t, a])
            vb = vb and np.isfinite(z[b - 1, t, a])
        if va != vb:
            return False
    return True


@njit_inline
def _start_block(zr, j, i_k, Qs, Ps_, w_cov, c_prev, c_cur, c_pre, dt, q00, q01, q11):
    """Window sums (and covariance tables) for block ``j`` from the ring: the previous block's
    suffixes, and the current block's prefix through index ``i_k − 1``."""
    N, n_a = zr.shape
    _suffix_sums(zr, j, N, n_a, Qs)
    Ps_[:] = 0.0
    if w_cov:
        cov_suffix_table(zr, j, N, dt, q00, q01, q11, c_prev)
        c_pre[:] = 0.0
    for i in range(i_k):
        ok = not np.isnan(zr[i, 0])
        if ok:
            _sums_add(Ps_, float(i), zr, i)
        if w_cov:
            cov_prefix_add(c_cur, c_pre, i, ok, dt, q00, q01, q11)


@njit_inline
def _kth_valid(zr, k, N, K):
    """Time and ring slot of the K-th valid sample of the horizon ending at ``k`` (which holds at
    least K): :func:`~._kernels_ufir._first_valid`."""
    idx = np.empty(K, np.int64)
    _first_valid(zr, 0, k - N + 1, k, N, K, idx)
    return idx[K - 1], idx[K - 1] % N


@njit_inline
def _not_ready(z, b, t, valid, ini, xs, p0, p00, p01, p11, dt, q00, q01, q11, r):
    """A sample without a FIR estimate: the SPEC §4.2 initialisation (positions from z, zero
    velocity, P₀) at the first valid one, else the per-axis KF step (dead zone / fallback,
    SPEC §6.2-5, §6.3). Returns ``(p00, p01, p11, ini, failed)`` (``failed``: a valid sample
    whose update was skipped)."""
    if not ini:
        if valid:
            p00, p01, p11 = _init_cv(z, b, t, xs, p0)
            ini = True
        return p00, p01, p11, ini, False
    p00, p01, p11, upd = _kf_step_cv(z, b, t, valid, xs, p00, p01, p11, dt, q00, q01, q11, r)
    return p00, p01, p11, ini, valid and not upd


@njit_inline
def _init_cv(z, b, t, xs, p0):
    """SPEC §4.2 initialisation of every axis from ``z[b, t]``: position, zero velocity; returns
    ``P₀``'s block."""
    for a in range(xs.shape[0]):
        xs[a, 0] = z[b, t, a]
        xs[a, 1] = 0.0
    return p0[0], p0[1], p0[2]


@njit_inline
def _load_axes(x, P, b, xs):
    """``xs (n_a, 2)`` from the state ``x[b]``; returns axis 0's covariance block."""
    for a in range(xs.shape[0]):
        xs[a, 0] = x[b, 2 * a]
        xs[a, 1] = x[b, 2 * a + 1]
    return P[b, 0, 0], 0.5 * (P[b, 0, 1] + P[b, 1, 0]), P[b, 1, 1]


@njit_inline
def _store_axes(x, P, b, xs, p00, p01, p11):
    """State ``x[b], P[b]`` from ``xs`` and the covariance block shared by all axes."""
    P[b, :, :] = 0.0
    for a in range(xs.shape[0]):
        i = 2 * a
        x[b, i] = xs[a, 0]
        x[b, i + 1] = xs[a, 1]
        P[b, i, i] = p00
        P[b, i, i + 1] = p01
        P[b, i + 1, i] = p01
        P[b, i + 1, i + 1] = p11


@njit_inline
def _push_row(z, b, t, zr, sl):
    """Store ``z[b, t]`` in ring slot ``sl`` (all NaN when any axis is missing); returns valid."""
    n_a = zr.shape[1]
    valid = True
    for a in range(n_a):
        if not np.isfinite(z[b, t, a]):
            valid = False
    for a in range(n_a):
        zr[sl, a] = z[b, t, a] if valid else np.nan
    return valid


@njit_inline
def _sums_add(S, u, zr, sl):
    """Add the valid ring row ``sl`` at local index ``u`` to ``S = [n, Σu, Σu², Σz_a, Σu z_a]``."""
    S[0] += 1.0
    S[1] += u
    S[2] += u * u
    for a in range(zr.shape[1]):
        zv = zr[sl, a]
        S[3 + 2 * a] += zv
        S[4 + 2 * a] += u * zv


@njit_inline
def _ls_line(Ps_, Qs, im, u_k, e, n, dt, xs):
    """Least-squares line through the horizon's valid samples, from the window sums, into ``xs``.

    ``Ps_``: prefix sums of the current block; ``Qs[im]``: suffix sums of the previous one from
    the horizon's start; ``u_k``, ``e = u_k + N``: the newest sample's local index in each.
    Returns ``1 / det`` of the normal equations in ``(p, β)`` (the covariance's closed form
    reuses it), or 0.0 (``xs`` untouched) when ``CᵀC`` is rank deficient.
    """
    # Σd, Σd² with d = k − t: block j part d = u_k − u, block j−1 part e − u
    D1 = u_k * Ps_[0] - Ps_[1] + e * Qs[im, 0] - Qs[im, 1]
    D2 = (u_k * u_k * Ps_[0] - 2.0 * u_k * Ps_[1] + Ps_[2]
          + e * e * Qs[im, 0] - 2.0 * e * Qs[im, 1] + Qs[im, 2])  # fmt: skip
    # normal equations in (position p, change per sample β): z_t = p − β d
    det = n * D2 - D1 * D1
    if not det > RANK_TOL * n * D2:
        return 0.0
    idet = 1.0 / det
    idet_dt = idet / dt
    for a in range(xs.shape[0]):
        Z0 = Ps_[3 + 2 * a] + Qs[im, 3 + 2 * a]
        Z1 = u_k * Ps_[3 + 2 * a] - Ps_[4 + 2 * a] + e * Qs[im, 3 + 2 * a] - Qs[im, 4 + 2 * a]
        xs[a, 0] = (D2 * Z0 - D1 * Z1) * idet  # x̂ = (CᵀC)⁻¹ Cᵀ Z: position
        xs[a, 1] = (D1 * Z0 - n * Z1) * idet_dt  # velocity = β / dt
    return idet


@njit_inline
def _kf_step_cv(z, b, t, valid, xs, p00, p01, p11, dt, q00, q01, q11, r):
    """Per-axis constant-velocity KF step on ``xs`` (shared covariance block); returns
    ``(p00, p01, p11, updated)``."""
    p00, p01, p11, g0, g1, iS, upd = _cov_step(
        p00, p01, p11, valid, True, 1.0, dt, 0.0, 1.0, q00, q01, q11, 1.0, 0.0, r
    )
    for a in range(xs.shape[0]):
        xp0 = xs[a, 0] + dt * xs[a, 1]
        xp1 = xs[a, 1]
        if upd:
            v = z[b, t, a] - xp0
            xp0 += g0 * v
            xp1 += g1 * v
        xs[a, 0] = xp0
        xs[a, 1] = xp1
    return p00, p01, p11, upd


@njit_inline
def _innovation(o_nu, z, b, t, xs, dt, ok):
    """``z − H F x̂_{k−1}`` per axis (NaN unless ``ok``: observed and initialised)."""
    for a in range(xs.shape[0]):
        o_nu[b, t, a] = z[b, t, a] - (xs[a, 0] + dt * xs[a, 1]) if ok else np.nan


@njit
def _iterative_cov(zr, k, N, K, Fa, Finva, Ha, Qa, Ra):
    """The horizon's covariance block from the iterative form (:func:`ufir_horizon_axes`, O(N));
    NaN when the horizon is not usable."""
    n_a = zr.shape[1]
    xf = np.empty(2 * n_a)
    Pf = np.empty((2 * n_a, 2 * n_a))
    code = ufir_horizon_axes(
        zr, k, N, K, Fa, Finva, Ha, Qa, Ra, np.empty(K, np.int64), np.empty((2, n_a)), xf, Pf
    )
    return (Pf[0, 0], Pf[0, 1], Pf[1, 1]) if code == 1 else _NAN3


@njit_inline
def _cov_tables(N):
    """The closed form's tables (:mod:`._kernels_ufir_cov`) for horizon ``N``; empty for −1."""
    n = N + 1 if N >= 0 else 0
    return np.zeros((n, N_PREV_COLS)), np.zeros((n, N_CUR_COLS)), np.zeros(3)
