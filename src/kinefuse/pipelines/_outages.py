"""Outage bookkeeping of the paper-B pipeline (Xu 2023 §3.1; SPEC §10.3, §13): pure array helpers.

No validation here (the public boundary in :mod:`kinefuse.pipelines.vision_assisted` validates);
every function works on one joint's boolean availability series ``(T,)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "SOURCE_NONE",
    "OutageEpisode",
    "available_runs",
    "find_episodes",
    "interpolate_gaps",
    "outage_intervals",
    "segment_start",
]

#: Source code of a sample without any estimate (camera-only before the first camera sample).
#: Not one of :data:`kinefuse.conventions.SOURCE_NAMES`; such samples have NaN positions.
SOURCE_NONE = -1


@dataclass(frozen=True)
class OutageEpisode:
    """One prediction-stage episode of one joint (SPEC §10.3 with the recovery rule).

    Attributes
    ----------
    start : int
        Outage onset ``a`` (first unavailable sample).
    stop : int
        End, exclusive: ``recovery_start + N`` when the camera came back for N consecutive
        samples, else T. Samples ``[start, stop)`` use the prediction-stage output.
    recovery_start : int
        First of the N consecutive available samples that end the episode (``stop`` when the
        episode runs to the end of the data).
    recovered : bool
        True when the episode ended by the recovery rule (False: it runs to the end).
    mode : str
        ``"bridged"`` (ELM-1 -> FIR-3 (+ ELM-2)) or ``"imu-fallback"`` (FIR-1 output: fewer
        than the minimum number of training samples before ``start``, e.g. an outage at the
        very start).
    train_start : int
        First sample of the ELM-1 training window (and of FIR-3's run); -1 without training.
    n_train : int
        Number of ELM-1 training samples (available samples in the window).
    n_train_elm2 : int
        Number of ELM-2 training samples (current available segment ∩ window).
    elm2_skipped : bool
        True when ELM-2 was not fitted (too few samples) and the output is FIR-3 alone.
    """

    start: int
    stop: int
    recovery_start: int
    recovered: bool
    mode: str = "bridged"
    train_start: int = -1
    n_train: int = 0
    n_train_elm2: int = 0
    elm2_skipped: bool = False


def available_runs(available: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximal runs of True: ``(starts, stops)`` with ``stops`` exclusive."""
    d = np.diff(np.concatenate(([0], available.astype(np.int8), [0])))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def outage_intervals(available: np.ndarray) -> tuple[tuple[int, int], ...]:
    """Maximal runs of False as ``((start, stop), ...)``, ``stop`` exclusive."""
    s, e = available_runs(~available)
    return tuple((int(a), int(b)) for a, b in zip(s, e, strict=True))


def find_episodes(available: np.ndarray, horizon: int) -> list[tuple[int, int, int, bool]]:
    """Prediction-stage episodes ``(start, stop, recovery_start, recovered)`` of one joint.

    An episode starts at an outage onset and ends only after the camera has been available
    for ``horizon`` (N) consecutive samples again (SPEC §10.3 recovery rule): it covers the
    outage and the N recovery samples. Outages separated by fewer than N available samples
    therefore fall into one episode. An episode without such a recovery runs to the end.
    """
    T = available.size
    gap_s, _ = available_runs(~available)
    run_s, run_e = available_runs(available)
    long_s = run_s[(run_e - run_s) >= horizon]
    out = []
    t = 0
    while True:
        i = np.searchsorted(gap_s, t, side="left")
        if i >= gap_s.size:
            break
        a = int(gap_s[i])
        k = np.searchsorted(long_s, a, side="right")
        if k < long_s.size:
            r = int(long_s[k])
            e = r + horizon
            out.append((a, e, r, True))
            t = e
        else:
            out.append((a, T, T, False))
            break
    return out


def segment_start(available: np.ndarray, onset: int) -> int:
    """Start of the maximal available run that ends at ``onset − 1`` (``onset`` if none)."""
    if onset == 0 or not available[onset - 1]:
        return onset
    before = np.flatnonzero(~available[:onset])
    return int(before[-1]) + 1 if before.size else 0


def interpolate_gaps(values: np.ndarray, available: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation across gaps of one joint's ``(T, 3)`` series.

    Returns
    -------
    out : ndarray, shape (T, 3)
        Values where available; linear interpolation between the neighbouring available samples
        inside gaps; the last available value held after the last one; NaN before the first.
    filled : ndarray of bool, shape (T,)
        True where ``out`` was interpolated or held.
    """
    T = values.shape[0]
    out = np.full((T, 3), np.nan)
    filled = np.zeros(T, dtype=bool)
    idx = np.flatnonzero(available)
    if idx.size == 0:
        return out, filled
    t = np.arange(T)
    for k in range(3):
        out[:, k] = np.interp(t, idx, values[idx, k])
    out[: idx[0]] = np.nan
    filled[idx[0] :] = ~available[idx[0] :]
    return out, filled
