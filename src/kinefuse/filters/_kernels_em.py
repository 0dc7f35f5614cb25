"""EM-adaptive KF and EM-KF/FIR integrated filter kernels (numba).

Paper A §3.2 (Eqs. 10-23, Algorithm 2) and §3.4 (Eq. 29) as corrected by SPEC §5.3 and §7.3.
Textbook symbols, no validation. The EM-KF does not decouple per axis (``Ω₁``, ``Ω₂`` hold outer
products of the innovation, SPEC §1), so these are tight dense loops on preallocated scratch
arrays. ``F`` and ``H`` are passed as sparse triplets ``(rows, cols, vals)`` of their non-zero
entries (9 and 3 entries for the 3-D constant-velocity model); any dense matrix works too.

Status bits returned by :func:`em_update`: 1 = R floor bound, 2 = P⁻ floor bound,
4 = ``S`` had to be regularised (SPEC §13), 8 = ``S`` could not be factorised (update skipped).

Two forms of each run loop:

* :func:`em_kf_run`, :func:`integrated_run`: the general form for any ``F``, ``H`` (sparse
  triplets), the reference.
* :func:`em_kf_run_cv`, :func:`integrated_run_cv`: the same arithmetic, in the same order (bit
  for bit the same results), specialised to the constant-velocity structure of SPEC §1
  (:func:`cv_structure`): ``F`` block-diagonal with a 2×2 block per axis and ``H`` selecting the
  position of each axis. Then ``x⁻ = F x`` and ``F P Fᵀ`` are per-axis 2×2 closed forms on the
  dense ``P``, ``H P`` is rows ``0, 2, 4`` of ``P``, ``H P Hᵀ`` a sub-matrix, and ``I − K H``
  only touches the position columns, so no product with ``F`` or ``H`` is formed. Every helper of
  the time loop is inlined at the numba IR level (``inline="always"``): a call of a compiled
  function with array arguments costs two atomic reference-count updates per array, which
  dominated the general form. The positive-definiteness tests of the floors use an LDLᵀ
  elimination (no square roots, off the critical path of the iteration).
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit
from kinefuse.filters._kernels_ufir import (
    _chol,
    fir_estimate,
    njit_inline,
    ufir_horizon_axes,
    ufir_taps,
)

#: Internal status bit of :func:`em_update_cv`: the last Joseph update computed only the position
#: block of ``P`` (complete it with :func:`joseph_cv` before using ``P``).
P_DEFERRED = 16

FLOOR_R, FLOOR_P, S_REGULARISED, S_FAILED = 1, 2, 4, 8


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


@njit
def _chol_t(A, L, tn):
    """Lower Cholesky of ``A[:n, :n]`` (``n = len(tn)``) into ``L``; False if not PD."""
    n = len(tn)
    for j in range(n):  # column by column, one reciprocal per pivot
        s = A[j, j]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if not (s > 0.0):
            return False
        d = np.sqrt(s)
        L[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = A[i, j]
            for p in range(j):
                s -= L[i, p] * L[j, p]
            L[i, j] = s * inv
    return True


@njit
def _chol_solve(L, B, tn, tm):
    """In place ``B[:n, :m] <- (L Lᵀ)⁻¹ B`` for a lower Cholesky factor ``L``.

    Row-major order so the ``m`` independent right-hand sides share each reciprocal pivot.
    """
    n = len(tn)
    m = len(tm)
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


@njit
def _chol_reg(S, L, work, tn):
    """Cholesky of ``S`` with SPEC §13 regularisation: 0 ok, 1 regularised, 2 failed."""
    n = len(tn)
    if _chol_t(S, L, tn):
        return 0
    tr = 0.0
    for i in range(n):
        tr += S[i, i]
    scale = max(tr / n, 1e-300)
    eps = 1e-12
    while eps <= 1e-6 * 1.0000001:
        for i in range(n):
            for j in range(n):
                work[i, j] = S[i, j]
            work[i, i] += eps * scale  # S + ε·tr(S)/n·I
        if _chol_t(work, L, tn):
            return 1
        eps *= 10.0
    return 2


@njit
def _quad_inv(L, v, tmp, tn):
    """``vᵀ (L Lᵀ)⁻¹ v`` by forward substitution only: ``‖L⁻¹ v‖²``."""
    n = len(tn)
    acc = 0.0
    for i in range(n):
        s = v[i]
        for p in range(i):
            s -= L[i, p] * tmp[p]
        tmp[i] = s / L[i, i]
        acc += tmp[i] * tmp[i]
    return acc


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
    if _chol(Aw, V, n):
        for i in range(n):
            for j in range(n):
                A[i, j] = c * Nom[i, j]
        return True
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    if not _chol(Nom, L, n):
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
    if not _chol(Nom, L, n):
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


@njit
def _floor_binds(A, Nom, c, W, L, tn):
    """True when ``A - c·Nom`` is not positive definite (cheap Cholesky test)."""
    n = len(tn)
    for i in range(n):
        for j in range(n):
            W[i, j] = A[i, j] - c * Nom[i, j]
    return not _chol_t(W, L, tn)


@njit
def _copy_vec(src, dst):
    for i in range(src.shape[0]):
        dst[i] = src[i]


@njit
def _copy_mat(src, dst):
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


@njit
def _get(x, P, b, xb, Pb):
    """Element ``b`` of the batched state into local arrays."""
    n = xb.shape[0]
    for i in range(n):
        xb[i] = x[b, i]
        for j in range(n):
            Pb[i, j] = P[b, i, j]


@njit
def _set(x, P, b, xb, Pb):
    n = xb.shape[0]
    for i in range(n):
        x[b, i] = xb[i]
        for j in range(n):
            P[b, i, j] = Pb[i, j]


@njit
def _put(o_mean, o_cov, b, t, xb, Pb):
    n = xb.shape[0]
    for i in range(n):
        o_mean[b, t, i] = xb[i]
        for j in range(n):
            o_cov[b, t, i, j] = Pb[i, j]


@njit
def _fill(o_nu, o_dist, o_R, b, t):
    """NaN diagnostics for a step without update."""
    n_z = o_nu.shape[2]
    for r1 in range(n_z):
        o_nu[b, t, r1] = np.nan
        if o_R.shape[0] > 0:
            for r2 in range(n_z):
                o_R[b, t, r1, r2] = np.nan
    o_dist[b, t] = np.nan


@njit
def kf_predict_sparse(tx, x, P, Fr, Fc, Fv, Q, xp, Pp, FP):
    """SPEC §4.2 ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (Eqs. 5-6 without the noise term), symmetrised."""
    n = len(tx)
    for i in range(n):
        xp[i] = 0.0
        for j in range(n):
            FP[i, j] = 0.0
    for t in range(len(Fv)):
        i = Fr[t]
        c = Fc[t]
        v = Fv[t]
        xp[i] += v * x[c]  # Eq. 5: x⁻ = F x
        for j in range(n):
            FP[i, j] += v * P[c, j]
    for i in range(n):
        for j in range(n):
            Pp[i, j] = Q[i, j]
    for t in range(len(Fv)):
        j = Fr[t]
        c = Fc[t]
        v = Fv[t]
        for i in range(n):
            Pp[i, j] += v * FP[i, c]  # Eq. 6: P⁻ = F P Fᵀ + Q
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (Pp[i, j] + Pp[j, i])
            Pp[i, j] = s
            Pp[j, i] = s


def em_scratch(n_x, n_z):
    """Scratch arrays of :func:`em_update`: ``(mats, vecs)`` tuples (allocated once per run)."""
    mats = (
        np.zeros((n_x, n_x)),  # Pm  P̄⁻
        np.zeros((n_z, n_x)),  # M   H P̄⁻ / H P
        np.zeros((n_z, n_z)),  # S
        np.zeros((n_z, n_z)),  # LS  chol(S)
        np.zeros((n_z, n_x)),  # Kt  Kᵀ
        np.zeros((n_x, n_x)),  # AP  (I − K H) P̄⁻
        np.zeros((n_x, n_z)),  # D   K R − AP Hᵀ
        np.zeros((n_x, n_x)),  # W   work
        np.zeros((n_x, n_x)),  # L6  work factor
    )
    vecs = (np.zeros(n_z), np.zeros(n_z), np.zeros(n_x))  # nu, e, tmp
    return mats, vecs


em_scratch_jit = njit(em_scratch)


@njit
def em_update(
    tx,
    tz,
    xp,
    Pp,
    z,
    Hr,
    Hc,
    Hv,
    R0,
    Rnom,
    Uprior,
    u_prior,
    n_iter,
    regularized,
    tau,
    floor_c,
    want_R,
    x,
    P,
    Rj,
    Om1,
    mats,
    vecs,
):
    """EM-KF measurement update at one time step (SPEC §5.3; paper A Algorithm 2 lines 5-17).

    Parameters
    ----------
    tx, tz : tuple
        ``size_tuple(n_x)``, ``size_tuple(n_z)`` (compile-time sizes).
    xp, Pp : ndarray, shape (n_x,), (n_x, n_x)
        Prediction ``x⁻``, ``P⁻`` (fixed through the iterations).
    z : ndarray, shape (n_z,)
        Valid measurement.
    Hr, Hc, Hv : ndarray
        Non-zeros of ``H``.
    R0 : ndarray, shape (n_z, n_z)
        ``R^{(0)}``: nominal R (option A) or the inverse-Wishart prior mean (option B).
    Rnom : ndarray, shape (n_z, n_z)
        Nominal R, reference of the R floor.
    Uprior, u_prior : ndarray, shape (n_z, n_z), and float
        ``Û⁻`` and ``û⁻`` (option B only).
    n_iter : int
        ``N_EM``; ``n_iter=1`` is exactly the KF update (SPEC §5.2-6).
    regularized : bool
        Option B blending: ``P̄⁻ ← (τP⁻ + Ω₂)/(τ+1)``, ``R ← (Û⁻ + Ω₁)/(û⁻ − n_z)``.
    tau : float
        τ (option B only).
    floor_c : float
        Floors: ``R ⪰ c·R_nom`` and ``P̄⁻ ⪰ c·P⁻`` in the generalised-eigenvalue sense.
    want_R : bool
        Compute ``R^{(N_EM)}`` after the last iteration (False for a plain KF update).
    x, P, Rj, Om1 : ndarray
        Outputs: posterior, ``R^{(N_EM)}`` and the last ``Ω₁``.
    mats, vecs : tuple of ndarray
        Scratch from :func:`em_scratch`; ``vecs[0]`` holds ``ν`` on return.

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
    Pm, M, S, LS, Kt, AP, D, W, L6 = mats
    nu, e, tmp = vecs
    n_x = len(tx)
    n_z = len(tz)
    nnz = len(Hv)
    status = 0
    nis = np.nan
    # ν = z − H x⁻ (fixed: x⁻ does not change through the iterations, SPEC §5.3)
    for r in range(n_z):
        nu[r] = z[r]
    for t in range(nnz):
        nu[Hr[t]] -= Hv[t] * xp[Hc[t]]
    for i in range(n_x):
        x[i] = xp[i]
        for j in range(n_x):
            P[i, j] = Pp[i, j]
            Pm[i, j] = Pp[i, j]  # P̄⁻^{(0)} = P⁻ (Alg. 2 line 6)
    for r1 in range(n_z):
        for r2 in range(n_z):
            Rj[r1, r2] = R0[r1, r2]  # R^{(0)} = nominal, reset every step (SPEC §5.2-6)
    for jit in range(n_iter):
        # M = H P̄⁻ (n_z, n_x)
        for r in range(n_z):
            for c in range(n_x):
                M[r, c] = 0.0
        for t in range(nnz):
            r = Hr[t]
            cc = Hc[t]
            v = Hv[t]
            for c in range(n_x):
                M[r, c] += v * Pm[cc, c]
        # S = H P̄⁻ Hᵀ + R^{(j)}
        for r1 in range(n_z):
            for r2 in range(n_z):
                S[r1, r2] = Rj[r1, r2]
        for t in range(nnz):
            r2 = Hr[t]
            cc = Hc[t]
            v = Hv[t]
            for r1 in range(n_z):
                S[r1, r2] += v * M[r1, cc]
        for r1 in range(n_z):
            for r2 in range(r1 + 1, n_z):
                sym = 0.5 * (S[r1, r2] + S[r2, r1])
                S[r1, r2] = sym
                S[r2, r1] = sym
        st = _chol_reg(S, LS, W, tz)
        if st == 2:  # SPEC §13: skip the update; later iterations keep the previous one
            status |= S_FAILED if jit == 0 else S_REGULARISED
            break
        if st == 1:
            status |= S_REGULARISED
        # Kᵀ = S⁻¹ H P̄⁻  → K^{(j+1)} (Alg. 2 line 8; SPEC §5.2-4 gain index)
        for r in range(n_z):
            for c in range(n_x):
                Kt[r, c] = M[r, c]
        _chol_solve(LS, Kt, tz, tx)
        if jit == 0:
            nis = _quad_inv(LS, nu, tmp, tz)
        # x^{(j+1)} = x⁻ + K^{(j+1)} ν  (Alg. 2 line 9, Eq. 8)
        for i in range(n_x):
            acc = xp[i]
            for r in range(n_z):
                acc += Kt[r, i] * nu[r]
            x[i] = acc
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
                acc = 0.0
                for r1 in range(n_z):
                    acc += Kt[r1, i] * Rj[r1, r2]
                D[i, r2] = acc
        for t in range(nnz):
            r = Hr[t]
            cc = Hc[t]
            v = Hv[t]
            for i in range(n_x):
                D[i, r] -= v * AP[i, cc]
        # P^{(j+1)} = AP (I − K H)ᵀ + K R Kᵀ = AP + D Kᵀ  (Joseph, Eq. 9; SPEC §5.3)
        for i in range(n_x):
            for j in range(i, n_x):
                acc = AP[i, j]
                for r in range(n_z):
                    acc += D[i, r] * Kt[r, j]
                P[i, j] = acc
        for i in range(n_x):
            for j in range(i + 1, n_x):
                P[j, i] = P[i, j]  # upper triangle computed: P is exactly symmetric
        if jit == n_iter - 1 and not want_R:
            break
        # e = z − H x^{(j+1)}  (posterior residual, SPEC §5.2-2)
        for r in range(n_z):
            e[r] = z[r]
        for t in range(nnz):
            e[Hr[t]] -= Hv[t] * x[Hc[t]]
        # Ω₁ = e eᵀ + H P Hᵀ  (Eq. 17 corrected) → R^{(j+1)} (SPEC §5.2-1)
        for r in range(n_z):
            for c in range(n_x):
                M[r, c] = 0.0
        for t in range(nnz):
            r = Hr[t]
            cc = Hc[t]
            v = Hv[t]
            for c in range(n_x):
                M[r, c] += v * P[cc, c]
        for r1 in range(n_z):
            for r2 in range(n_z):
                Om1[r1, r2] = e[r1] * e[r2]
        for t in range(nnz):
            r2 = Hr[t]
            cc = Hc[t]
            v = Hv[t]
            for r1 in range(n_z):
                Om1[r1, r2] += v * M[r1, cc]
        for r1 in range(n_z):
            for r2 in range(r1 + 1, n_z):
                sym = 0.5 * (Om1[r1, r2] + Om1[r2, r1])
                Om1[r1, r2] = sym
                Om1[r2, r1] = sym
        if regularized:  # option B: inverse-Wishart mean (Û⁻ + Ω₁)/(û⁻ − n_z)
            den = u_prior - n_z
            for r1 in range(n_z):
                for r2 in range(n_z):
                    Rj[r1, r2] = (Uprior[r1, r2] + Om1[r1, r2]) / den
        else:
            for r1 in range(n_z):
                for r2 in range(n_z):
                    Rj[r1, r2] = Om1[r1, r2]
        if _floor_binds(Rj, Rnom, floor_c, W, LS, tz):  # SPEC §5.4 floor
            if floor_clip(Rj, Rnom, floor_c, n_z):
                status |= FLOOR_R
        if jit == n_iter - 1:
            break
        # Ω₂ = P + (x − x⁻)(x − x⁻)ᵀ  (Eq. 18) → P̄⁻^{(j+1)} (SPEC §5.2-1)
        for i in range(n_x):
            tmp[i] = x[i] - xp[i]
        for i in range(n_x):
            for j in range(n_x):
                Pm[i, j] = P[i, j] + tmp[i] * tmp[j]
        if regularized:  # option B: (τ P⁻ + Ω₂)/(τ + 1)
            for i in range(n_x):
                for j in range(n_x):
                    Pm[i, j] = (tau * Pp[i, j] + Pm[i, j]) / (tau + 1.0)
        if _floor_binds(Pm, Pp, floor_c, W, L6, tx):
            if floor_clip(Pm, Pp, floor_c, n_x):
                status |= FLOOR_P
    return status, nis


@njit
def em_kf_run(
    tx,
    tz,
    z,
    x,
    P,
    init,
    u,
    U,
    Fr,
    Fc,
    Fv,
    Hr,
    Hc,
    Hv,
    Q,
    Rnom,
    Hpinv,
    P0,
    n_iter,
    regularized,
    tau,
    rho,
    floor_c,
    o_mean,
    o_cov,
    o_obs,
    o_nu,
    o_dist,
    o_Rem,
):
    """Run the EM-KF over ``z (B, T, n_z)``; state arrays updated in place.

    ``tx``, ``tz``: :func:`size_tuple` of ``n_x``, ``n_z``; ``Fr, Fc, Fv`` / ``Hr, Hc, Hv``:
    :func:`sparse_triplets` of ``F`` / ``H``.

    Returns counts ``[R floor bound, P⁻ floor bound, S regularised, S failed]``.
    """
    B, T = z.shape[0], z.shape[1]
    n_x = len(tx)
    n_z = len(tz)
    mats, vecs = em_scratch_jit(n_x, n_z)
    nu = vecs[0]
    xb = np.empty(n_x)
    Pb = np.empty((n_x, n_x))
    zt = np.empty(n_z)
    xp = np.empty(n_x)
    Pp = np.empty((n_x, n_x))
    FP = np.empty((n_x, n_x))
    xn = np.empty(n_x)
    Pn = np.empty((n_x, n_x))
    Rj = np.empty((n_z, n_z))
    Om1 = np.empty((n_z, n_z))
    R0 = np.empty((n_z, n_z))
    Ub = np.empty((n_z, n_z))
    counts = np.zeros(4, np.int64)
    nz3 = n_z + 1.0
    for b in range(B):
        _get(x, P, b, xb, Pb)
        ub = u[b]
        _copy_mat(U[b], Ub)
        initialized = init[b]
        for t in range(T):
            valid = True
            for c in range(n_z):
                zt[c] = z[b, t, c]
                if not np.isfinite(zt[c]):
                    valid = False
            if not initialized:
                if valid:  # SPEC §4.2 initialisation
                    for i in range(n_x):
                        acc = 0.0
                        for c in range(n_z):
                            acc += Hpinv[i, c] * zt[c]
                        xb[i] = acc
                    _copy_mat(P0, Pb)
                    initialized = True
                _put(o_mean, o_cov, b, t, xb, Pb)
                o_obs[b, t] = valid
                _fill(o_nu, o_dist, o_Rem, b, t)
                continue
            kf_predict_sparse(tx, xb, Pb, Fr, Fc, Fv, Q, xp, Pp, FP)
            u_pr = 0.0
            if regularized:  # option B time update of (û, Û) (SPEC §5.3)
                u_pr = rho * (ub - nz3) + nz3
                for r1 in range(n_z):
                    for r2 in range(n_z):
                        Ub[r1, r2] *= rho
            ok = False
            if valid:
                if regularized:  # R^{(0)} = IW prior mean Û⁻/(û⁻ − n_z − 1)
                    for r1 in range(n_z):
                        for r2 in range(n_z):
                            R0[r1, r2] = Ub[r1, r2] / (u_pr - nz3)
                else:
                    _copy_mat(Rnom, R0)
                status, nis = em_update(
                    tx, tz, xp, Pp, zt, Hr, Hc, Hv, R0, Rnom, Ub, u_pr, n_iter, regularized, tau, floor_c, True, xn, Pn,
                    Rj, Om1, mats, vecs,
                )  # fmt: skip
                if status:
                    for bit in range(4):
                        if status & (1 << bit):
                            counts[bit] += 1
                ok = not (status & S_FAILED)
            if ok:
                _copy_vec(xn, xb)
                _copy_mat(Pn, Pb)
                if regularized:  # û = û⁻ + 1, Û = Û⁻ + Ω₁
                    ub = u_pr + 1.0
                    for r1 in range(n_z):
                        for r2 in range(n_z):
                            Ub[r1, r2] += Om1[r1, r2]
                for r1 in range(n_z):
                    o_nu[b, t, r1] = nu[r1]
                    for r2 in range(n_z):
                        o_Rem[b, t, r1, r2] = Rj[r1, r2]
                o_dist[b, t] = nis
            else:
                _copy_vec(xp, xb)
                _copy_mat(Pp, Pb)
                if regularized:
                    ub = u_pr
                _fill(o_nu, o_dist, o_Rem, b, t)
            _put(o_mean, o_cov, b, t, xb, Pb)
            o_obs[b, t] = ok
        _set(x, P, b, xb, Pb)
        u[b] = ub
        _copy_mat(Ub, U[b])
        init[b] = initialized
    return counts


@njit
def integrated_run(
    tx,
    tz,
    z,
    x,
    P,
    init,
    zring,
    k0,
    N,
    K,
    Fr,
    Fc,
    Fv,
    Hr,
    Hc,
    Hv,
    Q,
    Rnom,
    LR,
    Hpinv,
    P0,
    n_em,
    th1,
    th2,
    gate_S,
    feedback,
    floor_c,
    axis_blocks,
    W,
    P_full,
    F,
    Finv,
    H,
    Fa,
    Finva,
    Ha,
    Qa,
    Ra,
    o_mean,
    o_cov,
    o_obs,
    o_nu,
    o_d1,
    o_d2,
    o_mode,
):
    """Run the EM-KF/FIR integrated filter over ``z (B, T, n_z)`` (SPEC §7.3); state in place.

    Per element and step: shared prediction ``x⁻, P⁻``; ``D₁`` (Eq. 29 with ``R``, or with ``S``
    when ``gate_S``); KF update if ``D₁ < th1``; else EM-KF (``N_EM`` iterations) and
    ``D₂ = νᵀ R_em⁻¹ ν``; EM-KF if ``D₂ < th2`` or the FIR is not available (``k < N−1`` or
    ``fir_ready=False``), else the batch-initialised UFIR computed on demand from the ring
    (:func:`~kinefuse.filters._kernels_ufir.fir_estimate`). ``LR`` is the Cholesky factor of
    ``Rnom``; the other arguments as in :func:`em_kf_run` and
    :func:`~kinefuse.filters._kernels_ufir.ufir_run`.

    Returns counts ``[R floor bound, P⁻ floor bound, S regularised, S failed]``.
    """
    B, T = z.shape[0], z.shape[1]
    n_x = len(tx)
    n_z = len(tz)
    mats, vecs = em_scratch_jit(n_x, n_z)
    xb = np.empty(n_x)
    Pb = np.empty((n_x, n_x))
    zt = np.empty(n_z)
    xp = np.empty(n_x)
    Pp = np.empty((n_x, n_x))
    FP = np.empty((n_x, n_x))
    xn = np.empty(n_x)
    Pn = np.empty((n_x, n_x))
    xf = np.empty(n_x)
    Pf = np.empty((n_x, n_x))
    Rj = np.empty((n_z, n_z))
    Om1 = np.empty((n_z, n_z))
    LRj = np.empty((n_z, n_z))
    Sg = np.empty((n_z, n_z))
    nu = np.empty(n_z)
    tmp = np.empty(n_z)
    xs = np.empty((0, n_x))
    Ps = np.empty((0, n_x, n_x))
    counts = np.zeros(4, np.int64)
    for b in range(B):
        _get(x, P, b, xb, Pb)
        initialized = init[b]
        zr = zring[b]
        for t in range(T):
            k = k0 + t
            sl = k % N
            valid = True
            for c in range(n_z):
                zt[c] = z[b, t, c]
                if not np.isfinite(zt[c]):
                    valid = False
            for c in range(n_z):
                zr[sl, c] = zt[c] if valid else np.nan
            o_d1[b, t] = np.nan
            o_d2[b, t] = np.nan
            for r in range(n_z):
                o_nu[b, t, r] = np.nan
            if not initialized:
                if valid:  # SPEC §4.2 initialisation
                    for i in range(n_x):
                        acc = 0.0
                        for c in range(n_z):
                            acc += Hpinv[i, c] * zt[c]
                        xb[i] = acc
                    _copy_mat(P0, Pb)
                    initialized = True
                _put(o_mean, o_cov, b, t, xb, Pb)
                o_obs[b, t] = valid
                o_mode[b, t] = 0 if valid else 3
                continue
            # Eqs. 5-6: x⁻, P⁻ shared by all branches
            kf_predict_sparse(tx, xb, Pb, Fr, Fc, Fv, Q, xp, Pp, FP)
            if not valid:  # predict only (SPEC §7.3)
                _copy_vec(xp, xb)
                _copy_mat(Pp, Pb)
                _put(o_mean, o_cov, b, t, xb, Pb)
                o_obs[b, t] = False
                o_mode[b, t] = 3
                continue
            for r in range(n_z):
                nu[r] = zt[r]
            for q in range(len(Hv)):
                nu[Hr[q]] -= Hv[q] * xp[Hc[q]]
            for r in range(n_z):
                o_nu[b, t, r] = nu[r]
            if gate_S:  # SPEC §7.2-2 option: νᵀ S⁻¹ ν with S = H P⁻ Hᵀ + R
                for r1 in range(n_z):
                    for r2 in range(n_z):
                        Sg[r1, r2] = Rnom[r1, r2]
                for q1 in range(len(Hv)):
                    for q2 in range(len(Hv)):
                        Sg[Hr[q1], Hr[q2]] += Hv[q1] * Pp[Hc[q1], Hc[q2]] * Hv[q2]
                if _chol_t(Sg, LRj, tz):
                    d1 = _quad_inv(LRj, nu, tmp, tz)
                else:
                    d1 = np.inf
            else:  # Eq. 29: D₁ = νᵀ R⁻¹ ν
                d1 = _quad_inv(LR, nu, tmp, tz)
            o_d1[b, t] = d1
            mode = 0
            if d1 < th1:  # KF update, Eqs. 7-9
                status, _nis = em_update(
                    tx, tz, xp, Pp, zt, Hr, Hc, Hv, Rnom, Rnom, Rnom, 0.0, 1, False, 0.0, floor_c, False, xn, Pn, Rj,
                    Om1, mats, vecs,
                )  # fmt: skip
            else:  # EM-KF, Alg. 2 lines 8-12 from P̄⁻^{(0)} = P⁻
                mode = 1
                status, _nis = em_update(
                    tx, tz, xp, Pp, zt, Hr, Hc, Hv, Rnom, Rnom, Rnom, 0.0, n_em, False, 0.0, floor_c, True, xn, Pn,
                    Rj, Om1, mats, vecs,
                )  # fmt: skip
            if status:
                for bit in range(4):
                    if status & (1 << bit):
                        counts[bit] += 1
            if status & S_FAILED:
                _copy_vec(xp, xb)
                _copy_mat(Pp, Pb)
                _put(o_mean, o_cov, b, t, xb, Pb)
                o_obs[b, t] = False
                o_mode[b, t] = 3
                continue
            use_fir = False
            if mode == 1:
                # D₂ = νᵀ R_em⁻¹ ν (Eq. 29 with the EM-updated R, SPEC §7.2-1); ν is unchanged
                if _chol_t(Rj, LRj, tz):
                    d2 = _quad_inv(LRj, nu, tmp, tz)
                else:
                    d2 = np.inf
                o_d2[b, t] = d2
                if not (d2 < th2) and k >= N - 1:  # FIR disabled while k < N−1 (SPEC §7.2-5)
                    use_fir = fir_estimate(
                        zr, k, N, K, True, axis_blocks, W, P_full, F, Finv, H, Q, Rnom, Fa, Finva, Ha, Qa, Ra, xs,
                        Ps, False, xf, Pf,
                    )  # fmt: skip
            if use_fir:
                o_mode[b, t] = 2
                _put(o_mean, o_cov, b, t, xf, Pf)
                if feedback:  # SPEC §7.2-4: the KF recursion continues from the FIR estimate
                    _copy_vec(xf, xb)
                    _copy_mat(Pf, Pb)
                else:
                    _copy_vec(xn, xb)
                    _copy_mat(Pn, Pb)
            else:
                o_mode[b, t] = mode
                _copy_vec(xn, xb)
                _copy_mat(Pn, Pb)
                _put(o_mean, o_cov, b, t, xb, Pb)
            o_obs[b, t] = True
        _set(x, P, b, xb, Pb)
        init[b] = initialized
    return counts


# ---------------------------------------------------------------------------------------------
# Constant-velocity specialisation (same arithmetic as above, bit for bit; see module docs)
# ---------------------------------------------------------------------------------------------


def cv_structure(F, H):
    """Per-axis blocks ``fb (n_a, 4) = [f00, f01, f10, f11]`` when the model has the CV structure.

    The structure: ``n_x = 2 n_z``; ``F`` zero outside the per-axis 2×2 blocks; ``H[a, 2a] = 1``
    and every other entry of ``H`` zero. Q and R may be dense. Returns None otherwise (the
    general kernels are used).
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


@njit_inline
def _chol_t_i(A, L, tn):
    """Inlined :func:`_chol_t` (same operations)."""
    n = len(tn)
    for j in range(n):
        s = A[j, j]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if not (s > 0.0):
            return False
        d = np.sqrt(s)
        L[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = A[i, j]
            for p in range(j):
                s -= L[i, p] * L[j, p]
            L[i, j] = s * inv
    return True


@njit_inline
def _chol_solve_i(L, B, tn, tm):
    """Inlined :func:`_chol_solve` (same operations)."""
    n = len(tn)
    m = len(tm)
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
def _chol_reg_i(S, L, work, tn):
    """:func:`_chol_reg` with the common (no regularisation) case inlined."""
    if _chol_t_i(S, L, tn):
        return 0
    return _chol_reg(S, L, work, tn)


@njit_inline
def _quad_inv_i(L, v, tmp, tn):
    """Inlined :func:`_quad_inv` (same operations)."""
    n = len(tn)
    acc = 0.0
    for i in range(n):
        s = v[i]
        for p in range(i):
            s -= L[i, p] * tmp[p]
        tmp[i] = s / L[i, i]
        acc += tmp[i] * tmp[i]
    return acc


@njit_inline
def _not_pd_above(A, Nom, c, W, tn):
    """True when ``A − c·Nom`` is not positive definite: LDLᵀ pivots, no square roots.

    Same test as :func:`_floor_binds` (all pivots > 0) with a shorter dependency chain; the two
    can only disagree for a matrix singular to rounding, where clipping changes nothing.
    """
    n = len(tn)
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
def cv_predict(ta, tx, xb, Pb, fb, Q, xp, Pp, FP):
    """:func:`kf_predict_sparse` for per-axis blocks ``fb[a] = [f00, f01, f10, f11]`` (same result).

    ``x⁻ = F x`` (Eq. 5) and ``P⁻ = F P Fᵀ + Q`` (Eq. 6) on a dense ``P``, symmetrised.
    """
    n_a = len(ta)
    n = len(tx)
    for a in range(n_a):
        i = 2 * a
        f00 = fb[a, 0]
        f01 = fb[a, 1]
        f10 = fb[a, 2]
        f11 = fb[a, 3]
        x0 = xb[i]
        x1 = xb[i + 1]
        xp[i] = f00 * x0 + f01 * x1  # Eq. 5
        xp[i + 1] = f10 * x0 + f11 * x1
        for j in range(n):  # F P, rows 2a, 2a+1
            p0 = Pb[i, j]
            p1 = Pb[i + 1, j]
            FP[i, j] = f00 * p0 + f01 * p1
            FP[i + 1, j] = f10 * p0 + f11 * p1
    for i in range(n):  # (F P) Fᵀ + Q, columns 2a, 2a+1 (Eq. 6)
        for a in range(n_a):
            j = 2 * a
            g0 = FP[i, j]
            g1 = FP[i, j + 1]
            Pp[i, j] = Q[i, j] + fb[a, 0] * g0 + fb[a, 1] * g1
            Pp[i, j + 1] = Q[i, j + 1] + fb[a, 2] * g0 + fb[a, 3] * g1
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (Pp[i, j] + Pp[j, i])
            Pp[i, j] = s
            Pp[j, i] = s


@njit_inline
def joseph_cv(ta, tx, Pm, Kt, Rj, AP, D, P, pos_only):
    """Joseph update ``P = (I − K H) P̄⁻ (I − K H)ᵀ + K R Kᵀ`` for ``H`` selecting positions.

    As in :func:`em_update`: ``AP = P̄⁻ − K (H P̄⁻)`` (``H P̄⁻`` = position rows of ``P̄⁻``),
    ``D = K R − AP Hᵀ``, ``P = AP + D Kᵀ`` (upper triangle, mirrored). ``pos_only``: only the
    position block ``P[2a, 2b]`` (all that ``Ω₁ = e eᵀ + H P Hᵀ`` needs); the same operations,
    so a later full call gives the same values there.
    """
    n_a = len(ta)
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
                acc = 0.0
                for r1 in range(n_a):
                    acc += Kt[r1, i] * Rj[r1, r2]
                D[i, r2] = acc - AP[i, 2 * r2]
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
            acc = 0.0
            for r1 in range(n_a):
                acc += Kt[r1, i] * Rj[r1, r2]
            D[i, r2] = acc - AP[i, 2 * r2]
    for i in range(n):
        for j in range(i, n):
            acc = AP[i, j]
            for r in range(n_a):
                acc += D[i, r] * Kt[r, j]
            P[i, j] = acc
            P[j, i] = acc


@njit_inline
def em_update_cv(
    ta, tx, xp, Pp, z, R0, Rnom, Uprior, u_prior, n_iter, regularized, tau, floor_c, want_R,
    defer, x, P, Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp,
):  # fmt: skip
    """:func:`em_update` for the CV structure (SPEC §5.3; paper A Algorithm 2 lines 5-17).

    Same arguments and results as :func:`em_update`, with the scratch passed one by one. ``x``,
    ``P`` may be the caller's state arrays (only ``xp``, ``Pp`` are read). ``defer`` (with
    ``want_R``): the last iteration computes only the position block of ``P`` and keeps its R in
    ``Rl``; the status then has :data:`P_DEFERRED` set and ``joseph_cv(..., Pm, Kt, Rl, ...)``
    completes ``P`` when it is needed (the integrated filter skips it when the FIR wins).
    """
    n_a = len(ta)
    n = len(tx)
    status = 0
    nis = np.nan
    for r in range(n_a):
        nu[r] = z[r] - xp[2 * r]  # ν = z − H x⁻ (fixed through the iterations)
    for i in range(n):
        x[i] = xp[i]
        for j in range(n):
            P[i, j] = Pp[i, j]
            Pm[i, j] = Pp[i, j]  # P̄⁻^{(0)} = P⁻
    for r1 in range(n_a):
        for r2 in range(n_a):
            Rj[r1, r2] = R0[r1, r2]  # R^{(0)}: nominal, reset every step
    for jit in range(n_iter):
        last = jit == n_iter - 1
        for r1 in range(n_a):  # S = H P̄⁻ Hᵀ + R^{(j)}
            for r2 in range(n_a):
                S[r1, r2] = Rj[r1, r2] + Pm[2 * r1, 2 * r2]
        for r1 in range(n_a):
            for r2 in range(r1 + 1, n_a):
                sym = 0.5 * (S[r1, r2] + S[r2, r1])
                S[r1, r2] = sym
                S[r2, r1] = sym
        st = _chol_reg_i(S, LS, W, ta)
        if st == 2:
            status |= S_FAILED if jit == 0 else S_REGULARISED
            break
        if st == 1:
            status |= S_REGULARISED
        for r in range(n_a):  # Kᵀ = S⁻¹ H P̄⁻  (K^{(j+1)})
            for c in range(n):
                Kt[r, c] = Pm[2 * r, c]
        _chol_solve_i(LS, Kt, ta, tx)
        if jit == 0:
            nis = _quad_inv_i(LS, nu, tmp, ta)
        for i in range(n):  # x^{(j+1)} = x⁻ + K ν
            acc = xp[i]
            for r in range(n_a):
                acc += Kt[r, i] * nu[r]
            x[i] = acc
        pos_only = last and want_R and defer
        if pos_only:
            status |= P_DEFERRED
            for r1 in range(n_a):
                for r2 in range(n_a):
                    Rl[r1, r2] = Rj[r1, r2]
        joseph_cv(ta, tx, Pm, Kt, Rj, AP, D, P, pos_only)  # P^{(j+1)} (Eq. 9)
        if last and not want_R:
            break
        for r in range(n_a):  # e = z − H x^{(j+1)}
            e[r] = z[r] - x[2 * r]
        for r1 in range(n_a):  # Ω₁ = e eᵀ + H P Hᵀ → R^{(j+1)}
            for r2 in range(n_a):
                Om1[r1, r2] = e[r1] * e[r2] + P[2 * r1, 2 * r2]
        for r1 in range(n_a):
            for r2 in range(r1 + 1, n_a):
                sym = 0.5 * (Om1[r1, r2] + Om1[r2, r1])
                Om1[r1, r2] = sym
                Om1[r2, r1] = sym
        if regularized:
            den = u_prior - n_a
            for r1 in range(n_a):
                for r2 in range(n_a):
                    Rj[r1, r2] = (Uprior[r1, r2] + Om1[r1, r2]) / den
        else:
            for r1 in range(n_a):
                for r2 in range(n_a):
                    Rj[r1, r2] = Om1[r1, r2]
        if _not_pd_above(Rj, Rnom, floor_c, W, ta):  # SPEC §5.4 floor
            # scratch free at this point: LS, S (the gain is computed), Om1 (copied), e
            if floor_clip_into(Rj, Rnom, floor_c, n_a, LS, S, Om1, e):
                status |= FLOOR_R
        if last:
            break
        for i in range(n):  # Ω₂ = P + (x − x⁻)(x − x⁻)ᵀ → P̄⁻^{(j+1)}
            tmp[i] = x[i] - xp[i]
        for i in range(n):
            for j in range(n):
                Pm[i, j] = P[i, j] + tmp[i] * tmp[j]
        if regularized:
            for i in range(n):
                for j in range(n):
                    Pm[i, j] = (tau * Pp[i, j] + Pm[i, j]) / (tau + 1.0)
        if _not_pd_above(Pm, Pp, floor_c, W, tx):
            if floor_clip(Pm, Pp, floor_c, n):
                status |= FLOOR_P
    return status, nis


def cv_scratch(n_x, n_z):
    """Scratch of :func:`em_update_cv`: ``Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp``."""
    return (
        np.empty((n_z, n_z)),
        np.empty((n_z, n_z)),
        np.empty((n_z, n_z)),
        np.empty((n_x, n_x)),
        np.empty((n_z, n_z)),
        np.empty((n_z, n_z)),
        np.empty((n_z, n_x)),
        np.empty((n_x, n_x)),
        np.empty((n_x, n_z)),
        np.empty((n_x, n_x)),
        np.empty(n_z),
        np.empty(n_z),
        np.empty(n_x),
    )


cv_scratch_jit = njit_inline(cv_scratch)


@njit_inline
def _count(counts, status):
    for bit in range(4):
        if status & (1 << bit):
            counts[bit] += 1


@njit_inline
def _load(x, P, b, xb, Pb, tx):
    n = len(tx)
    for i in range(n):
        xb[i] = x[b, i]
        for j in range(n):
            Pb[i, j] = P[b, i, j]


@njit_inline
def _store(x, P, b, xb, Pb, tx):
    n = len(tx)
    for i in range(n):
        x[b, i] = xb[i]
        for j in range(n):
            P[b, i, j] = Pb[i, j]


@njit_inline
def _init_from(zt, Hpinv, P0, xb, Pb, ta, tx):
    """SPEC §4.2 initialisation: ``x = H⁺ z``, ``P = P₀``."""
    n = len(tx)
    n_a = len(ta)
    for i in range(n):
        acc = 0.0
        for c in range(n_a):
            acc += Hpinv[i, c] * zt[c]
        xb[i] = acc
        for j in range(n):
            Pb[i, j] = P0[i, j]


@njit
def em_kf_run_cv(
    ta, tx, z, x, P, init, u, U, fb, Q, Rnom, Hpinv, P0, n_iter, regularized, tau, rho, floor_c,
    o_mean, o_cov, o_obs, o_nu, o_dist, o_Rem,
):  # fmt: skip
    """:func:`em_kf_run` for the CV structure; ``ta``, ``tx``: :func:`size_tuple` of ``n_z``,
    ``n_x``; ``fb``: :func:`cv_structure`. Same contract and results."""
    B, T = z.shape[0], z.shape[1]
    n = len(tx)
    n_a = len(ta)
    Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp = cv_scratch_jit(n, n_a)
    xb = np.empty(n)
    Pb = np.empty((n, n))
    zt = np.empty(n_a)
    xp = np.empty(n)
    Pp = np.empty((n, n))
    FP = np.empty((n, n))
    R0 = np.empty((n_a, n_a))
    Ub = np.empty((n_a, n_a))
    counts = np.zeros(4, np.int64)
    nz3 = n_a + 1.0
    for b in range(B):
        _load(x, P, b, xb, Pb, tx)
        ub = u[b]
        for r1 in range(n_a):
            for r2 in range(n_a):
                Ub[r1, r2] = U[b, r1, r2]
        initialized = init[b]
        for t in range(T):
            valid = True
            for c in range(n_a):
                zt[c] = z[b, t, c]
                if not np.isfinite(zt[c]):
                    valid = False
            ok = False
            if not initialized:
                if valid:  # SPEC §4.2 initialisation (no update)
                    _init_from(zt, Hpinv, P0, xb, Pb, ta, tx)
                    initialized = True
                ok = valid
                _fill(o_nu, o_dist, o_Rem, b, t)
            else:
                cv_predict(ta, tx, xb, Pb, fb, Q, xp, Pp, FP)  # Eqs. 5-6
                u_pr = 0.0
                if regularized:  # option B time update of (û, Û)
                    u_pr = rho * (ub - nz3) + nz3
                    for r1 in range(n_a):
                        for r2 in range(n_a):
                            Ub[r1, r2] *= rho
                nis = np.nan
                if valid:
                    for r1 in range(n_a):
                        for r2 in range(n_a):
                            if regularized:  # R^{(0)} = IW prior mean
                                R0[r1, r2] = Ub[r1, r2] / (u_pr - nz3)
                            else:
                                R0[r1, r2] = Rnom[r1, r2]
                    status, nis = em_update_cv(
                        ta, tx, xp, Pp, zt, R0, Rnom, Ub, u_pr, n_iter, regularized, tau, floor_c,
                        True, False, xb, Pb, Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp,
                    )  # fmt: skip
                    _count(counts, status)
                    ok = not (status & S_FAILED)
                if ok:  # (xb, Pb) hold the EM-KF posterior
                    if regularized:  # û = û⁻ + 1, Û = Û⁻ + Ω₁
                        ub = u_pr + 1.0
                        for r1 in range(n_a):
                            for r2 in range(n_a):
                                Ub[r1, r2] += Om1[r1, r2]
                    for r1 in range(n_a):
                        o_nu[b, t, r1] = nu[r1]
                        for r2 in range(n_a):
                            o_Rem[b, t, r1, r2] = Rj[r1, r2]
                    o_dist[b, t] = nis
                else:  # predict only
                    for i in range(n):
                        xb[i] = xp[i]
                        for j in range(n):
                            Pb[i, j] = Pp[i, j]
                    if regularized:
                        ub = u_pr
                    _fill(o_nu, o_dist, o_Rem, b, t)
            for i in range(n):
                o_mean[b, t, i] = xb[i]
                for j in range(n):
                    o_cov[b, t, i, j] = Pb[i, j]
            o_obs[b, t] = ok
        _store(x, P, b, xb, Pb, tx)
        u[b] = ub
        for r1 in range(n_a):
            for r2 in range(n_a):
                U[b, r1, r2] = Ub[r1, r2]
        init[b] = initialized
    return counts


@njit
def integrated_run_cv(
    ta, tx, z, x, P, init, zring, k0, N, K, fb, Q, Rnom, LR, Hpinv, P0, n_em, th1, th2, gate_S,
    feedback, floor_c, axis_blocks, W_taps, P_full, F, Finv, H, Fa, Finva, Ha, Qa, Ra,
    o_mean, o_cov, o_obs, o_nu, o_d1, o_d2, o_mode,
):  # fmt: skip
    """:func:`integrated_run` for the CV structure (SPEC §7.3); same contract and results.

    ``ta``, ``tx``: :func:`size_tuple` of ``n_z``, ``n_x``; ``fb``: :func:`cv_structure`;
    ``W_taps``: the UFIR taps (``W`` of :func:`integrated_run`). A complete horizon is evaluated
    by the inlined taps; the FIR call is made only for horizons with missing samples. When the
    FIR wins and is fed back, the EM branch's final covariance is never used, so only its
    position block (needed for ``R_em`` and D₂) is computed.
    """
    B, T = z.shape[0], z.shape[1]
    n = len(tx)
    n_a = len(ta)
    Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp = cv_scratch_jit(n, n_a)
    xb = np.empty(n)
    Pb = np.empty((n, n))
    zt = np.empty(n_a)
    xp = np.empty(n)
    Pp = np.empty((n, n))
    FP = np.empty((n, n))
    xf = np.empty(n)
    Pf = np.empty((n, n))
    LRj = np.empty((n_a, n_a))
    Sg = np.empty((n_a, n_a))
    xs = np.empty((0, n))
    Ps = np.empty((0, n, n))
    idx = np.empty(K, np.int64)
    xx = np.empty((2, Fa.shape[0]))
    counts = np.zeros(4, np.int64)
    for b in range(B):
        _load(x, P, b, xb, Pb, tx)
        initialized = init[b]
        zr = zring[b]
        for t in range(T):
            k = k0 + t
            sl = k % N
            valid = True
            for c in range(n_a):
                zt[c] = z[b, t, c]
                if not np.isfinite(zt[c]):
                    valid = False
            for c in range(n_a):
                zr[sl, c] = zt[c] if valid else np.nan
            o_d1[b, t] = np.nan
            o_d2[b, t] = np.nan
            for r in range(n_a):
                o_nu[b, t, r] = np.nan
            use_fir = False
            if not initialized:
                if valid:  # SPEC §4.2 initialisation
                    _init_from(zt, Hpinv, P0, xb, Pb, ta, tx)
                    initialized = True
                o_obs[b, t] = valid
                o_mode[b, t] = 0 if valid else 3
            else:
                cv_predict(ta, tx, xb, Pb, fb, Q, xp, Pp, FP)  # Eqs. 5-6, shared by all branches
                status = S_FAILED
                mode = 3
                if valid:
                    for r in range(n_a):
                        nu[r] = zt[r] - xp[2 * r]
                        o_nu[b, t, r] = nu[r]
                    if gate_S:  # SPEC §7.2-2 option: νᵀ S⁻¹ ν with S = H P⁻ Hᵀ + R
                        for r1 in range(n_a):
                            for r2 in range(n_a):
                                Sg[r1, r2] = Rnom[r1, r2] + Pp[2 * r1, 2 * r2]
                        if _chol_t_i(Sg, LRj, ta):
                            d1 = _quad_inv_i(LRj, nu, tmp, ta)
                        else:
                            d1 = np.inf
                    else:  # Eq. 29: D₁ = νᵀ R⁻¹ ν
                        d1 = _quad_inv_i(LR, nu, tmp, ta)
                    o_d1[b, t] = d1
                    mode = 0
                    if d1 < th1:  # KF update, Eqs. 7-9
                        status, _nis = em_update_cv(
                            ta, tx, xp, Pp, zt, Rnom, Rnom, Rnom, 0.0, 1, False, 0.0, floor_c, False,
                            False, xb, Pb, Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp,
                        )  # fmt: skip
                    else:  # EM-KF from P̄⁻^{(0)} = P⁻
                        mode = 1
                        status, _nis = em_update_cv(
                            ta, tx, xp, Pp, zt, Rnom, Rnom, Rnom, 0.0, n_em, False, 0.0, floor_c, True,
                            feedback, xb, Pb, Rj, Rl, Om1, Pm, S, LS, Kt, AP, D, W, nu, e, tmp,
                        )  # fmt: skip
                    _count(counts, status)
                if status & S_FAILED:  # missing z or S not factorisable: predict only
                    for i in range(n):
                        xb[i] = xp[i]
                        for j in range(n):
                            Pb[i, j] = Pp[i, j]
                    o_obs[b, t] = False
                    o_mode[b, t] = 3
                else:
                    if mode == 1:
                        # D₂ = νᵀ R_em⁻¹ ν (Eq. 29 with the EM-updated R); ν is unchanged
                        if _chol_t_i(Rj, LRj, ta):
                            d2 = _quad_inv_i(LRj, nu, tmp, ta)
                        else:
                            d2 = np.inf
                        o_d2[b, t] = d2
                        if not (d2 < th2) and k >= N - 1:  # no FIR while k < N−1
                            use_fir = ufir_taps(zr, k, N, W_taps, axis_blocks, xf)
                            if use_fir:  # complete horizon
                                for i in range(n):
                                    for j in range(n):
                                        Pf[i, j] = P_full[i, j]
                            else:  # missing samples: shared per-axis gains if possible
                                code = 0
                                if axis_blocks:
                                    code = ufir_horizon_axes(
                                        zr, k, N, K, Fa, Finva, Ha, Qa, Ra, idx, xx, xf, Pf
                                    )
                                    use_fir = code == 1
                                if code == 0:  # per-axis or dense form
                                    use_fir = fir_estimate(
                                        zr, k, N, K, True, axis_blocks, W_taps, P_full, F, Finv, H,
                                        Q, Rnom, Fa, Finva, Ha, Qa, Ra, xs, Ps, False, xf, Pf,
                                    )  # fmt: skip
                    if (status & P_DEFERRED) and not (use_fir and feedback):
                        joseph_cv(ta, tx, Pm, Kt, Rl, AP, D, Pb, False)  # complete the EM P
                    o_obs[b, t] = True
                    o_mode[b, t] = 2 if use_fir else mode
            if use_fir:
                for i in range(n):
                    o_mean[b, t, i] = xf[i]
                    for j in range(n):
                        o_cov[b, t, i, j] = Pf[i, j]
                if feedback:  # SPEC §7.2-4: the KF recursion continues from the FIR estimate
                    for i in range(n):
                        xb[i] = xf[i]
                        for j in range(n):
                            Pb[i, j] = Pf[i, j]
            else:
                for i in range(n):
                    o_mean[b, t, i] = xb[i]
                    for j in range(n):
                        o_cov[b, t, i, j] = Pb[i, j]
        _store(x, P, b, xb, Pb, tx)
        init[b] = initialized
    return counts
