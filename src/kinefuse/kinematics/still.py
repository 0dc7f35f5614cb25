"""Still-window detection for static calibration: where does every sensor hold still at once?

A window of ``window_s`` seconds is *still* when, on every sensor, the mean angular-rate
magnitude stays at or below ``max_rate_rad_s`` and the standard deviation of the specific-force
vector (the square root of the summed per-axis variances) at or below ``max_acc_std_m_s2``.
The angular rate is the gyroscope's when the stream has one, else the rate of change of the
orientation over 0.1 s (``2 arccos |<q_k, q_k+L>| / (t_k+L − t_k)``); a stream without an accelerometer is judged on
its rate alone. This is the usual zero-velocity test of foot-mounted inertial navigation
(Skog et al. 2010, "Zero-velocity detection — an algorithm evaluation", IEEE TBME 57(11)),
applied to a window and to all sensors jointly, as static sensor-to-segment calibrations use it
(e.g. the Xsens N-pose calibration, Roetenberg et al. 2009).

Defaults: 0.1 rad/s (5.7 deg/s) mean angular rate and 0.2 m/s² acceleration standard deviation;
a person standing quietly shows about 0.01-0.05 rad/s and 0.02-0.05 m/s² (the x-IMU3 and qmt
recordings of ``../shared/data`` at rest), walking 1-5 rad/s and 2-10 m/s².
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.io.recording import ImuStream

__all__ = [
    "MAX_ACC_STD_M_S2",
    "MAX_RATE_RAD_S",
    "MIN_STILL_S",
    "StillWindow",
    "find_still_window",
]

#: Default threshold of the mean angular-rate magnitude in a still window, rad/s.
MAX_RATE_RAD_S = 0.1
#: Default threshold of the acceleration standard deviation in a still window, m/s².
MAX_ACC_STD_M_S2 = 0.2
#: Most candidate windows one search examines (each holds per-sensor statistics; a day at the
#: default step of a 1-s window is 345 600).
MAX_CANDIDATES = 2_000_000
#: A recording shorter than the still window is one candidate window; a static calibration
#: refuses one shorter than this, s: over less, stillness cannot be told from a pause in a
#: movement (zero-velocity detectors judge windows of 0.1-0.5 s, Skog et al. 2010).
MIN_STILL_S = 0.25


@dataclass(frozen=True)
class StillWindow:
    """A calibration window and how still it was.

    Attributes
    ----------
    start_s, end_s : float
        Window bounds, s.
    rate_rad_s : float
        Largest (over sensors) mean angular-rate magnitude in the window, rad/s.
    acc_std_m_s2 : float
        Largest (over sensors) acceleration standard deviation in the window, m/s² (NaN when no
        sensor has an accelerometer).
    worst_rate, worst_acc : str
        Sensors with the largest rate and acceleration spread.
    signal : str
        ``"gyroscope"``, ``"orientation change"`` or a mix, what the rate was computed from.
    still : bool
        Both thresholds were met.
    """

    start_s: float
    end_s: float
    rate_rad_s: float
    acc_std_m_s2: float
    worst_rate: str
    worst_acc: str
    signal: str
    still: bool

    def describe(self) -> str:
        """One line: window, mean angular rate, acceleration spread, and the sensors."""
        acc = (
            f", acceleration std {self.acc_std_m_s2:.3f} m/s² ({self.worst_acc})"
            if np.isfinite(self.acc_std_m_s2)
            else ""
        )
        return (
            f"{self.start_s:.2f}-{self.end_s:.2f} s: mean angular rate "
            f"{self.rate_rad_s:.3f} rad/s = {np.degrees(self.rate_rad_s):.1f} deg/s "
            f"({self.worst_rate}, from {self.signal}){acc}"
        )


def _rate(st: ImuStream) -> tuple[np.ndarray, str]:
    """Angular-rate magnitude per sample, rad/s, and what it came from."""
    if st.gyr_rad_s is not None:
        return np.linalg.norm(st.gyr_rad_s, axis=1), "gyroscope"
    # rate over a 0.1 s lag: orientation outputs jitter from sample to sample
    q = st.q_world_from_sensor
    T = q.shape[0]
    lag = int(min(max(round(0.1 * st.rate_hz), 1), max(T - 1, 1))) if T > 1 else 1
    if T <= lag:
        return np.zeros(T), "orientation change"
    a, b = q[:-lag], q[lag:]
    dot = np.abs(np.sum(a * b, axis=1)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    w = 2.0 * np.arccos(np.clip(dot, 0.0, 1.0)) / (st.t_s[lag:] - st.t_s[:-lag])
    return np.concatenate([w, np.repeat(w[-1:], lag)]), "orientation change"


def _window_stats(t, x, starts, window_s):
    """Mean of x (T,) or total std of x (T, 3) over [s, s + window) for each start (nan-aware)."""
    a = np.searchsorted(t, starts - 1e-9)
    b = np.searchsorted(t, starts + window_s - 1e-9)
    x2 = x if x.ndim == 2 else x[:, None]
    ok = np.all(np.isfinite(x2), axis=1)
    xz = np.where(ok[:, None], x2, 0.0)
    c0 = np.concatenate([[0], np.cumsum(ok)])
    c1 = np.vstack([np.zeros((1, x2.shape[1])), np.cumsum(xz, axis=0)])
    c2 = np.vstack([np.zeros((1, x2.shape[1])), np.cumsum(xz**2, axis=0)])
    n = (c0[b] - c0[a]).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = (c1[b] - c1[a]) / n[:, None]
        if x.ndim == 1:
            out = m[:, 0]
        else:
            var = (c2[b] - c2[a]) / n[:, None] - m**2
            out = np.sqrt(np.sum(np.maximum(var, 0.0), axis=1))
    out[n < 2] = np.nan
    return out


def _check_thresholds(streams, window_s, max_rate_rad_s, max_acc_std_m_s2) -> None:
    if not streams:
        raise InputError("find_still_window: expected at least one IMU stream, got none")
    for name, v in (
        ("window_s", window_s),
        ("max_rate_rad_s", max_rate_rad_s),
        ("max_acc_std_m_s2", max_acc_std_m_s2),
    ):
        if not np.isfinite(v) or v <= 0:
            raise InputError(f"find_still_window: expected {name} finite and > 0, got {v}")


def _candidate_stats(streams, starts: np.ndarray, win: float):
    """Per sensor and candidate window: motion-rate and acceleration statistics, signals used."""
    rate = np.full((len(streams), starts.size), np.nan)
    acc = np.full((len(streams), starts.size), np.nan)
    signals = set()
    for i, st in enumerate(streams.values()):
        w, sig = _rate(st)
        signals.add(sig)
        rate[i] = _window_stats(st.t_s, w, starts, win)
        if st.acc_m_s2 is not None:
            acc[i] = _window_stats(st.t_s, st.acc_m_s2, starts, win)
    return rate, acc, signals


def find_still_window(
    streams: Mapping[str, ImuStream],
    window_s: float = 1.0,
    *,
    max_rate_rad_s: float = MAX_RATE_RAD_S,
    max_acc_std_m_s2: float = MAX_ACC_STD_M_S2,
    step_s: float | None = None,
) -> StillWindow:
    """The earliest window in which every sensor holds still (see the module docstring).

    Parameters
    ----------
    streams : mapping of str -> ImuStream
        The sensors that must be still (gyroscope or orientation; accelerometer optional).
    window_s : float
        Window length, s. A recording shorter than that is one candidate window.
    max_rate_rad_s, max_acc_std_m_s2 : float
        Stillness thresholds (defaults :data:`MAX_RATE_RAD_S`, :data:`MAX_ACC_STD_M_S2`).
    step_s : float, optional
        Spacing of the candidate window starts (default ``window_s / 4``).

    Returns
    -------
    StillWindow
        The earliest still window; if none is still, the stillest candidate with
        ``still=False`` (the caller decides whether that is an error).

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        No streams, a non-positive window or threshold, or no time span shared by the sensors.
    """
    _check_thresholds(streams, window_s, max_rate_rad_s, max_acc_std_m_s2)
    t0 = max(float(st.t_s[0]) for st in streams.values())
    t1 = min(float(st.t_s[-1]) for st in streams.values())
    if t1 <= t0:
        raise InputError(
            f"still-window search: the IMU streams {sorted(streams)} share no time span "
            f"(latest start {t0:.3f} s, earliest end {t1:.3f} s); a static calibration needs "
            f"them recorded together for {float(window_s):g} s"
        )
    win = min(float(window_s), t1 - t0 + 1e-6)
    step = float(step_s) if step_s is not None else win / 4.0
    if isinstance(step_s, (bool, np.bool_)) or not (math.isfinite(step) and step > 0):
        raise InputError(f"expected step_s finite and > 0 (s) or None, got {step_s!r}")
    n_starts = max(int(np.floor((t1 - t0 - win) / step + 1e-9)) + 1, 1)
    if n_starts > MAX_CANDIDATES:
        raise InputError(
            f"step_s = {step:g} s gives {n_starts} candidate windows over {t1 - t0:.4g} s (at most "
            f"{MAX_CANDIDATES}); give a longer step_s"
        )
    starts = t0 + np.arange(n_starts) * step
    rate, acc, signals = _candidate_stats(streams, starts, win)
    names = list(streams)
    with np.errstate(invalid="ignore"):
        r = np.max(np.where(np.isnan(rate), np.inf, rate), axis=0)
        has_acc = np.any(np.isfinite(acc), axis=0)
        a = np.where(has_acc, np.nanmax(np.where(np.isfinite(acc), acc, -np.inf), axis=0), np.nan)
    still = (r <= max_rate_rad_s) & (~has_acc | (a <= max_acc_std_m_s2))
    if np.any(still):
        k = int(np.flatnonzero(still)[0])
    else:  # stillest: the worse of the two criteria relative to its threshold
        score = np.maximum(r / max_rate_rad_s, np.where(has_acc, a / max_acc_std_m_s2, 0.0))
        k = int(np.argmin(score))
    a_k = float(a[k]) if has_acc[k] else float("nan")
    return StillWindow(
        start_s=float(starts[k]),
        end_s=float(starts[k] + win),
        rate_rad_s=float(r[k]),
        acc_std_m_s2=a_k,
        worst_rate=names[int(np.nanargmax(np.where(np.isnan(rate[:, k]), -np.inf, rate[:, k])))],
        worst_acc=(
            names[int(np.nanargmax(np.where(np.isnan(acc[:, k]), -np.inf, acc[:, k])))]
            if has_acc[k]
            else ""
        ),
        signal=" and ".join(sorted(signals)),
        still=bool(still[k]),
    )
