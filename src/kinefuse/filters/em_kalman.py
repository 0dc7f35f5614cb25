"""EM-adaptive Kalman filter of paper A (Sun 2024 §3.2), as corrected by SPEC §5."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.filters._base import (
    FilterResult,
    SingleModelFilter,
    check_state,
    flat_run,
    initial_covariance,
    make_initial_state,
    run_filter,
    run_outputs,
    run_result,
    unflat,
)
from kinefuse.filters._kernels_common import EMModel, model_structure, size_tuple
from kinefuse.filters._kernels_em import EMOptions, EMOutputs, em_kf_run
from kinefuse.models import LinearGaussianModel

__all__ = ["EMKalmanFilter", "EMKalmanResult", "EMKalmanState"]

#: Floor of the adapted R and P⁻, as a fraction of the nominal ones (SPEC §5.4).
FLOOR_FRACTION = 1e-3


class EMKalmanState(NamedTuple):
    """State of :class:`EMKalmanFilter`, batched over leading axes: the fields of
    :class:`~kinefuse.filters.GaussianState` followed by option B's inverse-Wishart pair.

    Attributes
    ----------
    x, P, initialized, k
        As in :class:`~kinefuse.filters.GaussianState`.
    u : ndarray, shape (...)
        Option B: inverse-Wishart degrees of freedom ``û`` (carried, unused by option A).
    U : ndarray, shape (..., n_z, n_z)
        Option B: inverse-Wishart scale ``Û``, m² (carried, unused by option A).
    """

    x: np.ndarray
    P: np.ndarray
    initialized: np.ndarray
    k: int
    u: np.ndarray
    U: np.ndarray


@dataclass(frozen=True, eq=False)
class EMKalmanResult(FilterResult):
    """:class:`~kinefuse.filters.FilterResult` plus the adapted measurement noise.

    Attributes
    ----------
    R_em : ndarray, shape (..., T, n_z, n_z)
        ``R^{(N_EM)}`` of each step, m² (NaN where not observed or at initialisation).
    """

    R_em: np.ndarray | None = None


# ---------------------------------------------------------------------------------------------
# helpers shared with ufir.py / integrated.py (the generic ones are in _base.py)


def check_model(model) -> LinearGaussianModel:
    """Refuse anything that is not a :class:`~kinefuse.models.LinearGaussianModel`."""
    if not isinstance(model, LinearGaussianModel):
        raise TypeError(
            f"expected model as a kinefuse.models.LinearGaussianModel, got {type(model).__name__}"
        )
    return model


def check_int(value, name: str, minimum: int) -> int:
    """Return ``value`` as int, requiring an integer type (not bool) and ``value >= minimum``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(
            f"expected {name} as an integer >= {minimum}, got {value!r} ({type(value).__name__})"
        )
    if value < minimum:
        raise InputError(f"expected {name} >= {minimum}, got {value}")
    return int(value)


def check_float(
    value, name: str, *, lo: float, lo_open: bool = False, hi: float = math.inf, allow_inf=False
):
    """Return ``value`` as float within ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``)."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise InputError(f"expected {name} as a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"expected {name} as a number, got {value!r}") from None
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise InputError(f"expected {name} finite, got {value!r}")
    bad_lo = v <= lo if lo_open else v < lo
    if bad_lo or v > hi:
        lo_s = f"> {lo}" if lo_open else f">= {lo}"
        hi_s = "" if math.isinf(hi) else f" and <= {hi}"
        raise InputError(f"expected {name} {lo_s}{hi_s}, got {value!r}")
    return v


def check_bool(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"expected {name} as True or False, got {value!r}")
    return bool(value)


def model_arrays(model: LinearGaussianModel) -> dict:
    """Contiguous arrays the kernels need (computed once per filter object)."""
    F = np.ascontiguousarray(model.F)
    H = np.ascontiguousarray(model.H)
    a = {
        "F": F,
        "H": H,
        "Q": np.ascontiguousarray(model.Q),
        "R": np.ascontiguousarray(model.R),
        "LR": np.ascontiguousarray(np.linalg.cholesky(model.R)),
        "Hpinv": np.ascontiguousarray(np.linalg.pinv(H)),
        "P0": np.ascontiguousarray(initial_covariance(model)),
    }
    # the kernels' model bundle; struct: CV blocks when (F, H) has that structure, else sparse
    a["em"] = EMModel(
        size_tuple(model.n_x), size_tuple(model.n_z), model_structure(F, H), a["Q"], a["R"],
        a["Hpinv"], a["P0"],
    )  # fmt: skip
    return a


def warn_counts(counts, what: str, *, floor_fraction: float = FLOOR_FRACTION) -> None:
    """One :class:`NumericalWarning` per call summarising the kernel's trouble counters."""
    n_r, n_p, n_reg, n_fail = counts.tolist() if hasattr(counts, "tolist") else counts
    if n_r or n_p:
        warnings.warn(
            f"{what}: the EM-adapted covariance floor (eigenvalues >= {floor_fraction:g} x nominal, "
            f"SPEC §5.4) bound on {n_r} step(s) for R and {n_p} iteration(s) for P⁻; "
            "consider fewer EM iterations",
            NumericalWarning,
            stacklevel=3,
        )
    if n_reg or n_fail:
        warnings.warn(
            f"{what}: innovation covariance S was regularised on {n_reg} step(s) and could not be "
            f"factorised on {n_fail} step(s) (update skipped, predict only; SPEC §13)",
            NumericalWarning,
            stacklevel=3,
        )


# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class EMKalmanFilter(SingleModelFilter):
    r"""EM-adaptive Kalman filter (paper A §3.2, Eqs. 10-23, Algorithm 2; SPEC §5.3).

    At every step the prediction ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` is followed by ``n_iter``
    EM iterations that re-estimate the measurement-noise covariance ``R`` and the predicted
    covariance ``P⁻`` from the current measurement, each followed by a Kalman update with the
    adapted pair.

    Parameters
    ----------
    model : LinearGaussianModel
        ``F (n_x, n_x)``, ``H (n_z, n_x)``, ``Q``, nominal ``R (n_z, n_z)`` (m²).
    n_iter : int, default 3
        ``N_EM`` (SPEC §5.4 default 3 for option A; Huang's 10 for option B). ``n_iter=1``
        leaves the state equal to the plain KF's (SPEC §5.2-6).
    regularized : bool, default False
        False: option A, paper-faithful raw EM. True: option B, inverse-Wishart /
        harmonic blending after Huang et al. (TAC 2018), with ``(û, Û)`` carried in the state.
    tau : float, default 3.0
        Option B: weight of the nominal ``P⁻`` in ``P̄⁻ = (τ P⁻ + Ω₂)/(τ + 1)``; > 0.
    rho : float, default 1 - exp(-4)
        Option B: forgetting factor of ``(û, Û)``; in (0, 1].

    Notes
    -----
    Option A, per step with a valid ``z`` (``x⁻`` fixed through the iterations)::

        P̄⁻ = P⁻ ; R⁽⁰⁾ = R_nom                                   (reset every step)
        for j = 0 .. N_EM-1:
            S = H P̄⁻ Hᵀ + R⁽ʲ⁾ ;  K⁽ʲ⁺¹⁾ = P̄⁻ Hᵀ S⁻¹               (Alg. 2 line 8, Eq. 7)
            x = x⁻ + K⁽ʲ⁺¹⁾ (z − H x⁻)                              (line 9, Eq. 8)
            P = (I − K H) P̄⁻ (I − K H)ᵀ + K R⁽ʲ⁾ Kᵀ                 (line 10, Eq. 9 Joseph)
            R⁽ʲ⁺¹⁾ = Ω₁ = (z − H x)(z − H x)ᵀ + H P Hᵀ              (Eq. 17, line 11)
            P̄⁻    = Ω₂ = P + (x − x⁻)(x − x⁻)ᵀ                     (Eq. 18, line 12)

    Option B replaces the last two lines by ``R = (Û⁻ + Ω₁)/(û⁻ − n_z)`` and
    ``P̄⁻ = (τ P⁻ + Ω₂)/(τ + 1)``, starts from ``R⁽⁰⁾ = Û⁻/(û⁻ − n_z − 1)`` and updates
    ``û⁻ = ρ(û − n_z − 1) + n_z + 1``, ``Û⁻ = ρ Û`` before and ``û = û⁻ + 1``, ``Û = Û⁻ + Ω₁``
    after each measurement (``û₀ = n_z + 2``, ``Û₀ = R_nom``).

    Floors (SPEC §5.4): after every iteration the adapted ``R`` and ``P̄⁻`` are kept at
    generalised eigenvalues ≥ 1e-3 relative to ``R_nom`` and to this step's ``P⁻``
    (``L⁻¹ A L⁻ᵀ`` clipped, ``L Lᵀ`` the nominal); a :class:`~kinefuse.exceptions.NumericalWarning`
    is emitted once per call when a floor binds.

    A NaN row predicts only. The first valid row of an element initialises it (SPEC §4.2:
    positions from ``z``, zero velocity, ``P₀``) without an update.

    ``result.distance`` is the NIS ``νᵀS⁻¹ν`` with the nominal ``S = H P⁻ Hᵀ + R``;
    ``result.R_em`` is ``R^{(N_EM)}``.

    Trusted fast path: ``_filter_unchecked(z, state)`` is :meth:`filter` without input checks,
    for kinefuse's own callers that validated ``z`` and pass back this filter's own state (see
    :mod:`kinefuse.filters._base`); the public ``step`` / ``filter`` always validate.

    Deviations from the paper
    -------------------------
    * Ω mapping swapped back (SPEC §5.2-1): ``R ← Ω₁`` (3×3), ``P̄⁻ ← Ω₂`` (6×6); Eqs. 20-23 and
      Algorithm 2 lines 11-12 assign the wrong (dimensionally impossible) pairs.
    * Eq. 17 uses the **posterior** mean of the current iteration, not the prior ``L^{-(l+1)}``
      (SPEC §5.2-2); Eqs. 13-14 read as the likelihood ``N(Hx, R)`` (SPEC §5.2-3).
    * Gain index: lines 9-10 use ``K^{(j+1)}`` (SPEC §5.2-4); the covariance uses the Joseph
      form (Eq. 9) rather than line 10's short form.
    * ``R`` is reset to the nominal value at every step (SPEC §5.2-6, §5.4); Algorithm 2 line 17
      stores ``R_k`` and carrying it raw makes it collapse. Option B (not in the paper) is the
      regularised ablation of SPEC §5.3.
    * The prediction drops the noise term of Eq. 5 / line 3, and uses ``P_{k−1}`` (SPEC §4.1).
    * Eigenvalue floors on the adapted R and P⁻ (SPEC §5.4) are not in the paper.
    * ``N_EM`` is not given by the paper; default 3 (SPEC §5.4).
    """

    model: LinearGaussianModel
    n_iter: int = 3
    regularized: bool = False
    tau: float = 3.0
    rho: float = 1.0 - math.exp(-4.0)
    _arrays: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        check_model(self.model)
        object.__setattr__(self, "n_iter", check_int(self.n_iter, "n_iter", 1))
        object.__setattr__(self, "regularized", check_bool(self.regularized, "regularized"))
        object.__setattr__(self, "tau", check_float(self.tau, "tau", lo=0.0, lo_open=True))
        object.__setattr__(self, "rho", check_float(self.rho, "rho", lo=0.0, lo_open=True, hi=1.0))
        object.__setattr__(self, "_arrays", model_arrays(self.model))

    def init(self, batch_shape=(), mean=None, cov=None) -> EMKalmanState:
        """Initial state for ``batch_shape`` elements.

        Parameters
        ----------
        batch_shape : tuple of int
        mean : array_like, shape (..., n_x), optional
            Initial mean; without it each element initialises at its first valid measurement.
        cov : array_like, shape (..., n_x, n_x), optional
            Initial covariance (default ``P₀`` of SPEC §4.2).
        """
        g = make_initial_state(self.model, batch_shape, mean, cov)
        bs = g.initialized.shape
        n_z = self.model.n_z
        u = np.full(bs, n_z + 2.0)  # û₀ = n_z + 2 (SPEC §5.3 option B)
        U = np.array(np.broadcast_to(self.model.R, (*bs, n_z, n_z)))  # Û₀ = (û₀ − n_z − 1) R_nom
        return EMKalmanState(g.x, g.P, g.initialized, g.k, u, U)

    def filter(self, z, state: EMKalmanState | None = None) -> tuple[EMKalmanState, EMKalmanResult]:
        """Filter a series.

        Parameters
        ----------
        z : array_like of float, shape (..., T, n_z)
            Position measurements, m; NaN rows are missing.
        state : EMKalmanState, optional
            State to resume from (default ``init(z.shape[:-2])``).

        Returns
        -------
        state : EMKalmanState
            State after the last sample (resume with it: split-and-resume equals one run).
        result : EMKalmanResult
            ``mean (..., T, n_x)``, ``cov (..., T, n_x, n_x)``, ``position (..., T, n_z)``,
            ``observed (..., T)``, ``innovation (..., T, n_z)``, ``distance (..., T)`` (NIS),
            ``R_em (..., T, n_z, n_z)``.
        """
        return run_filter(self, z, state)

    def _check_state(self, state, bs):
        n_x, n_z = self.model.n_x, self.model.n_z
        check_state(
            state, EMKalmanState, bs, {"x": (n_x,), "P": (n_x, n_x), "u": (), "U": (n_z, n_z)}
        )

    def _run(self, z: np.ndarray, state: EMKalmanState):
        a = self._arrays
        bs, zf, x, P, init, u, U = flat_run(z, state, ("x", "P", "initialized", "u", "U"))
        B, T, n_z = zf.shape
        o_mean, o_cov, o_obs, o_nu = run_outputs(B, T, self.model.n_x, n_z)
        o_dist = np.empty((B, T))
        o_Rem = np.empty((B, T, n_z, n_z))
        opt = EMOptions(self.n_iter, self.regularized, self.tau, self.rho, FLOOR_FRACTION)
        out = EMOutputs(o_mean, o_cov, o_obs, o_nu, o_dist, o_Rem)
        counts = em_kf_run(a["em"], opt, zf, x, P, init, u, U, out)
        warn_counts(counts, "EMKalmanFilter")
        new_state = EMKalmanState(*unflat(bs, x, P, init), int(state.k) + T, *unflat(bs, u, U))
        res = EMKalmanResult(
            **run_result(bs, self.model.H, o_mean, o_cov, o_obs, o_nu),
            distance=o_dist.reshape(*bs, T),
            R_em=o_Rem.reshape(*bs, T, n_z, n_z),
        )
        return new_state, res
