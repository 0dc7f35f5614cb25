"""EM-adaptive KF kernels (numba): the EM-KF update and its run loop.

Paper A §3.2 (Eqs. 10-23, Algorithm 2) as corrected by SPEC §5.3. Textbook symbols, no
validation. The EM-KF does not decouple per axis (``Ω₁``, ``Ω₂`` hold outer products of the
innovation, SPEC §1), so these are tight dense loops on preallocated scratch arrays
(:class:`EMScratch`). The integrated EM-KF/FIR filter's loop, which calls the same update, is
in :mod:`._kernels_integrated`; the Cholesky factorisation and the floors are in
:mod:`._kernels_linalg`.

Status bits returned by :func:`em_update`: 1 = R floor bound, 2 = P⁻ floor bound,
4 = ``S`` had to be regularised (SPEC §13), 8 = ``S`` could not be factorised (update skipped).

One loop, two model structures
------------------------------
:func:`em_kf_run` is written once over the structure operations of :mod:`._kernels_common`
and :func:`em_update`, which is :func:`em_update_sparse` (any ``H``, the reference) or
:func:`em_update_cv` (``H`` selects positions: ``H P`` is rows ``0, 2, 4`` of ``P`` and
``I − K H`` only touches the position columns), chosen at compile time by the class of
``struct``. The two forms perform the same operations in the same order (bit for bit the same
results) and sit next to each other so that a reader can check one against the other. The
positive-definiteness tests of the CV floors use an LDLᵀ elimination (no square roots, off the
critical path of the iteration).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kinefuse._compile import interpreting, njit, njit_inline
from kinefuse.filters._kernels_common import (
    CVStructure,
    add_times_sparse_t,
    copy_matrix,
    copy_state,
    init_from,
    load_element,
    predict,
    put_sample,
    read_row,
    sparse_times,
    step_arrays_jit,
    store_element,
    writable_copy,
)
from kinefuse.filters._kernels_linalg import (
    CHOL_FAILED,
    CHOL_REGULARISED,
    chol_solve_rows,
    chol_status,
    floor_binds,
    floor_clip,
    floor_clip_into,
    not_pd_above,
    quad_inv,
    symmetrize_into,
)

if not interpreting():  # compiled kernels choose the structure form at compile time
    from numba.extending import overload

#: Internal status bit of :func:`em_update_cv`: the last Joseph update computed only the position
#: block of ``P`` (complete it with :func:`complete_deferred` before using ``P``).
P_DEFERRED = 16

FLOOR_R, FLOOR_P, S_REGULARISED, S_FAILED = 1, 2, 4, 8


# ---------------------------------------------------------------------------------------------
# Argument bundles of the EM-KF
# ---------------------------------------------------------------------------------------------


class EMOptions(NamedTuple):
    """EM-KF settings: ``N_EM``, option B (``regularized``, ``tau``, ``rho``), floor fraction."""

    n_iter: int
    regularized: bool
    tau: float
    rho: float
    floor_c: float


class EMOutputs(NamedTuple):
    """Preallocated per-sample outputs, ``(B, T, ...)``: mean, cov, observed, ν, NIS, R_em."""

    mean: np.ndarray
    cov: np.ndarray
    observed: np.ndarray
    innovation: np.ndarray
    distance: np.ndarray
    R_em: np.ndarray


class EMIteration(NamedTuple):
    """What one :func:`em_update` call does (see :func:`em_update_sparse`)."""

    n_iter: int
    regularized: bool
    tau: float
    floor_c: float
    want_R: bool
    defer: bool


class EMScratch(NamedTuple):
    """Scratch of :func:`em_update` (allocated once per run by :func:`em_scratch`)."""

    Pm: np.ndarray  # P̄⁻ (n_x, n_x)
    M: np.ndarray  # H P̄⁻ / H P (n_z, n_x), sparse form
    S: np.ndarray  # S (n_z, n_z)
    LS: np.ndarray  # chol(S)
    Kt: np.ndarray  # Kᵀ (n_z, n_x)
    AP: np.ndarray  # (I − K H) P̄⁻ (n_x, n_x)
    D: np.ndarray  # K R − AP Hᵀ (n_x, n_z)
    W: np.ndarray  # work (n_x, n_x)
    L6: np.ndarray  # work factor (n_x, n_x)
    Rj: np.ndarray  # R^{(j)} (n_z, n_z)
    Rl: np.ndarray  # R of a deferred last Joseph update
    Om1: np.ndarray  # Ω₁
    nu: np.ndarray  # ν (n_z,)
    e: np.ndarray  # posterior residual (n_z,)
    tmp: np.ndarray  # (n_x,)


def em_scratch(n_x, n_z):
    """An :class:`EMScratch` for sizes ``n_x``, ``n_z``."""
    xx, zx, zz, xz = (n_x, n_x), (n_z, n_x), (n_z, n_z), (n_x, n_z)
    return EMScratch(
        np.zeros(xx), np.zeros(zx), np.zeros(zz), np.zeros(zz), np.zeros(zx), np.zeros(xx),
        np.zeros(xz), np.zeros(xx), np.zeros(xx), np.zeros(zz), np.zeros(zz), np.zeros(zz),
        np.zeros(n_z), np.zeros(n_z), np.zeros(n_x),
    )  # fmt: skip


em_scratch_jit = njit_inline(em_scratch)


# ---------------------------------------------------------------------------------------------
# The EM update: sparse (reference) and CV forms
# ---------------------------------------------------------------------------------------------


@njit_inline
def _em_start(xp, Pp, R0, x, P, Pm, Rj, n, n_z):
    """``x = x⁻``, ``P = P̄⁻^{(0)} = P⁻`` (Alg. 2 line 6), ``R^{(0)} = R0`` (SPEC §5.2-6)."""
    for i in range(n):
        x[i] = xp[i]
        for j in range(n):
            P[i, j] = Pp[i, j]
            Pm[i, j] = Pp[i, j]
    for r1 in range(n_z):
        for r2 in range(n_z):
            Rj[r1, r2] = R0[r1, r2]


@njit_inline
def _gain_mean(xp, Kt, nu, x, n, n_z):
    """``x = x⁻ + K ν`` from ``Kᵀ`` (Eq. 8)."""
    for i in range(n):
        acc = xp[i]
        for r in range(n_z):
            acc += Kt[r, i] * nu[r]
        x[i] = acc


@njit_inline
def _r_from_omega1(Om1, Uprior, u_prior, regularized, Rj, n_z):
    """``R = Ω₁`` (option A) or the inverse-Wishart mean ``(Û⁻ + Ω₁)/(û⁻ − n_z)`` (option B)."""
    if regularized:
        den = u_prior - n_z
        for r1 in range(n_z):
            for r2 in range(n_z):
                Rj[r1, r2] = (Uprior[r1, r2] + Om1[r1, r2]) / den
    else:
        for r1 in range(n_z):
            for r2 in range(n_z):
                Rj[r1, r2] = Om1[r1, r2]


@njit_inline
def _pm_from_omega2(P, x, xp, Pp, regularized, tau, tmp, Pm, n):
    """``P̄⁻ = Ω₂ = P + (x − x⁻)(x − x⁻)ᵀ`` (Eq. 18), option B: ``(τ P⁻ + Ω₂)/(τ + 1)``."""
    for i in range(n):
        tmp[i] = x[i] - xp[i]
    for i in range(n):
        for j in range(n):
            Pm[i, j] = P[i, j] + tmp[i] * tmp[j]
    if regularized:
        for i in range(n):
            for j in range(n):
                Pm[i, j] = (tau * Pp[i, j] + Pm[i, j]) / (tau + 1.0)


@njit_inline
def _residual(Hr, Hc, Hv, z, x, out, n_z):
    """``out = z − H x`` for ``H`` given by its non-zeros."""
    for r in range(n_z):
        out[r] = z[r]
    for t in range(len(Hv)):
        out[Hr[t]] -= Hv[t] * x[Hc[t]]


@njit_inline
def _h_m_ht(Hr, Hc, Hv, M, A, out, n_z):
    """``out = A + M Hᵀ`` (``M = H X``: ``H X Hᵀ``), symmetrised, for ``H`` given by its non-zeros."""
    for r1 in range(n_z):
        for r2 in range(n_z):
            out[r1, r2] = A[r1, r2]
    add_times_sparse_t(Hr, Hc, Hv, M, out, n_z)
    symmetrize_into(out, n_z)


@njit_inline
def _kr(Kt, Rj, i, r2, n_z):
    """``(K R)[i, r2]`` from ``Kᵀ``."""
    acc = 0.0
    for r1 in range(n_z):
        acc += Kt[r1, i] * Rj[r1, r2]
    return acc


@njit_inline
def _ap_plus_dkt(AP, D, Kt, P, n, n_z):
    """Joseph form ``P = AP + D Kᵀ`` (upper triangle, mirrored: ``P`` exactly symmetric)."""
    for i in range(n):
        for j in range(i, n):
            acc = AP[i, j]
            for r in range(n_z):
                acc += D[i, r] * Kt[r, j]
            P[i, j] = acc
            P[j, i] = acc


@njit
def em_update_sparse(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc):
    """EM-KF measurement update at one time step, any ``H`` (SPEC §5.3; paper A Alg. 2 lines 5-17).

    Parameters
    ----------
    struct : SparseStructure
        Non-zeros of ``F`` and ``H`` (only ``H`` is used here).
    tx, tz : tuple
        ``size_tuple(n_x)``, ``size_tuple(n_z)`` (compile-time sizes).
    xp, Pp : ndarray, shape (n_x,), (n_x, n_x)
        Prediction ``x⁻``, ``P⁻`` (fixed through the iterations).
    z : ndarray, shape (n_z,)
        Valid measurement.
    R0 : ndarray, shape (n_z, n_z)
        ``R^{(0)}``: nominal R (option A) or the inverse-Wishart prior mean (option B).
    Rnom : ndarray, shape (n_z, n_z)
        Nominal R, reference of the R floor.
    Uprior, u_prior : ndarray, shape (n_z, n_z), and float
        ``Û⁻`` and ``û⁻`` (option B only).
    it : EMIteration
        ``n_iter`` (``N_EM``; 1 is exactly the KF update, SPEC §5.2-6), ``regularized``
        (option B blending ``P̄⁻ ← (τP⁻ + Ω₂)/(τ+1)``, ``R ← (Û⁻ + Ω₁)/(û⁻ − n_z)``), ``tau``,
        ``floor_c`` (``R ⪰ c·R_nom``, ``P̄⁻ ⪰ c·P⁻`` in the generalised-eigenvalue sense),
        ``want_R`` (compute ``R^{(N_EM)}`` after the last iteration; False for a KF update) and
        ``defer`` (ignored here: the general form always completes ``P``).
    x, P : ndarray
        Outputs: the posterior (may be the caller's state arrays: only ``xp``, ``Pp`` are read).
    sc : EMScratch
        From :func:`em_scratch`; on return ``sc.nu`` holds ``ν``, ``sc.Rj`` ``R^{(N_EM)}`` and
        ``sc.Om1`` the last ``Ω₁``.

    Returns
    -------
    status : int
        Bit set of ``FLOOR_R``, ``FLOOR_P``, ``S_REGULARISED``, ``S_FAILED``.
    nis : float
        ``νᵀS⁻¹ν`` with the first-iteration (nominal) S.

    Notes
    -----
    The Joseph product ``(I − K H) P̄⁻ (I − K H)ᵀ + K R Kᵀ`` is evaluated through the sparsity
    of ``H``: ``AP = P̄⁻ − K (H P̄⁻)``, then ``P = AP + (K R − AP Hᵀ) Kᵀ`` (upper triangle,
    mirrored) — the same product, not the short form.
    """
    Pm, M, S, LS, Kt, AP, D, W, L6 = sc.Pm, sc.M, sc.S, sc.LS, sc.Kt, sc.AP, sc.D, sc.W, sc.L6
    Rj, Om1, nu, e, tmp = sc.Rj, sc.Om1, sc.nu, sc.e, sc.tmp
    Hr, Hc, Hv = struct.Hr, struct.Hc, struct.Hv
    n_iter, regularized, tau, floor_c, want_R, _defer = it
    n_x = len(tx)
    n_z = len(tz)
    status = 0
    nis = np.nan
    # ν = z − H x⁻ (fixed: x⁻ does not change through the iterations, SPEC §5.3)
    _residual(Hr, Hc, Hv, z, xp, nu, n_z)
    _em_start(xp, Pp, R0, x, P, Pm, Rj, n_x, n_z)  # P̄⁻^(0) = P⁻, R^(0) reset every step
    for jit in range(n_iter):
        sparse_times(Hr, Hc, Hv, Pm, M, n_z, n_x)  # M = H Pm
        _h_m_ht(Hr, Hc, Hv, M, Rj, S, n_z)  # S = H P̄⁻ Hᵀ + R^{(j)}
        st = chol_status(S, LS, n_z)
        if st == CHOL_FAILED:  # SPEC §13: skip the update; later iterations keep the previous one
            status |= S_FAILED if jit == 0 else S_REGULARISED
            break
        if st == CHOL_REGULARISED:
            status |= S_REGULARISED
        # Kᵀ = S⁻¹ H P̄⁻  → K^{(j+1)} (Alg. 2 line 8; SPEC §5.2-4 gain index)
        for r in range(n_z):
            for c in range(n_x):
                Kt[r, c] = M[r, c]
        chol_solve_rows(LS, Kt, n_z, n_x)
        if jit == 0:
            nis = quad_inv(LS, nu, tmp, n_z)
        _gain_mean(xp, Kt, nu, x, n_x, n_z)  # x^(j+1) = x⁻ + K^(j+1) ν (Alg. 2 line 9, Eq. 8)
        # AP = (I − K H) P̄⁻ = P̄⁻ − K (H P̄⁻)
        for i in range(n_x):
            for c in range(n_x):
                acc = Pm[i, c]
                for r in range(n_z):
                    acc -= Kt[r, i] * M[r, c]
                AP[i, c] = acc
        # D = K R^{(j)} − AP Hᵀ  (n_x, n_z)
        for i in range(n_x):
            for r2 in range(n_z):
                D[i, r2] = _kr(Kt, Rj, i, r2, n_z)
        for t in range(len(Hv)):
            for i in range(n_x):
                D[i, Hr[t]] -= Hv[t] * AP[i, Hc[t]]
        # P^{(j+1)} = AP (I − K H)ᵀ + K R Kᵀ = AP + D Kᵀ  (Joseph, Eq. 9; SPEC §5.3)
        _ap_plus_dkt(AP, D, Kt, P, n_x, n_z)
        if jit == n_iter - 1 and not want_R:
            break
        # e = z − H x^{(j+1)}  (posterior residual, SPEC §5.2-2)
        _residual(Hr, Hc, Hv, z, x, e, n_z)
        # Ω₁ = e eᵀ + H P Hᵀ  (Eq. 17 corrected) → R^{(j+1)} (SPEC §5.2-1)
        sparse_times(Hr, Hc, Hv, P, M, n_z, n_x)  # M = H P
        for r1 in range(n_z):
            for r2 in range(n_z):
                Om1[r1, r2] = e[r1] * e[r2]
        _h_m_ht(Hr, Hc, Hv, M, Om1, Om1, n_z)  # Om1 += M Hᵀ
        _r_from_omega1(Om1, Uprior, u_prior, regularized, Rj, n_z)  # R^(j+1)
        if floor_binds(Rj, Rnom, floor_c, W, LS, n_z):  # SPEC §5.4 floor
            if floor_clip(Rj, Rnom, floor_c, n_z):
                status |= FLOOR_R
        if jit == n_iter - 1:
            break
        _pm_from_omega2(P, x, xp, Pp, regularized, tau, tmp, Pm, n_x)  # P̄⁻^(j+1), Eq. 18
        if floor_binds(Pm, Pp, floor_c, W, L6, n_x):
            if floor_clip(Pm, Pp, floor_c, n_x):
                status |= FLOOR_P
    return status, nis


@njit_inline
def joseph_cv(tx, tz, Pm, Kt, Rj, AP, D, P, pos_only):
    """Joseph update ``P = (I − K H) P̄⁻ (I − K H)ᵀ + K R Kᵀ`` for ``H`` selecting positions.

    As in :func:`em_update_sparse`: ``AP = P̄⁻ − K (H P̄⁻)`` (``H P̄⁻`` = position rows of ``P̄⁻``),
    ``D = K R − AP Hᵀ``, ``P = AP + D Kᵀ`` (upper triangle, mirrored). ``pos_only``: only the
    position block ``P[2a, 2b]`` (all that ``Ω₁ = e eᵀ + H P Hᵀ`` needs); the same operations,
    so a later full call gives the same values there.
    """
    n_a = len(tz)
    n = len(tx)
    if pos_only:
        for a in range(n_a):
            i = 2 * a
            for b in range(n_a):
                c = 2 * b
                acc = Pm[i, c]
                for r in range(n_a):
                    acc -= Kt[r, i] * Pm[2 * r, c]
                AP[i, c] = acc
            for r2 in range(n_a):
                D[i, r2] = _kr(Kt, Rj, i, r2, n_a) - AP[i, 2 * r2]
        for a in range(n_a):
            i = 2 * a
            for b in range(a, n_a):
                j = 2 * b
                acc = AP[i, j]
                for r in range(n_a):
                    acc += D[i, r] * Kt[r, j]
                P[i, j] = acc
                P[j, i] = acc
        return
    for i in range(n):
        for c in range(n):
            acc = Pm[i, c]
            for r in range(n_a):
                acc -= Kt[r, i] * Pm[2 * r, c]
            AP[i, c] = acc
    for i in range(n):
        for r2 in range(n_a):
            D[i, r2] = _kr(Kt, Rj, i, r2, n_a) - AP[i, 2 * r2]
    _ap_plus_dkt(AP, D, Kt, P, n, n_a)


@njit
def em_update_cv(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc):
    """:func:`em_update_sparse` for the CV structure (SPEC §5.3; paper A Alg. 2 lines 5-17).

    Same arguments and results; ``H`` selects positions, so ``H A`` is rows ``0, 2, 4`` of ``A``
    and no product with ``H`` is formed. ``it.defer`` (with ``it.want_R``): the last iteration
    computes only the position block of ``P`` and keeps its R in ``sc.Rl``; the status then has
    :data:`P_DEFERRED` set and :func:`complete_deferred` completes ``P`` when it is needed (the
    integrated filter skips it when the FIR wins).
    """
    Rj, Rl, Om1, Pm, S, LS, Kt = sc.Rj, sc.Rl, sc.Om1, sc.Pm, sc.S, sc.LS, sc.Kt
    AP, D, W, nu, e, tmp = sc.AP, sc.D, sc.W, sc.nu, sc.e, sc.tmp
    n_iter, regularized, tau, floor_c, want_R, defer = it
    n_a = len(tz)
    n = len(tx)
    status = 0
    nis = np.nan
    for r in range(n_a):
        nu[r] = z[r] - xp[2 * r]  # ν = z − H x⁻ (fixed through the iterations)
    _em_start(xp, Pp, R0, x, P, Pm, Rj, n, n_a)  # P̄⁻^(0) = P⁻, R^(0) reset every step
    for jit in range(n_iter):
        last = jit == n_iter - 1
        for r1 in range(n_a):  # S = H P̄⁻ Hᵀ + R^{(j)}
            for r2 in range(n_a):
                S[r1, r2] = Rj[r1, r2] + Pm[2 * r1, 2 * r2]
        symmetrize_into(S, n_a)
        st = chol_status(S, LS, n_a)
        if st == CHOL_FAILED:
            status |= S_FAILED if jit == 0 else S_REGULARISED
            break
        if st == CHOL_REGULARISED:
            status |= S_REGULARISED
        for r in range(n_a):  # Kᵀ = S⁻¹ H P̄⁻  (K^{(j+1)})
            for c in range(n):
                Kt[r, c] = Pm[2 * r, c]
        chol_solve_rows(LS, Kt, n_a, n)
        if jit == 0:
            nis = quad_inv(LS, nu, tmp, n_a)
        _gain_mean(xp, Kt, nu, x, n, n_a)  # x^(j+1) = x⁻ + K^(j+1) ν (Alg. 2 line 9, Eq. 8)
        pos_only = last and want_R and defer
        if pos_only:
            status |= P_DEFERRED
            for r1 in range(n_a):
                for r2 in range(n_a):
                    Rl[r1, r2] = Rj[r1, r2]
        joseph_cv(tx, tz, Pm, Kt, Rj, AP, D, P, pos_only)  # P^{(j+1)} (Eq. 9)
        if last and not want_R:
            break
        for r in range(n_a):  # e = z − H x^{(j+1)}
            e[r] = z[r] - x[2 * r]
        for r1 in range(n_a):  # Ω₁ = e eᵀ + H P Hᵀ → R^{(j+1)}
            for r2 in range(n_a):
                Om1[r1, r2] = e[r1] * e[r2] + P[2 * r1, 2 * r2]
        symmetrize_into(Om1, n_a)
        _r_from_omega1(Om1, Uprior, u_prior, regularized, Rj, n_a)  # R^(j+1)
        if not_pd_above(Rj, Rnom, floor_c, W, n_a):  # SPEC §5.4 floor
            # scratch free at this point: LS, S (the gain is computed), Om1 (copied), e
            if floor_clip_into(Rj, Rnom, floor_c, n_a, LS, S, Om1, e):
                status |= FLOOR_R
        if last:
            break
        _pm_from_omega2(P, x, xp, Pp, regularized, tau, tmp, Pm, n)  # P̄⁻^(j+1), Eq. 18
        if not_pd_above(Pm, Pp, floor_c, W, n):
            if floor_clip(Pm, Pp, floor_c, n):
                status |= FLOOR_P
    return status, nis


# ---------------------------------------------------------------------------------------------
# Dispatch by structure class (compile time; Python isinstance when interpreted)
# ---------------------------------------------------------------------------------------------


def em_update(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc):
    """EM-KF measurement update (:func:`em_update_sparse`, :func:`em_update_cv`)."""
    impl = em_update_cv if isinstance(struct, CVStructure) else em_update_sparse
    return impl(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc)


if not interpreting():

    @overload(em_update, inline="always")
    def _em_update(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc):
        # A call of the compiled form, not its body: inlining the large update into each run
        # loop compiled it three times (once on its own for the overload's typing, once per
        # loop) and made the run loops slow to compile; one call per step costs nothing
        # measurable beside the N_EM iterations of 6×6 arithmetic.
        cv = getattr(struct, "instance_class", None) is CVStructure
        impl = em_update_cv if cv else em_update_sparse

        def call(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc):
            return impl(struct, tx, tz, xp, Pp, z, R0, Rnom, Uprior, u_prior, it, x, P, sc)

        return call


@njit_inline
def complete_deferred(tx, tz, sc, P):
    """Complete a ``P`` whose last Joseph update was deferred (status :data:`P_DEFERRED`)."""
    joseph_cv(tx, tz, sc.Pm, sc.Kt, sc.Rl, sc.AP, sc.D, P, False)


@njit_inline
def count_status(counts, status):
    """Add an :func:`em_update` status to ``counts[bit]`` (R floor, P⁻ floor, S reg., S failed)."""
    for bit in range(4):
        if status & (1 << bit):
            counts[bit] += 1


@njit_inline
def _fill_nan(out, b, t, tz):
    """NaN diagnostics for a step without update."""
    n_z = len(tz)
    for r1 in range(n_z):
        out.innovation[b, t, r1] = np.nan
        for r2 in range(n_z):
            out.R_em[b, t, r1, r2] = np.nan
    out.distance[b, t] = np.nan


@njit_inline
def _prior_predict(regularized, rho, ub, Ub, n_z):
    """Option B time update of the inverse-Wishart ``(û, Û)`` (SPEC §5.3); returns ``û⁻``."""
    if not regularized:
        return 0.0
    nz3 = n_z + 1.0
    for r1 in range(n_z):
        for r2 in range(n_z):
            Ub[r1, r2] *= rho
    return rho * (ub - nz3) + nz3


@njit_inline
def _initial_R(regularized, Ub, u_pr, Rnom, R0, n_z):
    """``R^{(0)}``: nominal (option A) or the IW prior mean ``Û⁻/(û⁻ − n_z − 1)`` (option B)."""
    nz3 = n_z + 1.0
    for r1 in range(n_z):
        for r2 in range(n_z):
            if regularized:
                R0[r1, r2] = Ub[r1, r2] / (u_pr - nz3)
            else:
                R0[r1, r2] = Rnom[r1, r2]


@njit_inline
def _put_update(out, b, t, sc, nis, n_z):
    """Diagnostics of an update: ``ν``, ``R^{(N_EM)}``, NIS."""
    for r1 in range(n_z):
        out.innovation[b, t, r1] = sc.nu[r1]
        for r2 in range(n_z):
            out.R_em[b, t, r1, r2] = sc.Rj[r1, r2]
    out.distance[b, t] = nis


# ---------------------------------------------------------------------------------------------
# The EM-KF run loop
# ---------------------------------------------------------------------------------------------


@njit
def em_kf_run(m, opt, z, x, P, init, u, U, out):
    """Run the EM-KF over ``z (B, T, n_z)``; state arrays updated in place.

    Parameters
    ----------
    m : EMModel
    opt : EMOptions
    z : ndarray, shape (B, T, n_z)
        NaN rows are missing (predict only).
    x, P, init, u, U : ndarray, shapes (B, n_x), (B, n_x, n_x), (B,), (B,), (B, n_z, n_z)
        State (updated in place): mean, covariance, initialised flag, option B's ``(û, Û)``.
    out : EMOutputs
        Written for every sample.

    Returns
    -------
    counts : ndarray of int64, shape (4,)
        Samples on which ``[R floor bound, P⁻ floor bound, S regularised, S failed]``.
    """
    tx, tz, struct, Q, Rnom, Hpinv, P0 = m
    n_iter, regularized, tau, rho, floor_c = opt
    o_mean, o_cov, o_obs = out.mean, out.cov, out.observed
    B, T = z.shape[0], z.shape[1]
    n = len(tx)
    n_a = len(tz)
    sc = em_scratch_jit(n, n_a)
    it = EMIteration(n_iter, regularized, tau, floor_c, True, False)
    xb, Pb, zt, xp, Pp, FP = step_arrays_jit(n, n_a)
    R0 = np.empty((n_a, n_a))
    Ub = np.empty((n_a, n_a))
    Rn = writable_copy(Rnom, n_a)  # em_update: one compiled signature for both run loops
    counts = np.zeros(4, np.int64)
    for b in range(B):
        load_element(x, P, b, xb, Pb, tx)
        ub = u[b]
        copy_matrix(U[b], Ub, n_a)
        initialized = init[b]
        for t in range(T):
            valid = read_row(z, b, t, zt, tz)
            ok = False
            if not initialized:
                if valid:  # SPEC §4.2 initialisation (no update)
                    init_from(zt, Hpinv, P0, xb, Pb, tx, tz)
                    initialized = True
                ok = valid
                _fill_nan(out, b, t, tz)
            else:
                predict(struct, tx, tz, xb, Pb, Q, xp, Pp, FP)  # Eqs. 5-6
                u_pr = _prior_predict(regularized, rho, ub, Ub, n_a)  # option B (û⁻, Û⁻)
                nis = np.nan
                if valid:
                    _initial_R(regularized, Ub, u_pr, Rnom, R0, n_a)  # R^{(0)}
                    status, nis = em_update(
                        struct, tx, tz, xp, Pp, zt, R0, Rn, Ub, u_pr, it, xb, Pb, sc
                    )
                    count_status(counts, status)
                    ok = not (status & S_FAILED)
                if ok:  # (xb, Pb) hold the EM-KF posterior
                    if regularized:  # û = û⁻ + 1, Û = Û⁻ + Ω₁
                        ub = u_pr + 1.0
                        for r1 in range(n_a):
                            for r2 in range(n_a):
                                Ub[r1, r2] += sc.Om1[r1, r2]
                    _put_update(out, b, t, sc, nis, n_a)
                else:  # predict only
                    copy_state(xp, Pp, xb, Pb, n)
                    if regularized:
                        ub = u_pr
                    _fill_nan(out, b, t, tz)
            put_sample(o_mean, o_cov, b, t, xb, Pb, tx)
            o_obs[b, t] = ok
        store_element(x, P, b, xb, Pb, tx)
        u[b] = ub
        copy_matrix(Ub, U[b], n_a)
        init[b] = initialized
    return counts
