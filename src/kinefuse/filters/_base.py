"""Shared pieces of the filter objects: result container, state container, input checks.

No numerics here beyond initialisation; kernels live in ``_kernels*.py``.

Trusted fast path
-----------------
The public ``step`` / ``filter`` of every filter validate their inputs (shapes, dtypes, ±inf,
the state's type and shapes): tens to hundreds of µs a call, more than the compiled step itself
on one frame of a few joints. Code inside kinefuse that has validated its data already and
passes back a state the filter returned itself (the streaming processors,
:class:`kinefuse.pipelines.paper_b.PaperBCore`) calls ``flt._filter_unchecked(z, state)``
instead: the compiled loop of ``filter`` (the same numbers) without any check. Its contract:
``z`` is a float64 array ``(..., T, n_z)`` (the IMM: ``(..., T, M, n_z)``) without ±inf, and
``state`` comes from this filter's ``init`` / ``step`` / ``filter`` / ``_filter_unchecked``
with ``z``'s batch shape. Anything else is undefined (no error; wrong numbers or an error inside
a kernel). Users call ``step`` / ``filter``, which stay checked.

In place: an owner that keeps a state to itself and steps it every frame may skip even the
state copy. ``UFIRFilter._run_cv_inplace`` (constant-velocity route), ``IMM._run_inplace`` and
``IntegratedFilter._run_inplace`` run the same compiled loop on the state's own flat arrays
``(B, ...)``, updated in place, and return only the outputs; the owner
(:class:`kinefuse.pipelines.paper_b.PaperBCore`,
:class:`kinefuse.streaming.processors.IntegratedProcessor`) keeps the time index and never
hands those arrays to anyone else (a checkpoint is a deep copy).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from kinefuse._validation import as_float_array, check_psd_stack
from kinefuse.exceptions import InputError, NumericalWarning

#: Initial velocity standard deviation, m/s (SPEC §4.2 and §12.2).
SIGMA_V0_M_S = 1.0


def warn_regularised(n_steps: int, what: str, matrix: str = "innovation covariance S") -> None:
    """ONE :class:`NumericalWarning` per call when a kernel had to regularise ``matrix``.

    ``n_steps`` is the count a kernel returns (steps whose Cholesky factorisation needed the
    SPEC §13 ladder ``+ ε·tr/n·I``); nothing happens when it is 0.
    """
    n = int(n_steps)
    if n:
        warnings.warn(
            f"{what}: {matrix} was not positive definite on {n} step(s) and was regularised "
            "(+ eps*tr/n*I, SPEC §13)",
            NumericalWarning,
            stacklevel=3,
        )


class GaussianState(NamedTuple):
    """Gaussian filter state, batched over leading axes.

    Attributes
    ----------
    x : ndarray, shape (..., n_x)
        Posterior mean (NaN until initialised).
    P : ndarray, shape (..., n_x, n_x)
        Posterior covariance (NaN until initialised).
    initialized : ndarray of bool, shape (...)
        False until the element has seen its first valid measurement (or was given a state).
    k : int
        Number of steps taken (time index of the next step).
    """

    x: np.ndarray
    P: np.ndarray
    initialized: np.ndarray
    k: int


@dataclass(frozen=True, eq=False)
class FilterResult:
    """Per-sample output of a filter run.

    Attributes
    ----------
    mean : ndarray, shape (..., T, n_x)
        Posterior state means.
    cov : ndarray, shape (..., T, n_x, n_x)
        Posterior state covariances.
    position : ndarray, shape (..., T, n_z)
        ``H @ mean``: the filtered positions, m.
    observed : ndarray of bool, shape (..., T)
        True where a valid measurement was used (False: predict only).
    innovation : ndarray, shape (..., T, n_z) or None
        ``z - H x⁻``; NaN where not observed.
    distance : ndarray, shape (..., T) or None
        Mahalanobis distance of the innovation (filter-specific: NIS ``νᵀS⁻¹ν`` for the KF,
        paper A's D₁ ``νᵀR⁻¹ν`` for the integrated filter); NaN where not observed.
    mode : ndarray of int8, shape (..., T) or None
        Active branch per sample (see :data:`kinefuse.conventions.MODE_NAMES`).
    cov_blocks : ndarray, shape (..., T, n_a, 3) or None
        Compact covariance of an axis-blocked model (:class:`~kinefuse.filters.KalmanFilter`,
        :func:`~kinefuse.filters.rts_smooth`): for axis ``a``, ``[p00, p01, p11]`` of the 2x2
        covariance of state components ``(2a, 2a+1)`` (position, velocity); every other entry
        of the full covariance is zero. When all axes share one model block the array is a
        read-only broadcast view of a single stored block. ``cov`` is then computed from it on
        first access (:func:`expand_cov_blocks`) and cached; the position variances are
        ``cov_blocks[..., 0]`` without expanding.

    Any field may be None when the caller asked a filter not to compute it (``outputs=``).
    """

    mean: np.ndarray | None
    cov: np.ndarray | None
    position: np.ndarray | None
    observed: np.ndarray | None
    innovation: np.ndarray | None = None
    distance: np.ndarray | None = None
    mode: np.ndarray | None = None
    cov_blocks: np.ndarray | None = None


def _get_cov(self):
    cov = self.__dict__.get("_cov")
    if cov is None and self.__dict__.get("cov_blocks") is not None:
        cov = expand_cov_blocks(self.cov_blocks)
        self.__dict__["_cov"] = cov
    return cov


def _set_cov(self, value):  # dataclass __init__ assigns through this (frozen: only there)
    self.__dict__["_cov"] = value


def _fast(cls, mean, position, observed, innovation, distance, cov_blocks):
    """Internal constructor of the online hot path (the dataclass ``__init__`` costs ~1 µs)."""
    r = object.__new__(cls)
    d = r.__dict__
    d["mean"] = mean
    d["_cov"] = None
    d["position"] = position
    d["observed"] = observed
    d["innovation"] = innovation
    d["distance"] = distance
    d["mode"] = None
    d["cov_blocks"] = cov_blocks
    return r


FilterResult.fast = classmethod(_fast)

# ``cov`` as a property: stored when given, else expanded lazily from ``cov_blocks``.
FilterResult.cov = property(_get_cov, _set_cov, doc="Full covariances, shape (..., T, n_x, n_x).")

#: Output names the filters accept in ``outputs=`` (the fields of :class:`FilterResult`).
OUTPUT_NAMES = ("mean", "cov", "position", "observed", "innovation", "distance")


def check_outputs(outputs) -> frozenset:
    """Validate ``outputs=`` (None = all) and return the set of wanted output names."""
    if outputs is None:
        return frozenset(OUTPUT_NAMES)
    if isinstance(outputs, str):
        outputs = (outputs,)
    try:
        wanted = frozenset(outputs)
    except TypeError:
        raise InputError(
            f"expected outputs as a tuple of names from {OUTPUT_NAMES}, got {outputs!r}"
        ) from None
    bad = sorted(str(w) for w in wanted - frozenset(OUTPUT_NAMES))
    if bad:
        raise InputError(f"expected outputs from {OUTPUT_NAMES}, got unknown {bad}")
    return wanted


def expand_cov_blocks(cov_blocks: np.ndarray) -> np.ndarray:
    """Full covariances ``(..., n_x, n_x)`` (``n_x = 2 n_a``) from the per-axis block layout
    ``(..., n_a, 3)`` of :attr:`FilterResult.cov_blocks`; entries outside the blocks are 0
    (NaN where a block is NaN: an element without a state yet)."""
    cb = np.asarray(cov_blocks)
    lead, n_a = cb.shape[:-2], cb.shape[-2]
    n_x = 2 * n_a
    if n_a > 1 and cb.strides[-2] == 0:  # one block broadcast to every axis: read it once
        return expand_shared_block(cb[..., 0, :], n_a)
    dst, src = _block_index(n_a)
    c2 = cb.reshape(math.prod(lead), 3 * n_a)
    full = np.zeros((c2.shape[0], n_x * n_x))
    full[:, dst] = c2[:, src]  # one gather/scatter: this runs on online steps
    unknown = np.isnan(c2).any(axis=1)
    if unknown.any():
        full[unknown] = np.nan
    return full.reshape(*lead, n_x, n_x)


def expand_shared_block(block: np.ndarray, n_a: int) -> np.ndarray:
    """Full covariances ``(..., 2 n_a, 2 n_a)`` with the one block ``(..., 3)`` ``[p00, p01,
    p11]`` on every axis (:func:`expand_cov_blocks` of a block broadcast to all axes)."""
    lead = block.shape[:-1]
    # block (..., 2, 2) times the axis identity: (..., a, i, b, j) = [a == b] block[i, j] is the
    # interleaved (..., n_x, n_x); a NaN block makes the whole matrix NaN (NaN * 0)
    full = block[..., _BLOCK_2X2].reshape(*lead, 1, 2, 1, 2) * _axis_eye(n_a)
    full += 0.0  # -0.0 (a negative p01 times 0) -> +0.0, as the zeros of the general layout
    return full.reshape(*lead, 2 * n_a, 2 * n_a)


_BLOCK_2X2 = np.array([0, 1, 1, 2])  # [p00, p01, p11] -> [[p00, p01], [p01, p11]]


@functools.cache
def _axis_eye(n_a: int) -> np.ndarray:
    """``(n_a, 1, n_a, 1)`` identity: the block pattern of an axis-blocked covariance."""
    return np.eye(n_a).reshape(n_a, 1, n_a, 1)


@functools.cache
def _block_index(n_a: int) -> tuple[np.ndarray, np.ndarray]:
    """``(dst, src)``: ``full.reshape(n_x * n_x)[dst] = blocks.reshape(3 * n_a)[src]`` puts the
    per-axis ``[p00, p01, p11]`` of ``blocks (n_a, 3)`` into the ``(n_x, n_x)`` covariance."""
    n_x = 2 * n_a
    i = 2 * np.arange(n_a)
    a = np.arange(n_a)
    dst = np.concatenate([i * n_x + i, i * n_x + i + 1, (i + 1) * n_x + i, (i + 1) * n_x + i + 1])
    src = np.concatenate([3 * a, 3 * a + 1, 3 * a + 1, 3 * a + 2])
    return dst, src


def positions(mean: np.ndarray, H: np.ndarray) -> np.ndarray:
    """``H @ mean`` over leading axes: ``(..., n_x) -> (..., n_z)``."""
    return mean @ H.T  # (an einsum costs ~10 us more per call: this runs on every online step)


def flat(a: np.ndarray, nb: int, dtype=np.float64) -> np.ndarray:
    """Copy of ``a`` with its ``nb`` leading (batch) axes flattened into one, C-contiguous."""
    a = np.asarray(a)
    B = math.prod(a.shape[:nb])  # (np.prod costs ~10 us a call: this runs on every step)
    return np.array(a.reshape((B, *a.shape[nb:])), dtype=dtype, order="C")  # always a copy


def flat_run(z: np.ndarray, state, names: tuple[str, ...]):
    """The kernel inputs of a single-model filter's ``_run``.

    Returns ``(batch_shape, z (B, T, n_z), *arrays)``: ``z`` C-contiguous, and a flattened copy
    (:func:`flat`, updated in place by the kernel) of each state field in ``names``
    (``"initialized"`` as bool, the others float64).
    """
    bs = z.shape[:-2]
    nb = len(bs)
    T, n_z = z.shape[-2:]
    zf = np.ascontiguousarray(z.reshape(-1, T, n_z))
    arrays = (
        flat(getattr(state, n), nb, bool if n == "initialized" else np.float64) for n in names
    )
    return (bs, zf, *arrays)


def run_outputs(B: int, T: int, n_x: int, n_z: int):
    """Empty kernel outputs every single-model filter writes: ``mean (B, T, n_x)``,
    ``cov (B, T, n_x, n_x)``, ``observed (B, T)`` bool, ``innovation (B, T, n_z)``."""
    return (
        np.empty((B, T, n_x)),
        np.empty((B, T, n_x, n_x)),
        np.empty((B, T), bool),
        np.empty((B, T, n_z)),
    )


def unflat(bs: tuple[int, ...], *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Arrays ``(B, ...)`` back to ``(*bs, ...)`` (the inverse of :func:`flat`)."""
    return tuple(a.reshape((*bs, *a.shape[1:])) for a in arrays)


def run_result(bs: tuple[int, ...], H: np.ndarray, mean, cov, observed, innovation) -> dict:
    """The :class:`FilterResult` fields of :func:`run_outputs` (batch axes restored) with
    ``position = H mean``, as keyword arguments."""
    mean, cov, observed, innovation = unflat(bs, mean, cov, observed, innovation)
    return {
        "mean": mean,
        "cov": cov,
        "position": positions(mean, H),
        "observed": observed,
        "innovation": innovation,
    }


def initial_covariance(model, sigma_v0: float = SIGMA_V0_M_S) -> np.ndarray:
    """``P₀``: R on the measured (position) components, ``σ_v0²`` on the rest (SPEC §4.2)."""
    H = model.H
    P0 = H.T @ model.R @ H
    unmeasured = np.ones(model.n_x, dtype=bool)
    unmeasured[np.flatnonzero(np.any(H != 0, axis=0))] = False
    P0[unmeasured, unmeasured] = sigma_v0**2
    return P0


def check_measurements(z, n_z: int, check_inf: bool = True) -> np.ndarray:
    """Validate a measurement series ``(..., T, n_z)``; return float64, C-contiguous.

    ``check_inf=False`` leaves the ±inf check to a kernel that reads ``z`` anyway.
    """
    arr = as_float_array(z, "z")
    if arr.ndim < 2 or arr.shape[-1] != n_z:
        raise InputError(f"expected z with shape (..., T, {n_z}), got {arr.shape}")
    if arr.shape[-2] == 0:
        raise InputError(f"expected z with at least one time step, got shape {arr.shape}")
    if check_inf and np.any(np.isinf(arr)):
        raise InputError("expected z finite or NaN (missing), got ±inf")
    return arr


def check_step_measurement(z, n_z: int, batch_shape: tuple[int, ...]) -> np.ndarray:
    """Validate one time slice ``(..., n_z)`` against the state's batch shape."""
    arr = as_float_array(z, "z")
    if arr.shape != (*batch_shape, n_z):
        raise InputError(
            f"expected z with shape {(*batch_shape, n_z)} (batch_shape + (n_z,)), got {arr.shape}"
        )
    if np.any(np.isinf(arr)):
        raise InputError("expected z finite or NaN (missing), got ±inf")
    return arr


def check_state_batch(state: GaussianState, z: np.ndarray) -> None:
    """Ensure a given state matches the batch shape of ``z (..., T, n_z)``."""
    if tuple(state.initialized.shape) != tuple(z.shape[:-2]):
        raise InputError(
            f"expected state with batch shape {z.shape[:-2]} (z's leading axes), got {state.initialized.shape}"
        )


def check_not_all_missing(z: np.ndarray, state: GaussianState | None) -> None:
    """Refuse series that never observe anything for an element that has no initial state."""
    init = np.zeros(z.shape[:-2], dtype=bool) if state is None else np.asarray(state.initialized)
    # an element whose first row is valid passes at once; the others are read whole
    bad = np.asarray(~init & ~np.all(np.isfinite(z[..., 0, :]), axis=-1)).reshape(init.shape)
    if np.any(bad):
        bad[bad] = ~np.any(np.all(np.isfinite(z[bad]), axis=-1), axis=-1)
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f" (batch element {idx})" if z.ndim > 2 else ""
        raise InputError(
            f"z{where} is all NaN: expected at least one valid measurement row, or an initial state "
            "passed as state=filter.init(..., mean=..., cov=...)"
        )


def check_batch_shape(batch_shape) -> tuple[int, ...]:
    """Validate ``batch_shape`` (an int or a tuple of non-negative ints) and return a tuple."""
    if isinstance(batch_shape, (int, np.integer)):
        batch_shape = (int(batch_shape),)
    try:
        batch_shape = tuple(int(b) for b in batch_shape)
    except TypeError:
        raise InputError(f"expected batch_shape as a tuple of ints, got {batch_shape!r}") from None
    if any(b < 0 for b in batch_shape):
        raise InputError(f"expected non-negative batch_shape, got {batch_shape}")
    return batch_shape


def broadcast_copy(a, shape, name: str, *, finite: bool = False, order: str = "K") -> np.ndarray:
    """A copy of ``a`` broadcast to ``shape`` (an initial mean, covariance or μ).

    Raises InputError saying the expected and the actual shape, and (``finite``) when an entry
    is not finite.
    """
    try:
        out = np.array(np.broadcast_to(a, shape), order=order)
    except ValueError:
        raise InputError(f"expected {name} broadcastable to {shape}, got {a.shape}") from None
    if finite and not np.all(np.isfinite(out)):
        raise InputError(f"expected a finite initial {name}")
    return out


def make_initial_state(model, batch_shape=(), mean=None, cov=None) -> GaussianState:
    """Build the state returned by ``init``: uninitialised (NaN) unless ``mean`` is given.

    Parameters
    ----------
    batch_shape : tuple of int
    mean : array_like, shape (..., n_x), optional
        Initial state; broadcast to ``batch_shape``.
    cov : array_like, shape (..., n_x, n_x), optional
        Initial covariance; defaults to :func:`initial_covariance`.
    """
    batch_shape = check_batch_shape(batch_shape)
    n_x = model.n_x
    if mean is None:
        if cov is not None:
            raise InputError("cov given without mean: pass both or neither")
        x = np.full((*batch_shape, n_x), np.nan)
        P = np.full((*batch_shape, n_x, n_x), np.nan)
        return GaussianState(x, P, np.zeros(batch_shape, dtype=bool), 0)
    m = as_float_array(mean, "mean", last_dim=n_x)
    x = broadcast_copy(m, (*batch_shape, n_x), "mean", finite=True)
    c = initial_covariance(model) if cov is None else as_float_array(cov, "cov")
    P = broadcast_copy(c, (*batch_shape, n_x, n_x), "cov", finite=True)
    if cov is not None:
        check_psd_stack(c, "cov")
    return GaussianState(x, P, np.ones(batch_shape, dtype=bool), 0)


def batch_shape_of(state) -> tuple[int, ...]:
    """The batch shape of a filter state (the shape of its ``initialized``)."""
    return tuple(np.shape(state.initialized))


def check_state(state, cls, batch_shape, extra=None) -> None:
    """Type and batch-shape check of a state passed back by the user.

    ``batch_shape=None`` accepts the state's own batch shape (``step``).
    """
    if not isinstance(state, cls):
        raise InputError(
            f"expected state as a {cls.__name__} (from this filter's init/filter), got {type(state).__name__}"
        )
    want = batch_shape_of(state) if batch_shape is None else tuple(batch_shape)
    if batch_shape_of(state) != want:
        raise InputError(
            f"expected state with batch shape {want} (z's leading axes), got {batch_shape_of(state)}"
        )
    for name, shape in (extra or {}).items():
        got = tuple(np.shape(getattr(state, name)))
        if got != (*want, *shape):
            raise InputError(f"expected state.{name} with shape {(*want, *shape)}, got {got}")


def take_step(result, nb: int):
    """The single time slice of a ``T = 1`` result (``(..., 1, ...) -> (..., ...)``)."""
    kw = {}
    for f in fields(result):
        v = getattr(result, f.name)
        kw[f.name] = None if v is None else v[(slice(None),) * nb + (0,)]
    return type(result)(**kw)


def run_filter(flt, z, state, **kwargs):
    """``filter`` of the single-model filters: validate ``z`` and the state, then ``flt._run``
    (``kwargs`` passed on)."""
    z = check_measurements(z, flt.model.n_z)
    if state is None:
        state = flt.init(z.shape[:-2])
    else:
        flt._check_state(state, z.shape[:-2])
    check_not_all_missing(z, state)
    return flt._run(z, state, **kwargs)


def run_step(flt, state, z):
    """``step`` of the single-model filters: one ``T = 1`` run of ``flt._run``, T axis dropped."""
    flt._check_state(state, None)
    bs = batch_shape_of(state)
    z = check_step_measurement(z, flt.model.n_z, bs)
    state, res = flt._run(z[..., None, :], state)
    return state, take_step(res, len(bs))


class SingleModelFilter:
    """``step`` and the trusted ``_filter_unchecked`` shared by the single-model filters.

    A subclass (:class:`~kinefuse.filters.EMKalmanFilter`, :class:`~kinefuse.filters.UFIRFilter`,
    :class:`~kinefuse.filters.IntegratedFilter`) has ``model``, ``_check_state(state,
    batch_shape)`` and the unchecked compiled run ``_run(z (..., T, n_z), state)``.
    """

    __slots__ = ()

    def step(self, state, z):
        """One time step: ``z (..., n_z)`` with the state's batch shape; fields lose the T axis.

        Parameters
        ----------
        state : NamedTuple
            This filter's state (from ``init``, ``filter`` or a previous ``step``).
        z : array_like of float, shape (..., n_z)
            The measurement at this step, m; a row with NaN is missing.

        Returns
        -------
        state : NamedTuple
            The state after the step (the input state is not modified).
        result : FilterResult
            This filter's result type, without the time axis.
        """
        return run_step(self, state, z)

    def _filter_unchecked(self, z: np.ndarray, state):
        """``filter`` on the trusted fast path: no checks (contract: module docstring)."""
        return self._run(z, state)
