"""Compiled batch kernels of the Kalman filter and the RTS smoother (numba), dense and per-axis.

Two forms of each loop over ``(B, T)``:

* ``*_dense``: the reference, built on the single-element kernels of :mod:`._kernels`
  (matrices, Cholesky solves). Used for models that are not block-diagonal per axis (full R).
* ``*_axis``: the exact per-axis decoupling of SPEC §1. When F, Q, H, R and P are block-diagonal
  per axis, the ``n_x``-state problem splits into ``n_axes`` independent 2-state problems with a
  scalar measurement; every line below is scalar arithmetic on the 2x2 block
  ``[[p00, p01], [p01, p11]]`` and no 6x6 matrix is formed. Covariances are still stored as full
  ``(n_x, n_x)`` arrays (off-block entries are zero) so both forms share one data layout.

Textbook symbols (``x, P, F, Q, H, R, K, S, nu, C``), no validation: the callers in
:mod:`kinefuse.filters.kalman` and :mod:`kinefuse.filters.smoothing` validate. Arrays are
float64, C-contiguous; leading batch axes are flattened to ``B``. A measurement row with any NaN
is missing (SPEC §4.2): predict only. Outputs of an element before its first valid measurement
(no initial state) are NaN.
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels import kf_predict, kf_update_status, mahalanobis
from kinefuse.filters._kernels_blocks import _cov_step, rts2_step
from kinefuse.filters._kernels_linalg import (
    CHOL_FAILED,
    CHOL_REGULARISED,
    chol_solve_rows,
    chol_status,
)

__all__ = [
    "axis_block_params",
    "pack_axis_params",
    "state_blocks_shared",
    "state_is_block_diagonal",
    "kf_filter_axis",
    "kf_filter_dense",
    "load_filtered",
    "rts_axis",
    "rts_dense",
]


def axis_block_params(F, Q, H, R, P0):
    """Per-axis blocks of an axis-blocked model (plain NumPy, not compiled).

    Returns ``Fb (n_a, 2, 2)``, ``Qb (n_a, 2, 2)``, ``Hb (n_a, 2)``, ``r (n_a,)``,
    ``P0b (n_a, 2, 2)`` with ``n_a = n_z``; axis ``a`` owns state components ``2a, 2a+1`` and
    measurement component ``a``.
    """
    n_a = H.shape[0]
    Fb = np.empty((n_a, 2, 2))
    Qb = np.empty((n_a, 2, 2))
    P0b = np.empty((n_a, 2, 2))
    Hb = np.empty((n_a, 2))
    r = np.empty(n_a)
    for a in range(n_a):
        s = slice(2 * a, 2 * a + 2)
        Fb[a] = F[s, s]
        Qb[a] = Q[s, s]
        P0b[a] = P0[s, s]
        Hb[a] = H[a, s]
        r[a] = R[a, a]
    return Fb, Qb, Hb, r, P0b


def pack_axis_params(F, Q, H, R, P0):
    """Per-axis model blocks packed for :mod:`._kernels_blocks`.

    Returns ``par (n_a, 10)`` = ``[f00, f01, f10, f11, q00, q01, q11, h0, h1, r]``,
    ``p0 (n_a, 3)`` = ``[p00, p01, p11]`` and ``shared``: True when all axes have the same
    ``par`` and ``p0`` rows (their covariances then coincide; one block is stored).
    """
    Fb, Qb, Hb, r, P0b = axis_block_params(F, Q, H, R, P0)
    n_a = Fb.shape[0]
    par = np.empty((n_a, 10))
    par[:, 0:4] = Fb.reshape(n_a, 4)
    par[:, 4] = Qb[:, 0, 0]
    par[:, 5] = 0.5 * (Qb[:, 0, 1] + Qb[:, 1, 0])
    par[:, 6] = Qb[:, 1, 1]
    par[:, 7:9] = Hb
    par[:, 9] = r
    p0 = np.stack([P0b[:, 0, 0], 0.5 * (P0b[:, 0, 1] + P0b[:, 1, 0]), P0b[:, 1, 1]], axis=1)
    shared = bool(np.all(par == par[0]) and np.all(p0 == p0[0]))
    return par, np.ascontiguousarray(p0), shared


def state_blocks_shared(P: np.ndarray, init: np.ndarray) -> bool:
    """True when every initialised ``P (B, n_x, n_x)`` has the same 2x2 block on every axis
    (as read by the block kernel: ``[p00, (p01 + p10)/2, p11]``)."""
    Pi = P[init]
    if Pi.shape[0] == 0:
        return True
    p00 = Pi[:, 0::2, 0::2].diagonal(axis1=1, axis2=2)
    p11 = Pi[:, 1::2, 1::2].diagonal(axis1=1, axis2=2)
    p01 = 0.5 * (
        Pi[:, 0::2, 1::2].diagonal(axis1=1, axis2=2) + Pi[:, 1::2, 0::2].diagonal(axis1=1, axis2=2)
    )
    return bool(
        np.all(p00 == p00[:, :1]) and np.all(p01 == p01[:, :1]) and np.all(p11 == p11[:, :1])
    )


# --------------------------------------------------------------------------------------------
# Kalman filter
# --------------------------------------------------------------------------------------------


@njit
def state_is_block_diagonal(P, init):
    """True when every initialised ``P[b] (n_x, n_x)`` is zero outside the per-axis 2x2 blocks."""
    B, n_x, _ = P.shape
    for b in range(B):
        if not init[b]:
            continue
        for i in range(n_x):
            for j in range(n_x):
                if i // 2 != j // 2 and P[b, i, j] != 0.0:
                    return False
    return True


@njit
def _fill_nan_step(mean, cov, pos, obs, nu, dist, b, t):
    mean[b, t, :] = np.nan
    cov[b, t, :, :] = np.nan
    pos[b, t, :] = np.nan
    obs[b, t] = False
    nu[b, t, :] = np.nan
    dist[b, t] = np.nan


@njit
def kf_filter_axis(z, x, P, init, Fb, Qb, Hb, r, P0b, mean, cov, pos, obs, nu, dist):
    """Per-axis KF over ``z (B, T, n_z)``; state ``x (B, n_x)``, ``P``, ``init (B,)`` in place.

    Outputs (preallocated; ``cov`` zero-filled by the caller): ``mean (B, T, n_x)``,
    ``cov (B, T, n_x, n_x)``, ``pos (B, T, n_z)``, ``obs (B, T)``, ``nu (B, T, n_z)``,
    ``dist (B, T)`` (NIS ``νᵀS⁻¹ν = Σ_a ν_a²/S_a``, S diagonal). The covariance arithmetic is
    :func:`._kernels_blocks._cov_step` (general form), that of the block layout.
    """
    B, T, n_z = z.shape
    n_a = Fb.shape[0]
    xs = np.empty((n_a, 2))  # per-axis state [position, velocity]
    Ps = np.empty((n_a, 3))  # per-axis covariance [p00, p01, p11]
    for b in range(B):
        for a in range(n_a):
            i = 2 * a
            xs[a, 0] = x[b, i]
            xs[a, 1] = x[b, i + 1]
            Ps[a, 0] = P[b, i, i]
            Ps[a, 1] = 0.5 * (P[b, i, i + 1] + P[b, i + 1, i])
            Ps[a, 2] = P[b, i + 1, i + 1]
        ini = init[b]
        for t in range(T):
            valid = True
            for a in range(n_z):
                if np.isnan(z[b, t, a]):
                    valid = False
            if not ini:
                if not valid:
                    _fill_nan_step(mean, cov, pos, obs, nu, dist, b, t)
                    continue
                _init_axes(z, b, t, Hb, P0b, xs, Ps, nu)
                ini = True
                obs[b, t] = True
                dist[b, t] = np.nan
            else:
                updated, d = _kf_axes_step(z, b, t, valid, Fb, Qb, Hb, r, xs, Ps, nu)
                obs[b, t] = updated
                if updated:
                    dist[b, t] = d
                else:
                    dist[b, t] = np.nan
                    for a in range(n_z):
                        nu[b, t, a] = np.nan
            _put_axis_states(mean, cov, b, t, xs, Ps)
            for a in range(n_a):
                pos[b, t, a] = Hb[a, 0] * xs[a, 0] + Hb[a, 1] * xs[a, 1]
        init[b] = ini
        if ini:
            x[b, :] = 0.0
            P[b, :, :] = 0.0
            for a in range(n_a):
                i = 2 * a
                x[b, i] = xs[a, 0]
                x[b, i + 1] = xs[a, 1]
                P[b, i, i] = Ps[a, 0]
                P[b, i, i + 1] = Ps[a, 1]
                P[b, i + 1, i] = Ps[a, 1]
                P[b, i + 1, i + 1] = Ps[a, 2]


@njit_inline
def _put_axis_states(mean, cov, b, t, xs, Ps):
    """Per-axis states ``xs (n_a, 2)`` and blocks ``Ps (n_a, 3)`` into ``mean[b, t]`` and the
    axis blocks of ``cov[b, t]`` (full-matrix layout)."""
    for a in range(xs.shape[0]):
        i = 2 * a
        mean[b, t, i] = xs[a, 0]
        mean[b, t, i + 1] = xs[a, 1]
        cov[b, t, i, i] = Ps[a, 0]
        cov[b, t, i, i + 1] = Ps[a, 1]
        cov[b, t, i + 1, i] = Ps[a, 1]
        cov[b, t, i + 1, i + 1] = Ps[a, 2]


@njit_inline
def _init_axes(z, b, t, Hb, P0b, xs, Ps, nu):
    """SPEC §4.2 initialisation [J]: ``x₀ = H⁺ z`` (positions = z, velocities = 0), ``P₀``."""
    for a in range(xs.shape[0]):
        h0 = Hb[a, 0]
        h1 = Hb[a, 1]
        hh = h0 * h0 + h1 * h1
        xs[a, 0] = h0 * z[b, t, a] / hh
        xs[a, 1] = h1 * z[b, t, a] / hh
        Ps[a, 0] = P0b[a, 0, 0]
        Ps[a, 1] = P0b[a, 0, 1]
        Ps[a, 2] = P0b[a, 1, 1]
        nu[b, t, a] = np.nan


@njit_inline
def _kf_axes_step(z, b, t, valid, Fb, Qb, Hb, r, xs, Ps, nu):
    """One KF step of every axis in ``xs``/``Ps``; returns ``(updated, NIS)``.

    ``updated`` is False if ``z`` is missing or an axis' ``S`` cannot be factorised (SPEC
    §13: that axis predicts only; the caller then marks the whole step unobserved).
    """
    d = 0.0
    updated = valid
    for a in range(xs.shape[0]):
        f00 = Fb[a, 0, 0]
        f01 = Fb[a, 0, 1]
        f10 = Fb[a, 1, 0]
        f11 = Fb[a, 1, 1]
        h0 = Hb[a, 0]
        h1 = Hb[a, 1]
        x0 = xs[a, 0]
        x1 = xs[a, 1]
        # SPEC §4.2 kf_predict / paper A Eq. 5 (no noise term): x⁻ = F x
        xp0 = f00 * x0 + f01 * x1
        xp1 = f10 * x0 + f11 * x1
        p00, p01, p11, k0, k1, iS, upd = _cov_step(
            Ps[a, 0], Ps[a, 1], Ps[a, 2], valid, False,
            f00, f01, f10, f11, Qb[a, 0, 0], Qb[a, 0, 1], Qb[a, 1, 1], h0, h1, r[a],
        )  # fmt: skip
        Ps[a, 0] = p00
        Ps[a, 1] = p01
        Ps[a, 2] = p11
        if upd:
            v = z[b, t, a] - (h0 * xp0 + h1 * xp1)  # ν = z − H x⁻
            xp0 = xp0 + k0 * v  # Eq. 8: x = x⁻ + K ν
            xp1 = xp1 + k1 * v
            nu[b, t, a] = v
            d += v * v * iS  # NIS νᵀS⁻¹ν, S diagonal across axes
        elif valid:
            updated = False  # S could not be factorised
        else:
            nu[b, t, a] = np.nan
        xs[a, 0] = xp0
        xs[a, 1] = xp1
    return updated, d


@njit
def kf_filter_dense(z, x, P, init, F, Q, H, R, P0, Hpinv, mean, cov, pos, obs, nu, dist):
    """Dense reference KF over ``z (B, T, n_z)`` (SPEC §4.2); same in/out contract as the axis form.

    ``Hpinv (n_x, n_z)`` is the pseudo-inverse of H used for ``x₀ = H⁺ z``. Returns the number
    of updates whose ``S`` had to be regularised (SPEC §13; the caller warns).
    """
    B, T, n_z = z.shape
    n_reg = 0
    for b in range(B):
        xb = x[b].copy()
        Pb = P[b].copy()
        ini = init[b]
        for t in range(T):
            zt = z[b, t].copy()
            valid = not np.any(np.isnan(zt))
            if not ini:
                if not valid:
                    _fill_nan_step(mean, cov, pos, obs, nu, dist, b, t)
                    continue
                xb = Hpinv @ zt  # SPEC §4.2 initialisation [J]
                Pb = P0.copy()
                ini = True
                obs[b, t] = True
                nu[b, t, :] = np.nan
                dist[b, t] = np.nan
            else:
                xb, Pb = kf_predict(xb, Pb, F, Q)  # paper A Eqs. 5-6 (SPEC §4.1 form)
                ok = False
                if valid:
                    xn, Pn, v, S, status = kf_update_status(xb, Pb, zt, H, R)  # Eqs. 7-9, Joseph
                    ok = status != CHOL_FAILED
                    n_reg += status == CHOL_REGULARISED
                    if ok:
                        xb = xn
                        Pb = Pn
                        nu[b, t, :] = v
                        dist[b, t] = mahalanobis(v, S)  # NIS νᵀS⁻¹ν
                obs[b, t] = ok
                if not ok:
                    nu[b, t, :] = np.nan
                    dist[b, t] = np.nan
            mean[b, t, :] = xb
            cov[b, t, :, :] = Pb
            pos[b, t, :] = H @ xb
        x[b, :] = xb
        P[b, :, :] = Pb
        init[b] = ini
    return n_reg


# --------------------------------------------------------------------------------------------
# RTS smoother (SPEC §9): fixed interval (lag < 0) or fixed lag (lag >= 0)
# --------------------------------------------------------------------------------------------


@njit
def _segment_ends(mean, mask, b):
    """``end[t]``: last index of the usable run containing ``t`` (-1 where not usable)."""
    T = mean.shape[1]
    end = np.empty(T, dtype=np.int64)
    nxt = -1
    for t in range(T - 1, -1, -1):
        if mask[b, t] and np.isfinite(mean[b, t, 0]):
            if nxt < 0:
                nxt = t
            end[t] = nxt
        else:
            end[t] = -1
            nxt = -1
    return end


@njit
def _copy_filtered(mean, cov, sm_mean, sm_cov, b, t, want_cov):
    sm_mean[b, t, :] = mean[b, t, :]
    if want_cov:
        sm_cov[b, t, :, :] = cov[b, t, :, :]


@njit
def _offblock_abs_sum(cov2, b, t, off):
    """Sum of |entries| of ``cov[b, t]`` outside the axis blocks (``cov2`` = cov as (B, T, n_x²))."""
    acc = 0.0
    for k in range(off.shape[0]):
        acc += abs(cov2[b, t, off[k]])
    return acc


@njit
def _rts_axis_pass(mean, cov, cov2, off, Fb, Qb, b, e, t0, sx, sP, sm_mean, sm_cov, write_all):
    """Backward RTS pass on every axis from the filtered estimate at ``e`` down to ``t0``.

    Stores every sample ``t0..e`` (``write_all``) or only ``t0``. Returns False if a stored
    sample's filtered covariance has cross-axis entries (``write_all`` only).
    """
    n_a = Fb.shape[0]
    for a in range(n_a):  # x̃_e = x̂_e, P̃_e = P̂_e
        i = 2 * a
        sx[a, 0] = mean[b, e, i]
        sx[a, 1] = mean[b, e, i + 1]
        sP[a, 0] = cov[b, e, i, i]
        sP[a, 1] = cov[b, e, i, i + 1]
        sP[a, 2] = cov[b, e, i + 1, i + 1]
    for t in range(e, t0 - 1, -1):
        store = write_all or t == t0
        if write_all and _offblock_abs_sum(cov2, b, t, off) != 0.0:
            return False
        if t < e:
            for a in range(n_a):
                i = 2 * a
                f00 = Fb[a, 0, 0]
                f01 = Fb[a, 0, 1]
                f10 = Fb[a, 1, 0]
                f11 = Fb[a, 1, 1]
                m0 = mean[b, t, i]
                m1 = mean[b, t, i + 1]
                ok, c00, c01, c10, c11, n00, n01, n11 = rts2_step(
                    cov[b, t, i, i], cov[b, t, i, i + 1], cov[b, t, i + 1, i + 1],
                    sP[a, 0], sP[a, 1], sP[a, 2], False,
                    f00, f01, f10, f11, Qb[a, 0, 0], Qb[a, 0, 1], Qb[a, 1, 1],
                )  # fmt: skip
                sP[a, 0] = n00
                sP[a, 1] = n01
                sP[a, 2] = n11
                if not ok:  # P⁻ not PD: restart from the filtered estimate at t
                    sx[a, 0] = m0
                    sx[a, 1] = m1
                    continue
                # x̃_t = x̂_t + C (x̃_{t+1} − F x̂_t)
                e0 = sx[a, 0] - (f00 * m0 + f01 * m1)
                e1 = sx[a, 1] - (f10 * m0 + f11 * m1)
                sx[a, 0] = m0 + c00 * e0 + c01 * e1
                sx[a, 1] = m1 + c10 * e0 + c11 * e1
        if store:
            _put_axis_states(sm_mean, sm_cov, b, t, sx, sP)
    return True


@njit
def rts_axis(mean, cov, mask, Fb, Qb, lag, sm_mean, sm_cov):
    """Per-axis RTS over filtered ``mean (B, T, n_x)``, ``cov (B, T, n_x, n_x)``.

    Smooths independently within each maximal run of samples where ``mask (B, T)`` is True and
    the filtered mean is finite; other samples are copied. ``lag < 0``: fixed interval; else the
    estimate at ``t`` conditions on measurements up to ``min(t + lag, end of run)`` (O(T·lag)).
    ``sm_cov`` must be zero-filled by the caller. A step whose ``P⁻`` is not positive definite
    restarts the pass from the filtered estimate at that sample.

    Returns False (outputs incomplete) as soon as a smoothed sample's filtered covariance has
    cross-axis entries: the decoupling is then not exact and the caller must use the dense form.
    """
    B, T, n_x = mean.shape
    n_a = Fb.shape[0]
    cov2 = cov.reshape(B, T, n_x * n_x)
    off = np.empty(n_x * n_x - 4 * n_a, dtype=np.int64)
    k = 0
    for i in range(n_x):
        for j in range(n_x):
            if i // 2 != j // 2:
                off[k] = i * n_x + j
                k += 1
    sx = np.empty((n_a, 2))
    sP = np.empty((n_a, 3))
    for b in range(B):
        end = _segment_ends(mean, mask, b)
        if lag < 0:
            t = T - 1
            while t >= 0:
                if end[t] < 0:
                    _copy_filtered(mean, cov, sm_mean, sm_cov, b, t, True)
                    t -= 1
                    continue
                t0 = t  # start of the run ending at t
                while t0 > 0 and end[t0 - 1] == t:
                    t0 -= 1
                if not _rts_axis_pass(
                    mean, cov, cov2, off, Fb, Qb, b, t, t0, sx, sP, sm_mean, sm_cov, True
                ):
                    return False
                t = t0 - 1
        else:
            for t in range(T):
                if end[t] < 0:
                    _copy_filtered(mean, cov, sm_mean, sm_cov, b, t, True)
                    continue
                if _offblock_abs_sum(cov2, b, t, off) != 0.0:
                    return False
                e = min(end[t], t + lag)
                _rts_axis_pass(
                    mean, cov, cov2, off, Fb, Qb, b, e, t, sx, sP, sm_mean, sm_cov, False
                )
    return True


@njit_inline
def _rts_dense_step(F, Q, mean, cov, b, t, s, Ps, FP, Pp, L, D, d, want_cov, n):
    """One backward RTS step (SPEC §9), dense, in place on ``s, Ps`` (``x̃_{t+1}, P̃_{t+1}`` in,
    ``x̃_t, P̃_t`` out) from the filtered ``mean[b, t], cov[b, t]``; no allocation and no array
    view (``FP, Pp, L, D (n, n)``, ``d (n,)``: scratch; a view made per step costs numba
    reference-count calls). Returns the ``CHOL_*`` status of ``P⁻``; on ``CHOL_FAILED`` the
    step returns the filtered estimate. Without ``want_cov`` only the mean is advanced (its
    recursion reads the filtered covariances, never ``P̃``). ``n``: the state size (a
    compile-time constant in :func:`rts_dense6`)."""
    for i in range(n):  # F P̂_t
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += F[i, k] * cov[b, t, k, j]
            FP[i, j] = acc
    for i in range(n):  # P⁻_{t+1} = F P̂_t Fᵀ + Q (symmetrised)
        for j in range(i + 1):
            acc = 0.0
            for k in range(n):
                acc += FP[i, k] * F[j, k]
            Pp[i, j] = acc + 0.5 * (Q[i, j] + Q[j, i])
    for i in range(n):
        for j in range(i + 1, n):
            Pp[i, j] = Pp[j, i]
    status = chol_status(Pp, L, n)
    if status == CHOL_FAILED:
        for i in range(n):
            s[i] = mean[b, t, i]
            if want_cov:
                for j in range(n):
                    Ps[i, j] = cov[b, t, i, j]
        return status
    chol_solve_rows(L, FP, n, n)  # FP ← Cᵀ = (P⁻)⁻¹ F P̂_t, i.e. C = P̂_t Fᵀ (P⁻)⁻¹
    for i in range(n):  # d = x̃_{t+1} − F x̂_t;  D = P̃_{t+1} − P⁻
        acc = s[i]
        for k in range(n):
            acc -= F[i, k] * mean[b, t, k]
        d[i] = acc
        if want_cov:
            for j in range(n):
                D[i, j] = Ps[i, j] - Pp[i, j]
    for i in range(n):  # x̃_t = x̂_t + C d
        acc = mean[b, t, i]
        for k in range(n):
            acc += FP[k, i] * d[k]
        s[i] = acc
    if not want_cov:
        return status
    for i in range(n):  # Pp ← C D (rows of C are the columns of FP)
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += FP[k, i] * D[k, j]
            Pp[i, j] = acc
    for i in range(n):  # P̃_t = P̂_t + C D Cᵀ (symmetrised)
        for j in range(i + 1):
            acc = 0.0
            for k in range(n):
                acc += Pp[i, k] * FP[k, j]
            Ps[i, j] = acc
    for i in range(n):
        for j in range(i + 1):
            v = 0.5 * (cov[b, t, i, j] + cov[b, t, j, i]) + Ps[i, j]
            Ps[i, j] = v
            Ps[j, i] = v
    return status


@njit_inline
def load_filtered(mean, cov, b, t, s, Ps, n):
    """``s ← mean[b, t]``, ``Ps ← cov[b, t]`` (``n`` states; element loops, no array view): the
    start of an RTS run, ``x̃_{t_end} = x̂_{t_end}``, ``P̃_{t_end} = P̂_{t_end}``. Shared with the
    ``"kinefuse"`` fusion's RTS (:mod:`kinefuse.pipelines._kinefuse_kernels`)."""
    for i in range(n):
        s[i] = mean[b, t, i]
        for j in range(n):
            Ps[i, j] = cov[b, t, i, j]


@njit_inline
def _put_smoothed(sm_mean, sm_cov, b, t, s, Ps, want_cov, n, cidx):
    """Store ``x̃_t`` (and the rows/columns ``cidx`` of ``P̃_t``) at ``(b, t)`` (element loops,
    no view)."""
    for i in range(n):
        sm_mean[b, t, i] = s[i]
    if want_cov:
        k = cidx.shape[0]
        for i in range(k):
            for j in range(k):
                sm_cov[b, t, i, j] = Ps[cidx[i], cidx[j]]


@njit_inline
def _rts_dense_loop(mean, cov, mask, F, Q, lag, sm_mean, sm_cov, n_x, cidx):
    """The loop of :func:`rts_dense` for states of size ``n_x``."""
    B, T = mean.shape[:2]
    want_cov = sm_cov.shape[0] > 0
    n_reg = 0
    s = np.empty(n_x)
    Ps = np.empty((n_x, n_x))
    FP, Pp = np.zeros((n_x, n_x)), np.zeros((n_x, n_x))
    L, D, d = np.zeros((n_x, n_x)), np.zeros((n_x, n_x)), np.zeros(n_x)
    for b in range(B):
        end = _segment_ends(mean, mask, b)
        if lag < 0:
            for t in range(T - 1, -1, -1):
                if end[t] < 0:
                    load_filtered(mean, cov, b, t, s, Ps, n_x)  # outside the runs: the filtered
                    _put_smoothed(sm_mean, sm_cov, b, t, s, Ps, want_cov, n_x, cidx)
                    continue
                if t == end[t]:
                    load_filtered(mean, cov, b, t, s, Ps, n_x)
                else:
                    st = _rts_dense_step(
                        F, Q, mean, cov, b, t, s, Ps, FP, Pp, L, D, d, want_cov, n_x
                    )
                    n_reg += st == CHOL_REGULARISED
                _put_smoothed(sm_mean, sm_cov, b, t, s, Ps, want_cov, n_x, cidx)
        else:
            for t in range(T):
                if end[t] < 0:
                    load_filtered(mean, cov, b, t, s, Ps, n_x)  # outside the runs: the filtered
                    _put_smoothed(sm_mean, sm_cov, b, t, s, Ps, want_cov, n_x, cidx)
                    continue
                e = min(end[t], t + lag)
                load_filtered(mean, cov, b, e, s, Ps, n_x)
                for u in range(e - 1, t - 1, -1):
                    st = _rts_dense_step(
                        F, Q, mean, cov, b, u, s, Ps, FP, Pp, L, D, d, want_cov, n_x
                    )
                    n_reg += st == CHOL_REGULARISED
                _put_smoothed(sm_mean, sm_cov, b, t, s, Ps, want_cov, n_x, cidx)
    return n_reg


@njit
def rts_dense(mean, cov, mask, F, Q, lag, sm_mean, sm_cov, cidx):
    """Dense reference RTS; same contract as :func:`rts_axis`. A zero-length ``sm_cov`` (first
    axis 0) asks for the smoothed means only: the covariance recursion is skipped. ``sm_cov``
    of shape ``(B, T, k, k)`` receives the rows and columns ``cidx (k,)`` of the smoothed
    covariance (e.g. the position states), ``cidx = arange(n_x)`` the whole matrix.

    Returns the number of backward steps whose ``P⁻`` had to be regularised (SPEC §13).
    """
    return _rts_dense_loop(mean, cov, mask, F, Q, lag, sm_mean, sm_cov, mean.shape[2], cidx)


@njit
def rts_dense6(mean, cov, mask, F, Q, lag, sm_mean, sm_cov, cidx):
    """:func:`rts_dense` for 6 states (3-D constant velocity: paper B's IMM output), the size a
    compile-time constant so that the compiler unrolls the 6x6 loops. The same arithmetic."""
    if mean.shape[2] != 6:
        raise ValueError("rts_dense6 takes 6 states")
    return _rts_dense_loop(mean, cov, mask, F, Q, lag, sm_mean, sm_cov, 6, cidx)
