"""IMM kernels (numba): mixing, log-domain model probabilities, combination, batched time loop.

Paper B (Xu 2023) Eqs. 24-48 as corrected by SPEC §8.2-§8.3. Textbook symbols, no validation.
Shapes: ``M`` models, ``n_x`` states, ``n_z`` measurement components; ``mu (M,)``,
``xs (M, n_x)``, ``Ps (M, n_x, n_x)``, ``Gamma (M, M)`` with ``Gamma[i, m] = P(m at t | i at t-1)``.

The per-model KF predict/update are the dense reference kernels of :mod:`._kernels`
(``kf_predict``, ``kf_update`` with the Joseph form, ``chol_lower`` with the SPEC §13 ladder).
:func:`imm_run` uses allocation-free ``_*_into`` transcriptions of them and of the IMM steps:
every scratch array is allocated once per call and written in place, and every sum is
accumulated in the same order as the allocating kernel, so the results are bitwise identical
to composing the allocating kernels (checked against a NumPy transcription in
``tests/test_imm.py``). Sizes are passed explicitly so that :func:`imm_run` can hand the
compiler constant sizes for the IMM of paper B (see there).

No per-axis form: even when every model is block-diagonal per axis, the spread-of-means terms
of the mixing (Eq. 28) and of the combination (Eq. 48), ``(x_i − x̄)(x_i − x̄)ᵀ``, couple the
axes, so the IMM does not decouple per axis. The dense form is exact for all models.
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels import chol_lower, chol_solve_into, matmul_into
from kinefuse.filters._kernels_linalg import (
    CHOL_FAILED,
    CHOL_REGULARISED,
    chol_status,
    symmetrize_into,
)

LOG_2PI = float(np.log(2.0 * np.pi))


# --------------------------------------------------------------------------------------------
# Allocation-free single-element kernels (outputs and scratch passed in, written in place).
# Each one reproduces the operation order of its allocating reference in :mod:`._kernels`.
# --------------------------------------------------------------------------------------------


@njit
def _finite1(a, n):
    for i in range(n):
        if not np.isfinite(a[i]):
            return False
    return True


@njit
def _finite2(a, n):
    for i in range(n):
        for j in range(n):
            if not np.isfinite(a[i, j]):
                return False
    return True


@njit_inline
def _matmul_bt_add(A, B, Q, C, n, m, k):
    """``C[:n, :m] = A[:n, :k] B[:m, :k]ᵀ + Q[:n, :m]`` (each sum from 0, then ``+ Q``)."""
    for i in range(n):
        for j in range(m):
            s = 0.0
            for p in range(k):
                s += A[i, p] * B[j, p]
            C[i, j] = s + Q[i, j]


@njit_inline
def _kf_predict_into(x, P, F, Q, x_pred, P_pred, FP, n):
    """KF prediction, SPEC §4.2 (as :func:`._kernels.kf_predict`); ``FP (n, n)`` scratch."""
    for i in range(n):
        s = 0.0
        for p in range(n):
            s += F[i, p] * x[p]
        x_pred[i] = s  # SPEC §4.2: x⁻ = F x
    matmul_into(F, P, FP, n, n, n)
    _matmul_bt_add(FP, F, Q, P_pred, n, n, n)  # SPEC §4.2: P⁻ = F P Fᵀ + Q
    symmetrize_into(P_pred, n)


@njit_inline
def _kf_update_into(x_pred, P_pred, z, H, R, x, P, nu, S, L, HP, Kt, A, AP, KR, y, n_x, n_z):
    """KF update with the Joseph form, SPEC §4.2 (as :func:`._kernels.kf_update`).

    Writes ``x, P`` (only when ok), ``nu, S`` and the Cholesky factor ``L`` of ``S``; returns
    the ``CHOL_*`` status of ``S`` (``CHOL_FAILED``: not factorised, ``x, P`` untouched). Scratch: ``HP (n_z, n_x)``,
    ``Kt (n_z, n_x)`` (= Kᵀ), ``A, AP (n_x, n_x)``, ``KR (n_x, n_z)``, ``y (n_z,)``.
    """
    for i in range(n_z):
        s = 0.0
        for p in range(n_x):
            s += H[i, p] * x_pred[p]
        nu[i] = z[i] - s  # SPEC §4.2: ν = z − H x⁻
    matmul_into(H, P_pred, HP, n_z, n_x, n_x)  # H P⁻ = (P⁻ Hᵀ)ᵀ
    _matmul_bt_add(HP, H, R, S, n_z, n_z, n_x)  # SPEC §4.2: S = H P⁻ Hᵀ + R
    status = chol_status(S, L, n_z)
    if status == CHOL_FAILED:
        return status
    chol_solve_into(L, HP, Kt, y, n_z, n_x)  # SPEC §4.2: Kᵀ = solve(S, H P⁻), column by column
    for i in range(n_x):
        s = 0.0
        for p in range(n_z):
            s += Kt[p, i] * nu[p]
        x[i] = x_pred[i] + s  # SPEC §4.2: x = x⁻ + K ν
    matmul_into(Kt, H, A, n_x, n_z, n_x, True)  # A = I − K H
    for i in range(n_x):
        for j in range(n_x):
            A[i, j] = -A[i, j]
        A[i, i] += 1.0
    matmul_into(A, P_pred, AP, n_x, n_x, n_x)
    matmul_into(Kt, R, KR, n_x, n_z, n_z, True)  # K R
    for i in range(n_x):
        for j in range(n_x):
            s = 0.0
            for p in range(n_x):
                s += AP[i, p] * A[j, p]
            s2 = 0.0
            for p in range(n_z):
                s2 += KR[i, p] * Kt[p, j]
            P[i, j] = s + s2  # SPEC §4.2 Joseph form: P = A P⁻ Aᵀ + K R Kᵀ
    symmetrize_into(P, n_x)
    return status


@njit
def _loglik_chol(nu, L, y, n):
    """``(log Λ, νᵀS⁻¹ν)`` from the Cholesky factor ``L`` of ``S`` (see :func:`gauss_loglik`)."""
    quad = 0.0
    logdet = 0.0
    for i in range(n):
        s = nu[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]  # forward substitution: y = L⁻¹ ν
        quad += y[i] * y[i]  # νᵀ S⁻¹ ν = ‖L⁻¹ ν‖²
        logdet += 2.0 * np.log(L[i, i])  # log det S = 2 Σ log L_ii
    if not np.isfinite(quad):
        return -np.inf, np.inf
    return -0.5 * (quad + logdet + n * LOG_2PI), quad  # SPEC §8.3 logΛ


@njit
def _apply_floor_into(mu, floor, fixed, M):
    """:func:`apply_floor` with a boolean scratch ``fixed (M,)``."""
    if floor <= 0.0:
        return
    for m in range(M):
        fixed[m] = False
    for _it in range(M + 1):
        n_fixed = 0
        free_sum = 0.0
        for m in range(M):
            if fixed[m]:
                n_fixed += 1
            else:
                free_sum += mu[m]
        target = 1.0 - n_fixed * floor
        n_free = M - n_fixed
        changed = False
        for m in range(M):
            if not fixed[m]:
                if free_sum > 0.0:
                    mu[m] *= target / free_sum
                else:
                    mu[m] = target / n_free
                if mu[m] < floor:
                    mu[m] = floor
                    fixed[m] = True
                    changed = True
        if not changed:
            return


@njit
def _imm_mix_into(mu, Gamma, xs, Ps, cbar, x0, P0, w, d, M, n_x):
    """:func:`imm_mix` writing ``cbar (M,)``, ``x0 (M, n_x)``, ``P0 (M, n_x, n_x)``.

    Scratch ``w (M,)``, ``d (n_x,)``.
    """
    for m in range(M):
        c = 0.0
        for i in range(M):
            c += Gamma[i, m] * mu[i]  # Eq. 25 (corrected): c̄_m = Σ_i Γ_im μ_i
        cbar[m] = c
    for m in range(M):
        for i in range(M):
            if cbar[m] > 0.0:
                w[i] = Gamma[i, m] * mu[i] / cbar[m]  # Eq. 26 (corrected): μ_{i|m} = Γ_im μ_i / c̄_m
            else:
                w[i] = mu[i]  # unreachable model (c̄_m = 0): no interaction
        for k in range(n_x):
            x0[m, k] = 0.0
        for i in range(M):
            wi = w[i]
            for k in range(n_x):
                x0[m, k] += wi * xs[i, k]  # Eq. 27: x0_m = Σ_i μ_{i|m} x_i
        for j in range(n_x):
            for k in range(n_x):
                P0[m, j, k] = 0.0
        for i in range(M):
            wi = w[i]
            for k in range(n_x):
                d[k] = xs[i, k] - x0[m, k]
            for j in range(n_x):
                wd = wi * d[j]
                for k in range(n_x):
                    P0[m, j, k] += wi * Ps[i, j, k]  # Eq. 28: P0_m = Σ_i μ_{i|m}(P_i + d dᵀ)
                    P0[m, j, k] += wd * d[k]
        symmetrize_into(P0[m], n_x)


@njit_inline
def _logsumexp_masked(a, mask, masked, M):
    """``log Σ_m exp(a[m])`` over ``m`` with ``mask[m]`` (all ``m`` unless ``masked``); ``−inf``
    when every such entry is ``−inf``."""
    mx = -np.inf
    for m in range(M):
        if (mask[m] or not masked) and a[m] > mx:
            mx = a[m]
    if mx == -np.inf:
        return -np.inf
    s = 0.0
    for m in range(M):
        if mask[m] or not masked:
            s += np.exp(a[m] - mx)
    return mx + np.log(s)


@njit
def _imm_probabilities_into(loglik, updated, cbar, mu_floor, mu, ll, lw, fixed, M):
    """:func:`imm_probabilities` writing ``mu (M,)``; scratch ``ll, lw (M,)``, ``fixed (M,)``."""
    n_upd = 0
    for m in range(M):
        if updated[m]:
            n_upd += 1
    fill = 0.0
    if n_upd > 0:  # log-mean-exp of the updated models' log-likelihoods
        fill = _logsumexp_masked(loglik, updated, True, M) - np.log(n_upd)
    if n_upd == 0 or fill == -np.inf:
        for m in range(M):
            ll[m] = 0.0
    else:
        ref = -np.inf
        for m in range(M):
            ll[m] = loglik[m] if updated[m] else fill
            if ll[m] > ref:
                ref = ll[m]
        for m in range(M):
            ll[m] -= ref  # shift so that max log Λ = 0 before adding log c̄ (no absorption)
    for m in range(M):
        lw[m] = ll[m] + np.log(cbar[m]) if cbar[m] > 0.0 else -np.inf  # log(Λ_m c̄_m)
    lc = _logsumexp_masked(lw, updated, False, M)  # Eq. 45: log c = log Σ_m Λ_m c̄_m
    total = 0.0
    for m in range(M):
        mu[m] = np.exp(lw[m] - lc)  # Eq. 46 (corrected): μ_m = Λ_m c̄_m / c
        total += mu[m]
    for m in range(M):
        mu[m] /= total  # exact normalisation against rounding
    _apply_floor_into(mu, mu_floor, fixed, M)


@njit
def _imm_combine_into(mu, xs, Ps, x, P, d, M, n_x):
    """:func:`imm_combine` writing ``x (n_x,)``, ``P (n_x, n_x)``; scratch ``d (n_x,)``."""
    for k in range(n_x):
        x[k] = 0.0
    for m in range(M):
        for k in range(n_x):
            x[k] += mu[m] * xs[m, k]  # Eq. 47
    for j in range(n_x):
        for k in range(n_x):
            P[j, k] = 0.0
    for m in range(M):
        wm = mu[m]
        for k in range(n_x):
            d[k] = xs[m, k] - x[k]
        for j in range(n_x):
            wd = wm * d[j]
            for k in range(n_x):
                P[j, k] += wm * Ps[m, j, k]  # Eq. 48
                P[j, k] += wd * d[k]
    symmetrize_into(P, n_x)


# --------------------------------------------------------------------------------------------
# Allocating single-step kernels (reference and test entry points).
# --------------------------------------------------------------------------------------------


@njit
def gauss_loglik(nu, S):
    """Gaussian log-likelihood of an innovation, SPEC §8.3 (paper B Eqs. 39-40 in log form).

    ``log Λ = −½ (νᵀS⁻¹ν + log det S + n_z log 2π)``. Returns ``(log Λ, νᵀS⁻¹ν, ok)``; an
    overflowing ``νᵀS⁻¹ν`` gives ``log Λ = −inf`` (never NaN).
    """
    L, ok = chol_lower(S)
    if not ok:
        return np.nan, np.nan, False
    ll, quad = _loglik_chol(nu, L, np.empty(nu.shape[0]), nu.shape[0])
    return ll, quad, True


@njit
def logsumexp(a):
    """``log Σ exp(a)``; ``−inf`` when every entry is ``−inf``."""
    mx = -np.inf
    for v in a:
        if v > mx:
            mx = v
    if mx == -np.inf:
        return -np.inf
    s = 0.0
    for v in a:
        s += np.exp(v - mx)
    return mx + np.log(s)


@njit
def apply_floor(mu, floor):
    """Raise entries below ``floor`` to exactly ``floor`` and rescale the rest to sum to 1.

    SPEC §8.3 "μ floor" (avoid lock-in). Requires ``floor < 1/M``. In place.
    """
    M = mu.shape[0]
    _apply_floor_into(mu, floor, np.zeros(M, dtype=np.bool_), M)


@njit
def imm_mix(mu, Gamma, xs, Ps):
    """IMM interaction (mixing) step, paper B Eqs. 25-28 as corrected in SPEC §8.2.

    Returns ``(cbar (M,), x0 (M, n_x), P0 (M, n_x, n_x))``.
    """
    M, n_x = xs.shape
    cbar = np.empty(M)
    x0 = np.empty((M, n_x))
    P0 = np.empty((M, n_x, n_x))
    _imm_mix_into(mu, Gamma, xs, Ps, cbar, x0, P0, np.empty(M), np.empty(n_x), M, n_x)
    return cbar, x0, P0


@njit
def imm_probabilities(loglik, updated, cbar, mu_floor):
    """Model probabilities from log-likelihoods, paper B Eqs. 45-46 (corrected) in log domain.

    ``updated[m]`` False (measurement of model m missing or unusable): its log-likelihood is set
    to the log-mean-exp of the updated models' (for M = 2: equal to the other's), so it carries
    no evidence (SPEC §8.3 edge case). No model updated, or every updated log-likelihood
    ``−inf``: no evidence, ``μ = c̄``. Then the floor is applied. Returns ``mu (M,)``.
    """
    M = cbar.shape[0]
    mu = np.empty(M)
    _imm_probabilities_into(
        loglik,
        updated,
        cbar,
        mu_floor,
        mu,
        np.empty(M),
        np.empty(M),
        np.zeros(M, dtype=np.bool_),
        M,
    )
    return mu


@njit
def imm_combine(mu, xs, Ps):
    """Combined estimate, paper B Eqs. 47-48: ``x = Σ μ_m x_m``, ``P = Σ μ_m (P_m + d dᵀ)``."""
    M, n_x = xs.shape
    x = np.empty(n_x)
    P = np.empty((n_x, n_x))
    _imm_combine_into(mu, xs, Ps, x, P, np.empty(n_x), M, n_x)
    return x, P


# --------------------------------------------------------------------------------------------
# Batched time loop
# --------------------------------------------------------------------------------------------


@njit_inline
def _imm_loop(
    z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
    out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis, M, n_x, n_z
):  # fmt: skip
    """Body of :func:`imm_run` for ``M`` models, ``n_x`` states, ``n_z`` measurements.

    Returns the number of model updates whose ``S`` had to be regularised (SPEC §13).
    """
    B, T = z.shape[0], z.shape[1]
    # per-model outputs with a zero-length first axis are not wanted (not written)
    w_models = out_xm.shape[0] > 0  # out_xm, out_Pm
    w_diag = out_ll.shape[0] > 0  # out_ll, out_nu, out_nis
    n_reg = 0
    valid = np.zeros(M, dtype=np.bool_)
    updated = np.zeros(M, dtype=np.bool_)
    loglik = np.zeros(M)
    xin = np.empty((M, n_x))
    Pin = np.empty((M, n_x, n_x))
    xm = np.empty((M, n_x))
    Pm = np.empty((M, n_x, n_x))
    # scratch of the mixing, KF and probability kernels
    cbar = np.empty(M)
    x0 = np.empty((M, n_x))
    P0 = np.empty((M, n_x, n_x))
    w = np.empty(M)
    d = np.empty(n_x)
    x_pred = np.empty(n_x)
    P_pred = np.empty((n_x, n_x))
    FP = np.empty((n_x, n_x))
    nu = np.empty(n_z)
    S = np.empty((n_z, n_z))
    L = np.empty((n_z, n_z))
    HP = np.empty((n_z, n_x))
    Kt = np.empty((n_z, n_x))
    A = np.empty((n_x, n_x))
    AP = np.empty((n_x, n_x))
    KR = np.empty((n_x, n_z))
    y = np.empty(n_z)
    mu_new = np.empty(M)
    ll_s = np.empty(M)
    lw = np.empty(M)
    fixed = np.zeros(M, dtype=np.bool_)
    for b in range(B):
        for t in range(T):
            n_valid = 0
            for m in range(M):
                valid[m] = _finite1(z[b, t, m], n_z)
                if valid[m]:
                    n_valid += 1
                updated[m] = False
                loglik[m] = np.nan
                out_mobs[b, t, m] = False
                if w_diag:
                    out_ll[b, t, m] = np.nan
                    out_nis[b, t, m] = np.nan
                    for k in range(n_z):
                        out_nu[b, t, m, k] = np.nan
            # model-conditioned inputs at t−1: external (R2) where given, else own posteriors
            ready = True
            for i in range(M):
                use_prev = False
                if has_prev:
                    use_prev = _finite1(prev_x[b, t, i], n_x) and _finite2(prev_P[b, t, i], n_x)
                if use_prev:
                    xin[i] = prev_x[b, t, i]
                    Pin[i] = prev_P[b, t, i]
                elif init[b]:
                    xin[i] = xs[b, i]
                    Pin[i] = Ps[b, i]
                else:
                    ready = False
            if not ready:
                if n_valid == 0:  # nothing to start from: outputs stay NaN
                    out_x[b, t] = np.nan
                    out_P[b, t] = np.nan
                    if w_models:
                        out_xm[b, t] = np.nan
                        out_Pm[b, t] = np.nan
                    out_mu[b, t] = mu[b]
                    out_obs[b, t] = False
                    continue
                src0 = 0
                for m in range(M - 1, -1, -1):
                    if valid[m]:
                        src0 = m
                for m in range(M):  # initialise at the measurement, zero unmeasured states
                    src = m if valid[m] else src0
                    for i in range(n_x):
                        s = 0.0
                        for p in range(n_z):
                            s += Hpinv[src, i, p] * z[b, t, src, p]
                        xs[b, m, i] = s
                    Ps[b, m] = P_init[src]
                    out_mobs[b, t, m] = valid[m]
                init[b] = True
                _imm_combine_into(mu[b], xs[b], Ps[b], out_x[b, t], out_P[b, t], d, M, n_x)
                if w_models:
                    out_xm[b, t] = xs[b]
                    out_Pm[b, t] = Ps[b]
                out_mu[b, t] = mu[b]
                out_obs[b, t] = True
                continue
            _imm_mix_into(mu[b], Gamma, xin, Pin, cbar, x0, P0, w, d, M, n_x)  # Eqs. 25-28
            for m in range(M):
                _kf_predict_into(x0[m], P0[m], F[m], Q[m], x_pred, P_pred, FP, n_x)  # Eqs. 29-32
                xm[m] = x_pred
                Pm[m] = P_pred
                if valid[m]:
                    status = _kf_update_into(
                        x_pred, P_pred, z[b, t, m], H[m], R[m], xm[m], Pm[m], nu, S, L, HP, Kt,
                        A, AP, KR, y, n_x, n_z,
                    )  # Eqs. 33-38  # fmt: skip
                    n_reg += status == CHOL_REGULARISED
                    if status != CHOL_FAILED:
                        ll, nis = _loglik_chol(nu, L, y, n_z)  # Eqs. 39-44 (log form)
                        if w_diag:
                            out_nu[b, t, m] = nu
                            out_nis[b, t, m] = nis
                            out_ll[b, t, m] = ll
                        out_mobs[b, t, m] = True
                        updated[m] = True
                        loglik[m] = ll
            _imm_probabilities_into(
                loglik, updated, cbar, mu_floor, mu_new, ll_s, lw, fixed, M
            )  # Eqs. 45-46
            _imm_combine_into(mu_new, xm, Pm, out_x[b, t], out_P[b, t], d, M, n_x)  # Eqs. 47-48
            mu[b] = mu_new
            xs[b] = xm
            Ps[b] = Pm
            if w_models:
                out_xm[b, t] = xm
                out_Pm[b, t] = Pm
            out_mu[b, t] = mu_new
            any_obs = False
            for m in range(M):
                if out_mobs[b, t, m]:
                    any_obs = True
            out_obs[b, t] = n_valid > 0 and any_obs
    return n_reg


@njit
def imm_run_paper_b(
    z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
    out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis,
):  # fmt: skip
    """:func:`imm_run` for two 3-D constant-velocity models (``M, n_x, n_z = 2, 6, 3``).

    The sizes are compile-time constants, so the compiler unrolls the small matrix loops of
    the KF predict/update (inlined).
    """
    return _imm_loop(
        z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
        out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis, 2, 6, 3
    )  # fmt: skip


@njit
def imm_run_any(
    z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
    out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis,
):  # fmt: skip
    """:func:`imm_run` for any sizes (read from the arrays)."""
    M, n_z = z.shape[2], z.shape[3]
    n_x = F.shape[1]
    return _imm_loop(
        z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
        out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis, M, n_x, n_z
    )  # fmt: skip


def imm_run(
    z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
    out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis,
):  # fmt: skip
    """Run the IMM over ``z (B, T, M, n_z)`` for every batch element ``b``; SPEC §8.3.

    State ``xs (B, M, n_x)``, ``Ps (B, M, n_x, n_x)``, ``mu (B, M)``, ``init (B,)`` is updated in
    place. ``prev_x (B, T, M, n_x)``, ``prev_P (B, T, M, n_x, n_x)`` (read only if
    ``has_prev``): externally supplied posteriors at t−1 used for mixing at step t (reading R2);
    a non-finite entry for model i means "use the IMM's own posterior of model i".
    Outputs are written into the ``out_*`` arrays (leading axes ``(B, T)``). Returns the number
    of model updates whose ``S`` had to be regularised (SPEC §13; the caller warns).

    Every temporary is allocated once per call (no allocation inside the loops); the arithmetic
    is that of :func:`imm_mix`, :func:`._kernels.kf_predict`, :func:`._kernels.kf_update`,
    :func:`gauss_loglik`, :func:`imm_probabilities` and :func:`imm_combine`. One source, two
    compiled loops chosen here (in Python, so that only the one a run needs is compiled):
    :func:`imm_run_paper_b` for two 3-D constant-velocity models (the IMM of paper B) with the
    sizes as compile-time constants, :func:`imm_run_any` for any other sizes. Both give the same
    numbers.
    """
    M, n_z = z.shape[2], z.shape[3]
    n_x = F.shape[1]
    run = imm_run_paper_b if (M, n_x, n_z) == (2, 6, 3) else imm_run_any
    return run(
        z, has_prev, prev_x, prev_P, F, Q, H, R, Hpinv, P_init, Gamma, mu_floor, xs, Ps, mu, init,
        out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis,
    )  # fmt: skip
