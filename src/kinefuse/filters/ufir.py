"""Iterative unbiased FIR (UFIR) filter of paper A §3.3 / paper B §3.3, as corrected by SPEC §6."""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.filters._base import (
    FilterResult,
    SingleModelFilter,
    check_batch_shape,
    check_outputs,
    check_state,
    flat_run,
    make_initial_state,
    run_filter,
    run_outputs,
    run_result,
    unflat,
)
from kinefuse.filters._kernels_axis import pack_axis_params, state_blocks_shared
from kinefuse.filters._kernels_ufir import ufir_gains
from kinefuse.filters._kernels_ufir_run import ufir_run, ufir_run_cv
from kinefuse.filters.em_kalman import (
    check_int,
    check_model,
    model_arrays,
)
from kinefuse.models import LinearGaussianModel

__all__ = ["UFIRFilter", "UFIRResult", "UFIRState"]

_INITS = ("batch", "stored")


class UFIRState(NamedTuple):
    """State of :class:`UFIRFilter`, batched over leading axes.

    Attributes
    ----------
    x : ndarray, shape (..., n_x)
        Last output ``x̂_{k-1}`` (NaN until initialised).
    P : ndarray, shape (..., n_x, n_x)
        Last output covariance.
    initialized : ndarray of bool, shape (...)
    k : int
        Number of steps taken (time index of the next sample).
    z_buf : ndarray, shape (..., N, n_z)
        Ring buffer of the last N measurements; time ``t`` in slot ``t % N``; NaN = missing.
    x_buf : ndarray, shape (..., N, n_x) for ``init="stored"``, else (..., 0, n_x)
        Ring buffer of the last N outputs (slot ``t % N``).
    P_buf : ndarray, shape (..., N, n_x, n_x) for ``init="stored"``, else (..., 0, n_x, n_x)
        Ring buffer of the last N output covariances.
    """

    x: np.ndarray
    P: np.ndarray
    initialized: np.ndarray
    k: int
    z_buf: np.ndarray
    x_buf: np.ndarray
    P_buf: np.ndarray


class _SharedBlocksState(UFIRState):
    """A :class:`UFIRState` returned by the constant-velocity route (:meth:`UFIRFilter._run_cv`):
    every initialised ``P`` holds one 2x2 block on every axis, so the next call takes that route
    without re-checking (``state_blocks_shared``). ``_replace`` returns a plain ``UFIRState``
    (a changed state is checked again)."""

    __slots__ = ()

    def _replace(self, **kwargs) -> UFIRState:
        return UFIRState(*self)._replace(**kwargs)


_NO_COVB = np.empty((0, 0, 0, 0))  # ufir_run_cv's covariance output when it is not wanted


def _warn_failed(n_fail: int, stacklevel: int = 4) -> None:
    """ONE warning per call when the stored-init KF update could not factorise S."""
    if n_fail:
        warnings.warn(
            f"UFIRFilter: KF update skipped on {n_fail} step(s): S could not be factorised (SPEC §13)",
            NumericalWarning,
            stacklevel=stacklevel,  # 4: the caller of UFIRFilter.filter / step, as before
        )


@dataclass(frozen=True, eq=False)
class UFIRResult(FilterResult):
    """:class:`~kinefuse.filters.FilterResult` plus the FIR readiness flag.

    Attributes
    ----------
    fir_ready : ndarray of bool, shape (..., T)
        True where the output is the FIR estimate; False in the dead zone (``k < N−1``) and
        where the horizon held fewer than K valid samples (the KF step was used instead).
    """

    fir_ready: np.ndarray | None = None


def ufir_model_arrays(model: LinearGaussianModel, horizon: int) -> dict:
    """Model arrays plus ``F⁻¹``, per-axis blocks and the precomputed full-horizon taps."""
    a = model_arrays(model)
    F = a["F"]
    n_x = model.n_x
    cond = np.linalg.cond(F)
    if not np.isfinite(cond) or cond > 1e12:
        raise InputError(
            f"expected an invertible transition matrix F for the UFIR, got cond(F) = {cond:.3g}"
        )
    Finv = np.linalg.inv(F)
    a["Finv"] = np.ascontiguousarray(Finv)
    K = n_x
    W, P_full = ufir_gains(F, Finv, a["H"], a["Q"], a["R"], horizon, K)
    a["W"] = np.ascontiguousarray(W)
    a["P_full"] = np.ascontiguousarray(P_full)
    a["K"] = K
    if model.axis_blocks:
        n_ax = model.n_z
        blk = [slice(2 * i, 2 * i + 2) for i in range(n_ax)]
        a["Fa"] = np.ascontiguousarray([F[s, s] for s in blk])
        a["Finva"] = np.ascontiguousarray([Finv[s, s] for s in blk])
        a["Ha"] = np.ascontiguousarray([a["H"][i : i + 1, s] for i, s in enumerate(blk)])
        a["Qa"] = np.ascontiguousarray([a["Q"][s, s] for s in blk])
        a["Ra"] = np.ascontiguousarray([a["R"][i : i + 1, i : i + 1] for i in range(n_ax)])
        par, p0, shared = pack_axis_params(F, a["Q"], a["H"], a["R"], a["P0"])
        f = par[0]
        cv = shared and f[0] == 1.0 and f[2] == 0.0 and f[3] == 1.0 and f[7] == 1.0 and f[8] == 0.0
        if cv:
            Pf = a["P_full"]
            pfull = np.array([Pf[0, 0], 0.5 * (Pf[0, 1] + Pf[1, 0]), Pf[1, 1]])
            # ufir_run_cv's model arguments, in its order: N, K, dt, q00, q01, q11, r, p0, pfull,
            # and the per-axis blocks of its iterative form
            a["cv"] = (horizon, K, float(f[1]), float(f[4]), float(f[5]), float(f[6]),
                       float(f[9]), np.ascontiguousarray(p0[0]), pfull, a["Fa"], a["Finva"],
                       a["Ha"], a["Qa"], a["Ra"])  # fmt: skip
    else:
        a["Fa"] = np.zeros((0, 2, 2))
        a["Finva"] = np.zeros((0, 2, 2))
        a["Ha"] = np.zeros((0, 1, 2))
        a["Qa"] = np.zeros((0, 2, 2))
        a["Ra"] = np.zeros((0, 1, 1))
    return a


#: Longest accepted horizon, samples: the full-horizon taps (:func:`ufir_gains`) cost
#: O(horizon²) time at construction (0.1 s at 1000, about 1.5 minutes at 10 000 samples).
MAX_HORIZON_SAMPLES = 2000


def check_horizon(horizon, n_x: int) -> int:
    """``horizon`` must be an integer in [state dimension + 1, :data:`MAX_HORIZON_SAMPLES`].

    The lower bound is SPEC §6.3 (``N ≥ K + 1``); the upper bound keeps the construction of
    the taps (O(N²)) and the per-element ring buffers bounded: a mistyped horizon
    (``10**6``) is an error, not a MemoryError or a run of hours.
    """
    if isinstance(horizon, (bool, np.bool_)) or not isinstance(horizon, (int, np.integer)):
        raise InputError(
            f"expected horizon as an integer number of samples >= {n_x + 1}, got {horizon!r} "
            f"({type(horizon).__name__})"
        )
    if horizon < n_x + 1:
        raise InputError(
            f"expected horizon >= state dimension + 1 = {n_x + 1} samples (UFIR needs K = n_x = {n_x} "
            f"samples for its batch initialisation plus one), got {horizon}"
        )
    if horizon > MAX_HORIZON_SAMPLES:
        raise InputError(
            f"expected horizon <= {MAX_HORIZON_SAMPLES} samples (the FIR taps cost O(horizon²) "
            f"time and memory to build), got {horizon}"
        )
    return check_int(horizon, "horizon", n_x + 1)


def check_buffer_memory(batch_shape, n_values: int, what: str) -> None:
    """Refuse ring buffers of ``prod(batch_shape) * n_values`` floats larger than half the RAM."""
    n_bytes = 8 * int(np.prod(batch_shape, dtype=np.int64)) * int(n_values)
    try:
        avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX: no bound known
        return
    if n_bytes > avail // 2:
        raise InputError(
            f"{what}: the filter state for batch shape {tuple(batch_shape)} needs "
            f"{n_bytes / 2**30:.1f} GiB, more than half of this machine's "
            f"{avail / 2**30:.1f} GiB; use a shorter horizon or filter fewer series at once"
        )


@dataclass(frozen=True, eq=False, init=False)
class UFIRFilter(SingleModelFilter):
    r"""Iterative unbiased FIR filter with KF dead zone (paper A §3.3, Eqs. 24-28, Algorithm 3).

    Parameters
    ----------
    model : LinearGaussianModel
        ``F`` (must be invertible), ``H``, ``Q``, ``R``. Q and R enter only the error
        covariance, never the estimate (UFIR).
    horizon : int, default 20
        ``N`` (paper A ``N_FIR``, paper B ``L``), samples; ≥ ``n_x + 1`` (SPEC §6.4: 20 at 30 Hz).
    init : {"batch", "stored"}, default "batch"
        Stored as the attribute ``init_mode`` (``init()`` is the state factory). Initialisation of each horizon (SPEC §6.2-3): "batch" least squares over the first K
        valid samples (a true FIR); "stored" starts from the filter's own output at ``s``
        (paper B, Algorithm 1 lines 11-12), with ``G_s`` still from the batch form.

    Notes
    -----
    For ``k ≥ N − 1``, with ``m = k − N + 1`` and ``K = n_x`` (SPEC §6.3)::

        s = m + K − 1   (generalised: the K-th valid sample of the horizon)
        C = [H F^{-(s-i₁)}; …; H]   G_s = (CᵀC)⁻¹   x̂_s = G_s Cᵀ [z_{i₁}; …; z_s]
        P_s = G_s Cᵀ (I_K ⊗ R) C G_s
        for l = s+1 … k:
            x⁻ = F x ; P⁻ = F P Fᵀ + Q                                   (Eqs. 24-25)
            z_l missing: x, P, G = x⁻, P⁻, F G Fᵀ ; continue
            G = (HᵀH + (F G Fᵀ)⁻¹)⁻¹ ;  K = G Hᵀ                          (Eq. 26 corrected)
            x = x⁻ + K (z_l − H x⁻)                                       (Eq. 27)
            P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ                          (Eq. 28, Joseph)

    ``G`` is propagated in information form (``G⁻¹ = HᵀH + F⁻ᵀ G⁻¹ F⁻¹``). With batch init the
    output is the least-squares fit of the model through the valid samples of the horizon
    (for the constant-velocity model: per axis, the straight line's position and slope at the
    newest sample). For ``k < N − 1`` (dead zone), and when the horizon holds fewer than K valid
    samples or ``C`` is rank deficient, a KF step (SPEC §4.2, Joseph) is taken and
    ``fir_ready`` is False. A missing newest sample yields the FIR prediction through the
    horizon (``observed=False``).

    Speed: with ``model.axis_blocks`` and batch init, a complete horizon is evaluated as
    precomputed taps ``x̂_k = Σ_i W_i z_{m+i}`` with the data-independent ``P̂_k`` (exact,
    SPEC §6.3 "Fast exact forms"); horizons with missing samples use the per-axis 2-state
    iterative form; the dense ``n_x``-state iterative form is the reference.

    ``result.innovation`` is ``z_k − H F x̂_{k−1}``.

    Trusted fast path: ``_filter_unchecked(z, state)`` is :meth:`filter` without input checks,
    for kinefuse's own callers that validated ``z`` and pass back this filter's own state (see
    :mod:`kinefuse.filters._base`); the public ``step`` / ``filter`` always validate.

    Deviations from the paper
    -------------------------
    * Gain: ``G = (HᵀH + (F G Fᵀ)⁻¹)⁻¹``, ``K = G Hᵀ`` (Shmaliy & Simon 2013); paper A's Eq. 26
      ``(HHᵀ + (T H Tᵀ)⁻¹)⁻¹ H`` is dimensionally impossible (SPEC §6.2-1).
    * Horizon indices: Algorithm 3's ``m2 = M_FIR + N_FIR − 1`` is a typo for
      ``s = m1 + M_FIR − 1`` (SPEC §6.2-2); with a constant m2 the filter would not be FIR.
    * Batch initialisation of each horizon (``x̂_s``, ``G_s``, ``P_s`` from least squares),
      which the paper never initialises (SPEC §6.2-3); "stored" is paper B's variant.
    * Covariance by the Joseph form (Eq. 28) everywhere; Algorithm 3 line 10's short form is
      wrong for a non-Kalman gain (SPEC §6.2-4).
    * KF in the dead zone ``k < N − 1`` (paper B's choice; paper A starts at ``k = N − 1``;
      SPEC §6.2-5); generalised batch init and KF fallback for horizons with missing samples
      (SPEC §6.3).
    * The prediction drops the noise term (SPEC §6.2-6).
    """

    model: LinearGaussianModel
    horizon: int = 20
    init_mode: str = "batch"
    _arrays: dict = field(default=None, init=False, repr=False, compare=False)

    def __init__(
        self,
        model: LinearGaussianModel,
        horizon: int = 20,
        init: str = "batch",
        *,
        init_mode: str | None = None,
    ):
        # hand-written so that the constructor takes ``init=`` while ``init()`` stays the
        # state factory shared by all filters; the choice is stored as ``init_mode``
        # (also accepted as a keyword so that ``dataclasses.replace`` works)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "horizon", horizon)
        object.__setattr__(self, "init_mode", init if init_mode is None else init_mode)
        self.__post_init__()

    def __post_init__(self):
        check_model(self.model)
        object.__setattr__(self, "horizon", check_horizon(self.horizon, self.model.n_x))
        if not isinstance(self.init_mode, str) or self.init_mode not in _INITS:
            raise InputError(f"expected init one of {_INITS}, got {self.init_mode!r}")
        object.__setattr__(self, "_arrays", ufir_model_arrays(self.model, self.horizon))

    @property
    def _n_stored(self) -> int:
        return self.horizon if self.init_mode == "stored" else 0

    def init(self, batch_shape=(), mean=None, cov=None) -> UFIRState:
        """Initial state for ``batch_shape`` elements (empty horizon; see ``EMKalmanFilter.init``).

        Parameters
        ----------
        batch_shape : tuple of int
        mean : array_like, shape (..., n_x), optional
        cov : array_like, shape (..., n_x, n_x), optional
        """
        n_x, n_z, N = self.model.n_x, self.model.n_z, self.horizon
        ns = self._n_stored
        check_buffer_memory(
            check_batch_shape(batch_shape),
            N * n_z + (ns + 1) * n_x * (n_x + 1),
            f"UFIR horizon {N}",
        )
        g = make_initial_state(self.model, batch_shape, mean, cov)
        bs = g.initialized.shape
        return UFIRState(
            g.x,
            g.P,
            g.initialized,
            g.k,
            np.full((*bs, N, n_z), np.nan),
            np.full((*bs, ns, n_x), np.nan),
            np.full((*bs, ns, n_x, n_x), np.nan),
        )

    def filter(
        self, z, state: UFIRState | None = None, outputs=None
    ) -> tuple[UFIRState, UFIRResult]:
        """Filter a series.

        Parameters
        ----------
        z : array_like of float, shape (..., T, n_z)
            Position measurements, m; NaN rows are missing.
        state : UFIRState, optional
            State to resume from (default: fresh state for ``z.shape[:-2]``).
        outputs : tuple of str, optional
            Fields to compute (see :meth:`KalmanFilter.filter
            <kinefuse.filters.KalmanFilter.filter>`); default all. The constant-velocity fast
            path is O(1) per step for any horizon, its covariance included (a closed form on
            horizons with missing samples, :mod:`kinefuse.filters._kernels_ufir_cov`); leaving
            out ``"cov"`` skips that part.

        Returns
        -------
        state : UFIRState
        result : UFIRResult
            ``mean``, ``cov``, ``position``, ``observed``, ``innovation``, ``fir_ready (..., T)``.

        Warns
        -----
        UserWarning
            A fresh state and a horizon longer than the series: the FIR never takes over and
            every output is the KF dead zone.
        """
        out = run_filter(self, z, state, outputs=check_outputs(outputs))
        T = np.shape(z)[-2]  # z passed run_filter's checks: (..., T, n_z)
        if state is None and 0 < T < self.horizon:
            warnings.warn(
                f"UFIR horizon {self.horizon} samples is longer than the series ({T} samples): "
                "the FIR never fills and every output comes from the KF dead zone",
                UserWarning,
                stacklevel=2,
            )
        return out

    def _check_state(self, state, bs):
        n_x, n_z, N, ns = self.model.n_x, self.model.n_z, self.horizon, self._n_stored
        check_state(
            state,
            UFIRState,
            bs,
            {
                "x": (n_x,),
                "P": (n_x, n_x),
                "z_buf": (N, n_z),
                "x_buf": (ns, n_x),
                "P_buf": (ns, n_x, n_x),
            },
        )

    def _run(self, z: np.ndarray, state: UFIRState, fast: bool = True, outputs=None):
        a = self._arrays
        if fast and self._cv_route:
            if type(state) is _SharedBlocksState:  # the route's own output: shared blocks
                return self._run_cv(z, state, outputs)
            P = np.asarray(state.P).reshape(-1, self.model.n_x, self.model.n_x)
            if state_blocks_shared(P, np.asarray(state.initialized).reshape(-1)):
                return self._run_cv(z, state, outputs)
        N = self.horizon
        names = ("x", "P", "initialized", "z_buf", "x_buf", "P_buf")
        bs, zf, x, P, init, zring, xring, Pring = flat_run(z, state, names)
        B, T, n_z = zf.shape
        o_mean, o_cov, o_obs, o_nu = run_outputs(B, T, self.model.n_x, n_z)
        o_ready = np.empty((B, T), bool)
        n_fail = ufir_run(
            zf, x, P, init, zring, xring, Pring, int(state.k), N, a["K"], self.init_mode == "stored", bool(fast),
            bool(self.model.axis_blocks), a["W"], a["P_full"], a["F"], a["Finv"], a["H"], a["Q"], a["R"],
            a["Fa"], a["Finva"], a["Ha"], a["Qa"], a["Ra"], a["Hpinv"], a["P0"],
            o_mean, o_cov, o_obs, o_nu, o_ready,
        )  # fmt: skip
        _warn_failed(n_fail)
        new_state = UFIRState(
            *unflat(bs, x, P, init), int(state.k) + T, *unflat(bs, zring, xring, Pring)
        )
        res = UFIRResult(
            **run_result(bs, self.model.H, o_mean, o_cov, o_obs, o_nu),
            fir_ready=o_ready.reshape(*bs, T),
        )
        return new_state, res

    def _run_cv(self, z: np.ndarray, state: UFIRState, outputs):
        """The O(1)-per-step constant-velocity route (:func:`._kernels_ufir_run.ufir_run_cv`)."""
        w = check_outputs(None) if outputs is None else outputs
        n_x = self.model.n_x
        bs, zf, x, P, init, zring = flat_run(z, state, ("x", "P", "initialized", "z_buf"))
        T, n_z = zf.shape[1:]
        o_mean, o_covb, o_obs, o_nu, o_ready = self._run_cv_inplace(
            zf, x, P, init, zring, int(state.k), "cov" in w
        )
        ns = self._n_stored
        new_state = _SharedBlocksState(
            *unflat(bs, x, P, init),
            int(state.k) + T,
            *unflat(bs, zring),
            np.asarray(state.x_buf).reshape(*bs, ns, n_x),
            np.asarray(state.P_buf).reshape(*bs, ns, n_x, n_x),
        )
        mean = o_mean.reshape(*bs, T, n_x)
        cov_blocks = None
        if "cov" in w:
            cov_blocks = np.broadcast_to(o_covb.reshape(*bs, T, 1, 3), (*bs, T, n_z, 3))
        res = UFIRResult(
            mean=mean if "mean" in w else None,
            cov=None,
            position=np.ascontiguousarray(mean[..., 0::2]) if "position" in w else None,
            observed=o_obs.reshape(*bs, T) if "observed" in w else None,
            innovation=o_nu.reshape(*bs, T, n_z) if "innovation" in w else None,
            cov_blocks=cov_blocks,
            fir_ready=o_ready.reshape(*bs, T),
        )
        return new_state, res

    def _run_cv_inplace(self, z, x, P, init, zring, k: int, want_cov: bool = True):
        """The kernel call of :meth:`_run_cv` on flat arrays updated in place.

        ``z (B, T, n_z)`` C-contiguous float64 without ±inf; ``x (B, n_x)``, ``P (B, n_x, n_x)``,
        ``init (B,)`` and ``zring (B, N, n_z)`` C-contiguous, every initialised ``P`` holding one
        2x2 block on every axis (a fresh state, or this route's output); ``k`` the time index of
        ``z[:, 0]``. For owners of such arrays that step them without copies
        (:class:`kinefuse.pipelines.paper_b.PaperBCore`); the filter's ``filter``/``step`` copy
        the state first.

        Returns
        -------
        mean (B, T, n_x), cov_blocks (B, T, 1, 3) (empty without ``want_cov``), observed (B, T),
        innovation (B, T, n_z), fir_ready (B, T)
        """
        B, T, n_z = z.shape
        o_mean = np.empty((B, T, self.model.n_x))
        o_covb = np.empty((B, T, 1, 3)) if want_cov else _NO_COVB
        o_obs = np.empty((B, T), bool)
        o_nu = np.empty((B, T, n_z))
        o_ready = np.empty((B, T), bool)
        n_fail = ufir_run_cv(
            z, x, P, init, zring, k, *self._arrays["cv"], o_mean, o_covb, o_obs, o_nu,
            o_ready,
        )  # fmt: skip
        if n_fail:
            _warn_failed(n_fail, 5)
        return o_mean, o_covb, o_obs, o_nu, o_ready

    @property
    def _cv_route(self) -> bool:
        """True when :meth:`_run` takes the constant-velocity route for shared-block states."""
        return "cv" in self._arrays and self.init_mode == "batch"
