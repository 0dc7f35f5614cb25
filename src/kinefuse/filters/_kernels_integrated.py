"""EM-KF/FIR integrated filter kernel (numba): paper A §3.4 (Eq. 29) as corrected by SPEC §7.3.

One run loop, :func:`integrated_run`, over the structure operations of :mod:`._kernels_common`
and the EM update of :mod:`._kernels_em` (chosen at compile time by the class of
``m.struct``: the sparse reference or the constant-velocity form, bit for bit the same), and
the UFIR of :mod:`._kernels_ufir` computed on demand from the measurement ring. Textbook
symbols, no validation.

Per element and step: shared prediction ``x⁻, P⁻``; ``D₁`` (Eq. 29 with ``R``, or with ``S``
when ``gate_S``); KF update if ``D₁ < th1``; else EM-KF (``N_EM`` iterations) and
``D₂ = νᵀ R_em⁻¹ ν``; EM-KF if ``D₂ < th2`` or the FIR is not available (``k < N−1`` or
``fir_ready=False``), else the batch-initialised UFIR. A complete horizon is evaluated by the
precomputed taps (:func:`~._kernels_ufir.ufir_taps`); the general FIR call is made only for
horizons with missing samples. When the FIR wins and is fed back, the EM branch's final
covariance is never used, so (CV form) only its position block, needed for ``R_em`` and D₂, is
computed.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels_common import (
    copy_state,
    init_from,
    innovation,
    innovation_cov,
    load_element,
    predict,
    put_sample,
    read_row,
    step_arrays_jit,
    store_element,
    writable_copy,
)
from kinefuse.filters._kernels_em import (
    P_DEFERRED,
    S_FAILED,
    EMIteration,
    complete_deferred,
    count_status,
    em_scratch_jit,
    em_update,
)
from kinefuse.filters._kernels_linalg import chol_shifted, quad_inv
from kinefuse.filters._kernels_ufir import fir_estimate, ufir_horizon_axes, ufir_taps


class FIRModel(NamedTuple):
    """The UFIR side of the integrated filter (see :func:`~._kernels_ufir.fir_estimate`).

    ``N`` horizon, ``K`` batch-initialisation length, ``axis_blocks`` (per-axis 2×2 model),
    ``W`` the full-horizon taps and ``P_full`` their covariance, the dense model ``F, Finv, H``
    and the per-axis blocks ``Fa, Finva, Ha, Qa, Ra``.
    """

    N: int
    K: int
    axis_blocks: bool
    W: np.ndarray
    P_full: np.ndarray
    F: np.ndarray
    Finv: np.ndarray
    H: np.ndarray
    Fa: np.ndarray
    Finva: np.ndarray
    Ha: np.ndarray
    Qa: np.ndarray
    Ra: np.ndarray


class IntegratedOptions(NamedTuple):
    """Switch settings (SPEC §7.2): ``N_EM``, thresholds on D₁ and D₂, D₁ with ``S``
    (``gate_S``) or ``R``, FIR feedback into the KF recursion, EM floor fraction; ``LR`` is the
    Cholesky factor of the nominal ``R`` (D₁ of Eq. 29)."""

    n_em: int
    th1: float
    th2: float
    gate_S: bool
    feedback: bool
    floor_c: float
    LR: np.ndarray


class IntegratedOutputs(NamedTuple):
    """Preallocated per-sample outputs ``(B, T, ...)``: mean, cov, observed, ν, D₁, D₂, mode."""

    mean: np.ndarray
    cov: np.ndarray
    observed: np.ndarray
    innovation: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    mode: np.ndarray


@njit_inline
def _fir(zr, k, fir, Q, R, K, idx, xx, xs, Ps, xf, Pf):
    """Batch-initialised UFIR at ``k`` into ``xf, Pf`` by the cheapest exact route; fir_ready."""
    N = fir.N
    if ufir_taps(zr, k, N, fir.W, fir.axis_blocks, xf):  # complete horizon
        for i in range(Pf.shape[0]):
            for j in range(Pf.shape[1]):
                Pf[i, j] = fir.P_full[i, j]
        return True
    code = 0  # missing samples: shared per-axis gains if possible
    if fir.axis_blocks:
        code = ufir_horizon_axes(
            zr, k, N, K, fir.Fa, fir.Finva, fir.Ha, fir.Qa, fir.Ra, idx, xx, xf, Pf
        )
    if code != 0:
        return code == 1
    # fast = True, stored = False, as run-time bools (k >= N - 1 holds here): constants would
    # make numba compile a second specialisation of fir_estimate beside the UFIR filter's
    fast = k >= N - 1
    return fir_estimate(
        zr, k, N, K, fast, fir.axis_blocks, fir.W, fir.P_full, fir.F, fir.Finv, fir.H, Q, R,
        fir.Fa, fir.Finva, fir.Ha, fir.Qa, fir.Ra, xs, Ps, not fast, xf, Pf,
    )  # fmt: skip


@njit_inline
def _nan_diagnostics(out, b, t, n_z):
    """D₁, D₂ and ν of a sample before they are known (NaN: no update)."""
    out.d1[b, t] = np.nan
    out.d2[b, t] = np.nan
    for r in range(n_z):
        out.innovation[b, t, r] = np.nan


@njit_inline
def _mahalanobis(M, L, nu, tmp, n_z):
    """``νᵀ M⁻¹ ν`` through the Cholesky factor of ``M`` (into ``L``); inf if not PD."""
    if chol_shifted(M, L, n_z, 0.0):
        return quad_inv(L, nu, tmp, n_z)
    return np.inf


@njit_inline
def _distance1(struct, tz, gate_S, Pp, R, LR, S, L, nu, tmp):
    """D₁ = νᵀ R⁻¹ ν (Eq. 29, ``LR`` = chol(R)), or νᵀ S⁻¹ ν with S = H P⁻ Hᵀ + R (SPEC §7.2-2)."""
    n_z = len(tz)
    if gate_S:
        innovation_cov(struct, tz, Pp, R, S)
        return _mahalanobis(S, L, nu, tmp, n_z)
    return quad_inv(LR, nu, tmp, n_z)


def _scratch(n, n_z, fir):
    """FIR estimate ``xf, Pf``; ``L``, ``S`` of the distances; empty stored-posterior rings and
    the index / per-axis work arrays of the FIR kernels."""
    return (
        np.empty(n),
        np.empty((n, n)),
        np.empty((n_z, n_z)),
        np.empty((n_z, n_z)),
        np.empty((0, n)),
        np.empty((0, n, n)),
        np.empty(fir.K, np.int64),
        np.empty((2, fir.Fa.shape[0])),
    )


_scratch_jit = njit_inline(_scratch)


@njit
def integrated_run(m, fir, opt, z, x, P, init, zring, k0, out):
    """Run the EM-KF/FIR integrated filter over ``z (B, T, n_z)`` (SPEC §7.3); state in place.

    Parameters
    ----------
    m : EMModel
    fir : FIRModel
    opt : IntegratedOptions
    z : ndarray, shape (B, T, n_z)
        NaN rows are missing (predict only).
    x, P, init, zring : ndarray, shapes (B, n_x), (B, n_x, n_x), (B,), (B, N, n_z)
        State (updated in place); ``zring`` is the measurement ring (slot ``k % N``).
    k0 : int
        Time index of ``z[:, 0]``.
    out : IntegratedOutputs
        Written for every sample; ``mode`` 0 KF, 1 EM-KF, 2 FIR, 3 predict only.

    Returns
    -------
    counts : ndarray of int64, shape (4,)
        Samples on which ``[R floor bound, P⁻ floor bound, S regularised, S failed]``.
    """
    tx, tz, struct, Q, Rnom, Hpinv, P0 = m
    n_em, th1, th2, gate_S, feedback, floor_c, LR = opt
    N = fir.N
    B, T = z.shape[0], z.shape[1]
    n = len(tx)
    n_a = len(tz)
    sc = em_scratch_jit(n, n_a)
    nu, tmp = sc.nu, sc.tmp
    kf_it = EMIteration(1, False, 0.0, floor_c, False, False)  # Eqs. 7-9
    em_it = EMIteration(n_em, False, 0.0, floor_c, True, feedback)
    xb, Pb, zt, xp, Pp, FP = step_arrays_jit(n, n_a)
    xf, Pf, LRj, Sg, xs, Ps, idx, xx = _scratch_jit(n, n_a, fir)
    Rn = writable_copy(Rnom, n_a)  # em_update: one compiled signature for both run loops
    counts = np.zeros(4, np.int64)
    for b in range(B):
        load_element(x, P, b, xb, Pb, tx)
        initialized = init[b]
        zr = zring[b]
        for t in range(T):
            k = k0 + t
            valid = read_row(z, b, t, zt, tz)
            for c in range(n_a):
                zr[k % N, c] = zt[c] if valid else np.nan
            _nan_diagnostics(out, b, t, n_a)
            use_fir = False
            if not initialized:
                if valid:  # SPEC §4.2 initialisation
                    init_from(zt, Hpinv, P0, xb, Pb, tx, tz)
                    initialized = True
                out.observed[b, t] = valid
                out.mode[b, t] = 0 if valid else 3
            else:
                predict(struct, tx, tz, xb, Pb, Q, xp, Pp, FP)  # Eqs. 5-6, shared by all branches
                status = S_FAILED
                mode = 3
                if valid:
                    innovation(struct, tz, zt, xp, nu)
                    for r in range(n_a):
                        out.innovation[b, t, r] = nu[r]
                    d1 = _distance1(struct, tz, gate_S, Pp, Rnom, LR, Sg, LRj, nu, tmp)
                    out.d1[b, t] = d1
                    mode = 0 if d1 < th1 else 1  # KF update, else EM-KF from P̄⁻^{(0)} = P⁻
                    status, _nis = em_update(
                        struct, tx, tz, xp, Pp, zt, Rn, Rn, Rn, 0.0,
                        kf_it if mode == 0 else em_it, xb, Pb, sc,
                    )  # fmt: skip
                    count_status(counts, status)
                if status & S_FAILED:  # missing z or S not factorisable: predict only
                    copy_state(xp, Pp, xb, Pb, n)
                    out.observed[b, t] = False
                    out.mode[b, t] = 3
                else:
                    if mode == 1:  # D₂ = νᵀ R_em⁻¹ ν (Eq. 29 with the EM R, SPEC §7.2-1)
                        d2 = _mahalanobis(sc.Rj, LRj, nu, tmp, n_a)
                        out.d2[b, t] = d2
                        if not (d2 < th2) and k >= N - 1:  # no FIR while k < N−1 (SPEC §7.2-5)
                            use_fir = _fir(zr, k, fir, Q, Rnom, fir.K, idx, xx, xs, Ps, xf, Pf)
                    if (status & P_DEFERRED) and not (use_fir and feedback):
                        complete_deferred(tx, tz, sc, Pb)  # complete the EM P
                    out.observed[b, t] = True
                    out.mode[b, t] = 2 if use_fir else mode
            if use_fir:
                put_sample(out.mean, out.cov, b, t, xf, Pf, tx)
                if feedback:  # SPEC §7.2-4: the KF recursion continues from the FIR estimate
                    copy_state(xf, Pf, xb, Pb, n)
            else:
                put_sample(out.mean, out.cov, b, t, xb, Pb, tx)
        store_element(x, P, b, xb, Pb, tx)
        init[b] = initialized
    return counts
