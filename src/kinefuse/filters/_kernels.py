"""Dense single-element Kalman kernels (numba), the reference form used by every filter.

Textbook symbols (``x, P, F, Q, H, R, K, S, nu``), no validation. Each line carries the SPEC
equation it implements. Arrays are single elements: ``x (n_x,)``, ``P (n_x, n_x)``.
Fast per-axis forms for batches live beside these (see module docs of the filter objects).
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels_linalg import CHOL_FAILED, chol_status


@njit
def symmetrize(P):
    """``(P + Pᵀ)/2`` (SPEC §1 numerical hygiene)."""
    return 0.5 * (P + P.T)


# Small dense products as explicit loops: for the 2-6 dimensional matrices of this package they
# are as fast as BLAS calls and compile in a fraction of the time of numba's ``@``/``np.dot``
# wrappers (the cold-start compile time of every filter depends on it).


@njit_inline
def matmul_into(A, B, C, n, k, m, at=False):
    """``C[:n, :m] = A[:n, :k] @ B[:k, :m]`` in place, skipping the zero entries of ``A``.

    ``at``: ``A`` is given transposed (``C = Aᵀ B`` with ``A (k, n)``).
    """
    for i in range(n):
        for j in range(m):
            C[i, j] = 0.0
        for p in range(k):
            a = A[p, i] if at else A[i, p]
            if a != 0.0:
                for j in range(m):
                    C[i, j] += a * B[p, j]


@njit
def matmul(A, B):
    """``A @ B`` for small dense 2-D arrays."""
    n, k = A.shape
    m = B.shape[1]
    C = np.empty((n, m))
    matmul_into(A, B, C, n, k, m)
    return C


@njit
def matmul_bt(A, B):
    """``A @ B.T`` for small dense 2-D arrays."""
    n, k = A.shape
    m = B.shape[0]
    C = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for p in range(k):
                s += A[i, p] * B[j, p]
            C[i, j] = s
    return C


@njit
def matvec(A, x):
    """``A @ x`` for a small dense matrix and vector."""
    n, k = A.shape
    y = np.empty(n)
    for i in range(n):
        s = 0.0
        for p in range(k):
            s += A[i, p] * x[p]
        y[i] = s
    return y


@njit
def add_outer(P, w, d):
    """``P += w * d dᵀ`` in place."""
    n = d.shape[0]
    for i in range(n):
        for j in range(n):
            P[i, j] += w * d[i] * d[j]


@njit
def kf_predict(x, P, F, Q):
    """KF prediction, SPEC §4.2: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``."""
    x_pred = matvec(F, x)  # SPEC §4.2 kf_predict
    P_pred = matmul_bt(matmul(F, P), F) + Q  # SPEC §4.2 kf_predict
    return x_pred, symmetrize(P_pred)


@njit
def chol_lower_into(S, L, n):
    """Lower Cholesky factor of SPD ``S[:n, :n]`` into ``L[:n, :n]`` (no allocation); returns ok.

    :func:`~._kernels_linalg.chol_status` (SPEC §13: on failure add ``ε·tr(S)/n·I`` with
    ε = 1e-12, ×10 up to 1e-6), so gains and likelihoods of every kernel agree.
    """
    return chol_status(S, L, n) != CHOL_FAILED


@njit
def chol_lower(S):
    """Lower Cholesky factor of SPD ``S`` with the SPEC §13 regularisation ladder
    (:func:`chol_lower_into`). Returns ``(L, ok)``."""
    n = S.shape[0]
    L = np.zeros_like(S)
    ok = chol_lower_into(S, L, n)
    return L, ok


@njit
def chol_solve_spd(S, B):
    """Solve ``S X = B`` for SPD ``S`` via :func:`~._kernels_linalg.chol_status` (SPEC §13).

    Returns ``(X, status)``: a ``CHOL_*`` status of :mod:`._kernels_linalg`; ``X`` is NaN when
    ``S`` stayed indefinite (``CHOL_FAILED``).
    """
    n = S.shape[0]
    L = np.zeros_like(S)
    status = chol_status(S, L, n)
    if status == CHOL_FAILED:
        return np.full_like(B, np.nan), status
    X = np.empty_like(B)
    chol_solve_into(L, B, X, np.empty(n), n, B.shape[1])
    return X, status


@njit_inline
def chol_solve_into(L, B, X, y, n, m):
    """``X[:n, :m]`` solving ``L Lᵀ X = B[:n, :m]`` for the lower factor ``L`` (forward, then
    back substitution, column by column); ``y (n,)`` scratch. No allocation."""
    for c in range(m):
        for i in range(n):
            s = B[i, c]
            for k in range(i):
                s -= L[i, k] * y[k]
            y[i] = s / L[i, i]
        for i in range(n - 1, -1, -1):
            s = y[i]
            for k in range(i + 1, n):
                s -= L[k, i] * X[k, c]
            X[i, c] = s / L[i, i]


@njit
def kf_update_status(x_pred, P_pred, z, H, R):
    """KF update with the Joseph form, SPEC §4.2 ``kf_update``.

    Returns ``(x, P, nu, S, status)`` with the ``CHOL_*`` status of the factorisation of ``S``
    (:mod:`._kernels_linalg`). The caller handles missing ``z`` (predict only); when ``S`` could
    not be factorised (``CHOL_FAILED``) ``(x_pred, P_pred)`` is returned.
    """
    nu = z - matvec(H, x_pred)  # SPEC §4.2: ν = z − H x⁻
    HP = matmul(H, P_pred)  # H P⁻ = (P⁻ Hᵀ)ᵀ
    S = matmul_bt(HP, H) + R  # SPEC §4.2: S = H P⁻ Hᵀ + R
    Kt, status = chol_solve_spd(S, HP)  # SPEC §4.2: K = solve(S, H P⁻)ᵀ
    if status == CHOL_FAILED:
        return x_pred.copy(), P_pred.copy(), nu, S, status
    K = Kt.T.copy()
    x = x_pred + matvec(K, nu)  # SPEC §4.2: x = x⁻ + K ν
    A = -matmul(K, H)
    for i in range(A.shape[0]):
        A[i, i] += 1.0
    P = matmul_bt(matmul(A, P_pred), A) + matmul_bt(matmul(K, R), K)  # SPEC §4.2 Joseph form
    return x, symmetrize(P), nu, S, status


@njit
def kf_update(x_pred, P_pred, z, H, R):
    """:func:`kf_update_status` returning ``(x, P, nu, S, ok)``, ``ok`` False when ``S`` could
    not be factorised (then ``(x_pred, P_pred)`` is returned)."""
    x, P, nu, S, status = kf_update_status(x_pred, P_pred, z, H, R)
    return x, P, nu, S, status != CHOL_FAILED


@njit
def mahalanobis(nu, M):
    """``νᵀ M⁻¹ ν`` via Cholesky; NaN if ``M`` cannot be factorised."""
    X, status = chol_solve_spd(M, nu.reshape(-1, 1).copy())
    if status == CHOL_FAILED:
        return np.nan
    s = 0.0
    for i in range(nu.shape[0]):
        s += nu[i] * X[i, 0]
    return s
