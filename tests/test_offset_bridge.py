"""Tests of the causal outage bridge of ``"kinefuse"`` (kinefuse.pipelines.offset_bridge)."""

from __future__ import annotations

import numpy as np

from kinefuse.pipelines.offset_bridge import prequential_bridge


def _motion(T=900, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) / 30.0
    truth = np.stack([0.3 * np.sin(0.9 * t), 0.2 * np.cos(0.6 * t), 0.1 * np.sin(1.3 * t)], -1)
    seen = np.ones(T, dtype=bool)
    for a in (200, 420, 650):
        seen[a : a + 45] = False
    return truth, seen, rng


def test_exact_chain_is_left_alone():
    # chain = truth, camera = truth + 2 cm noise: any offset only adds camera noise
    truth, seen, rng = _motion()
    cam = truth + rng.normal(0, 0.02, truth.shape)
    pos, var, choices = prequential_bridge(truth, cam, seen)
    assert len(choices) == 3
    # at most a heavily smoothed, decaying offset is added: a small fraction of the camera
    # noise (an EWMA over >= 30 samples of 2 cm noise has ~2.6 mm std, decaying)
    err = np.sqrt(np.mean(np.sum((pos[~seen] - truth[~seen]) ** 2, -1)))
    assert err < 0.004
    assert all(c[3] == 0.0 or c[2] >= 30 for c in choices)
    assert np.all(np.isnan(pos[seen]))
    # its variance is the camera noise the history shows (0.02² per axis, ~3 % of 2 k pairs)
    np.testing.assert_allclose(var[~seen], 0.02**2, rtol=0.25)


def test_constant_chain_offset_is_held_and_smoothed():
    truth, seen, rng = _motion(seed=1)
    off = np.array([0.05, -0.03, 0.02])
    chain = truth - off
    cam = truth + rng.normal(0, 0.02, truth.shape)
    pos, var, choices = prequential_bridge(chain, cam, seen)
    err = np.sqrt(np.mean(np.sum((pos[~seen] - truth[~seen]) ** 2, -1)))
    assert err < 0.01  # well below the offset (6 cm) and the camera noise (3.5 cm 3-D)
    assert all(c[2] >= 10 for c in choices)  # the offset is averaged over many samples


def test_prefers_the_better_base():
    truth, seen, rng = _motion(seed=2)
    cam = truth + rng.normal(0, 0.01, truth.shape)
    bad = truth + 0.1 * np.sin(np.arange(truth.shape[0]) / 7.0)[:, None]  # pose-like error
    pos, _, choices = prequential_bridge((bad, truth), cam, seen)
    assert all(c[1] == 1 for c in choices)
    np.testing.assert_allclose(pos[~seen], truth[~seen], atol=0.01)


def test_causal_and_needs_history():
    truth, seen, rng = _motion(seed=3)
    chain = truth + 0.03
    cam = truth + rng.normal(0, 0.01, truth.shape)
    pos, _, _ = prequential_bridge(chain, cam, seen)
    chain2, cam2 = chain.copy(), cam.copy()
    chain2[500:] += 0.2
    cam2[500:] -= 0.1
    pos2, _, _ = prequential_bridge(chain2, cam2, seen)
    np.testing.assert_array_equal(pos2[:500], pos[:500])
    # too little history before the first onset: nothing bridged
    p3, _, ch = prequential_bridge(chain, cam, seen, min_history=250)
    assert np.all(np.isnan(p3[200:245])) and [c[0] for c in ch] == [420, 650]


def test_scores_equal_the_pairwise_sum():
    # oracle: the score's definition, pair by pair (the bridge sums it in O(T) recursions)
    from kinefuse.pipelines.offset_bridge import (
        BRIDGE_SMOOTH_SAMPLES,
        _cumulative_scores,
        _ewma,
        _weights,
    )

    truth, seen, rng = _motion(T=160, seed=4)
    seen[rng.random(seen.size) < 0.1] = False
    e = np.where(seen[:, None], rng.normal(0.0, 0.02, truth.shape) + 0.03, np.nan)
    smooth = {ts: _ewma(e, seen, ts) for ts in BRIDGE_SMOOTH_SAMPLES}
    H, at = 12, np.array([5, 40, 99, 159])
    cands, sse, n = _cumulative_scores([e], [smooth], seen, H, at)
    for c, (_, ts, td) in enumerate(cands):
        eb = smooth[ts]
        want_sse, want_n = np.zeros(at.size), np.zeros(at.size)
        for s in range(160):
            for h in range(1, H + 1):
                t = s + h
                if t >= 160 or not seen[t] or not np.all(np.isfinite(eb[s])):
                    continue
                term = np.sum((e[t] - _weights(td, np.array([h]))[0] * eb[s]) ** 2)
                want_sse[t <= at] += term
                want_n[t <= at] += 1
        np.testing.assert_allclose(n[c], want_n)
        np.testing.assert_allclose(sse[c], want_sse, rtol=1e-9, atol=1e-15)


def test_horizon_errors_equal_their_definition():
    # oracle: per horizon, the mean of r² over the complete pairs of the window, in numpy
    from kinefuse.pipelines.offset_bridge import BRIDGE_VAR_WINDOW, _horizon_mse

    rng = np.random.default_rng(5)
    T, H = 3300, 20
    e = rng.normal(0.0, 0.01, (T, 3))
    eb = rng.normal(0.0, 0.01, (T, 3))
    e[rng.random(T) < 0.05, 1] = np.nan
    eb[:40] = np.nan
    for td, a in ((np.inf, 3200), (10.0, 25), (0.0, 60)):
        got = _horizon_mse(e, eb, td, a, H)
        lo = max(a - BRIDGE_VAR_WINDOW, 0)
        want = np.full((H, 3), np.nan)
        for h in range(1, min(H, a - lo - 1) + 1):
            w = 0.0 if td == 0 else np.exp(-h / td)
            r = e[lo + h : a] - w * eb[lo : a - h]
            ok = np.all(np.isfinite(r), axis=-1)
            if ok.any():
                want[h - 1] = np.mean(r[ok] ** 2, axis=0)
        # horizons without a pair take the last scored one (the first, before any)
        scored = np.flatnonzero(np.isfinite(want[:, 0]))
        for k in range(H):
            if scored.size and not np.isfinite(want[k, 0]):
                before = scored[scored < k]
                want[k] = want[before[-1] if before.size else scored[0]]
        np.testing.assert_allclose(got, want, rtol=1e-12)
