"""Model structure and run-loop pieces shared by the EM-KF and integrated-filter kernels (numba).

A kernel is written once over the operations that depend on the model's structure:
:func:`predict` (``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``), :func:`innovation` (``ν = z − H x⁻``) and
:func:`innovation_cov` (``S = H P⁻ Hᵀ + R``), plus the EM update of :mod:`._kernels_em`. Each
is chosen at compile time by the class of its ``struct`` argument
(``numba.extending.overload``, inlined; a Python ``isinstance`` when the kernels run
interpreted):

* :class:`SparseStructure`: any ``F`` and ``H``, passed as sparse triplets ``(rows, cols,
  vals)`` of their non-zero entries (:func:`sparse_triplets`, 9 and 3 entries for the 3-D
  constant-velocity model); the reference.
* :class:`CVStructure`: the constant-velocity structure of SPEC §1 (:func:`cv_structure`):
  ``F`` block-diagonal with a 2×2 block per axis and ``H`` selecting the position of each axis.
  Then ``x⁻ = F x`` and ``F P Fᵀ`` are per-axis 2×2 closed forms on the dense ``P``, ``H P``
  is rows ``0, 2, 4`` of ``P`` and ``H P Hᵀ`` a sub-matrix, so no product with ``F`` or ``H``
  is formed. The same arithmetic in the same order as the sparse form: bit for bit the same
  results (tests/test_filter_fastpaths.py).

Sizes travel as tuples ``(0,) * n`` (:func:`size_tuple`): their length is a compile-time
constant, so numba specialises the kernels per model size and LLVM unrolls the 6×6 / 3×3 loops.
Every helper of a time loop is inlined at the numba IR level (``njit_inline``): a call of a
compiled function with array arguments costs two atomic reference-count updates per array.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kinefuse._compile import interpreting, njit_inline
from kinefuse.filters._kernels_linalg import symmetrize_into

if not interpreting():  # compiled kernels choose the structure form at compile time
    from numba.extending import overload


# ---------------------------------------------------------------------------------------------
# Argument bundles (NamedTuples are numba arguments; fields are read once before the loops)
# ---------------------------------------------------------------------------------------------


class CVStructure(NamedTuple):
    """Constant-velocity structure: ``fb (n_z, 4)``, per-axis blocks ``[f00, f01, f10, f11]``."""

    fb: np.ndarray


class SparseStructure(NamedTuple):
    """Any ``F``, ``H``: :func:`sparse_triplets` ``(rows, cols, vals)`` of each."""

    Fr: tuple
    Fc: tuple
    Fv: tuple
    Hr: tuple
    Hc: tuple
    Hv: tuple


class EMModel(NamedTuple):
    """The model as the kernels need it (built once per filter object).

    ``tx``, ``tz``: :func:`size_tuple` of ``n_x``, ``n_z`` (compile-time sizes); ``struct``:
    :class:`CVStructure` or :class:`SparseStructure`; ``Q``, ``R`` (the nominal R), ``Hpinv``
    (``H⁺``, SPEC §4.2 initialisation) and ``P0`` (initial covariance).
    """

    tx: tuple
    tz: tuple
    struct: object
    Q: np.ndarray
    R: np.ndarray
    Hpinv: np.ndarray
    P0: np.ndarray


def sparse_triplets(M):
    """Non-zero entries of ``M`` as tuples ``(rows, cols, vals)``.

    Tuples (not arrays) so that their length, like the sizes ``tx = (0,) * n_x`` and
    ``tz = (0,) * n_z`` passed to the kernels, is a compile-time constant: numba specialises the
    kernels per model size and LLVM unrolls the 6×6 / 3×3 loops.
    """
    r, c = np.nonzero(M)
    return tuple(int(i) for i in r), tuple(int(i) for i in c), tuple(float(v) for v in M[r, c])


def size_tuple(n: int) -> tuple:
    """``(0,) * n``: carries a matrix size as a compile-time constant (see :func:`sparse_triplets`)."""
    return (0,) * int(n)


def cv_structure(F, H):
    """Per-axis blocks ``fb (n_a, 4) = [f00, f01, f10, f11]`` when the model has the CV structure.

    The structure: ``n_x = 2 n_z``; ``F`` zero outside the per-axis 2×2 blocks; ``H[a, 2a] = 1``
    and every other entry of ``H`` zero. Q and R may be dense. Returns None otherwise (the
    sparse form is used).
    """
    F = np.asarray(F, dtype=np.float64)
    H = np.asarray(H, dtype=np.float64)
    n_z, n_x = H.shape
    if n_x != 2 * n_z or F.shape != (n_x, n_x):
        return None
    mask = np.kron(np.eye(n_z), np.ones((2, 2))).astype(bool)
    if np.any(F[~mask] != 0.0):
        return None
    Hsel = np.zeros((n_z, n_x))
    Hsel[np.arange(n_z), 2 * np.arange(n_z)] = 1.0
    if not np.array_equal(H, Hsel):
        return None
    return np.ascontiguousarray(
        [F[2 * a : 2 * a + 2, 2 * a : 2 * a + 2].ravel() for a in range(n_z)]
    )


def model_structure(F, H):
    """:class:`CVStructure` when ``(F, H)`` has the CV structure, else :class:`SparseStructure`."""
    fb = cv_structure(F, H)
    if fb is not None:
        return CVStructure(fb)
    return sparse_structure(F, H)


def sparse_structure(F, H):
    """:class:`SparseStructure` of ``(F, H)`` (valid for every model; the reference form)."""
    return SparseStructure(*sparse_triplets(np.asarray(F)), *sparse_triplets(np.asarray(H)))


# ---------------------------------------------------------------------------------------------
# Structure operations: the sparse (reference) and CV forms of each
# ---------------------------------------------------------------------------------------------


@njit_inline
def sparse_times(Ar, Ac, Av, B, M, n_rows, n_cols):
    """``M = A B`` (``(n_rows, n_cols)``) for ``A`` given by its non-zeros ``(Ar, Ac, Av)``."""
    for r in range(n_rows):
        for c in range(n_cols):
            M[r, c] = 0.0
    for t in range(len(Av)):
        r = Ar[t]
        k = Ac[t]
        v = Av[t]
        for c in range(n_cols):
            M[r, c] += v * B[k, c]


@njit_inline
def add_times_sparse_t(Ar, Ac, Av, M, C, n_rows):
    """``C += M Aᵀ`` for ``A`` given by its non-zeros (each entry summed in the order of ``t``)."""
    for i in range(n_rows):
        for t in range(len(Av)):
            C[i, Ar[t]] += Av[t] * M[i, Ac[t]]


@njit_inline
def predict_sparse(struct, tx, tz, x, P, Q, xp, Pp, FP):
    """SPEC §4.2 ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (Eqs. 5-6 without the noise term), symmetrised."""
    Fr, Fc, Fv = struct.Fr, struct.Fc, struct.Fv
    n = len(tx)
    for i in range(n):
        xp[i] = 0.0
    for t in range(len(Fv)):
        xp[Fr[t]] += Fv[t] * x[Fc[t]]  # Eq. 5: x⁻ = F x
    sparse_times(Fr, Fc, Fv, P, FP, n, n)  # F P
    for i in range(n):
        for j in range(n):
            Pp[i, j] = Q[i, j]
    add_times_sparse_t(Fr, Fc, Fv, FP, Pp, n)  # Eq. 6: P⁻ = F P Fᵀ + Q
    symmetrize_into(Pp, n)


@njit_inline
def predict_cv(struct, tx, tz, x, P, Q, xp, Pp, FP):
    """:func:`predict_sparse` for per-axis blocks ``struct.fb[a] = [f00, f01, f10, f11]`` (same result).

    ``x⁻ = F x`` (Eq. 5) and ``P⁻ = F P Fᵀ + Q`` (Eq. 6) on a dense ``P``, symmetrised.
    """
    fb = struct.fb
    n_a = len(tz)
    n = len(tx)
    for a in range(n_a):
        i = 2 * a
        f00 = fb[a, 0]
        f01 = fb[a, 1]
        f10 = fb[a, 2]
        f11 = fb[a, 3]
        x0 = x[i]
        x1 = x[i + 1]
        xp[i] = f00 * x0 + f01 * x1  # Eq. 5
        xp[i + 1] = f10 * x0 + f11 * x1
        for j in range(n):  # F P, rows 2a, 2a+1
            p0 = P[i, j]
            p1 = P[i + 1, j]
            FP[i, j] = f00 * p0 + f01 * p1
            FP[i + 1, j] = f10 * p0 + f11 * p1
    for i in range(n):  # (F P) Fᵀ + Q, columns 2a, 2a+1 (Eq. 6)
        for a in range(n_a):
            j = 2 * a
            g0 = FP[i, j]
            g1 = FP[i, j + 1]
            Pp[i, j] = Q[i, j] + fb[a, 0] * g0 + fb[a, 1] * g1
            Pp[i, j + 1] = Q[i, j + 1] + fb[a, 2] * g0 + fb[a, 3] * g1
    symmetrize_into(Pp, n)


@njit_inline
def innovation_sparse(struct, tz, z, xp, nu):
    """``ν = z − H x⁻``."""
    Hr, Hc, Hv = struct.Hr, struct.Hc, struct.Hv
    for r in range(len(tz)):
        nu[r] = z[r]
    for q in range(len(Hv)):
        nu[Hr[q]] -= Hv[q] * xp[Hc[q]]


@njit_inline
def innovation_cv(struct, tz, z, xp, nu):
    """:func:`innovation_sparse` for ``H`` selecting positions."""
    for r in range(len(tz)):
        nu[r] = z[r] - xp[2 * r]


@njit_inline
def innovation_cov_sparse(struct, tz, Pp, R, S):
    """``S = H P⁻ Hᵀ + R``."""
    Hr, Hc, Hv = struct.Hr, struct.Hc, struct.Hv
    n_z = len(tz)
    for r1 in range(n_z):
        for r2 in range(n_z):
            S[r1, r2] = R[r1, r2]
    for q1 in range(len(Hv)):
        for q2 in range(len(Hv)):
            S[Hr[q1], Hr[q2]] += Hv[q1] * Pp[Hc[q1], Hc[q2]] * Hv[q2]


@njit_inline
def innovation_cov_cv(struct, tz, Pp, R, S):
    """:func:`innovation_cov_sparse` for ``H`` selecting positions."""
    n_z = len(tz)
    for r1 in range(n_z):
        for r2 in range(n_z):
            S[r1, r2] = R[r1, r2] + Pp[2 * r1, 2 * r2]


# ---------------------------------------------------------------------------------------------
# Dispatch by structure class (compile time; Python isinstance when interpreted)
# ---------------------------------------------------------------------------------------------


def predict(struct, tx, tz, x, P, Q, xp, Pp, FP):
    """SPEC §4.2 ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (Eqs. 5-6), symmetrised, for ``struct``."""
    impl = predict_cv if isinstance(struct, CVStructure) else predict_sparse
    impl(struct, tx, tz, x, P, Q, xp, Pp, FP)


def innovation(struct, tz, z, xp, nu):
    """``ν = z − H x⁻`` for ``struct``."""
    impl = innovation_cv if isinstance(struct, CVStructure) else innovation_sparse
    impl(struct, tz, z, xp, nu)


def innovation_cov(struct, tz, Pp, R, S):
    """``S = H P⁻ Hᵀ + R`` for ``struct``."""
    impl = innovation_cov_cv if isinstance(struct, CVStructure) else innovation_cov_sparse
    impl(struct, tz, Pp, R, S)


def _is_cv(struct) -> bool:
    """Typing-time test: is the numba type of ``struct`` a :class:`CVStructure`?"""
    return getattr(struct, "instance_class", None) is CVStructure


if not interpreting():  # the three overloads: same signatures as the stubs above

    @overload(predict, inline="always")
    def _predict(struct, tx, tz, x, P, Q, xp, Pp, FP):
        return (predict_cv if _is_cv(struct) else predict_sparse).py_func

    @overload(innovation, inline="always")
    def _innovation(struct, tz, z, xp, nu):
        return (innovation_cv if _is_cv(struct) else innovation_sparse).py_func

    @overload(innovation_cov, inline="always")
    def _innovation_cov(struct, tz, Pp, R, S):
        return (innovation_cov_cv if _is_cv(struct) else innovation_cov_sparse).py_func


# ---------------------------------------------------------------------------------------------
# Run-loop helpers (shared with the integrated filter)
# ---------------------------------------------------------------------------------------------


def step_arrays(n, n_z):
    """Per-element work arrays of a run loop: ``xb, Pb`` (state), ``zt`` (measurement row),
    ``xp, Pp`` (prediction), ``FP`` (``F P``)."""
    return (
        np.empty(n),
        np.empty((n, n)),
        np.empty(n_z),
        np.empty(n),
        np.empty((n, n)),
        np.empty((n, n)),
    )


step_arrays_jit = njit_inline(step_arrays)


@njit_inline
def copy_matrix(src, dst, n):
    """``dst[:n, :n] = src[:n, :n]``."""
    for i in range(n):
        for j in range(n):
            dst[i, j] = src[i, j]


@njit_inline
def writable_copy(A, n):
    """A new ``(n, n)`` array holding ``A[:n, :n]``.

    The run loops pass the model's (possibly read-only) ``R`` to :func:`._kernels_em.em_update`
    through such a copy, so that the update is compiled for one signature, not one per loop.
    """
    B = np.empty((n, n))
    copy_matrix(A, B, n)
    return B


@njit_inline
def copy_state(xs, Ps, xd, Pd, n):
    """``xd = xs``, ``Pd = Ps`` (e.g. predict only: the posterior is the prediction)."""
    for i in range(n):
        xd[i] = xs[i]
        for j in range(n):
            Pd[i, j] = Ps[i, j]


@njit_inline
def load_element(x, P, b, xb, Pb, tx):
    """Element ``b`` of the batched state into the local ``xb``, ``Pb``."""
    n = len(tx)
    for i in range(n):
        xb[i] = x[b, i]
        for j in range(n):
            Pb[i, j] = P[b, i, j]


@njit_inline
def store_element(x, P, b, xb, Pb, tx):
    """The local ``xb``, ``Pb`` back into element ``b`` of the batched state."""
    n = len(tx)
    for i in range(n):
        x[b, i] = xb[i]
        for j in range(n):
            P[b, i, j] = Pb[i, j]


@njit_inline
def put_sample(mean, cov, b, t, xb, Pb, tx):
    """``mean[b, t] = xb``, ``cov[b, t] = Pb``."""
    n = len(tx)
    for i in range(n):
        mean[b, t, i] = xb[i]
        for j in range(n):
            cov[b, t, i, j] = Pb[i, j]


@njit_inline
def init_from(zt, Hpinv, P0, xb, Pb, tx, tz):
    """SPEC §4.2 initialisation: ``x = H⁺ z``, ``P = P₀``."""
    n = len(tx)
    n_a = len(tz)
    for i in range(n):
        acc = 0.0
        for c in range(n_a):
            acc += Hpinv[i, c] * zt[c]
        xb[i] = acc
        for j in range(n):
            Pb[i, j] = P0[i, j]


@njit_inline
def read_row(z, b, t, zt, tz):
    """``zt = z[b, t]``; True when every component is finite (a valid measurement)."""
    valid = True
    for c in range(len(tz)):
        zt[c] = z[b, t, c]
        if not np.isfinite(zt[c]):
            valid = False
    return valid
