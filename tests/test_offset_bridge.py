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
