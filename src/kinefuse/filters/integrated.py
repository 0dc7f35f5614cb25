"""EM-based KF/FIR integrated filter of paper A (Sun 2024 §3.4), as corrected by SPEC §7."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.filters._base import (
    FilterResult,
    SingleModelFilter,
    check_batch_shape,
    check_state,
    flat_run,
    make_initial_state,
    run_filter,
    run_outputs,
    run_result,
    unflat,
)
from kinefuse.filters._kernels_integrated import (
    FIRModel,
    IntegratedOptions,
    IntegratedOutputs,
    integrated_run,
)
from kinefuse.filters.em_kalman import (
    FLOOR_FRACTION,
    check_bool,
    check_float,
    check_int,
    check_model,
    warn_counts,
)
from kinefuse.filters.ufir import check_buffer_memory, check_horizon, ufir_model_arrays
from kinefuse.models import LinearGaussianModel

__all__ = ["IntegratedFilter", "IntegratedResult", "IntegratedState"]

_GATES = ("R", "S")


class IntegratedState(NamedTuple):
    """State of :class:`IntegratedFilter`, batched over leading axes.

    Attributes
    ----------
    x : ndarray, shape (..., n_x)
        KF/EM-KF posterior mean (the FIR estimate after a FIR step when ``fir_feedback``).
    P : ndarray, shape (..., n_x, n_x)
        Its covariance.
    initialized : ndarray of bool, shape (...)
    k : int
        Number of steps taken.
    z_buf : ndarray, shape (..., N, n_z)
        Ring buffer of the last N measurements (slot ``t % N``) from which the batch-initialised
        UFIR is computed on demand.
    """

    x: np.ndarray
    P: np.ndarray
    initialized: np.ndarray
    k: int
    z_buf: np.ndarray


@dataclass(frozen=True, eq=False)
class IntegratedResult(FilterResult):
    """:class:`~kinefuse.filters.FilterResult` with the branch trace of the integrated filter.

    ``mode (..., T)`` int8 holds 0 KF, 1 EM-KF, 2 FIR, 3 predict-only
    (:data:`kinefuse.conventions.MODE_NAMES`); ``distance (..., T)`` is D₁.

    Attributes
    ----------
    distance2 : ndarray, shape (..., T)
        D₂ ``= νᵀ R_em⁻¹ ν`` after the EM iterations; NaN where not computed (KF or predict).
    """

    distance2: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class IntegratedFilter(SingleModelFilter):
    r"""EM-based KF/FIR integrated filter (paper A §3.4, Eq. 29, Fig. 2; SPEC §7.3).

    Parameters
    ----------
    model : LinearGaussianModel
        ``F`` (invertible), ``H``, ``Q``, nominal ``R``.
    horizon : int, default 20
        UFIR horizon N, samples (≥ ``n_x + 1``).
    threshold1 : float, default 2.0
        KF gate: KF update when ``D₁ < threshold1`` (paper A: 2). ``inf`` gives the plain KF.
        With ``gate="S"`` a χ²-style value such as 7.81 is the natural choice.
    threshold2 : float, default 2.0
        EM gate: EM-KF result when ``D₂ < threshold2``, else FIR (SPEC §7.2-3 default 2).
    n_em_iter : int, default 3
        ``N_EM`` of the EM-KF branch (option A, raw EM with R reset to nominal each step).
    gate : {"R", "S"}, default "R"
        Covariance of D₁: "R" paper-literal ``νᵀR⁻¹ν`` (Eq. 29); "S" the NIS ``νᵀS⁻¹ν``,
        ``S = H P⁻ Hᵀ + R`` (SPEC §7.2-2). D₂ always uses the EM-adapted ``R_em``.
    fir_feedback : bool, default True
        After a FIR step continue the KF recursion from the FIR estimate (SPEC §7.2-4); False
        keeps the KF/EM state internally and only outputs the FIR estimate.

    Notes
    -----
    Per element and time step (SPEC §7.3)::

        x⁻, P⁻ = F x, F P Fᵀ + Q                     (Eqs. 5-6; shared by all branches)
        z missing:  x, P = x⁻, P⁻                     mode 3 (predict)
        ν = z − H x⁻ ;  D₁ = νᵀ R⁻¹ ν                 (Eq. 29)
        D₁ < th1:   KF update (Eqs. 7-9, Joseph)      mode 0
        else:       EM-KF from P̄⁻⁽⁰⁾ = P⁻ (Alg. 2 lines 8-12, SPEC §5.3) -> x_e, P_e, R_em
                    D₂ = νᵀ R_em⁻¹ ν                  (Eq. 29 with the EM R; ν unchanged)
                    D₂ < th2 or k < N−1 or FIR not ready:  x_e, P_e     mode 1
                    else: batch UFIR over the last N samples (Eqs. 24-28, SPEC §6.3)   mode 2

    Each batch element takes its own branch inside one compiled loop; the UFIR is evaluated
    only when its branch is chosen (precomputed taps for a complete horizon, per-axis
    iterative form when it holds missing samples). The first valid row initialises an element
    (mode 0, no update).

    Trusted fast path: ``_filter_unchecked(z, state)`` is :meth:`filter` without input checks,
    for kinefuse's own callers that validated ``z`` and pass back this filter's own state (see
    :mod:`kinefuse.filters._base`); the public ``step`` / ``filter`` always validate.

    Deviations from the paper
    -------------------------
    * EM branch as corrected in SPEC §5.3 (swapped Ω₁→R / Ω₂→P⁻ mapping restored, posterior
      residual in Eq. 17, gain ``K^{(j+1)}``, Joseph covariance, R reset to nominal each
      step, eigenvalue floors) — see :class:`~kinefuse.filters.EMKalmanFilter`.
    * FIR branch as corrected in SPEC §6 (gain ``G = (HᵀH + (FGFᵀ)⁻¹)⁻¹``, horizon index
      ``s = m + K − 1`` instead of ``m2``, batch initialisation, Joseph covariance) — see
      :class:`~kinefuse.filters.UFIRFilter`. The FIR is not selectable while ``k < N − 1``
      (dead zone) or when the horizon has fewer than K valid samples (SPEC §7.2-5).
    * Which R in Eq. 29: nominal R for D₁, ``R_em = R^{(N_EM)}`` for D₂ (SPEC §7.2-1); the
      option ``gate="S"`` is not in the paper (SPEC §7.2-2).
    * ``threshold2`` is not given by the paper; default 2 (SPEC §7.2-3).
    * The state after a FIR step is not specified; default feeds the FIR estimate back
      (SPEC §7.2-4).
    """

    model: LinearGaussianModel
    horizon: int = 20
    threshold1: float = 2.0
    threshold2: float = 2.0
    n_em_iter: int = 3
    gate: str = "R"
    fir_feedback: bool = True
    _arrays: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        check_model(self.model)
        object.__setattr__(self, "horizon", check_horizon(self.horizon, self.model.n_x))
        for name in ("threshold1", "threshold2"):
            object.__setattr__(
                self, name, check_float(getattr(self, name), name, lo=0.0, allow_inf=True)
            )
        object.__setattr__(self, "n_em_iter", check_int(self.n_em_iter, "n_em_iter", 1))
        if not isinstance(self.gate, str) or self.gate not in _GATES:
            raise InputError(f"expected gate one of {_GATES}, got {self.gate!r}")
        object.__setattr__(self, "fir_feedback", check_bool(self.fir_feedback, "fir_feedback"))
        a = ufir_model_arrays(self.model, self.horizon)
        th1 = self.threshold1 if math.isfinite(self.threshold1) else np.inf
        a["fir"] = FIRModel(
            self.horizon, a["K"], bool(self.model.axis_blocks), a["W"], a["P_full"], a["F"],
            a["Finv"], a["H"], a["Fa"], a["Finva"], a["Ha"], a["Qa"], a["Ra"],
        )  # fmt: skip
        a["opt"] = IntegratedOptions(
            self.n_em_iter, th1, self.threshold2, self.gate == "S", self.fir_feedback,
            FLOOR_FRACTION, a["LR"],
        )  # fmt: skip
        object.__setattr__(self, "_arrays", a)

    def init(self, batch_shape=(), mean=None, cov=None) -> IntegratedState:
        """Initial state for ``batch_shape`` elements (empty horizon).

        Parameters
        ----------
        batch_shape : tuple of int
        mean : array_like, shape (..., n_x), optional
        cov : array_like, shape (..., n_x, n_x), optional
        """
        n_x, n_z = self.model.n_x, self.model.n_z
        check_buffer_memory(
            check_batch_shape(batch_shape),
            self.horizon * n_z + n_x * (n_x + 1),
            f"integrated filter horizon {self.horizon}",
        )
        g = make_initial_state(self.model, batch_shape, mean, cov)
        bs = g.initialized.shape
        return IntegratedState(
            g.x, g.P, g.initialized, g.k, np.full((*bs, self.horizon, n_z), np.nan)
        )

    def filter(
        self, z, state: IntegratedState | None = None
    ) -> tuple[IntegratedState, IntegratedResult]:
        """Filter a series.

        Parameters
        ----------
        z : array_like of float, shape (..., T, n_z)
            Position measurements, m; NaN rows are missing.
        state : IntegratedState, optional

        Returns
        -------
        state : IntegratedState
        result : IntegratedResult
            ``mean``, ``cov``, ``position``, ``observed``, ``innovation (..., T, n_z)``,
            ``distance`` (D₁), ``distance2`` (D₂), ``mode (..., T)`` int8.
        """
        return run_filter(self, z, state)

    def _check_state(self, state, bs):
        n_x, n_z = self.model.n_x, self.model.n_z
        check_state(
            state, IntegratedState, bs, {"x": (n_x,), "P": (n_x, n_x), "z_buf": (self.horizon, n_z)}
        )

    def _run(self, z: np.ndarray, state: IntegratedState):
        bs, zf, x, P, init, zring = flat_run(z, state, ("x", "P", "initialized", "z_buf"))
        T = zf.shape[1]
        o_mean, o_cov, o_obs, o_nu, o_d1, o_d2, o_mode = self._run_inplace(
            zf, x, P, init, zring, int(state.k)
        )
        new_state = IntegratedState(*unflat(bs, x, P, init), int(state.k) + T, *unflat(bs, zring))
        res = IntegratedResult(
            **run_result(bs, self.model.H, o_mean, o_cov, o_obs, o_nu),
            distance=o_d1.reshape(*bs, T),
            mode=o_mode.reshape(*bs, T),
            distance2=o_d2.reshape(*bs, T),
        )
        return new_state, res

    def _run_inplace(self, z, x, P, init, zring, k: int):
        """The kernel call of :meth:`_run` on flat arrays updated in place (the in-place form of
        the trusted fast path, :mod:`kinefuse.filters._base`).

        ``z (B, T, n_z)`` C-contiguous float64 without ±inf; state ``x (B, n_x)``, ``P (B, n_x,
        n_x)``, ``init (B,)``, ``zring (B, N, n_z)`` C-contiguous, updated in place; ``k`` the
        time index of ``z[:, 0]``. Returns ``mean, cov, observed, innovation, distance,
        distance2, mode``, each with leading axes ``(B, T)``.
        """
        a = self._arrays
        B, T, n_z = z.shape
        o_mean, o_cov, o_obs, o_nu = run_outputs(B, T, self.model.n_x, n_z)
        o_d1 = np.empty((B, T))
        o_d2 = np.empty((B, T))
        o_mode = np.empty((B, T), np.int8)
        out = IntegratedOutputs(o_mean, o_cov, o_obs, o_nu, o_d1, o_d2, o_mode)
        counts = integrated_run(a["em"], a["fir"], a["opt"], z, x, P, init, zring, k, out)
        warn_counts(counts, "IntegratedFilter")
        return o_mean, o_cov, o_obs, o_nu, o_d1, o_d2, o_mode
