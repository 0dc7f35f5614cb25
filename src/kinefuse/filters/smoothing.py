"""Rauch-Tung-Striebel smoothing of filter results (paper B: Xu 2023 §3.1; SPEC §9). Offline.

Three entry points over one compiled backward recursion (:mod:`._kernels_axis`):

* :func:`rts_smooth`: fixed-interval RTS over the whole series, or over each contiguous run of
  ``mask`` (offline);
* :func:`rts_smooth_segments`: fixed-interval RTS per contiguous *available* segment (paper B's
  use; default availability = the samples the filter observed) (offline);
* :func:`fixed_lag_smooth`: the estimate at ``t`` given measurements up to ``t + lag``; causal
  with a delay of ``lag`` samples (the online option of SPEC §9).
"""

from __future__ import annotations

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.filters._base import FilterResult, initial_covariance, warn_regularised
from kinefuse.filters._kernels_axis import (
    axis_block_params,
    pack_axis_params,
    rts_axis,
    rts_dense,
    rts_dense6,
)
from kinefuse.filters._kernels_blocks import rts_blocks
from kinefuse.models import LinearGaussianModel

__all__ = ["fixed_lag_smooth", "rts_smooth", "rts_smooth_segments"]


def _check_inputs(model, result, mask):
    if not isinstance(model, LinearGaussianModel):
        raise InputError(f"expected model as a LinearGaussianModel, got {type(model).__name__}")
    for name in ("mean", "cov", "observed"):
        if not hasattr(result, name):
            raise InputError(
                f"expected result as a FilterResult (from a filter's filter()), got "
                f"{type(result).__name__} without .{name}"
            )
    n_x = model.n_x
    mean = np.asarray(result.mean)
    cov = np.asarray(result.cov)
    if not (np.issubdtype(mean.dtype, np.floating) and np.issubdtype(cov.dtype, np.floating)):
        raise InputError(f"expected float mean and cov, got dtypes {mean.dtype} and {cov.dtype}")
    if mean.ndim < 2 or mean.shape[-1] != n_x:
        raise InputError(f"expected result.mean with shape (..., T, {n_x}), got {mean.shape}")
    if mean.shape[-2] == 0:
        raise InputError(
            f"expected at least one time step, got result.mean with shape {mean.shape}"
        )
    if cov.shape != (*mean.shape, n_x):
        raise InputError(f"expected result.cov with shape {(*mean.shape, n_x)}, got {cov.shape}")
    observed = np.asarray(result.observed)
    if observed.shape != mean.shape[:-1]:
        raise InputError(
            f"expected result.observed with shape {mean.shape[:-1]}, got {observed.shape}"
        )
    return mean, cov, _check_mask(mask, mean.shape[:-1])


def _check_mask(mask, lead):
    if mask is None:
        return np.ones(lead, dtype=bool)
    m = np.asarray(mask)
    if m.dtype != bool:
        raise InputError(f"expected mask as a bool array, got dtype {m.dtype}")
    if m.shape != lead:
        raise InputError(f"expected mask with shape {lead} (..., T), got {m.shape}")
    return m


def _block_inputs(model, result):
    """``(mean, cov_blocks (..., T, n_c, 3), par)`` when ``result`` carries the per-axis block
    layout of an axis-blocked model (n_c = 1 when the blocks are one shared block), else None."""
    cb = getattr(result, "cov_blocks", None)
    if cb is None or not model.axis_blocks or getattr(result, "observed", None) is None:
        return None
    mean = np.asarray(result.mean)
    cb = np.asarray(cb)
    n_a = model.n_x // 2
    if mean.ndim < 2 or mean.shape[-1] != model.n_x or cb.shape != (*mean.shape[:-1], n_a, 3):
        return None
    if not (mean.dtype == np.float64 and cb.dtype == np.float64):
        return None
    par, _p0, shared = pack_axis_params(
        model.F, model.Q, model.H, model.R, initial_covariance(model)
    )
    if shared and n_a > 1 and cb.strides[-2] == 0:
        cb = cb[..., :1, :]  # one block stored for every axis
    return mean, cb, par


def _smooth_blocks(model, result, mask, inputs, wanted_pos=True) -> FilterResult:
    """Fixed-interval RTS on the block layout (:func:`._kernels_blocks.rts_blocks`)."""
    mean, cb, par = inputs
    n_x = model.n_x
    lead = mean.shape[:-1]
    T = lead[-1]
    n_c = cb.shape[-2]
    mean3 = np.ascontiguousarray(mean).reshape(-1, T, n_x)
    cb4 = np.ascontiguousarray(cb).reshape(-1, T, n_c, 3)
    m2 = np.ascontiguousarray(mask).reshape(-1, T)
    B = mean3.shape[0]
    sm_mean = np.empty((B, T, n_x))
    sm_cb = np.empty((B, T, n_c, 3))
    sm_pos = np.empty((B, T, model.n_z)) if wanted_pos else np.empty((0, 0, 0))
    rts_blocks(mean3, cb4, m2, par, sm_mean, sm_cb, sm_pos)
    sm_cb = sm_cb.reshape(*lead, n_c, 3)
    if n_c == 1 and n_x // 2 > 1:
        sm_cb = np.broadcast_to(sm_cb, (*lead, n_x // 2, 3))
    return FilterResult(
        mean=sm_mean.reshape(*lead, n_x),
        cov=None,
        position=sm_pos.reshape(*lead, model.n_z) if wanted_pos else None,
        observed=np.array(result.observed, dtype=bool),
        innovation=None,
        distance=None,
        mode=None if getattr(result, "mode", None) is None else np.array(result.mode),
        cov_blocks=sm_cb,
    )


def _selected_states(H: np.ndarray) -> np.ndarray | None:
    """The state index each row of ``H`` selects (``H = I[idx]``), or None for another H."""
    idx = np.argmax(np.abs(H), axis=1)
    return idx if np.array_equal(H, np.eye(H.shape[1])[idx]) else None


def _check_cov(cov):
    """The smoothers' ``cov`` option: True, False or ``"position"``."""
    if isinstance(cov, (bool, np.bool_)):
        return bool(cov)
    if isinstance(cov, str) and cov == "position":
        return cov
    raise InputError(f"expected cov as a bool or 'position', got {cov!r}")


def _position_block(res: FilterResult, H: np.ndarray, idx) -> FilterResult:
    """``res`` with ``cov`` replaced by its position block ``H P Hᵀ`` (the rows and columns
    ``idx`` of the states H selects, when it does: the same numbers, NaN elsewhere kept out)."""
    P = res.cov
    block = H @ P @ H.T if idx is None else P[..., idx[:, None], idx]
    return FilterResult(
        mean=res.mean, cov=block, position=res.position, observed=res.observed,
        innovation=res.innovation, distance=res.distance, mode=res.mode,
    )  # fmt: skip


def _smooth(model, result, mask, lag: int, position: bool = True, cov=True) -> FilterResult:
    """The smoothers' common body; ``cov``: True (all of P̃), False (none) or ``"position"``
    (the position states' block: on the dense path only that block is written)."""
    H = np.asarray(model.H) if isinstance(model, LinearGaussianModel) else None
    sel = _selected_states(H) if cov == "position" else None  # the block's states, if H selects
    if lag < 0 and isinstance(model, LinearGaussianModel):
        inputs = _block_inputs(model, result)
        if inputs is not None:
            lead = inputs[0].shape[:-1]
            m = _check_mask(mask, lead)
            if np.asarray(result.observed).shape != lead:
                raise InputError(
                    f"expected result.observed with shape {lead}, got {np.shape(result.observed)}"
                )
            res = _smooth_blocks(model, result, m, inputs, position)
            return _position_block(res, H, sel) if cov == "position" else res
    mean, P, m = _check_inputs(model, result, mask)
    n_x = model.n_x
    lead = mean.shape[:-1]
    T = lead[-1]
    mean3 = np.ascontiguousarray(mean, dtype=np.float64).reshape(-1, T, n_x)
    cov3 = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, T, n_x, n_x)
    m2 = np.ascontiguousarray(m).reshape(-1, T)
    B = mean3.shape[0]
    sm_mean = np.empty((B, T, n_x))
    done = False
    if model.axis_blocks:
        sm_cov = np.zeros((B, T, n_x, n_x))
        Fb, Qb, _Hb, _r, _P0b = axis_block_params(
            model.F, model.Q, model.H, model.R, np.zeros((n_x, n_x))
        )
        done = rts_axis(mean3, cov3, m2, Fb, Qb, lag, sm_mean, sm_cov)
    if not done:  # dense; a zero-length sm_cov: the means only (their recursion needs no P̃)
        cidx = np.arange(n_x) if sel is None else sel
        k = cidx.size
        sm_cov = np.empty((B, T, k, k) if cov is not False else (0, 0, k, k))
        dense = rts_dense6 if n_x == 6 else rts_dense  # (6: the loops unrolled)
        n_reg = dense(mean3, cov3, m2, model.F, model.Q, lag, sm_mean, sm_cov, cidx)
        warn_regularised(n_reg, "RTS smoother", "predicted covariance P⁻")
    sm_mean = sm_mean.reshape(*lead, n_x)
    res = FilterResult(
        mean=sm_mean,
        cov=sm_cov.reshape(*lead, *sm_cov.shape[2:]) if cov is not False else None,
        position=sm_mean @ model.H.T,  # H x̃ (BLAS matmul; same as _base.positions)
        observed=np.array(result.observed, dtype=bool),
        innovation=None,
        distance=None,
        mode=None if getattr(result, "mode", None) is None else np.array(result.mode),
    )
    # the block is still to be taken when the full P̃ was written (axis path, or H not a selection)
    full_written = done or sel is None
    return _position_block(res, H, sel) if cov == "position" and full_written else res


def rts_smooth(
    model: LinearGaussianModel, result: FilterResult, mask=None, position: bool = True
) -> FilterResult:
    """Offline fixed-interval Rauch-Tung-Striebel smoother (SPEC §9; paper B §3.1).

    Parameters
    ----------
    model : LinearGaussianModel
        The model the filter ran with (``F``, ``Q`` are used).
    result : FilterResult
        Filtered ``mean (..., T, n_x)`` and ``cov (..., T, n_x, n_x)``, e.g. from
        :meth:`KalmanFilter.filter`; may contain predict-only samples (``observed = False``)
        and leading uninitialised (NaN) samples.
    mask : array_like of bool, shape (..., T), optional
        Smooth independently within each maximal run of True (a fixed interval per run;
        smoothing never crosses a False sample); samples where False are returned as
        filtered. Default: the whole series is one interval.
    position : bool, default True
        Compute ``position = H mean``; False leaves it None (not written: the block form's
        outputs are then only the smoothed mean and covariance blocks).

    Returns
    -------
    FilterResult
        Smoothed ``mean``, ``cov``, ``position = H mean`` (m); ``observed`` and ``mode`` copied
        from ``result``; ``innovation`` and ``distance`` are None (they are filter
        diagnostics, see ``result``). NaN (uninitialised) samples stay NaN.

    Notes
    -----
    For ``t = t_end − 1`` down to ``t_start`` (``x̂, P̂`` filtered; ``x̃, P̃`` smoothed)::

        P⁻_{t+1} = F P̂_t Fᵀ + Q                 (recomputed: the filter's own prediction)
        C_t      = P̂_t Fᵀ (P⁻_{t+1})⁻¹          (Cholesky / LDLᵀ solve, no inverse)
        x̃_t = x̂_t + C_t (x̃_{t+1} − F x̂_t)
        P̃_t = P̂_t + C_t (P̃_{t+1} − P⁻_{t+1}) C_tᵀ

    starting from ``x̃_{t_end} = x̂_{t_end}``. For a predict-only sample ``x̂_{t+1} = F x̂_t``,
    which the recursion handles without special cases. When the model and the covariances are
    block-diagonal per axis the exact per-axis decoupling is used (SPEC §1); otherwise the
    dense form. A run shorter than two samples is returned unchanged.

    Deviations from the paper
    -------------------------
    Paper B names RTS smoothing of the IMM output but gives no type, lag or equations; SPEC §9
    fixes the standard RTS (as in filterpy's ``rts_smoother``), fixed-interval per available
    segment.
    """
    return _smooth(model, result, mask, -1, bool(position))


def rts_smooth_segments(
    model: LinearGaussianModel, result: FilterResult, available=None, *, cov: bool = True
) -> FilterResult:
    """Offline fixed-interval RTS per contiguous available segment (paper B default, SPEC §9).

    Parameters
    ----------
    model : LinearGaussianModel
    result : FilterResult
        Filtered series ``(..., T, ...)``.
    available : array_like of bool, shape (..., T), optional
        Per-sample availability (paper B: Kinect joint tracked). Default ``result.observed``.
        Each maximal run of available samples is smoothed on its own; other samples (outages)
        are returned as filtered.
    cov : bool or "position", default True
        Return the smoothed covariances. False: ``cov`` is None, and on full (not axis-blocked)
        covariances they are not computed (the means' recursion reads only the filtered ones:
        about a third less work). ``"position"``: ``cov`` is the position states' block
        ``H P̃ Hᵀ``, shape ``(..., T, n_z, n_z)``, the same numbers as that block of the full
        output; on full covariances only that block is written (paper B's offline output
        needs no more: a quarter of the memory for 6 states).

    Returns
    -------
    FilterResult
        As :func:`rts_smooth`.
    """
    if available is None:
        available = getattr(result, "observed", None)
    return _smooth(model, result, available, -1, True, _check_cov(cov))


def fixed_lag_smooth(
    model: LinearGaussianModel, result: FilterResult, lag: int, mask=None, *, cov=True
) -> FilterResult:
    """Fixed-lag RTS: the estimate at ``t`` given the measurements up to ``t + lag``.

    Causal with a delay of ``lag`` samples (SPEC §9 online option: lag 30 at 30 Hz); exact:
    the RTS recursion is run backward from ``min(t + lag, end of run)``, starting at the
    filtered estimate there. Cost O(T · lag).

    Parameters
    ----------
    model : LinearGaussianModel
    result : FilterResult
        Filtered series, as for :func:`rts_smooth`.
    lag : int
        Lag in samples, >= 0 (0 returns the filtered values).
    mask : array_like of bool, shape (..., T), optional
        As in :func:`rts_smooth`: windows never cross a False sample.
    cov : bool or "position", default True
        As in :func:`rts_smooth_segments`.

    Returns
    -------
    FilterResult
        As :func:`rts_smooth`. The last ``lag`` samples of each run use a shorter window and
        equal the fixed-interval values.
    """
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
        raise InputError(f"expected lag as an int >= 0 (samples), got {lag!r}")
    return _smooth(model, result, mask, int(lag), True, _check_cov(cov))
