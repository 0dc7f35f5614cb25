"""State-space models: the constant-velocity model of paper A (Sun 2024, Eqs. 3-4 and 30).

State layout is interleaved per axis, ``[x, vx, y, vy, z, vz]`` (see :mod:`kinefuse.conventions`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinefuse._validation import as_float, positive_finite, psd_matrix, readonly_array
from kinefuse.exceptions import InputError

__all__ = ["LinearGaussianModel", "constant_velocity"]


@dataclass(frozen=True, eq=False)
class LinearGaussianModel:
    """Linear-Gaussian state-space model ``x_k = F x_{k-1} + w``, ``z_k = H x_k + v``.

    Parameters
    ----------
    F : ndarray, shape (n_x, n_x)
        Transition matrix (paper A's ``T``).
    H : ndarray, shape (n_z, n_x)
        Measurement matrix (paper A's ``H``, paper B's ``G``).
    Q : ndarray, shape (n_x, n_x)
        Process-noise covariance, symmetric PSD.
    R : ndarray, shape (n_z, n_z)
        Measurement-noise covariance, symmetric positive definite.
    dt_s : float
        Sampling interval in seconds the matrices were built for.

    Notes
    -----
    The arrays are stored read-only copies; the model is immutable. ``axis_blocks`` is True when
    F, Q, H and R are block-diagonal per axis (per-axis 2-state problems, SPEC §1), which the
    compiled fast paths of the KF, UFIR and RTS exploit exactly.
    """

    F: np.ndarray
    H: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    dt_s: float = float("nan")
    axis_blocks: bool = field(init=False)

    def __post_init__(self):
        F = np.asarray(self.F, dtype=float)
        if F.ndim != 2 or F.shape[0] != F.shape[1]:
            raise InputError(f"expected F with shape (n_x, n_x), got {F.shape}")
        n_x = F.shape[0]
        H = np.asarray(self.H, dtype=float)
        if H.ndim != 2 or H.shape[1] != n_x:
            raise InputError(f"expected H with shape (n_z, {n_x}), got {H.shape}")
        n_z = H.shape[0]
        if not (np.all(np.isfinite(F)) and np.all(np.isfinite(H))):
            raise InputError("expected F and H finite, got non-finite entries")
        Q = psd_matrix(self.Q, "Q", n_x)
        R = psd_matrix(self.R, "R", n_z, strict=True)
        for name, val in (("F", F), ("H", H), ("Q", Q), ("R", R)):
            object.__setattr__(self, name, readonly_array(val))
        object.__setattr__(self, "dt_s", float(self.dt_s))
        object.__setattr__(self, "axis_blocks", _is_axis_blocked(F, H, Q, R))

    @property
    def n_x(self) -> int:
        """State dimension."""
        return self.F.shape[0]

    @property
    def n_z(self) -> int:
        """Measurement dimension."""
        return self.H.shape[0]

    def replace(self, **changes) -> LinearGaussianModel:
        """Return a copy with some of ``F, H, Q, R, dt_s`` replaced."""
        kw = {k: getattr(self, k) for k in ("F", "H", "Q", "R", "dt_s")}
        kw.update(changes)
        return LinearGaussianModel(**kw)


def _is_axis_blocked(F, H, Q, R) -> bool:
    n_x, n_z = F.shape[0], H.shape[0]
    if n_x != 2 * n_z:
        return False
    mask_x = np.kron(np.eye(n_z), np.ones((2, 2))).astype(bool)
    mask_z = np.eye(n_z, dtype=bool)
    mask_h = np.kron(np.eye(n_z), np.ones((1, 2))).astype(bool)
    return bool(
        np.all(F[~mask_x] == 0)
        and np.all(Q[~mask_x] == 0)
        and np.all(R[~mask_z] == 0)
        and np.all(H[~mask_h] == 0)
    )


def constant_velocity(dt_s: float, q, r, n_axes: int = 3) -> LinearGaussianModel:
    """Constant-velocity model of paper A (Sun 2024, Eqs. 3-4, Q from Eq. 30).

    Parameters
    ----------
    dt_s : float
        Sampling interval, s (paper A: 1/30 s).
    q : float
        Process-noise scale. Per axis ``Q = q * [[dt²/4, dt/2], [dt/2, 1]]``; ``q`` is the
        variance of the velocity increment per step, (m/s)².
    r : float or ndarray, shape (n_axes, n_axes)
        Measurement-noise variance, m²: a scalar gives ``R = r * I``; a full symmetric positive
        definite matrix is accepted as ``R``.
    n_axes : {2, 3}
        Number of position axes (paper B's 2-D model is ``n_axes=2``).

    Returns
    -------
    LinearGaussianModel
        ``F = blockdiag([[1, dt], [0, 1]])``, ``H = blockdiag([1, 0])``, ``Q``, ``R``; state
        ``[x, vx, y, vy(, z, vz)]``.

    Notes
    -----
    Per axis ``Q = g gᵀ`` with ``g = [dt/2, 1]ᵀ``: rank one, PSD, singular (SPEC §1). It equals
    the discrete white-noise-acceleration model with ``σ_a² = q / dt²``.

    Deviations from the paper
    -------------------------
    Paper B's model is 2-D but its tables report z; kinefuse uses the 3-D model by default and
    the 2-D one as ``n_axes=2`` (SPEC §3.3).
    """
    dt = positive_finite(dt_s, "dt_s")
    if isinstance(n_axes, bool) or n_axes not in (2, 3):
        raise InputError(f"expected n_axes 2 or 3, got {n_axes!r}")
    if isinstance(q, (str, bytes, bool, np.bool_)):  # float("1") would accept text
        raise InputError(f"expected q as a number >= 0, got {q!r} ({type(q).__name__})")
    if isinstance(r, (str, bytes, bool, np.bool_)) or (
        isinstance(r, np.ndarray) and r.dtype.kind not in "iuf"
    ):
        raise InputError(f"expected r as a number or an (n, n) matrix, got {r!r}")
    q = as_float(q, f"expected q as a number >= 0, got {q!r}")
    if not np.isfinite(q) or q < 0:
        raise InputError(f"expected q finite and >= 0, got {q!r}")
    r_arr = (
        np.asarray(r, dtype=float)
        if np.isscalar(r) or isinstance(r, (list, tuple, np.ndarray))
        else None
    )
    if r_arr is None:
        raise InputError(f"expected r as a number or an ({n_axes}, {n_axes}) matrix, got {r!r}")
    if r_arr.ndim == 0:
        rv = float(r_arr)
        if not np.isfinite(rv) or rv <= 0:
            raise InputError(f"expected r finite and > 0, got {r!r}")
        R = rv * np.eye(n_axes)
    else:
        R = r_arr
        if R.shape != (n_axes, n_axes):
            raise InputError(f"expected r as a scalar or shape ({n_axes}, {n_axes}), got {R.shape}")
    eye = np.eye(n_axes)
    F = np.kron(eye, np.array([[1.0, dt], [0.0, 1.0]]))
    H = np.kron(eye, np.array([[1.0, 0.0]]))
    Q = q * np.kron(eye, np.array([[dt * dt / 4.0, dt / 2.0], [dt / 2.0, 1.0]]))
    return LinearGaussianModel(F=F, H=H, Q=Q, R=R, dt_s=dt)
