"""Frame alignment: the rotation between two frames from paired directions (Kabsch).

SPEC §2.2 "Kinect side" (c): the rotation between the IMU world frame and the camera/reference
frame, rotation only, and its heading-only variant; the joint estimate of that rotation and the
segment axes by alternating least squares, with a check of how well the window determines it.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.kinematics.forward import rotation_z

__all__ = [
    "alignment_sensitivity",
    "angles_deg",
    "heading_rotation",
    "kabsch_rotation",
    "solve_alignment",
    "unit_direction",
]


def _paired(P, Q, weights):
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape:
        raise InputError(
            f"expected P and Q with the same shape (N, 3), got {P.shape} and {Q.shape}"
        )
    w = np.ones(P.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (P.shape[0],) or np.any(w < 0):
        raise InputError(f"expected weights >= 0 with shape (N,) = ({P.shape[0]},), got {w.shape}")
    ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(Q), axis=1) & np.isfinite(w) & (w > 0)
    if not np.any(ok):
        raise InputError("expected at least one finite pair of vectors in P and Q, got none")
    return P[ok], Q[ok], w[ok]


def kabsch_rotation(P, Q, weights=None) -> np.ndarray:
    """Rotation (no translation, no scale) that best maps the vectors ``P`` onto ``Q``.

    Parameters
    ----------
    P, Q : array_like, shape (N, 3)
        Paired vectors (e.g. segment directions in the camera frame and in the IMU world frame).
        Rows with NaN are ignored.
    weights : array_like, shape (N,), optional
        Non-negative weights (default 1).

    Returns
    -------
    R : ndarray, shape (3, 3)
        Proper rotation minimising ``Σ w_k ‖R p_k − q_k‖²``; ``Q ≈ P @ R.T``. Equals
        ``Rotation.align_vectors(Q, P, weights)[0].as_matrix()``.

    Notes
    -----
    Kabsch: ``H = Σ w p qᵀ = U S Vᵀ``, ``R = V diag(1, 1, det(V Uᵀ)) Uᵀ``. With vectors spanning
    fewer than two directions the rotation is not unique (a NumericalWarning is raised).
    """
    P, Q, w = _paired(P, Q, weights)
    H = (P * w[:, None]).T @ Q
    U, S, Vt = np.linalg.svd(H)
    if S[1] <= 1e-10 * max(S[0], 1e-300):
        warnings.warn(
            "kabsch_rotation: the vectors span fewer than two directions; the rotation is not unique",
            NumericalWarning,
            stacklevel=2,
        )
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def heading_rotation(P, Q, weights=None) -> np.ndarray:
    """Rotation about the vertical (z) axis only that best maps ``P`` onto ``Q``.

    Parameters
    ----------
    P, Q : array_like, shape (N, 3)
        Paired vectors in two frames that share the z (up) axis.
    weights : array_like, shape (N,), optional
        Non-negative weights.

    Returns
    -------
    R : ndarray, shape (3, 3)
        ``R_z(ψ)`` with ``ψ = atan2(Σ w (p × q)_z, Σ w (p_x q_x + p_y q_y))`` (least squares in the
        horizontal plane).
    """
    P, Q, w = _paired(P, Q, weights)
    s = np.sum(w * (P[:, 0] * Q[:, 1] - P[:, 1] * Q[:, 0]))
    c = np.sum(w * (P[:, 0] * Q[:, 0] + P[:, 1] * Q[:, 1]))
    return rotation_z(np.arctan2(s, c))


def unit_direction(v: np.ndarray, where: str) -> np.ndarray:
    """``v / ‖v‖``; an InputError naming ``where`` when ``v`` is (nearly) zero or not finite."""
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-9:
        raise InputError(
            f"{where}: the calibration window gives no usable direction (sum of directions ≈ 0)"
        )
    return v / n


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between the vectors ``a`` and ``b`` along the last axis, deg."""
    c = np.clip(
        np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)),
        -1.0,
        1.0,
    )
    return np.degrees(np.arccos(c))


def solve_alignment(W: dict, U: dict, align: str):
    """Alternating least squares for ``R_world_from_camera`` and the axes, multi-start.

    W[s] : (K, 3, 3) world-from-sensor; U[s] : (K, 3) unit directions in the camera frame.
    """

    def axes_given(Rc):
        return {
            s: unit_direction(np.einsum("kji,kj->i", W[s], U[s] @ Rc.T), f"segment {s!r}")
            for s in W
        }

    def cost(Rc, A):
        return sum(
            float(np.sum((U[s] @ Rc.T - np.einsum("kij,j->ki", W[s], A[s])) ** 2)) for s in W
        )

    def rot_given(A):
        P = np.concatenate([U[s] for s in W])
        Q = np.concatenate([np.einsum("kij,j->ki", W[s], A[s]) for s in W])
        return heading_rotation(P, Q) if align == "heading" else kabsch_rotation(P, Q)

    if align == "heading":
        starts = [Rotation.from_rotvec([0, 0, a]).as_matrix() for a in np.arange(8) * np.pi / 4]
    else:
        starts = list(Rotation.create_group("O").as_matrix())

    def descend(Rc, A, c_old, n_iter):
        for _ in range(n_iter):
            Rc = rot_given(A)
            A = axes_given(Rc)
            c = cost(Rc, A)
            if c_old - c <= 1e-12 * max(c_old, 1.0):
                return c, Rc, A
            c_old = c
        return c_old, Rc, A

    # a few sweeps from every start, then the best one to convergence
    best = None
    for Rc in starts:
        A = axes_given(Rc)
        cand = descend(Rc, A, cost(Rc, A), 20)
        if best is None or cand[0] < best[0] - 1e-12:
            best = cand
    best = descend(best[1], best[2], best[0], 1000)
    return best[1], best[2]


def alignment_sensitivity(W: dict, U: dict, Rc: np.ndarray, align: str) -> list[str]:
    """World axes about which a 5° change of ``Rc`` hides in the noise [J].

    A 5° rotation of ``Rc`` (axes re-fitted) must add, in quadrature, more than
    ``max(0.5°, RMS misfit)`` to the RMS misfit; otherwise that axis is reported.
    """

    def misfit(R):
        err = []
        for s in W:
            V = U[s] @ R.T
            a = unit_direction(np.einsum("kji,kj->i", W[s], V), f"segment {s!r}")
            err.append(angles_deg(np.einsum("kij,j->ki", W[s], a), V))
        return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))

    base = misfit(Rc)
    weak = []
    for name, e in (("z", (0, 0, 1)), ("x", (1, 0, 0)), ("y", (0, 1, 0)))[
        : 1 if align == "heading" else 3
    ]:
        R = Rotation.from_rotvec(np.radians(5.0) * np.asarray(e, dtype=float)).as_matrix() @ Rc
        if np.sqrt(max(misfit(R) ** 2 - base**2, 0.0)) < max(0.5, base):
            weak.append(name)
    return weak
