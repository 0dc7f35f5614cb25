"""Small dense linear algebra shared by every kernel (numba): ONE Cholesky, solves, floors.

* :func:`chol_shifted` is the package's only Cholesky factorisation; :func:`chol_status`
  (inlined fast path) and :func:`chol_regularised` add the SPEC §13 regularisation ladder
  (``S + ε·tr(S)/n·I`` with ε = 1e-12, ×10 up to 1e-6) and return a status
  (:data:`CHOL_OK`, :data:`CHOL_REGULARISED`, :data:`CHOL_FAILED`). Kernels pass the status
  (or a count of non-zero statuses) out to the filter objects, which turn it into ONE warning
  per call (SPEC §13; STYLE.md: warn, never silently fix).
* Triangular solves and quadratic forms with a factor: :func:`chol_solve_rows` (in place, many
  right-hand sides), :func:`quad_inv`.
* The EM-KF floors (SPEC §5.4): :func:`floor_clip` raises generalised eigenvalues, with the
  LAPACK reference :func:`floor_clip_lapack`; :func:`floor_binds` / :func:`not_pd_above` test
  whether a floor binds.

Sizes are plain ints; inlined callers (``njit_inline``) pass compile-time constants
(``len(size_tuple)``) so LLVM unrolls the small loops.
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline

CHOL_OK, CHOL_REGULARISED, CHOL_FAILED = 0, 1, 2


@njit_inline
def chol_shifted(A, L, n, shift):
    """Lower Cholesky factor of ``A[:n, :n] + shift·I`` into the lower triangle of ``L``.

    Row by row, ``L[i, j] = (A[i, j] − Σ_p L[i, p] L[j, p]) / L[j, j]``; the strict upper
    triangle of ``L`` is not touched. Returns False (``L`` partly written) when a pivot is not
    positive and finite, i.e. the matrix is not (numerically) positive definite.
    """
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j]
            if i == j:
                s += shift  # SPEC §13: S + ε·tr(S)/n·I (shift 0: the plain factorisation)
            for p in range(j):
                s -= L[i, p] * L[j, p]
            if i == j:
                if not (s > 0.0 and s < np.inf):
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@njit
def chol_regularised(S, L, n):
    """:func:`chol_shifted` with the SPEC §13 ladder: returns a ``CHOL_*`` status.

    ``CHOL_OK``: ``S`` itself was factorised; ``CHOL_REGULARISED``: ``S + ε·tr(S)/n·I`` for the
    smallest ε in 1e-12, 1e-11, ..., 1e-6 that works; ``CHOL_FAILED``: none did.
    """
    if chol_shifted(S, L, n, 0.0):
        return CHOL_OK
    tr = 0.0
    for i in range(n):
        tr += S[i, i]
    scale = max(tr / n, 1e-300)
    eps = 1e-12
    while eps <= 1e-6 * 1.0000001:
        if chol_shifted(S, L, n, eps * scale):
            return CHOL_REGULARISED
        eps *= 10.0
    return CHOL_FAILED


@njit_inline
def chol_status(S, L, n):
    """:func:`chol_regularised` with the common case (no regularisation) inlined."""
    if chol_shifted(S, L, n, 0.0):
        return CHOL_OK
    return chol_regularised(S, L, n)


@njit_inline
def symmetrize_into(A, n):
    """``A ← (A + Aᵀ)/2`` in place for ``A[:n, :n]`` (SPEC §1 numerical hygiene)."""
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (A[i, j] + A[j, i])
            A[i, j] = v
            A[j, i] = v


@njit_inline
def chol_solve_rows(L, B, n, m):
    """In place ``B[:n, :m] <- (L Lᵀ)⁻¹ B`` for a lower Cholesky factor ``L``.

    Row-major order so the ``m`` independent right-hand sides share each reciprocal pivot.
    """
    for i in range(n):
        d = 1.0 / L[i, i]
        for c in range(m):
            s = B[i, c]
            for p in range(i):
                s -= L[i, p] * B[p, c]
            B[i, c] = s * d
    for i in range(n - 1, -1, -1):
        d = 1.0 / L[i, i]
        for c in range(m):
            s = B[i, c]
            for p in range(i + 1, n):
                s -= L[p, i] * B[p, c]
            B[i, c] = s * d


@njit_inline
def quad_inv(L, v, tmp, n):
    """``vᵀ (L Lᵀ)⁻¹ v`` by forward substitution only: ``‖L⁻¹ v‖²``."""
    acc = 0.0
    for i in range(n):
        s = v[i]
        for p in range(i):
            s -= L[i, p] * tmp[p]
        tmp[i] = s / L[i, i]
        acc += tmp[i] * tmp[i]
    return acc


@njit_inline
def not_pd_above(A, Nom, c, W, n):
    """True when ``A − c·Nom`` is not positive definite: LDLᵀ pivots, no square roots.

    Same test as :func:`floor_binds` (all pivots > 0) with a shorter dependency chain; the two
    can only disagree for a matrix singular to rounding, where clipping changes nothing.
    """
    for i in range(n):
        for j in range(i, n):
            W[i, j] = A[i, j] - c * Nom[i, j]
    for k in range(n):  # right-looking elimination on the upper triangle
        d = W[k, k]
        if not (d > 0.0):
            return True
        inv = 1.0 / d
        for i in range(k + 1, n):
            f = W[k, i] * inv
            for j in range(i, n):
                W[i, j] -= f * W[k, j]
    return False


@njit_inline
def floor_binds(A, Nom, c, W, L, n):
    """True when ``A - c·Nom`` is not positive definite (Cholesky test)."""
    for i in range(n):
        for j in range(n):
            W[i, j] = A[i, j] - c * Nom[i, j]
    return not chol_shifted(W, L, n, 0.0)


@njit
def _jacobi_eigh(A, V, n):
    """Eigen-decomposition of symmetric ``A[:n, :n]`` in place by cyclic Jacobi rotations.

    On return the diagonal of ``A`` holds the eigenvalues and the columns of ``V`` the
    eigenvectors (``A_in = V diag V``ᵀ). Golub & Van Loan, *Matrix Computations*, Alg. 8.5.3
    (symmetric Schur 2×2 rotations); quadratic convergence, a handful of sweeps for n ≤ 6.
    """
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(60):
        off = 0.0
        dia = 0.0
        for i in range(n):
            dia += A[i, i] * A[i, i]
            for j in range(i + 1, n):
                off += A[i, j] * A[i, j]
        if off <= 1e-30 * dia or off == 0.0:  # off-diagonal ~1e-15 relative: converged
            return
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq * apq <= 1e-36 * abs(A[p, p] * A[q, q]):
                    A[p, q] = 0.0  # below rounding of the diagonal: already decoupled
                    A[q, p] = 0.0
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                cs = 1.0 / np.sqrt(t * t + 1.0)
                sn = t * cs
                for k in range(n):  # A ← A J (columns p, q)
                    akp = A[k, p]
                    akq = A[k, q]
                    A[k, p] = cs * akp - sn * akq
                    A[k, q] = sn * akp + cs * akq
                for k in range(n):  # A ← Jᵀ A (rows p, q)
                    apk = A[p, k]
                    aqk = A[q, k]
                    A[p, k] = cs * apk - sn * aqk
                    A[q, k] = sn * apk + cs * aqk
                A[p, q] = 0.0
                A[q, p] = 0.0
                for k in range(n):  # V ← V J
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = cs * vkp - sn * vkq
                    V[k, q] = sn * vkp + cs * vkq


@njit
def floor_clip(A, Nom, c, n):
    """Raise the generalised eigenvalues of ``A`` w.r.t. ``Nom`` to at least ``c`` (SPEC §5.4).

    ``A ← L (V max(Λ, c) Vᵀ) Lᵀ`` with ``Nom = L Lᵀ`` and ``L⁻¹ A L⁻ᵀ = V Λ Vᵀ``. Returns False
    (``A`` untouched) when ``Nom`` is not positive definite or ``A`` is not finite.

    Small fixed-size arithmetic only (triangular solves and :func:`_jacobi_eigh`, no LAPACK
    call, no temporaries per product): with many EM iterations the floor binds on almost every
    step, and the LAPACK form (:func:`floor_clip_lapack`, the reference) cost ~10 µs a call.
    """
    return floor_clip_into(
        A, Nom, c, n, np.zeros((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty(n)
    )


@njit_inline
def _eigvec3(B, lam, u):
    """Unit eigenvector of symmetric 3×3 ``B`` for the simple eigenvalue ``lam`` (largest cross
    product of two rows of ``B − lam I``) into ``u``; False if the rows are (nearly) parallel."""
    a0, a1, a2 = B[0, 0] - lam, B[0, 1], B[0, 2]
    b0, b1, b2 = B[1, 0], B[1, 1] - lam, B[1, 2]
    c0, c1, c2 = B[2, 0], B[2, 1], B[2, 2] - lam
    best = -1.0
    for k in range(3):
        if k == 0:
            x, y, w = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        elif k == 1:
            x, y, w = a1 * c2 - a2 * c1, a2 * c0 - a0 * c2, a0 * c1 - a1 * c0
        else:
            x, y, w = b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0
        nn = x * x + y * y + w * w
        if nn > best:
            best = nn
            u[0], u[1], u[2] = x, y, w
    scale = a0 * a0 + a1 * a1 + a2 * a2 + b0 * b0 + b1 * b1 + b2 * b2 + c0 * c0 + c1 * c1 + c2 * c2
    if not (best > 1e-20 * scale * scale):
        return False
    inv = 1.0 / np.sqrt(best)
    for i in range(3):
        u[i] *= inv
    return True


@njit_inline
def _clip3(B, c, u):
    """Raise the eigenvalues of symmetric 3×3 ``B`` to at least ``c``, in place, in closed form.

    Eigenvalues by the trigonometric method (Smith 1961, *Commun. ACM* 4(4):168); then with two
    clipped ``B ← c I + (λ₁ − c) u uᵀ`` (``u`` the top eigenvector), with one ``B ← B + (c − λ₃)
    v vᵀ`` (``v`` the bottom one). The error stays at rounding level also for close eigenvalues
    (a poorly determined eigenvector then carries a proportionally small weight). Returns False
    (``B`` untouched) when an eigenvector cannot be formed; the caller then uses Jacobi.
    """
    p1 = B[0, 1] * B[0, 1] + B[0, 2] * B[0, 2] + B[1, 2] * B[1, 2]
    if p1 == 0.0:  # diagonal
        for i in range(3):
            if B[i, i] < c:
                B[i, i] = c
        return True
    q = (B[0, 0] + B[1, 1] + B[2, 2]) / 3.0
    d0 = B[0, 0] - q
    d1 = B[1, 1] - q
    d2 = B[2, 2] - q
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1) / 6.0)
    ip = 1.0 / p
    m00, m11, m22 = d0 * ip, d1 * ip, d2 * ip
    m01, m02, m12 = B[0, 1] * ip, B[0, 2] * ip, B[1, 2] * ip
    r = 0.5 * (m00 * (m11 * m22 - m12 * m12) - m01 * (m01 * m22 - m12 * m02)
               + m02 * (m01 * m12 - m11 * m02))  # fmt: skip
    r = min(1.0, max(-1.0, r))
    phi = np.arccos(r) / 3.0
    lam1 = q + 2.0 * p * np.cos(phi)
    lam3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    lam2 = 3.0 * q - lam1 - lam3
    nb = (lam1 < c) + (lam2 < c) + (lam3 < c)
    if nb == 0:
        return True
    if nb == 3:
        for i in range(3):
            for j in range(3):
                B[i, j] = c if i == j else 0.0
        return True
    if nb == 2:
        if not _eigvec3(B, lam1, u):
            return False
        w = lam1 - c
        for i in range(3):
            for j in range(3):
                B[i, j] = w * u[i] * u[j] + (c if i == j else 0.0)
        return True
    if not _eigvec3(B, lam3, u):
        return False
    w = c - lam3
    for i in range(3):
        for j in range(3):
            B[i, j] += w * u[i] * u[j]
    return True


@njit_inline
def floor_clip_into(A, Nom, c, n, L, Aw, V, wv):
    """:func:`floor_clip` on caller scratch ``L, Aw, V (≥ n, ≥ n)``, ``wv (≥ n,)`` (no allocation)."""
    for i in range(n):
        for j in range(n):
            if not np.isfinite(A[i, j]):
                return False
    # Every generalised eigenvalue below c (c·Nom − A positive definite; the usual case once
    # the EM has collapsed R): all are raised to c, i.e. A = c·Nom, no eigenvectors needed.
    for i in range(n):
        for j in range(n):
            Aw[i, j] = c * Nom[i, j] - A[i, j]
            V[i, j] = 0.0
    if chol_shifted(Aw, V, n, 0.0):
        for i in range(n):
            for j in range(n):
                A[i, j] = c * Nom[i, j]
        return True
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    if not chol_shifted(Nom, L, n, 0.0):
        return False
    for j in range(n):  # Y = L⁻¹ A (forward substitution, column j)
        for i in range(n):
            s = A[i, j]
            for k in range(i):
                s -= L[i, k] * Aw[k, j]
            Aw[i, j] = s / L[i, i]
    for i in range(n):  # Aw = Y L⁻ᵀ = (L⁻¹ Yᵀ)ᵀ: forward substitution on the rows of Y
        for j in range(n):
            s = Aw[i, j]
            for k in range(j):
                s -= L[j, k] * Aw[i, k]
            Aw[i, j] = s / L[j, j]
    for i in range(n):
        for j in range(i + 1, n):
            sym = 0.5 * (Aw[i, j] + Aw[j, i])
            Aw[i, j] = sym
            Aw[j, i] = sym
    if n == 3 and _clip3(Aw, c, wv):  # closed form (whitened A ← clipped, in place)
        for i in range(3):  # A = L Aw Lᵀ
            for k in range(3):
                acc = 0.0
                for p in range(i + 1):
                    acc += L[i, p] * Aw[p, k]
                V[i, k] = acc
        for i in range(3):
            for j in range(i + 1):
                acc = 0.0
                for k in range(j + 1):
                    acc += V[i, k] * L[j, k]
                A[i, j] = acc
                A[j, i] = acc
        return True
    _jacobi_eigh(Aw, V, n)
    for k in range(n):
        wv[k] = max(Aw[k, k], c)  # clipped eigenvalues
    for i in range(n):  # M = L V (into Aw)
        for k in range(n):
            s = 0.0
            for p in range(i + 1):
                s += L[i, p] * V[p, k]
            Aw[i, k] = s
    for i in range(n):  # A = M diag(w) Mᵀ, symmetric by construction
        for j in range(i + 1):
            s = 0.0
            for k in range(n):
                s += Aw[i, k] * wv[k] * Aw[j, k]
            A[i, j] = s
            A[j, i] = s
    return True


@njit
def floor_clip_lapack(A, Nom, c, n):
    """Reference form of :func:`floor_clip` with LAPACK's ``inv`` and ``eigh`` (tests only).

    ``A ← L (V max(Λ, c) Vᵀ) Lᵀ`` with ``Nom = L Lᵀ`` and ``L⁻¹ A L⁻ᵀ = V Λ Vᵀ``. Returns False
    (``A`` untouched) when ``Nom`` is not positive definite or ``A`` is not finite.
    """
    for i in range(n):
        for j in range(n):
            if not np.isfinite(A[i, j]):
                return False
    L = np.zeros((n, n))
    if not chol_shifted(Nom, L, n, 0.0):
        return False
    Li = np.linalg.inv(L)
    LiT = np.ascontiguousarray(Li.T)
    Ac = np.ascontiguousarray(A[:n, :n])
    Aw = Li @ Ac @ LiT
    Aw = 0.5 * (Aw + Aw.T)
    w, V = np.linalg.eigh(Aw)
    for i in range(n):
        if w[i] < c:
            w[i] = c
    Vw = np.ascontiguousarray(V * w)
    VT = np.ascontiguousarray(V.T)
    LT = np.ascontiguousarray(L.T)
    Ar = L @ (Vw @ VT) @ LT
    for i in range(n):
        for j in range(n):
            A[i, j] = 0.5 * (Ar[i, j] + Ar[j, i])
    return True
