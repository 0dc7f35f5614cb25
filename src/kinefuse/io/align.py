"""Time alignment: resampling orientations (SLERP) and positions (linear), common timelines and
clock-offset estimation by cross-correlation.

Layout note: these functions take time on axis 0 (``(T, ...)``), the layout of
:class:`~kinefuse.io.recording.ImuStream` and :class:`~kinefuse.io.recording.JointStream`.
No function invents data: outside the source time range, and inside gaps longer than
``max_gap_s`` (including gaps made by NaN/unavailable samples), the output is NaN / unavailable.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
from scipy import signal
from scipy.spatial.transform import Rotation, Slerp

from kinefuse.exceptions import InputError
from kinefuse.io.recording import ImuStream, JointStream, Recording

__all__ = [
    "ClockOffset",
    "common_timeline",
    "estimate_clock_offset",
    "resample_coverage",
    "resample_orientation",
    "resample_positions",
    "resample_recording",
]


def _times(t, name: str) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1:
        raise InputError(f"expected {name} with shape (T,), got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"expected finite {name}")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(
            f"expected strictly increasing {name}, got {t[i]!r} then {t[i + 1]!r} at index {i}"
        )
    return t


def _default_gap(t_src: np.ndarray, max_gap_s: float | None) -> float:
    if max_gap_s is not None:
        g = float(max_gap_s)
        if not g > 0:
            raise InputError(f"expected max_gap_s > 0, got {max_gap_s!r}")
        return g
    if t_src.size < 2:
        return 0.0
    return 1.5 * float(np.median(np.diff(t_src)))


def _brackets(tv: np.ndarray, t_new: np.ndarray, max_gap: float):
    """Left index, weight and validity of each ``t_new`` between valid source times ``tv``.

    A target is valid when it equals a valid source time, or lies strictly between two
    consecutive valid source times no more than ``max_gap`` apart.
    """
    n = tv.size
    out_ok = np.zeros(t_new.size, dtype=bool)
    k = np.zeros(t_new.size, dtype=int)
    w = np.zeros(t_new.size)
    if n == 0:
        return k, w, out_ok
    i = np.searchsorted(tv, t_new, side="right") - 1  # tv[i] <= t < tv[i+1]
    exact = (i >= 0) & (tv[np.clip(i, 0, n - 1)] == t_new)
    inner = (i >= 0) & (i < n - 1)
    ic = np.clip(i, 0, max(n - 2, 0))
    if n >= 2:
        gap = tv[ic + 1] - tv[ic]
        inner &= gap <= max_gap * (1 + 1e-9)
        w = np.where(inner, (t_new - tv[ic]) / np.where(gap > 0, gap, 1.0), 0.0)
    else:
        inner[:] = False
    k = np.where(exact, np.clip(i, 0, n - 1), ic)
    w = np.where(exact, 0.0, w)
    out_ok = exact | inner
    return k, w, out_ok


def resample_orientation(t_src, q, t_new, *, max_gap_s: float | None = None) -> np.ndarray:
    """Resample unit quaternions by SLERP (:class:`scipy.spatial.transform.Slerp`).

    Parameters
    ----------
    t_src : array_like, shape (T,)
        Source times, s, strictly increasing.
    q : array_like, shape (T, 4) or (T, J, 4)
        Scalar-first ``wxyz`` quaternions; NaN rows are missing samples.
    t_new : array_like, shape (T_new,)
        Target times, s, strictly increasing.
    max_gap_s : float or None
        Largest interval between two valid source samples that may be interpolated across,
        s. Default ``1.5 * median(diff(t_src))``: any missing sample breaks interpolation.

    Returns
    -------
    q_new : ndarray, shape (T_new, 4) or (T_new, J, 4)
        Interpolated quaternions (unit norm, wxyz); NaN outside the source range and inside
        gaps longer than ``max_gap_s``. Targets equal to a valid source time return it exactly
        (up to normalisation).
    """
    t_src = _times(t_src, "t_src")
    t_new = _times(t_new, "t_new")
    q = np.asarray(q, dtype=float)
    if q.ndim not in (2, 3) or q.shape[0] != t_src.size or q.shape[-1] != 4:
        raise InputError(
            f"expected q with shape (T, 4) or (T, J, 4) with T = {t_src.size}, got {q.shape}"
        )
    if q.ndim == 3:
        return np.stack(
            [
                resample_orientation(t_src, q[:, j], t_new, max_gap_s=max_gap_s)
                for j in range(q.shape[1])
            ],
            axis=1,
        )
    gap = _default_gap(t_src, max_gap_s)
    norm = np.linalg.norm(q, axis=1)
    valid = np.all(np.isfinite(q), axis=1) & (norm > 0)
    out = np.full((t_new.size, 4), np.nan)
    tv = t_src[valid]
    if tv.size == 0:
        return out
    k, _w, ok = _brackets(tv, t_new, gap)
    rots = Rotation.from_quat(q[valid] / norm[valid, None], scalar_first=True)
    if tv.size == 1:
        out[ok] = rots.as_quat(scalar_first=True)[0]
        return out
    slerp = Slerp(tv, rots)
    tt = np.clip(t_new[ok], tv[0], tv[-1])
    if tt.size:
        out[ok] = slerp(tt).as_quat(scalar_first=True)
    return out


def resample_coverage(t_src, usable, t_new, *, max_gap_s: float | None = None) -> np.ndarray:
    """Where :func:`resample_positions` gives a value at ``t_new``, without computing the values.

    Parameters
    ----------
    t_src : array_like, shape (T,)
        Source times, s, strictly increasing.
    usable : array_like of bool, shape (T,)
        The source samples that can be interpolated from (e.g. the finite rows).
    t_new : array_like, shape (T_new,)
        Target times, s, strictly increasing.
    max_gap_s : float or None
        As in :func:`resample_positions`.

    Returns
    -------
    ndarray of bool, shape (T_new,)
        :func:`resample_positions`' ``available_new`` for a signal usable at ``usable``.
    """
    t_src = _times(t_src, "t_src")
    t_new = _times(t_new, "t_new")
    u = np.asarray(usable, dtype=bool)
    if u.shape != t_src.shape:
        raise InputError(f"expected usable with shape {t_src.shape}, got {u.shape}")
    return _brackets(t_src[u], t_new, _default_gap(t_src, max_gap_s))[2]


def resample_positions(
    t_src, p, t_new, *, available=None, max_gap_s: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Resample positions (or any vector signal) by linear interpolation.

    Parameters
    ----------
    t_src : array_like, shape (T,)
        Source times, s, strictly increasing.
    p : array_like, shape (T, d) or (T, J, d)
        Samples (e.g. joint positions in m); rows with any NaN are missing.
    t_new : array_like, shape (T_new,)
        Target times, s, strictly increasing.
    available : array_like of bool, shape (T,) or (T, J), optional
        Source availability; unavailable samples are treated as missing.
    max_gap_s : float or None
        Largest interval between two usable source samples that may be interpolated across,
        s. Default ``1.5 * median(diff(t_src))``.

    Returns
    -------
    p_new : ndarray, shape (T_new, d) or (T_new, J, d)
        Interpolated samples; NaN where not available.
    available_new : ndarray of bool, shape (T_new,) or (T_new, J)
        True where both bracketing source samples were usable (or the target hits one exactly).
    """
    t_src = _times(t_src, "t_src")
    t_new = _times(t_new, "t_new")
    p = np.asarray(p, dtype=float)
    if p.ndim not in (2, 3) or p.shape[0] != t_src.size:
        raise InputError(
            f"expected p with shape (T, d) or (T, J, d) with T = {t_src.size}, got {p.shape}"
        )
    squeeze = p.ndim == 2
    p3 = p[:, None, :] if squeeze else p
    usable = np.all(np.isfinite(p3), axis=-1)
    if available is not None:
        a = np.asarray(available, dtype=bool)
        a = a[:, None] if squeeze and a.ndim == 1 else a
        if a.shape != usable.shape:
            raise InputError(
                f"expected available with shape {usable.shape if not squeeze else (t_src.size,)}, got {a.shape}"
            )
        usable &= a
    gap = _default_gap(t_src, max_gap_s)
    J = p3.shape[1]
    out = np.full((t_new.size, J, p3.shape[2]), np.nan)
    avail = np.zeros((t_new.size, J), dtype=bool)
    for j in range(J):
        idx = np.flatnonzero(usable[:, j])
        if idx.size == 0:
            continue
        tv = t_src[idx]
        k, w, ok = _brackets(tv, t_new, gap)
        pv = p3[idx, j]
        k1 = np.minimum(k + 1, idx.size - 1)
        val = (1 - w)[:, None] * pv[k] + w[:, None] * pv[k1]
        out[ok, j] = val[ok]
        avail[ok, j] = True
    if squeeze:
        return out[:, 0], avail[:, 0]
    return out, avail


def _resample_imu(s: ImuStream, t_new: np.ndarray, max_gap_s) -> ImuStream:
    kw = {}
    for f in ("acc_m_s2", "gyr_rad_s", "mag"):
        a = getattr(s, f)
        kw[f] = None if a is None else resample_positions(s.t_s, a, t_new, max_gap_s=max_gap_s)[0]
    q = s.q_world_from_sensor
    kw["q_world_from_sensor"] = (
        None if q is None else resample_orientation(s.t_s, q, t_new, max_gap_s=max_gap_s)
    )
    return replace(s, t_s=t_new, **kw)


def _resample_joints(js: JointStream, t_new: np.ndarray, max_gap_s) -> JointStream:
    p, a = resample_positions(
        js.t_s, js.position_m, t_new, available=js.available, max_gap_s=max_gap_s
    )
    return replace(js, t_s=t_new, position_m=p, available=a)


def resample_recording(recording: Recording, t_new, *, max_gap_s: float | None = None) -> Recording:
    """Every stream of ``recording`` resampled to ``t_new`` (SLERP for orientations, linear else).

    Parameters
    ----------
    recording : Recording
    t_new : array_like, shape (T_new,)
        Target times, s.
    max_gap_s : float or None
        Passed to the resamplers; ``None`` uses each stream's own ``1.5 * median dt``.

    Returns
    -------
    Recording
        Same keys; metadata copied with ``resampled_to`` added.
    """
    t_new = _times(t_new, "t_new")
    md = dict(recording.metadata)
    md["resampled_to"] = {"t0_s": float(t_new[0]), "n": int(t_new.size)}
    return Recording(
        imu={k: _resample_imu(s, t_new, max_gap_s) for k, s in recording.imu.items()},
        vision=None
        if recording.vision is None
        else _resample_joints(recording.vision, t_new, max_gap_s),
        reference=None
        if recording.reference is None
        else _resample_joints(recording.reference, t_new, max_gap_s),
        reference_orientation={
            k: _resample_imu(s, t_new, max_gap_s)
            for k, s in recording.reference_orientation.items()
        },
        metadata=md,
    )


def _streams(recording: Recording):
    out = list(recording.imu.values()) + list(recording.reference_orientation.values())
    out += [js for js in (recording.vision, recording.reference) if js is not None]
    return out


def common_timeline(
    recording: Recording,
    rate_hz: float | None = None,
    *,
    span: str = "overlap",
    max_gap_s: float | None = None,
) -> Recording:
    """Resample all streams of a recording onto one uniform time base.

    Parameters
    ----------
    recording : Recording
    rate_hz : float or None
        Output rate, Hz. Default: the vision stream's median rate if there is a vision stream
        (SPEC §12: IMU resampled to the camera), else the slowest IMU rate.
    span : {"overlap", "union"}
        ``"overlap"`` (default): from the latest stream start to the earliest stream end, so
        every stream covers the whole timeline. ``"union"``: earliest start to latest end;
        streams are NaN / unavailable where they have no data.
    max_gap_s : float or None
        Passed to the resamplers.

    Returns
    -------
    Recording
        All streams share ``t_s = t0 + n / rate_hz``; ``metadata["timeline"]`` records
        ``t0_s``, ``rate_hz``, ``span``.

    Raises
    ------
    InputError
        No streams, or the streams do not overlap.
    """
    streams = _streams(recording)
    if not streams:
        raise InputError("expected a recording with at least one stream, got none")
    if rate_hz is None:
        if recording.vision is not None and len(recording.vision) > 1:
            rate_hz = float(1.0 / np.median(np.diff(recording.vision.t_s)))
        else:
            rates = [s.rate_hz for s in recording.imu.values() if len(s) > 1]
            if not rates:
                raise InputError("cannot infer rate_hz: no stream with two samples; pass rate_hz=")
            rate_hz = float(min(rates))
    rate_hz = float(rate_hz)
    if not rate_hz > 0:
        raise InputError(f"expected rate_hz > 0, got {rate_hz}")
    starts = [float(s.t_s[0]) for s in streams if len(s)]
    ends = [float(s.t_s[-1]) for s in streams if len(s)]
    if span == "overlap":
        t0, t1 = max(starts), min(ends)
    elif span == "union":
        t0, t1 = min(starts), max(ends)
    else:
        raise InputError(f"expected span 'overlap' or 'union', got {span!r}")
    if t1 < t0:
        raise InputError(
            f"streams do not overlap in time: latest start {t0:.6g} s > earliest end {t1:.6g} s"
        )
    n = int(np.floor((t1 - t0) * rate_hz * (1 + 1e-12))) + 1
    t_new = t0 + np.arange(n) / rate_hz
    out = resample_recording(recording, t_new, max_gap_s=max_gap_s)
    out.metadata.pop("resampled_to", None)
    out.metadata["timeline"] = {"t0_s": t0, "rate_hz": rate_hz, "span": span}
    return out


class ClockOffset(NamedTuple):
    """Result of :func:`estimate_clock_offset`.

    Attributes
    ----------
    offset_s : float
        Add to ``t_b`` to put stream b on stream a's clock: ``t_b_aligned = t_b + offset_s``.
    correlation : float
        Normalised cross-correlation at the peak, in [-1, 1]; low values (< ~0.5) mean the
        estimate is unreliable.
    """

    offset_s: float
    correlation: float


def _magnitude(t, sig, name):
    t = _times(t, f"t_{name}")
    s = np.asarray(sig, dtype=float)
    if s.ndim == 1:
        s = np.abs(s)
    elif s.ndim == 2:
        s = np.linalg.norm(s, axis=1)
    else:
        raise InputError(f"expected sig_{name} with shape (T,) or (T, d), got {s.shape}")
    if s.shape[0] != t.size:
        raise InputError(
            f"expected sig_{name} with {t.size} samples to match t_{name}, got {s.shape[0]}"
        )
    return t, s


def _on_grid(t, s, dt):
    grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) / dt)) + 1) * dt
    ok = np.isfinite(s)
    v = np.interp(grid, t[ok], s[ok]) if ok.sum() >= 2 else np.full(grid.size, np.nan)
    # mark grid points inside long gaps (> 1.5 median dt) as missing
    tv = t[ok]
    if tv.size >= 2:
        _, _, inside = _brackets(tv, grid, 1.5 * float(np.median(np.diff(t))))
        v[~inside] = np.nan
    return grid, v


def estimate_clock_offset(
    t_a, sig_a, t_b, sig_b, *, max_lag_s: float, rate_hz: float | None = None
) -> ClockOffset:
    """Estimate the clock offset between two streams by cross-correlating signal magnitudes.

    Both signals are reduced to magnitudes (``|x|`` or ``||x||`` over the last axis, e.g.
    angular-rate norms of two IMUs on one segment, or an IMU's angular rate vs. a camera's
    joint speed), resampled to a common uniform grid, standardised, and cross-correlated with
    a per-lag normalisation over the overlap (Pearson correlation at each lag). The peak within
    ``|offset| <= max_lag_s`` is refined by parabolic interpolation.

    Parameters
    ----------
    t_a, t_b : array_like, shape (T_a,), (T_b,)
        Sample times, s, each on its own clock.
    sig_a, sig_b : array_like, shape (T_a,) or (T_a, d); (T_b,) or (T_b, d)
        Signals (NaN = missing).
    max_lag_s : float
        Largest offset searched, s.
    rate_hz : float or None
        Grid rate; default the faster of the two median rates.

    Returns
    -------
    ClockOffset
        ``offset_s`` with ``t_b + offset_s`` on a's clock, and the peak ``correlation``.

    Notes
    -----
    With ``a(t) = b(t - d)``: a sample of b stamped ``t_b`` happened at a-time ``t_b + d``.
    On the grid, ``c[L] = sum_n a[n + L] b[n]`` peaks at ``L*``, so ``d = t_a0 - t_b0 + L* dt``.
    """
    t_a, a = _magnitude(t_a, sig_a, "a")
    t_b, b = _magnitude(t_b, sig_b, "b")
    if t_a.size < 3 or t_b.size < 3:
        raise InputError("expected at least 3 samples in each stream")
    if not max_lag_s > 0:
        raise InputError(f"expected max_lag_s > 0, got {max_lag_s!r}")
    if rate_hz is None:
        rate_hz = max(1.0 / np.median(np.diff(t_a)), 1.0 / np.median(np.diff(t_b)))
    dt = 1.0 / float(rate_hz)
    ga, va = _on_grid(t_a, a, dt)
    gb, vb = _on_grid(t_b, b, dt)
    ma, mb = np.isfinite(va), np.isfinite(vb)
    if ma.sum() < 3 or mb.sum() < 3:
        raise InputError("expected at least 3 finite samples in each signal")
    va = np.where(ma, (va - np.nanmean(va)) / (np.nanstd(va) or 1.0), 0.0)
    vb = np.where(mb, (vb - np.nanmean(vb)) / (np.nanstd(vb) or 1.0), 0.0)
    fa, fb = ma.astype(float), mb.astype(float)
    num = signal.correlate(va, vb, mode="full")
    n_ov = signal.correlate(fa, fb, mode="full")
    sa = signal.correlate(va, fb, mode="full")
    sb = signal.correlate(fa, vb, mode="full")
    saa = signal.correlate(va * va, fb, mode="full")
    sbb = signal.correlate(fa, vb * vb, mode="full")
    lags = signal.correlation_lags(va.size, vb.size, mode="full")
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = num - sa * sb / n_ov
        var_a = saa - sa**2 / n_ov
        var_b = sbb - sb**2 / n_ov
        r = cov / np.sqrt(var_a * var_b)
    offsets = ga[0] - gb[0] + lags * dt
    min_overlap = max(3, int(0.25 * min(ma.sum(), mb.sum())))
    ok = (np.abs(offsets) <= max_lag_s) & (n_ov >= min_overlap) & np.isfinite(r)
    if not np.any(ok):
        raise InputError(
            f"no lag within max_lag_s = {max_lag_s} s gives enough overlap between the two streams "
            f"(a: {t_a[0]:.6g}..{t_a[-1]:.6g} s, b: {t_b[0]:.6g}..{t_b[-1]:.6g} s)"
        )
    r_ok = np.where(ok, r, -np.inf)
    i = int(np.argmax(r_ok))
    frac = 0.0
    if 0 < i < r.size - 1 and ok[i - 1] and ok[i + 1]:
        y0, y1, y2 = r[i - 1], r[i], r[i + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            frac = float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5))
    return ClockOffset(offset_s=float(offsets[i] + frac * dt), correlation=float(r[i]))
