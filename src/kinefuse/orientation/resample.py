"""Resampling of orientation time series onto another timeline (SLERP)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from kinefuse._validation import as_float_array
from kinefuse.exceptions import InputError

__all__ = ["slerp_resample"]


def slerp_resample(t_src_s, q_src, t_dst_s, *, max_gap_s: float | None = None) -> np.ndarray:
    """SLERP orientations onto new sample times.

    Parameters
    ----------
    t_src_s : array_like, shape (T,)
        Source times, s, strictly increasing.
    q_src : array_like, shape (T, 4)
        ``wxyz`` quaternions; NaN rows = missing.
    t_dst_s : array_like, shape (M,)
        Target times, s.
    max_gap_s : float, optional
        Targets between two valid source samples farther apart than this are NaN. Default
        1.5 × the median source step.

    Returns
    -------
    q_dst : ndarray, shape (M, 4)
        ``wxyz``; NaN outside the valid source range and inside gaps. When the timelines are
        identical the input is returned unchanged (a copy).
    """
    t_src = as_float_array(t_src_s, "t_src_s")
    t_dst = as_float_array(t_dst_s, "t_dst_s")
    q = as_float_array(q_src, "q_src", last_dim=4)
    if t_src.ndim != 1 or q.shape != (t_src.size, 4):
        raise InputError(f"expected t_src_s (T,) and q_src (T, 4), got {t_src.shape} and {q.shape}")
    if t_dst.ndim != 1:
        raise InputError(f"expected t_dst_s with shape (M,), got {t_dst.shape}")
    if t_src.shape == t_dst.shape and np.array_equal(t_src, t_dst):
        return q.copy()
    ok = np.all(np.isfinite(q), axis=1)
    out = np.full((t_dst.size, 4), np.nan)
    if ok.sum() < 2:
        return out
    ts, qs = t_src[ok], q[ok]
    if max_gap_s is None:
        max_gap_s = 1.5 * float(np.median(np.diff(t_src))) if t_src.size > 1 else np.inf
    inside = (t_dst >= ts[0]) & (t_dst <= ts[-1])
    hi = np.clip(np.searchsorted(ts, t_dst, side="left"), 1, ts.size - 1)
    gap = ts[hi] - ts[hi - 1]
    exact = np.isin(t_dst, ts)
    use = inside & ((gap <= max_gap_s + 1e-12) | exact)
    if np.any(use):
        out[use] = Slerp(ts, Rotation.from_quat(qs, scalar_first=True))(t_dst[use]).as_quat(
            scalar_first=True
        )
    return out
