"""Interacting multiple model (IMM) fusion of per-sensor filters, paper B (Xu 2023) §3.3.

Each model has its own measurement stream (paper B: model 1 = IMU-chain position, model 2 =
Kinect position), so ``z`` carries a model axis: ``(..., T, M, n_z)``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import KW_ONLY, dataclass
from typing import NamedTuple

import numpy as np

from kinefuse._validation import as_float_array, check_psd_stack
from kinefuse.exceptions import InputError
from kinefuse.filters._base import (
    FilterResult,
    broadcast_copy,
    check_batch_shape,
    check_measurements,
    check_not_all_missing,
    check_step_measurement,
    initial_covariance,
    positions,
    warn_regularised,
)
from kinefuse.filters._kernels_imm import imm_run
from kinefuse.models import LinearGaussianModel

__all__ = ["IMM", "IMMResult", "IMMState", "IMMStep", "lag_posteriors"]

#: Default Markov matrix of paper B (SPEC §12.2): mean sojourn 20 samples.
DEFAULT_TRANSITION = ((0.95, 0.05), (0.05, 0.95))
_READINGS = ("R2", "R1")


class IMMState(NamedTuple):
    """IMM state, batched over leading axes.

    Attributes
    ----------
    x : ndarray, shape (..., M, n_x)
        Model-conditioned posterior means at the last step (NaN until initialised).
    P : ndarray, shape (..., M, n_x, n_x)
        Model-conditioned posterior covariances.
    mu : ndarray, shape (..., M)
        Model probabilities μ.
    initialized : ndarray of bool, shape (...)
        False until the element has seen a valid measurement (or was given a state).
    k : int
        Number of steps taken (time index of the next step).
    """

    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    initialized: np.ndarray
    k: int


class IMMStep(NamedTuple):
    """Output of one :meth:`IMM.step` (no time axis).

    Attributes
    ----------
    mean : ndarray, shape (..., n_x)
        Combined estimate (paper B Eq. 47).
    cov : ndarray, shape (..., n_x, n_x)
        Combined covariance (Eq. 48).
    position : ndarray, shape (..., n_z)
        ``H @ mean`` with the first model's ``H``, m.
    observed : ndarray of bool, shape (...)
        True when at least one model used its measurement.
    mu : ndarray, shape (..., M)
        Model probabilities after the step.
    model_mean, model_cov : ndarray, shapes (..., M, n_x), (..., M, n_x, n_x)
        Model-conditioned posteriors (KF-updated, Eqs. 35-38).
    model_observed : ndarray of bool, shape (..., M)
        True where model m was updated with its measurement.
    log_likelihood : ndarray, shape (..., M)
        ``log Λ_m`` (Eqs. 39-40 in log form); NaN where model m was not updated.
    model_innovation : ndarray, shape (..., M, n_z)
        ``ν_m = z_m − H x⁻_m``; NaN where not updated.
    model_distance : ndarray, shape (..., M)
        NIS ``ν_mᵀ S_m⁻¹ ν_m``; NaN where not updated.
    """

    mean: np.ndarray
    cov: np.ndarray
    position: np.ndarray
    observed: np.ndarray
    mu: np.ndarray
    model_mean: np.ndarray
    model_cov: np.ndarray
    model_observed: np.ndarray
    log_likelihood: np.ndarray
    model_innovation: np.ndarray
    model_distance: np.ndarray


@dataclass(frozen=True, eq=False)
class IMMResult(FilterResult):
    """Per-sample output of :meth:`IMM.filter`: :class:`FilterResult` plus IMM diagnostics.

    ``mean, cov, position, observed`` are the combined estimate (paper B Eqs. 47-48); the
    generic ``innovation``, ``distance`` and ``mode`` are None (see the per-model fields).

    Attributes
    ----------
    mu : ndarray, shape (..., T, M)
        Model probabilities μ_t.
    model_mean : ndarray, shape (..., T, M, n_x)
        Model-conditioned posterior means.
    model_cov : ndarray, shape (..., T, M, n_x, n_x)
        Model-conditioned posterior covariances.
    model_observed : ndarray of bool, shape (..., T, M)
        True where model m was updated with its own measurement.
    log_likelihood : ndarray, shape (..., T, M)
        ``log Λ_m``; NaN where model m was not updated.
    model_innovation : ndarray, shape (..., T, M, n_z)
        Innovations ``z_m − H x⁻_m``, m; NaN where not updated.
    model_distance : ndarray, shape (..., T, M)
        NIS ``νᵀS⁻¹ν`` per model; NaN where not updated.
    """

    mu: np.ndarray | None = None
    model_mean: np.ndarray | None = None
    model_cov: np.ndarray | None = None
    model_observed: np.ndarray | None = None
    log_likelihood: np.ndarray | None = None
    model_innovation: np.ndarray | None = None
    model_distance: np.ndarray | None = None


_IMM_RESULT_NONE = {f.name: None for f in dataclasses.fields(IMMResult)}


def _imm_result(fields: dict) -> IMMResult:
    """``IMMResult(**fields)`` without the dataclass ``__init__`` (about 4 µs of an online
    step), as :meth:`FilterResult.fast`: the fields not given are None."""
    r = object.__new__(IMMResult)
    d = r.__dict__
    d.update(_IMM_RESULT_NONE)
    del d["cov"]
    d["_cov"] = fields.pop("cov")
    d.update(fields)
    return r


def _selected_columns(H: np.ndarray) -> np.ndarray | None:
    """The column each row of ``H`` selects when ``H`` is a 0/1 selection matrix (one 1 per
    row): then ``H x`` is ``x[..., cols]``, the same numbers; else None."""
    H = np.asarray(H)
    ones = H == 1.0
    if not (np.all(ones | (H == 0.0)) and np.all(ones.sum(axis=1) == 1)):
        return None
    return np.argmax(ones, axis=1).astype(np.intp)


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class IMM:
    """IMM fusion of per-sensor models, paper B (Xu 2023) Eqs. 24-48, corrected per SPEC §8.

    Parameters
    ----------
    model_imu, model_cam : LinearGaussianModel, optional
        The two models of paper B (model 1: IMU-chain position, ``R_I``; model 2: camera
        position, ``R_V``). Give either these two or ``models``.
    models : sequence of LinearGaussianModel, keyword only
        ``M >= 2`` models with equal ``n_x`` and ``n_z``. F and Q may differ (classical IMM);
        in paper B they are equal and only ``R`` differs. Stored as a tuple.
    transition : array_like, shape (M, M)
        Markov matrix Γ (paper B Eq. 24): ``transition[i, m] = P(model m at t | model i at
        t−1)``; rows sum to 1. Default ``[[0.95, 0.05], [0.05, 0.95]]`` (SPEC §12.2).
    mu0 : array_like, shape (M,)
        Initial model probabilities, non-negative, sum 1. Default uniform.
    mu_floor : float
        Lower bound of every μ_m after each update, ``0 <= mu_floor < 1/M`` (default 1e-6;
        0 disables it).
    reading : {"R2", "R1"}
        ``"R2"`` (default, SPEC §8.2 literal reading): mixing may use externally supplied
        posteriors at t−1 (paper B's FIR-1 and FIR-2), passed as ``prev``; where ``prev`` is
        absent the IMM's own model-conditioned posteriors are used. ``"R1"``: the standard IMM
        (own posteriors only; feed FIR outputs as the measurements for the cascade reading);
        ``prev`` is refused.

    Notes
    -----
    One step (SPEC §8.3), with ``x_i, P_i`` the model-conditioned posteriors at t−1 (from
    ``prev`` in reading R2, else from the state)::

        c̄_m = Σ_i Γ_im μ_i                                   (25)
        μ_{i|m} = Γ_im μ_i / c̄_m                              (26)
        x0_m = Σ_i μ_{i|m} x_i ;  P0_m = Σ_i μ_{i|m} (P_i + (x_i − x0_m)(·)ᵀ)      (27)-(28)
        x⁻_m = F_m x0_m ;  P⁻_m = F_m P0_m F_mᵀ + Q_m         (29)-(32)
        ν_m = z_m − H x⁻_m ;  S_m = H P⁻_m Hᵀ + R_m ;  K_m = P⁻_m Hᵀ S_m⁻¹           (33)-(34), (41)-(44)
        x_m = x⁻_m + K_m ν_m ;  P_m = (I − K_m H) P⁻_m (·)ᵀ + K_m R_m K_mᵀ            (35)-(38), Joseph
        log Λ_m = −½ (ν_mᵀ S_m⁻¹ ν_m + log det S_m + n_z log 2π)                       (39)-(40)
        μ_m = exp(log Λ_m + log c̄_m − logsumexp_j(log Λ_j + log c̄_j))                (45)-(46)
        μ ← floor(μ)
        x̂ = Σ_m μ_m x_m ;  P̂ = Σ_m μ_m (P_m + (x_m − x̂)(·)ᵀ)                          (47)-(48)

    Missing data (NaN row of ``z[..., m, :]``): model m is predicted only and its log-likelihood
    is set to the log-mean-exp of the updated models' (M = 2: equal to the other's), so it
    carries no evidence; all models missing: predict only, ``μ = c̄``. An element that is not
    initialised starts at its first valid measurement (each model at its own ``z_m``, or at the
    first valid other model's if its own is missing): ``x = H⁺ z`` (zero velocity), ``P₀`` as
    for the KF (SPEC §12.2), μ unchanged, no likelihood at that sample.

    Trusted fast path: ``_filter_unchecked(z, state, prev)`` is :meth:`filter` without input
    checks, for kinefuse's own callers that validated ``z`` (and ``prev``: float64 with the
    shapes of :meth:`filter`, no ±inf) and pass back this IMM's own state (see
    :mod:`kinefuse.filters._base`); the public ``step`` / ``filter`` always validate.

    Deviations from the paper
    -------------------------
    * Eqs. 25-26: index typos fixed, ``c̄_m = Σ_i Γ_im μ_i`` and ``μ_{i|m} = Γ_im μ_i / c̄_m``
      (SPEC §8.2, checked against filterpy's ``IMMEstimator``).
    * Eqs. 41-44: the innovation uses the measurement matrix and the predicted state,
      ``ν_m = z_m − H x⁻_m`` (Eq. 43 wrongly used ``T^{1,j}`` for model 2); ``S_m`` uses
      ``P⁻_m``. Eq. 46: ``μ_m = Λ_m c̄_m / c``. Eq. 48: the summation index no longer collides
      with the joint index.
    * Each model gets its own measurement stream (the paper's structure; filterpy passes one
      z to all models).
    * Likelihoods in the log domain with log-sum-exp (no underflow, no 0/0 on huge
      innovations); an overflowing ``νᵀS⁻¹ν`` gives ``log Λ = −inf``, never NaN.
    * μ floor (default 1e-6) against lock-in. The floor is exact: entries below it are set to
      it and the others rescaled (SPEC §8.3's max-then-renormalise, up to O(floor²)).
    * Joseph-form covariance update (paper: ``(I − KG)P``); one ``R`` per model (the paper
      uses one R for both sensors: pass equal R for the paper-literal setting).
    """

    model_imu: LinearGaussianModel | None = None
    model_cam: LinearGaussianModel | None = None
    _: KW_ONLY
    models: tuple[LinearGaussianModel, ...] | None = None
    transition: np.ndarray = DEFAULT_TRANSITION
    mu0: np.ndarray | None = None
    mu_floor: float = 1e-6
    reading: str = "R2"

    def __post_init__(self):
        pair = (self.model_imu, self.model_cam)
        if self.models is not None:
            models = self.models
            if isinstance(models, LinearGaussianModel) or not hasattr(models, "__len__"):
                raise InputError(
                    f"expected models as a sequence of LinearGaussianModel, got {models!r}"
                )
            models = tuple(models)
            # both forms are accepted only when they agree (as dataclasses.replace passes them)
            if any(m is not None for m in pair) and (
                len(models) != 2 or models[0] is not pair[0] or models[1] is not pair[1]
            ):
                raise InputError(
                    "expected either model_imu and model_cam, or models=[...], got both"
                )
        else:
            if any(m is None for m in pair):
                raise InputError("expected two models (model_imu, model_cam) or models=[...]")
            models = pair
        if len(models) < 2:
            raise InputError(f"expected at least 2 models, got {len(models)}")
        for i, m in enumerate(models):
            if not isinstance(m, LinearGaussianModel):
                raise InputError(
                    f"expected models[{i}] as a LinearGaussianModel, got {type(m).__name__}"
                )
        n_x, n_z = models[0].n_x, models[0].n_z
        for i, m in enumerate(models):
            if (m.n_x, m.n_z) != (n_x, n_z):
                raise InputError(
                    f"expected every model with (n_x, n_z) = {(n_x, n_z)} (models[0]), "
                    f"got {(m.n_x, m.n_z)} for models[{i}]"
                )
        M = len(models)
        G = np.asarray(self.transition, dtype=float)
        if G.shape != (M, M):
            raise InputError(f"expected transition with shape ({M}, {M}), got {G.shape}")
        if not np.all(np.isfinite(G)) or np.any(G < 0):
            raise InputError("expected transition entries finite and >= 0")
        if not np.allclose(G.sum(axis=1), 1.0, rtol=0, atol=1e-9):
            raise InputError(
                "expected transition rows summing to 1 (transition[i, m] = P(m at t | i at t-1)), "
                f"got row sums {G.sum(axis=1)}"
            )
        if np.any(G.sum(axis=0) <= 0):
            raise InputError("expected every model reachable (each transition column sum > 0)")
        mu0 = np.full(M, 1.0 / M) if self.mu0 is None else np.asarray(self.mu0, dtype=float)
        _check_mu(mu0, M, "mu0")
        try:
            floor = float(self.mu_floor)
        except (TypeError, ValueError):
            raise InputError(f"expected mu_floor as a number, got {self.mu_floor!r}") from None
        if not (np.isfinite(floor) and 0.0 <= floor < 1.0 / M):
            raise InputError(f"expected 0 <= mu_floor < 1/M = {1.0 / M:.3g}, got {self.mu_floor!r}")
        if self.reading not in _READINGS:
            raise InputError(f"expected reading in {_READINGS}, got {self.reading!r}")
        object.__setattr__(self, "models", models)
        object.__setattr__(self, "transition", _readonly(G))
        object.__setattr__(self, "mu0", _readonly(mu0))
        object.__setattr__(self, "mu_floor", floor)
        # stacked model matrices for the kernel (private, read-only; not dataclass fields)
        stacked = {
            "_F": [m.F for m in models],
            "_Q": [m.Q for m in models],
            "_H": [m.H for m in models],
            "_R": [m.R for m in models],
            "_Hpinv": [np.linalg.pinv(m.H) for m in models],
            "_P_init": [initial_covariance(m) for m in models],
        }
        for name, mats in stacked.items():
            object.__setattr__(self, name, _readonly(np.stack(mats)))
        M, n_x, n_z = len(models), models[0].n_x, models[0].n_z
        no_per_model = (  # the kernel's zero-length per-model outputs (see _run_inplace)
            np.empty((0, 0, M, n_x)), np.empty((0, 0, M, n_x, n_x)), np.empty((0, 0, M)),
            np.empty((0, 0, M, n_z)), np.empty((0, 0, M)),
        )  # fmt: skip
        object.__setattr__(self, "_no_per_model", no_per_model)
        object.__setattr__(self, "_sizes", (M, n_x, n_z))
        object.__setattr__(self, "_pos_cols", _selected_columns(models[0].H))

    # ------------------------------------------------------------------ properties
    @property
    def n_models(self) -> int:
        """Number of models M."""
        return self._sizes[0]

    @property
    def n_x(self) -> int:
        """State dimension."""
        return self._sizes[1]

    @property
    def n_z(self) -> int:
        """Measurement dimension (per model)."""
        return self._sizes[2]

    @property
    def step_measurement_shape(self) -> tuple[int, int]:
        """Trailing shape ``(M, n_z)`` of one batch element's measurement in :meth:`step`.

        :class:`~kinefuse.filters.OnlineFilter` reads it to tell the batch axes from the
        per-model rows (the other filters take ``(n_z,)`` and do not need it).
        """
        return (self.n_models, self.n_z)

    # ------------------------------------------------------------------ state
    def init(self, batch_shape=(), mean=None, cov=None, mu=None) -> IMMState:
        """Initial state.

        Parameters
        ----------
        batch_shape : tuple of int
            Leading (batch) axes, e.g. ``(n_trials, n_joints)``.
        mean : array_like, broadcastable to (*batch_shape, M, n_x), optional
            Model-conditioned initial means; a ``(n_x,)`` vector starts every model there.
            Without it the elements start at their first valid measurement.
        cov : array_like, broadcastable to (*batch_shape, M, n_x, n_x), optional
            Initial covariances (only with ``mean``); default per model: ``P₀`` of SPEC §12.2
            (R on positions, 1 (m/s)² on velocities).
        mu : array_like, broadcastable to (*batch_shape, M), optional
            Initial model probabilities; default ``mu0``.

        Returns
        -------
        IMMState
        """
        batch_shape = check_batch_shape(batch_shape)
        M, n_x = self.n_models, self.n_x
        mu_arr = self.mu0 if mu is None else as_float_array(mu, "mu", last_dim=M)
        _check_mu(mu_arr, M, "mu")
        mu_b = broadcast_copy(mu_arr, (*batch_shape, M), "mu", order="C")
        if mean is None:
            if cov is not None:
                raise InputError("cov given without mean: pass both or neither")
            x = np.full((*batch_shape, M, n_x), np.nan)
            P = np.full((*batch_shape, M, n_x, n_x), np.nan)
            return IMMState(x, P, mu_b, np.zeros(batch_shape, dtype=bool), 0)
        m = as_float_array(mean, "mean", last_dim=n_x)
        x = broadcast_copy(m, (*batch_shape, M, n_x), "mean", finite=True, order="C")
        c = self._P_init if cov is None else as_float_array(cov, "cov")
        P = broadcast_copy(c, (*batch_shape, M, n_x, n_x), "cov", finite=True, order="C")
        if cov is not None:
            check_psd_stack(c, "cov")
        return IMMState(x, P, mu_b, np.ones(batch_shape, dtype=bool), 0)

    # ------------------------------------------------------------------ running
    def step(self, state: IMMState, z, prev=None) -> tuple[IMMState, IMMStep]:
        """One IMM step with one measurement per model.

        Parameters
        ----------
        state : IMMState
            From :meth:`init` or a previous step.
        z : array_like, shape (*batch_shape, M, n_z)
            ``z[..., m, :]`` is model m's measurement (paper B: m = 0 IMU, m = 1 camera), m;
            a NaN row means model m is not observed.
        prev : tuple (x_prev, P_prev), optional
            Reading R2 only: external model-conditioned posteriors at t−1, shapes
            ``(*batch_shape, M, n_x)`` and ``(*batch_shape, M, n_x, n_x)`` (paper B: FIR-1 and
            FIR-2). NaN entries of model i fall back to the IMM's own posterior of model i.

        Returns
        -------
        state : IMMState
        out : IMMStep
        """
        self._check_state(state)
        batch = tuple(state.initialized.shape)
        M = self.n_models
        zz = check_step_measurement(z, self.n_z, (*batch, M))
        pv = self._check_prev(prev, (*batch, M))
        if pv is not None:
            pv = (pv[0][..., None, :, :], pv[1][..., None, :, :, :])
        state, res = self._run(state, zz[..., None, :, :], pv)
        t_axis = len(batch)  # drop the length-1 time axis
        out = IMMStep(**{f: np.take(getattr(res, f), 0, axis=t_axis) for f in IMMStep._fields})
        return state, out

    def filter(self, z, state: IMMState | None = None, prev=None) -> tuple[IMMState, IMMResult]:
        """Run the IMM over a series; equals repeated :meth:`step`.

        Parameters
        ----------
        z : array_like, shape (..., T, M, n_z)
            Per-model measurements, m; NaN rows are missing.
        state : IMMState, optional
            Starting state (default ``init(batch_shape=z.shape[:-3])``).
        prev : tuple (x_prev, P_prev), optional
            Reading R2: shapes ``(..., T, M, n_x)`` and ``(..., T, M, n_x, n_x)``, aligned with
            the step that uses them: ``prev[..., t, :, :]`` holds the external posteriors at
            t−1 (NaN: use the IMM's own). Build it from per-sample filter outputs with
            :func:`lag_posteriors`.

        Returns
        -------
        state : IMMState
            State after the last sample (resume with ``filter(z_next, state=state)``).
        result : IMMResult
        """
        M = self.n_models
        zz = check_measurements(z, self.n_z)
        if zz.ndim < 3 or zz.shape[-2] != M:
            raise InputError(f"expected z with shape (..., T, {M}, {self.n_z}), got {zz.shape}")
        if zz.shape[-3] == 0:
            raise InputError(f"expected z with at least one time step, got shape {zz.shape}")
        batch = zz.shape[:-3]
        if state is None:
            state = self.init(batch_shape=batch)
        else:
            self._check_state(state)
            if tuple(state.initialized.shape) != tuple(batch):
                raise InputError(
                    f"expected state with batch shape {batch} (z's leading axes), got {state.initialized.shape}"
                )
        pv = self._check_prev(prev, zz.shape[:-1])
        if pv is None:
            flat = zz.reshape(*batch, zz.shape[-3] * M, self.n_z)
            check_not_all_missing(flat, state)
        return self._run(state, zz, pv)

    def _filter_unchecked(self, z: np.ndarray, state: IMMState, prev=None):
        """:meth:`filter` on the trusted fast path: no checks (contract: :mod:`._base`)."""
        return self._run(state, z, prev)

    # ------------------------------------------------------------------ internals
    def _check_state(self, state) -> None:
        if not isinstance(state, IMMState):
            raise InputError(f"expected an IMMState (from IMM.init), got {type(state).__name__}")
        M, n_x = self.n_models, self.n_x
        b = tuple(state.initialized.shape)
        if (
            state.x.shape != (*b, M, n_x)
            or state.P.shape != (*b, M, n_x, n_x)
            or state.mu.shape != (*b, M)
        ):
            raise InputError(
                f"expected state arrays with shapes {(*b, M, n_x)}, {(*b, M, n_x, n_x)}, {(*b, M)}, got "
                f"{state.x.shape}, {state.P.shape}, {state.mu.shape}"
            )

    def _check_prev(self, prev, lead: tuple[int, ...]):
        if prev is None:
            return None
        if self.reading == "R1":
            raise InputError(
                "reading='R1' is the standard IMM on its own posteriors: expected prev=None"
            )
        try:
            x_prev, P_prev = prev
        except (TypeError, ValueError):
            raise InputError("expected prev as a tuple (x_prev, P_prev)") from None
        n_x = self.n_x
        xp = as_float_array(x_prev, "x_prev")
        Pp = as_float_array(P_prev, "P_prev")
        if xp.shape != (*lead, n_x):
            raise InputError(f"expected x_prev with shape {(*lead, n_x)}, got {xp.shape}")
        if Pp.shape != (*lead, n_x, n_x):
            raise InputError(f"expected P_prev with shape {(*lead, n_x, n_x)}, got {Pp.shape}")
        if np.any(np.isinf(xp)) or np.any(np.isinf(Pp)):
            raise InputError("expected prev finite or NaN (not given), got ±inf")
        check_psd_stack(Pp, "P_prev")
        return xp, Pp

    def _run(self, state: IMMState, z: np.ndarray, prev) -> tuple[IMMState, IMMResult]:
        M, n_x, n_z = self.n_models, self.n_x, self.n_z
        batch = z.shape[:-3]
        T = z.shape[-3]
        B = math.prod(batch)  # (np.prod costs ~5 µs: this runs on every online step)
        zf = np.ascontiguousarray(z.reshape(B, T, M, n_z))
        if prev is not None:
            prev = (
                np.ascontiguousarray(prev[0].reshape(B, T, M, n_x)),
                np.ascontiguousarray(prev[1].reshape(B, T, M, n_x, n_x)),
            )
        # C order throughout: one compiled specialisation of the kernel (an F-ordered mu, e.g.
        # from a transposed state, would compile the whole loop a second time)
        xs = np.array(state.x, dtype=float, order="C").reshape(B, M, n_x)
        Ps = np.array(state.P, dtype=float, order="C").reshape(B, M, n_x, n_x)
        mu = np.array(state.mu, dtype=float, order="C").reshape(B, M)
        init = np.array(state.initialized, dtype=bool, order="C").reshape(B)
        result = self._run_inplace(zf, prev, xs, Ps, mu, init, batch)
        new_state = IMMState(
            xs.reshape(*batch, M, n_x),
            Ps.reshape(*batch, M, n_x, n_x),
            mu.reshape(*batch, M),
            init.reshape(batch),
            state.k + T,
        )
        return new_state, result

    def _run_inplace(self, z, prev, xs, Ps, mu, init, batch=None, per_model=True) -> IMMResult:
        """The kernel call of :meth:`_run` on flat arrays updated in place.

        ``z (B, T, M, n_z)`` C-contiguous float64 without ±inf; ``prev`` None or C-contiguous
        ``(x (B, T, M, n_x), P (B, T, M, n_x, n_x))``; state ``xs (B, M, n_x)``, ``Ps (B, M,
        n_x, n_x)``, ``mu (B, M)`` float64 and ``init (B,)`` bool, C-contiguous, updated in
        place. For owners of such arrays that step them without copies
        (:class:`kinefuse.pipelines.paper_b.PaperBCore`); ``filter`` and ``step`` copy the
        state first. Returns the result with leading axes ``batch`` (default ``(B,)``); without
        ``per_model`` its ``model_*`` and ``log_likelihood`` fields are None (not computed:
        they are most of the output's memory).
        """
        M, n_x, n_z = self._sizes
        B, T = z.shape[:2]
        batch = (B,) if batch is None else batch
        if prev is None:
            has_prev = False
            px = np.empty((0, 0, M, n_x))
            pP = np.empty((0, 0, M, n_x, n_x))
        else:
            has_prev = True
            px, pP = prev
        out_x = np.empty((B, T, n_x))
        out_P = np.empty((B, T, n_x, n_x))
        out_mu = np.empty((B, T, M))
        if per_model:
            out_xm = np.empty((B, T, M, n_x))
            out_Pm = np.empty((B, T, M, n_x, n_x))
            out_ll = np.empty((B, T, M))
            out_nu = np.empty((B, T, M, n_z))
            out_nis = np.empty((B, T, M))
        else:  # zero-length (not written by the kernel), one set per filter
            out_xm, out_Pm, out_ll, out_nu, out_nis = self._no_per_model
        out_obs = np.zeros((B, T), dtype=bool)
        out_mobs = np.zeros((B, T, M), dtype=bool)
        if B > 0 and T > 0:
            n_reg = imm_run(
                z, has_prev, px, pP, self._F, self._Q, self._H, self._R, self._Hpinv, self._P_init,
                self.transition,
                self.mu_floor, xs, Ps, mu, init,
                out_x, out_P, out_mu, out_xm, out_Pm, out_obs, out_mobs, out_ll, out_nu, out_nis,
            )  # fmt: skip
            if n_reg:
                warn_regularised(n_reg, "IMM")
        fields = {
            "mean": out_x,
            "cov": out_P,
            "observed": out_obs,
            "mu": out_mu,
            "model_observed": out_mobs,
        }
        if per_model:
            fields["model_mean"] = out_xm
            fields["model_cov"] = out_Pm
            fields["log_likelihood"] = out_ll
            fields["model_innovation"] = out_nu
            fields["model_distance"] = out_nis
        if batch != (B,):  # the batch axes back (every output is (B, T, ...))
            fields = {k: v.reshape(*batch, *v.shape[1:]) for k, v in fields.items()}
        mean = fields["mean"]
        cols = self._pos_cols  # H selects state components: H x̂ without the matrix product
        fields["position"] = positions(mean, self.models[0].H) if cols is None else mean[..., cols]
        return _imm_result(fields)


def lag_posteriors(mean, cov) -> tuple[np.ndarray, np.ndarray]:
    """Shift per-sample posteriors one step later along time, for :meth:`IMM.filter`'s ``prev``.

    Parameters
    ----------
    mean : array_like, shape (..., T, M, n_x)
        Posteriors of the M external filters at each sample t (e.g. FIR-1 and FIR-2 stacked on
        axis -2).
    cov : array_like, shape (..., T, M, n_x, n_x)

    Returns
    -------
    x_prev, P_prev : ndarray
        Same shapes; ``x_prev[..., t, :, :] = mean[..., t-1, :, :]`` and NaN at ``t = 0``
        (the IMM then uses its own posteriors, or starts at the measurement).
    """
    x = as_float_array(mean, "mean")
    P = as_float_array(cov, "cov")
    if x.ndim < 3 or P.shape != (*x.shape, x.shape[-1]):
        raise InputError(
            f"expected mean (..., T, M, n_x) and cov (..., T, M, n_x, n_x), got {x.shape} and {P.shape}"
        )
    x_prev = np.full_like(x, np.nan)
    P_prev = np.full_like(P, np.nan)
    x_prev[..., 1:, :, :] = x[..., :-1, :, :]
    P_prev[..., 1:, :, :, :] = P[..., :-1, :, :, :]
    return x_prev, P_prev


def _check_mu(mu: np.ndarray, M: int, name: str) -> None:
    if mu.shape[-1:] != (M,):
        raise InputError(f"expected {name} with shape (..., {M}), got {mu.shape}")
    if not np.all(np.isfinite(mu)) or np.any(mu < 0):
        raise InputError(f"expected {name} finite and >= 0")
    if not np.allclose(mu.sum(axis=-1), 1.0, rtol=0, atol=1e-9):
        raise InputError(f"expected {name} summing to 1, got sum {mu.sum(axis=-1)}")
