"""IMM kernels (numba): mixing, log-domain model probabilities, combination, batched time loop.

Paper B (Xu 2023) Eqs. 24-48 as corrected by SPEC §8.2-§8.3. Textbook symbols, no validation.
Shapes: ``M`` models, ``n_x`` states, ``n_z`` measurement components; ``mu (M,)``,
``xs (M, n_x)``, ``Ps (M, n_x, n_x)``, ``Gamma (M, M)`` with ``Gamma[i, m] = P(m at t | i at t-1)``.
The per-model KF predict/update are the dense reference kernels of :mod:`._kernels`.
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit
from kinefuse.filters._kernels import (
    add_outer,
    chol_lower,
    kf_predict,
    kf_update,
    matvec,
    symmetrize,
)

LOG_2PI = float(np.log(2.0 * np.pi))


@njit
def gauss_loglik(nu, S):
    """Gaussian log-likelihood of an innovation, SPEC §8.3 (paper B Eqs. 39-40 in log form).

    ``log Λ = −½ (νᵀS⁻¹ν + log det S + n_z log 2π)``. Returns ``(log Λ, νᵀS⁻¹ν, ok)``; an
    overflowing ``νᵀS⁻¹ν`` gives ``log Λ = −inf`` (never NaN).
    """
    L, ok = chol_lower(S)
    n = nu.shape[0]
    if not ok:
        return np.nan, np.nan, False
    y = np.empty(n)
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
        return -np.inf, np.inf, True
    return -0.5 * (quad + logdet + n * LOG_2PI), quad, True  # SPEC §8.3 logΛ


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
    if floor <= 0.0:
        return
    fixed = np.zeros(M, dtype=np.bool_)
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
def imm_mix(mu, Gamma, xs, Ps):
    """IMM interaction (mixing) step, paper B Eqs. 25-28 as corrected in SPEC §8.2.

    Returns ``(cbar (M,), x0 (M, n_x), P0 (M, n_x, n_x))``.
    """
    M, n_x = xs.shape
    cbar = np.zeros(M)
    for m in range(M):
        for i in range(M):
            cbar[m] += Gamma[i, m] * mu[i]  # Eq. 25 (corrected): c̄_m = Σ_i Γ_im μ_i
    x0 = np.zeros((M, n_x))
    P0 = np.zeros((M, n_x, n_x))
    w = np.empty(M)
    for m in range(M):
        for i in range(M):
            if cbar[m] > 0.0:
                w[i] = Gamma[i, m] * mu[i] / cbar[m]  # Eq. 26 (corrected): μ_{i|m} = Γ_im μ_i / c̄_m
            else:
                w[i] = mu[i]  # unreachable model (c̄_m = 0): no interaction
        for i in range(M):
            x0[m] += w[i] * xs[i]  # Eq. 27: x0_m = Σ_i μ_{i|m} x_i
        for i in range(M):
            d = xs[i] - x0[m]
            P0[m] += w[i] * Ps[i]  # Eq. 28: P0_m = Σ_i μ_{i|m}(P_i + d dᵀ)
            add_outer(P0[m], w[i], d)
        P0[m] = symmetrize(P0[m])
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
    ll = np.zeros(M)
    n_upd = 0
    for m in range(M):
        if updated[m]:
            n_upd += 1
    fill = 0.0
    if n_upd > 0:
        obs = np.empty(n_upd)
        j = 0
        for m in range(M):
            if updated[m]:
                obs[j] = loglik[m]
                j += 1
        fill = logsumexp(obs) - np.log(n_upd)
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
    lw = np.empty(M)
    for m in range(M):
        lw[m] = ll[m] + np.log(cbar[m]) if cbar[m] > 0.0 else -np.inf  # log(Λ_m c̄_m)
    lc = logsumexp(lw)  # Eq. 45: log c = log Σ_m Λ_m c̄_m
    mu = np.empty(M)
    total = 0.0
    for m in range(M):
        mu[m] = np.exp(lw[m] - lc)  # Eq. 46 (corrected): μ_m = Λ_m c̄_m / c
        total += mu[m]
    for m in range(M):
        mu[m] /= total  # exact normalisation against rounding
    apply_floor(mu, mu_floor)
    return mu


@njit
def imm_combine(mu, xs, Ps):
    """Combined estimate, paper B Eqs. 47-48: ``x = Σ μ_m x_m``, ``P = Σ μ_m (P_m + d dᵀ)``."""
    M, n_x = xs.shape
    x = np.zeros(n_x)
    for m in range(M):
        x += mu[m] * xs[m]  # Eq. 47
    P = np.zeros((n_x, n_x))
    for m in range(M):
        d = xs[m] - x
        P += mu[m] * Ps[m]  # Eq. 48
        add_outer(P, mu[m], d)
    return x, symmetrize(P)


@njit
def _row_finite(a):
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


@njit
def imm_run(
    z,
    has_prev,
    prev_x,
    prev_P,
    F,
    Q,
    H,
    R,
    Hpinv,
    P_init,
    Gamma,
    mu_floor,
    xs,
    Ps,
    mu,
    init,
    out_x,
    out_P,
    out_mu,
    out_xm,
    out_Pm,
    out_obs,
    out_mobs,
    out_ll,
    out_nu,
    out_nis,
):
    """Run the IMM over ``z (B, T, M, n_z)`` for every batch element ``b``; SPEC §8.3.

    State ``xs (B, M, n_x)``, ``Ps (B, M, n_x, n_x)``, ``mu (B, M)``, ``init (B,)`` is updated in
    place. ``prev_x (B, T, M, n_x)``, ``prev_P (B, T, M, n_x, n_x)`` (read only if
    ``has_prev``): externally supplied posteriors at t−1 used for mixing at step t (reading R2);
    a non-finite entry for model i means "use the IMM's own posterior of model i".
    Outputs are written into the ``out_*`` arrays (leading axes ``(B, T)``).
    """
    B, T, M, n_z = z.shape
    n_x = F.shape[1]
    valid = np.zeros(M, dtype=np.bool_)
    updated = np.zeros(M, dtype=np.bool_)
    loglik = np.zeros(M)
    xin = np.empty((M, n_x))
    Pin = np.empty((M, n_x, n_x))
    xm = np.empty((M, n_x))
    Pm = np.empty((M, n_x, n_x))
    for b in range(B):
        for t in range(T):
            n_valid = 0
            for m in range(M):
                valid[m] = _row_finite(z[b, t, m])
                if valid[m]:
                    n_valid += 1
                updated[m] = False
                loglik[m] = np.nan
            out_ll[b, t, :] = np.nan
            out_nu[b, t, :, :] = np.nan
            out_nis[b, t, :] = np.nan
            out_mobs[b, t, :] = False
            # model-conditioned inputs at t−1: external (R2) where given, else own posteriors
            ready = True
            for i in range(M):
                use_prev = False
                if has_prev:
                    use_prev = _row_finite(prev_x[b, t, i]) and _row_finite(prev_P[b, t, i])
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
                    xs[b, m] = matvec(Hpinv[src], z[b, t, src])
                    Ps[b, m] = P_init[src]
                    out_mobs[b, t, m] = valid[m]
                init[b] = True
                x, P = imm_combine(mu[b], xs[b], Ps[b])
                out_x[b, t] = x
                out_P[b, t] = P
                out_xm[b, t] = xs[b]
                out_Pm[b, t] = Ps[b]
                out_mu[b, t] = mu[b]
                out_obs[b, t] = True
                continue
            cbar, x0, P0 = imm_mix(mu[b], Gamma, xin, Pin)  # Eqs. 25-28
            for m in range(M):
                xp, Pp = kf_predict(x0[m], P0[m], F[m], Q[m])  # Eqs. 29-32
                xm[m] = xp
                Pm[m] = Pp
                if valid[m]:
                    x_u, P_u, nu, S, ok = kf_update(xp, Pp, z[b, t, m], H[m], R[m])  # Eqs. 33-38
                    if ok:
                        ll, nis, ok2 = gauss_loglik(nu, S)  # Eqs. 39-44 (log form)
                        xm[m] = x_u
                        Pm[m] = P_u
                        out_nu[b, t, m] = nu
                        out_nis[b, t, m] = nis
                        out_mobs[b, t, m] = True
                        if ok2:
                            updated[m] = True
                            loglik[m] = ll
                            out_ll[b, t, m] = ll
            mu_new = imm_probabilities(loglik, updated, cbar, mu_floor)  # Eqs. 45-46
            x, P = imm_combine(mu_new, xm, Pm)  # Eqs. 47-48
            mu[b] = mu_new
            xs[b] = xm
            Ps[b] = Pm
            out_x[b, t] = x
            out_P[b, t] = P
            out_xm[b, t] = xm
            out_Pm[b, t] = Pm
            out_mu[b, t] = mu_new
            out_obs[b, t] = n_valid > 0 and out_mobs[b, t].any()
