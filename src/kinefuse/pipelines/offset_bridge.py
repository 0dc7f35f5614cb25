"""Causal outage bridge of ``"kinefuse"``: the chain plus a decaying offset, chosen prequentially.

During a camera outage a causal method has the IMU chain and the past only. The chain error
``e_t = z^V_t − z^I_t`` is neither constant (a held offset adds the camera's noise and goes stale)
nor zero (a biased chain): :func:`prequential_bridge` predicts it as a smoothed last offset that
decays towards the chain, ``ê_{a−1+h} = φ_d^h · ē_{a−1}``, and chooses the smoothing and the
decay at each outage onset by their predictive error on the camera-seen history (prequential
model selection, Dawid 1984), which also gives the covariance per horizon.
"""

from __future__ import annotations

import numpy as np

from kinefuse.pipelines._kinefuse_kernels import bridge_scores, ewma_hold, horizon_sse

__all__ = [
    "BRIDGE_DECAY_SAMPLES",
    "BRIDGE_HORIZON",
    "BRIDGE_SMOOTH_SAMPLES",
    "BRIDGE_VAR_WINDOW",
    "prequential_bridge",
]

#: Time constants (samples) of the EWMA that smooths the camera-chain offset.
BRIDGE_SMOOTH_SAMPLES = (1.0, 3.0, 10.0, 30.0, 100.0)
#: Decay time constants (samples) of the held offset; 0 = no offset (the chain alone), inf = hold.
BRIDGE_DECAY_SAMPLES = (0.0, 3.0, 10.0, 30.0, 100.0, 300.0, np.inf)
#: Largest horizon (samples) over which candidates are scored: 60 = 2 s at 30 Hz.
BRIDGE_HORIZON = 60
#: Most recent history (samples) the predictive variance per horizon is computed from, so that
#: the cost per onset stays bounded on long recordings (3000 = 100 s at 30 Hz).
BRIDGE_VAR_WINDOW = 3000


def _ewma(e: np.ndarray, seen: np.ndarray, tau: float) -> np.ndarray:
    """Causal EWMA over the seen rows of ``e (T, 3)``, held through gaps; NaN before the first."""
    out = np.full((e.shape[0], 3), np.nan)
    # m_k = m_{k-1} + a (x_k − m_{k-1}), m_0 = x_0, over the seen rows x_k
    ewma_hold(e, seen, 1.0 - np.exp(-1.0 / tau), out)
    return out


def _weights(tau_d: float, h: np.ndarray) -> np.ndarray:
    if tau_d == 0:
        return np.zeros(h.shape)
    if np.isinf(tau_d):
        return np.ones(h.shape)
    return np.exp(-h / tau_d)


def prequential_bridge(
    z_imu,
    z_cam: np.ndarray,
    seen: np.ndarray,
    *,
    min_history: int = 30,
    horizon: int = BRIDGE_HORIZON,
):
    """Causal outage bridge of one joint: ``z^I + φ_d^h ē``, chosen on the seen history.

    Parameters
    ----------
    z_imu : ndarray, shape (T, 3), or sequence of them
        IMU-chain positions, m; NaN rows = missing. Several: alternative bases (e.g. the raw
        and the corrected chain, each value at t computed from data up to t), all scored.
    z_cam : ndarray, shape (T, 3)
        Camera positions, m (read only where ``seen``).
    seen : ndarray of bool, shape (T,)
        Camera available (and chain finite).
    min_history : int
        Seen samples needed before an onset to bridge it (else it is left out).
    horizon : int
        H, largest horizon of the score, samples.

    Returns
    -------
    position : ndarray, shape (T, 3)
        Bridged positions inside the bridged outages (from each onset to the next seen
        sample), NaN elsewhere.
    var : ndarray, shape (T, 3)
        Per-axis predictive variance, m²: the chosen candidate's mean squared prediction error
        at that horizon (beyond H: at H) over the last :data:`BRIDGE_VAR_WINDOW` samples.
    choices : list of (int, int, float, float)
        Per bridged onset ``(a, base, τ_s, τ_d)``: onset, index of the chosen base, time
        constants in samples.

    Notes
    -----
    Candidates: ``ē = EWMA_{τ_s}`` of ``e = z^V − z^I`` over the seen samples (held through
    gaps), decayed with ``w_h = exp(−h / τ_d)`` (grids :data:`BRIDGE_SMOOTH_SAMPLES`,
    :data:`BRIDGE_DECAY_SAMPLES`; ``τ_d = 0`` is the chain alone, ``∞`` holds the offset).
    Score at onset a: the mean over the pairs ``(s, s + h)``, ``1 <= h <= H``, both seen and
    ``s + h < a``, of ``|e_{s+h} − w_h ē_s|²``; each pair enters once it is complete, so the
    choice at a uses samples before a only (causal). The camera's white noise adds the same
    amount to every candidate's score and does not bias the choice.
    """
    bases = [np.asarray(z_imu, dtype=float)] if np.ndim(z_imu) == 2 else list(z_imu)
    T = bases[0].shape[0]
    for b in bases:
        seen = seen & np.all(np.isfinite(b), axis=-1)
    pos = np.full((T, 3), np.nan)
    var = np.full((T, 3), np.nan)
    onsets = np.flatnonzero(~seen[1:] & seen[:-1]) + 1
    n_seen = np.cumsum(seen)
    onsets = onsets[n_seen[onsets - 1] >= min_history]
    if onsets.size == 0:
        return pos, var, []
    errs = [np.where(seen[:, None], z_cam - b, np.nan) for b in bases]
    smooth = [{ts: _ewma(e, seen, ts) for ts in BRIDGE_SMOOTH_SAMPLES} for e in errs]
    cands, cum_sse, cum_n = _cumulative_scores(errs, smooth, seen, horizon, onsets - 1)
    choices = []
    for k, a in enumerate(onsets):
        score = cum_sse[:, k] / np.maximum(cum_n[:, k], 1.0)
        score[cum_n[:, k] == 0] = np.inf
        i, ts, td = cands[int(np.argmin(score))]
        nxt = np.flatnonzero(seen[a:])
        end = a + (int(nxt[0]) if nxt.size else T - a)
        hh = np.arange(1, end - a + 1)
        e, eb = errs[i], smooth[i][ts]
        pos[a:end] = bases[i][a:end] + _weights(td, hh)[:, None] * eb[a - 1]
        mse = _horizon_mse(e, eb, td, int(a), horizon)
        var[a:end] = mse[np.minimum(hh, horizon) - 1]
        choices.append((int(a), int(i), float(ts), float(td)))
    return pos, var, choices


def _cumulative_scores(errs, smooth, seen, horizon: int, at: np.ndarray):
    """Candidates ``(base, τ_s, τ_d)`` and, per candidate, the cumulative squared prediction
    error and pair count at the times ``at (n,)``: ``(cands, cum_sse (C, n), cum_n (C, n))``.

    A pair ``(s, s + h)`` counts at its completion time ``t = s + h``; the sums over the pairs
    are updated in O(1) per sample and decay (:func:`~kinefuse.pipelines._kinefuse_kernels.
    bridge_scores`), O(T) per candidate whatever the horizon.
    """
    T = seen.shape[0]
    H = int(min(horizon, max(T - 1, 0)))  # a pair needs h < T
    decays = [td for td in BRIDGE_DECAY_SAMPLES if td != 0]
    phis = np.array([1.0 if np.isinf(td) else np.exp(-1.0 / td) for td in decays])
    at = np.ascontiguousarray(at, dtype=np.int64)
    cands, cum_sse, cum_n = [], [], []
    for i, e in enumerate(errs):
        e0 = np.where(np.isfinite(e), e, 0.0)
        for ts in BRIDGE_SMOOTH_SAMPLES:
            eb = smooth[i][ts]
            okb = np.all(np.isfinite(eb), axis=-1)
            eb0 = np.where(okb[:, None], eb, 0.0)
            sse, n = np.empty((len(decays) + 1, at.size)), np.empty(at.size)
            bridge_scores(e0, eb0, okb, seen, H, phis, at, sse, n)
            if ts == BRIDGE_SMOOTH_SAMPLES[0]:  # the chain alone (τ_d = 0) does not depend on τ_s
                cands.append((i, ts, 0.0))
                cum_sse.append(sse[0])
                cum_n.append(n)
            for d, td in enumerate(decays):
                cands.append((i, ts, td))
                cum_sse.append(sse[d + 1])
                cum_n.append(n)
    return cands, np.array(cum_sse), np.array(cum_n)


def _horizon_mse(e, eb, td: float, a: int, horizon: int) -> np.ndarray:
    """Predictive variance per horizon ``(H, 3)`` of candidate ``(ē, τ_d)`` from the history
    before onset ``a`` (the last :data:`BRIDGE_VAR_WINDOW` samples); unscored horizons take
    the last scored one."""
    h_all = np.arange(1, horizon + 1)
    w = _weights(td, h_all)
    mse = np.full((horizon, 3), np.nan)
    lo = max(a - BRIDGE_VAR_WINDOW, 0)
    H = max(min(horizon, a - lo - 1), 0)  # horizons with a pair (s, s + h), lo <= s, s + h < a
    sse, n = np.zeros((H, 3)), np.zeros(H, dtype=np.int64)
    horizon_sse(e, eb, w, int(lo), int(a), sse, n)
    mse[:H] = np.where(n[:, None] > 0, sse / np.maximum(n, 1)[:, None], np.nan)
    return _fill_forward(mse)


def _fill_forward(m: np.ndarray) -> np.ndarray:
    """Rows that are NaN take the last finite row (the first finite one before it)."""
    ok = np.all(np.isfinite(m), axis=-1)
    if not np.any(ok):
        return m
    idx = np.where(ok, np.arange(m.shape[0]), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.flatnonzero(ok)[0])
    return m[idx]
