"""Paper B's step-wise core (PaperBCore): any split into blocks equals one block, and the batch
and streaming forms are that core (so stream == causal batch follows from the split rule)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from kinefuse.conventions import SOURCE_FUSED
from kinefuse.filters import rts_smooth_segments
from kinefuse.pipelines import VisionParams, vision_assisted
from kinefuse.pipelines._outages import find_episodes
from kinefuse.pipelines._paper_b_smooth import RunSmoother
from kinefuse.pipelines.paper_b import PaperBCore
from kinefuse.streaming.paper_b import VisionAssistedProcessor
from test_streaming_paper_b import DT, PARAMS, TOL, make_scenario


def _advance_in_blocks(core, z_imu, z_cam, av, cuts):
    zi, zc, a = (np.ascontiguousarray(np.swapaxes(x, 0, 1)) for x in (z_imu, z_cam, av))
    state = core.init(zi.shape[0])
    outs = [core.advance(state, zi[:, s:e], zc[:, s:e], a[:, s:e]) for s, e in cuts]
    return state, [np.concatenate([getattr(o, f) for o in outs], axis=1)
                   for f in ("position", "cov", "source", "imu_fallback", "elm2_skipped")]  # fmt: skip


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
@pytest.mark.parametrize("block", [1, 7, 250])
def test_blocks_equal_one_block(method, block):
    z_imu, z_cam, av = make_scenario(T=700)
    core = PaperBCore(method, PARAMS["short-window"], DT)
    T = z_imu.shape[0]
    s1, one = _advance_in_blocks(core, z_imu, z_cam, av, [(0, T)])
    edges = list(range(0, T, block)) + [T]
    s2, split = _advance_in_blocks(
        core, z_imu, z_cam, av, list(zip(edges[:-1], edges[1:], strict=True))
    )
    for a, b in zip(one, split, strict=True):
        if a.dtype.kind == "f":
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
            np.testing.assert_allclose(a, b, atol=TOL, rtol=0)
        else:
            np.testing.assert_array_equal(a, b)
    assert s1.episodes() == s2.episodes() and s1.k == s2.k == T


def test_batch_and_stream_are_the_core():
    z_imu, z_cam, av = make_scenario(T=400)
    params = VisionParams(train_window=120, min_train=40)
    res = vision_assisted(z_imu, z_cam, av, DT, "elm-fir", causal=True, params=params)
    state, (pos, cov, src, fb, sk) = _advance_in_blocks(
        PaperBCore("elm-fir", params, DT), z_imu, z_cam, av, [(0, 400)]
    )
    np.testing.assert_array_equal(pos.swapaxes(0, 1), res.position)  # the batch form: one block
    np.testing.assert_array_equal(src.T, res.source)
    assert state.episodes() == res.episodes
    proc = VisionAssistedProcessor("elm-fir", params, DT, joints=5)
    assert isinstance(proc.core, PaperBCore) and proc.core.params is params


def test_episodes_follow_the_closed_form_recovery_rule():
    """The step-wise episode machine gives the episodes of the closed-form rule (find_episodes)."""
    z_imu, z_cam, av = make_scenario()
    params = PARAMS["default"]
    state, _ = _advance_in_blocks(PaperBCore("elm-fir", params, DT), z_imu, z_cam, av, [(0, 1200)])
    for j, eps in enumerate(state.episodes()):
        expected = find_episodes(av[:, j] & np.isfinite(z_cam[:, j]).all(-1), params.horizon)
        assert [(e.start, e.stop, e.recovery_start, e.recovered) for e in eps] == expected


def test_recovery_rule_blocks_equal_an_explicit_count():
    """Oracle: the recovery rule as a frame-by-frame count (N consecutive available frames end
    an episode), for blocks of one frame (the online step) and longer blocks."""
    from kinefuse.pipelines.paper_b import _recovery, _run_length

    rng = np.random.default_rng(5)
    blocks = [np.array([a]) for a in (True, False)] + [rng.random(n) < 0.7 for n in (2, 9, 40)]
    for av in blocks:
        for run0 in (0, 3, 6, 19):
            for N in (7, 10, 20):
                run, want = run0, (av.size, False)
                for i, a in enumerate(av):
                    run = run + 1 if a else 0
                    if run >= N:
                        want = (i + 1, True)
                        break
                assert _recovery(av, run0, N) == want
                if not want[1]:
                    assert _run_length(av, run0) == run


@pytest.mark.parametrize("block", [1, 13, 250])
def test_run_smoother_equals_one_rts_over_the_series(block):
    """The batch form smooths each available run as it ends (RunSmoother); the oracle is one
    rts_smooth_segments over the whole series' IMM output, as the offline output is defined."""
    z_imu, z_cam, av = make_scenario(T=700)
    core = PaperBCore("elm-fir", PARAMS["short-window"], DT)
    zi, zc, a = (np.ascontiguousarray(np.swapaxes(x, 0, 1)) for x in (z_imu, z_cam, av))
    step = core.advance(core.init(zi.shape[0]), zi, zc, a)
    oracle = rts_smooth_segments(core.model_imu, step.imm, a, cov="position")
    pos, cov = step.position.copy(), step.cov.copy()
    smoother = RunSmoother(core.model_imu, pos, cov, step.source)
    T = a.shape[1]
    for s in range(0, T, block):
        e = min(s + block, T)
        part = SimpleNamespace(mean=step.imm.mean[:, s:e], cov=step.imm.cov[:, s:e])
        smoother.add(part, a[:, s:e], final=e == T)
    fused = step.source == SOURCE_FUSED
    assert fused.sum() > 0.5 * fused.size and (~a).any()
    np.testing.assert_array_equal(pos[fused], oracle.position[fused])
    np.testing.assert_array_equal(cov[fused], oracle.cov[fused])
    np.testing.assert_array_equal(pos[~fused], step.position[~fused])  # the rest untouched
