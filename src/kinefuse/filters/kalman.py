"""Linear Kalman filter (paper A: Sun 2024, Eqs. 5-9 and Algorithm 1; SPEC §4).

Layer 2 of the three-layer filter API (see STYLE.md): a frozen configuration object with
``init`` / ``step`` / ``filter``. The compiled loops live in :mod:`._kernels_blocks` (per-axis
blocks, the fast form) and :mod:`._kernels_axis` (the dense reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.filters._base import (
    FilterResult,
    GaussianState,
    check_measurements,
    check_not_all_missing,
    check_outputs,
    check_state_batch,
    check_step_measurement,
    initial_covariance,
    make_initial_state,
    warn_regularised,
)
from kinefuse.filters._kernels_axis import (
    axis_block_params,
    kf_filter_dense,
    pack_axis_params,
    state_blocks_shared,
    state_is_block_diagonal,
)
from kinefuse.filters._kernels_blocks import kf_filter_blocks, kf_step_blocks
from kinefuse.models import LinearGaussianModel

__all__ = ["KalmanFilter", "check_gaussian_state"]


class _AxisState(GaussianState):
    """A :class:`GaussianState` produced by the per-axis kernels of this module: finite,
    block-diagonal per axis, float64, C-contiguous. ``step`` trusts it without re-validating
    (the online hot path); any other state is validated first. ``_replace`` returns a plain
    ``GaussianState`` (a changed state is validated again)."""

    __slots__ = ()

    def _replace(self, **kwargs) -> GaussianState:
        return GaussianState(*self)._replace(**kwargs)


_METHODS = ("auto", "axis", "dense")
_F64 = np.dtype(np.float64)
_empty = np.empty
_BOOL = np.dtype(np.bool_)
_new_tuple = tuple.__new__  # _AxisState(...) without the NamedTuple __new__ (hot path)
_fast_result = FilterResult.fast.__func__  # FilterResult.fast without the classmethod binding

_step_entry = []  # kf_step_blocks' compiled entry point, once it is compiled (see _step_kernel)


def _step_kernel(args):
    """:func:`kf_step_blocks`, or its compiled entry point once numba has compiled it.

    An online step's arguments always have the same types (C-contiguous float64 / bool arrays
    of fixed ranks, a bool): the state's from the kernels' own outputs, the measurement checked
    by :meth:`KalmanFilter.step`'s hot path, the outputs allocated there. Calling the compiled
    function's entry point skips numba's per-call type dispatch (about 0.5 µs of a 5 µs step);
    the first call, and every call with kernels interpreted, goes through the dispatcher.
    """
    if _step_entry:
        return _step_entry[0]
    overloads = getattr(kf_step_blocks, "overloads", None)
    if overloads is not None:  # compiled (not interpreted): take the entry once it exists
        cres = overloads.get(tuple(kf_step_blocks.typeof_pyval(a) for a in args))
        if cres is not None:
            _step_entry.append(cres.entry_point)
    return kf_step_blocks


# Zero-length stand-ins for outputs a caller does not want (same dtypes/ranks: one compiled
# specialisation of the kernel serves every choice of outputs).
_NONE2 = np.empty((0, 0))
_NONE3 = np.empty((0, 0, 0))
_NONE4 = np.empty((0, 0, 0, 0))
_NONE_BOOL = np.empty((0, 0), dtype=bool)


def _unflatten_step(state, bshape, x_new, P_new, init_new, mean, covb, pos, obs, nu, dist):
    """:meth:`KalmanFilter.step`'s flat ``(B, ...)`` outputs reshaped to the batch shape."""
    n_x, n_z = x_new.shape[1], pos.shape[1]
    new_state = _new_tuple(_AxisState, (x_new.reshape(*bshape, n_x),
                           P_new.reshape(*bshape, n_x, n_x), init_new.reshape(bshape),
                           state.k + 1))  # fmt: skip
    out = _fast_result(
        FilterResult,
        mean.reshape(*bshape, n_x),
        pos.reshape(*bshape, n_z),
        obs.reshape(bshape),
        nu.reshape(*bshape, n_z),
        dist.reshape(bshape),
        covb.reshape(*bshape, *covb.shape[1:]),
    )
    return new_state, out


def check_gaussian_state(state, n_x: int) -> GaussianState:
    """Validate a :class:`GaussianState` given to ``step`` / ``filter``; return it as float64.

    Raises
    ------
    ValueError
        If ``state`` is not a GaussianState or its arrays have inconsistent shapes or dtypes.
    """
    if not isinstance(state, GaussianState):
        raise InputError(
            f"expected state as a GaussianState (from KalmanFilter.init or a previous step), "
            f"got {type(state).__name__}"
        )
    init = np.asarray(state.initialized)
    if init.dtype != np.bool_:
        raise InputError(f"expected state.initialized as a bool array, got dtype {init.dtype}")
    batch = init.shape
    x = np.asarray(state.x)
    P = np.asarray(state.P)
    if x.shape != (*batch, n_x):
        raise InputError(f"expected state.x with shape {(*batch, n_x)}, got {x.shape}")
    if P.shape != (*batch, n_x, n_x):
        raise InputError(f"expected state.P with shape {(*batch, n_x, n_x)}, got {P.shape}")
    for name, arr in (("state.x", x), ("state.P", P)):
        if arr.dtype.kind != "f":
            raise InputError(f"expected {name} as a float array, got dtype {arr.dtype}")
    if init.all():
        finite = np.isfinite(x).all() and np.isfinite(P).all()
    else:
        finite = np.isfinite(x[init]).all() and np.isfinite(P[init]).all()
    if not finite:
        raise InputError(
            "expected finite state.x and state.P for initialised elements, got NaN/inf"
        )
    k = state.k
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise InputError(f"expected state.k as a non-negative int, got {k!r}")
    return GaussianState(x, P, init, int(k))


@dataclass(frozen=True, eq=False)
class KalmanFilter:
    """Linear Kalman filter for a :class:`~kinefuse.models.LinearGaussianModel`, batched.

    Implements paper A (Sun 2024) Eqs. 5-9 / Algorithm 1 in the corrected form of SPEC §4, the
    "KF" baseline of both papers and the dead-zone filter of paper B's Algorithm 1 (lines 3-9).

    Parameters
    ----------
    model : LinearGaussianModel
        ``F (n_x, n_x)``, ``H (n_z, n_x)``, ``Q``, ``R``; e.g.
        :func:`kinefuse.models.constant_velocity` (positions in m, velocities in m/s).
    method : {"auto", "axis", "dense"}
        Compiled loop to use. ``"auto"`` takes the exact per-axis decoupling (SPEC §1: one
        2-state problem per axis, scalar arithmetic) when ``model.axis_blocks`` is True and the
        state covariance is block-diagonal per axis, else the dense reference. ``"axis"``
        requires an axis-blocked model; ``"dense"`` always uses the reference form.

    Notes
    -----
    Per step ``k`` (one time slice ``z_k (..., n_z)``, m)::

        x⁻ = F x_{k-1}                          (Eq. 5, corrected)
        P⁻ = F P_{k-1} Fᵀ + Q                   (Eq. 6, corrected)
        ν  = z_k − H x⁻ ;  S = H P⁻ Hᵀ + R
        K  = P⁻ Hᵀ S⁻¹   (Cholesky solve)      (Eq. 7)
        x_k = x⁻ + K ν                          (Eq. 8)
        P_k = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ  (Eq. 9, Joseph)

    A measurement row containing any NaN is missing: predict only, ``observed = False``,
    ``innovation`` and ``distance`` NaN. ``distance`` is the NIS ``νᵀ S⁻¹ ν`` (χ²(n_z) under
    the model). If ``S`` cannot be factorised even after the SPEC §13 regularisation the update
    is skipped and the sample reported as not observed.

    Initialisation: unless a state is given, an element is uninitialised (outputs NaN) until its
    first valid measurement row ``z``; there ``x = H⁺ z`` (positions = z, velocities = 0) and
    ``P = P₀ =`` :func:`~kinefuse.filters._base.initial_covariance` (R on positions,
    1 (m/s)² on velocities); that sample is reported ``observed = True`` with NaN innovation and
    distance (no prior existed). A state given through ``init(mean=..., cov=...)`` is the
    posterior *before* the first sample: the first step predicts and then updates.

    ``filter`` runs the same compiled loop as ``step``, so ``filter`` equals repeated ``step``
    and split-and-resume equals one run, to the bit.

    Trusted fast path: a state returned by ``step`` / ``filter`` on the per-axis path is marked
    as the filter's own (a private ``GaussianState`` subclass); ``step`` validates any other
    state, and takes a marked one with a float64, C-contiguous ``z`` of the right shape straight
    to one compiled call (±inf still raises). ``_filter_unchecked(z, state)`` is :meth:`filter`
    without input checks, for kinefuse's own callers that validated ``z`` and pass back this
    filter's own state (see :mod:`kinefuse.filters._base`).

    Deviations from the paper
    -------------------------
    * Eq. 5 / Algorithm 1 line 3 add the noise ``w`` to the prediction; the prediction is
      ``F x`` (SPEC §4.1).
    * Algorithm 1 line 4 uses ``P_k``; the recursion uses ``P_{k-1}`` (SPEC §4.1).
    * Algorithm 1 line 7 uses ``(I − K H) P⁻``; the Joseph form of Eq. 9 is used (SPEC §4.1).
    * The papers do not specify the initialisation; SPEC §4.2 / §12.2 [J] is used (above).
    * Missing measurements (NaN) are not treated by the papers; SPEC §1 / §13: predict only.
    * SPEC §13's optional divergence re-initialisation is not implemented.

    Examples
    --------
    >>> import numpy as np
    >>> from kinefuse.models import constant_velocity
    >>> kf = KalmanFilter(constant_velocity(1 / 30, q=1.0, r=0.01))
    >>> z = np.zeros((8, 100, 3))                       # 8 joints, 100 samples, ENU m
    >>> state, res = kf.filter(z)
    >>> res.position.shape, res.cov.shape
    ((8, 100, 3), (8, 100, 6, 6))
    """

    model: LinearGaussianModel
    method: str = "auto"
    _P0: np.ndarray = field(init=False, repr=False, compare=False)
    _Hpinv: np.ndarray = field(init=False, repr=False, compare=False)
    _blocks: tuple | None = field(init=False, repr=False, compare=False)
    _packed: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _step_plans: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if not isinstance(self.model, LinearGaussianModel):
            raise InputError(
                f"expected model as a LinearGaussianModel (e.g. kinefuse.models.constant_velocity(...)), "
                f"got {type(self.model).__name__}"
            )
        if self.method not in _METHODS:
            raise InputError(f"expected method in {_METHODS}, got {self.method!r}")
        if self.method == "axis" and not self.model.axis_blocks:
            raise InputError(
                "expected an axis-blocked model for method='axis' (F, Q, H, R block-diagonal per "
                "axis), got a model with cross-axis terms; use method='auto' or 'dense'"
            )
        m = self.model
        P0 = initial_covariance(m)
        object.__setattr__(self, "_P0", P0)
        object.__setattr__(self, "_Hpinv", np.ascontiguousarray(np.linalg.pinv(m.H)))
        if m.axis_blocks and self.method != "dense":
            # the 2x2 blocks (read by the streaming kernels) and their packed form (this module)
            blocks = tuple(
                np.ascontiguousarray(b) for b in axis_block_params(m.F, m.Q, m.H, m.R, P0)
            )
            object.__setattr__(self, "_packed", pack_axis_params(m.F, m.Q, m.H, m.R, P0))
        else:
            blocks = None
        object.__setattr__(self, "_blocks", blocks)

    # ---------------------------------------------------------------------------------------
    @property
    def n_x(self) -> int:
        """State dimension."""
        return self.model.n_x

    @property
    def n_z(self) -> int:
        """Measurement dimension."""
        return self.model.n_z

    def init(self, batch_shape=(), mean=None, cov=None) -> GaussianState:
        """Initial state for a batch of independent elements (joints, trials).

        Parameters
        ----------
        batch_shape : tuple of int
            Leading axes of the measurements, e.g. ``(n_joints,)``; ``()`` for one series.
        mean : array_like, shape (..., n_x), optional
            Posterior mean before the first sample (m, m/s), broadcast to ``batch_shape``.
            Without it each element initialises itself from its first valid measurement.
        cov : array_like, shape (..., n_x, n_x), optional
            Posterior covariance before the first sample; defaults to ``P₀``.

        Returns
        -------
        GaussianState
        """
        return make_initial_state(self.model, batch_shape, mean, cov)

    def step(self, state: GaussianState, z) -> tuple[GaussianState, FilterResult]:
        """One filter step on a time slice (online use).

        Parameters
        ----------
        state : GaussianState
            From :meth:`init` or the previous ``step`` / ``filter``; batch shape ``(...)``.
        z : array_like of float, shape (..., n_z)
            Measurement at this step, m; a row with NaN is missing (predict only).

        Returns
        -------
        state : GaussianState
            Posterior after this step (the input state is not modified).
        out : FilterResult
            The same fields as :meth:`filter` without the time axis: ``mean (..., n_x)``,
            ``cov (..., n_x, n_x)``, ``position (..., n_z)``, ``observed (...)``,
            ``innovation (..., n_z)``, ``distance (...)``.
        """
        if type(state) is _AxisState and self._blocks is not None:
            # Hot path (a trusted per-axis state): one compiled call, no re-validation of the
            # state; ``z`` is checked by type/shape attributes (anything unusual takes the
            # validated path below) and for ±inf by the kernel.
            x = state.x
            zshape, bshape, sx, sP, sb, sc, sz = self._step_plans.get(x.shape) or self._step_plan(
                x.shape
            )
            if (
                type(z) is np.ndarray
                and z.shape == zshape
                and z.dtype is _F64
                and z.flags.c_contiguous
            ):
                x_new, P_new, init_new = _empty(sx), _empty(sP), _empty(sb, _BOOL)
                mean, covb, pos = _empty(sx), _empty(sc), _empty(sz)
                obs, nu, dist = _empty(sb, _BOOL), _empty(sz), _empty(sb)
                if bshape is None:
                    args = (*self._packed, z, x, state.P, state.initialized,
                            x_new, P_new, init_new, mean, covb, pos, obs, nu, dist)  # fmt: skip
                else:
                    args = (*self._packed, z.reshape(sz), x.reshape(sx), state.P.reshape(sP),
                            state.initialized.reshape(sb), x_new, P_new, init_new, mean, covb,
                            pos, obs, nu, dist)  # fmt: skip
                if (_step_entry[0] if _step_entry else _step_kernel(args))(*args):
                    raise InputError("expected z finite or NaN (missing), got ±inf")
                if bshape is not None:
                    return _unflatten_step(state, bshape, *args[-9:])
                return (_new_tuple(_AxisState, (x_new, P_new, init_new, state.k + 1)),
                        _fast_result(FilterResult, mean, pos, obs, nu, dist, covb))  # fmt: skip
        st = check_gaussian_state(state, self.n_x)
        zs = check_step_measurement(z, self.n_z, st.initialized.shape)
        new_state, res = self._run(zs[..., None, :], st)
        blocks = res.cov_blocks
        out = FilterResult(
            mean=res.mean[..., 0, :],
            cov=None if blocks is not None else res.cov[..., 0, :, :],
            position=res.position[..., 0, :],
            observed=res.observed[..., 0],
            innovation=res.innovation[..., 0, :],
            distance=res.distance[..., 0],
            cov_blocks=None if blocks is None else blocks[..., 0, :, :],
        )
        return new_state, out

    def _step_plan(self, x_shape: tuple) -> tuple:
        """What the hot path of :meth:`step` needs for states of shape ``x_shape`` (cached per
        shape): the measurement shape, the batch shape to restore (None when already flat) and
        the flat shapes ``(B, n_x)``, ``(B, n_x, n_x)``, ``(B,)``, ``(B, n_a, 3)``, ``(B, n_z)``."""
        bshape, n_x = x_shape[:-1], x_shape[-1]
        B, n_z = math.prod(bshape), self.model.n_z
        plan = ((*bshape, n_z), None if len(bshape) == 1 else bshape, (B, n_x), (B, n_x, n_x),
                (B,), (B, self._packed[0].shape[0], 3), (B, n_z))  # fmt: skip
        self._step_plans[x_shape] = plan
        return plan

    def filter(
        self, z, state: GaussianState | None = None, outputs=None
    ) -> tuple[GaussianState, FilterResult]:
        """Filter whole series (batch use); equals repeated :meth:`step`.

        Parameters
        ----------
        z : array_like of float, shape (..., T, n_z)
            Measurements, m; leading axes are batch (joints, trials); NaN rows are missing.
        state : GaussianState, optional
            State to continue from (batch shape ``z.shape[:-2]``), e.g. the state returned by
            a previous call (split-and-resume). Without it, :meth:`init` with that batch shape;
            then every element needs at least one valid row.
        outputs : tuple of str, optional
            The result fields to compute, from ``("mean", "cov", "position", "observed",
            "innovation", "distance")``; the others are None and never written (memory
            traffic is most of a KF's cost). Default: all.

        Returns
        -------
        state : GaussianState
            Posterior after the last sample.
        result : FilterResult
            ``mean (..., T, n_x)``, ``cov (..., T, n_x, n_x)``, ``position (..., T, n_z)``,
            ``observed (..., T)``, ``innovation (..., T, n_z)``, ``distance (..., T)`` (NIS).
            On the per-axis path the covariance is stored as ``cov_blocks (..., T, n_a, 3)``
            (see :class:`~kinefuse.filters.FilterResult`) and ``cov`` expands it on access.

        Raises
        ------
        ValueError
            Wrong shape/dtype, ±inf, a batch-shape mismatch with ``state``, or (without
            ``state``) an element whose series is all NaN.
        """
        wanted = check_outputs(outputs)
        zz = check_measurements(z, self.n_z, check_inf=False)  # ±inf: found by the kernel
        if state is None:
            st = self.init(zz.shape[:-2])
        else:
            st = check_gaussian_state(state, self.n_x)
            check_state_batch(st, zz)
        new_state, result = self._run(zz, st, wanted)
        if state is None and not np.all(new_state.initialized):
            check_not_all_missing(zz, None)  # raises, naming the first all-NaN element
        return new_state, result

    def _filter_unchecked(self, z: np.ndarray, state: GaussianState):
        """:meth:`filter` on the trusted fast path: no checks (contract: :mod:`._base`)."""
        return self._run(z, state)

    # ---------------------------------------------------------------------------------------
    def _use_axis(self, P: np.ndarray, init: np.ndarray) -> bool:
        """Axis path if the model is axis-blocked and every initialised ``P (B, n_x, n_x)`` is too."""
        if self._blocks is None:
            return False
        ok = state_is_block_diagonal(P, init)
        if not ok and self.method == "axis":
            raise InputError(
                "expected a state covariance block-diagonal per axis for method='axis', "
                "got cross-axis entries; use method='auto' or 'dense'"
            )
        return ok

    def _run(
        self, z: np.ndarray, st: GaussianState, wanted: frozenset | None = None
    ) -> tuple[GaussianState, FilterResult]:
        """Run the compiled loop on validated ``z (..., T, n_z)`` from validated ``st``."""
        m = self.model
        n_x, n_z = m.n_x, m.n_z
        batch = z.shape[:-2]
        T = z.shape[-2]
        z3 = np.ascontiguousarray(z.reshape(-1, T, n_z))
        B = z3.shape[0]
        x = np.array(st.x, dtype=np.float64, order="C").reshape(B, n_x)
        P = np.array(st.P, dtype=np.float64, order="C").reshape(B, n_x, n_x)
        init = np.array(st.initialized, dtype=bool).reshape(B)
        w = check_outputs(None) if wanted is None else wanted
        use_axis = self._use_axis(P, init)
        mean = np.empty((B, T, n_x)) if "mean" in w else _NONE3
        pos = np.empty((B, T, n_z)) if "position" in w else _NONE3
        obs = np.empty((B, T), dtype=bool) if "observed" in w else _NONE_BOOL
        nu = np.empty((B, T, n_z)) if "innovation" in w else _NONE3
        dist = np.empty((B, T)) if "distance" in w else _NONE2
        cov = cov_blocks = None
        if use_axis:
            par, p0, shared = self._packed
            if shared and not state_blocks_shared(P, init):
                shared = False
            n_a = par.shape[0]
            p0c = p0[:1] if shared else p0
            covb = np.empty((B, T, p0c.shape[0], 3)) if "cov" in w else _NONE4
            if kf_filter_blocks(z3, x, P, init, par, p0c, mean, covb, pos, obs, nu, dist):
                raise InputError("expected z finite or NaN (missing), got ±inf")
            if "cov" in w:
                covb = covb.reshape(*batch, T, p0c.shape[0], 3)
                if shared:
                    covb = np.broadcast_to(covb, (*batch, T, n_a, 3))
                cov_blocks = covb
        else:
            if np.isinf(z3).any():
                raise InputError("expected z finite or NaN (missing), got ±inf")
            mean_d = mean if "mean" in w else np.empty((B, T, n_x))
            pos_d = pos if "position" in w else np.empty((B, T, n_z))
            obs_d = obs if "observed" in w else np.empty((B, T), dtype=bool)
            nu_d = nu if "innovation" in w else np.empty((B, T, n_z))
            dist_d = dist if "distance" in w else np.empty((B, T))
            cov_d = np.empty((B, T, n_x, n_x))
            n_reg = kf_filter_dense(
                z3, x, P, init, m.F, m.Q, m.H, m.R, self._P0, self._Hpinv,
                mean_d, cov_d, pos_d, obs_d, nu_d, dist_d,
            )  # fmt: skip
            warn_regularised(n_reg, "KalmanFilter")
            mean, pos, obs, nu, dist = mean_d, pos_d, obs_d, nu_d, dist_d
            if "cov" in w:
                cov = cov_d.reshape(*batch, T, n_x, n_x)
        state_cls = _AxisState if use_axis else GaussianState
        new_state = state_cls(
            x.reshape(*batch, n_x), P.reshape(*batch, n_x, n_x), init.reshape(batch), st.k + T
        )

        def shaped(name, arr, tail):
            return arr.reshape(*batch, T, *tail) if name in w else None

        result = FilterResult(
            mean=shaped("mean", mean, (n_x,)),
            cov=cov,
            position=shaped("position", pos, (n_z,)),
            observed=shaped("observed", obs, ()),
            innovation=shaped("innovation", nu, (n_z,)),
            distance=shaped("distance", dist, ()),
            cov_blocks=cov_blocks,
        )
        return new_state, result
