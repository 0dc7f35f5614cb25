"""Tests of the simple baselines registered in kinefuse.pipelines.METHODS (issue 11, point 4).

``offset-interp`` (offline), ``offset-hold`` (causal), ``camera-gapfill`` (Pose2Sim-like gap
filling): each checked against a closed form or a plain loop written here, plus causality.
"""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_CAMERA, SOURCE_IMU
from kinefuse.pipelines import METHODS, SOURCE_NONE, vision_assisted

DT = 1 / 30


def _scenario(seed=1, T=400, J=2):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    truth = np.stack(
        [np.stack([0.2 * np.sin(0.7 * t + j + k) for k in range(3)], -1) for j in range(J)], 1
    )
    cam = truth + rng.normal(0, 0.01, truth.shape)
    av = np.ones((T, J), dtype=bool)
    av[100:130, 0] = False  # 30 samples
    av[200:220, 0] = False  # 20 samples
    av[:5, 1] = False  # before the first camera sample
    av[300:321, 1] = False  # 21 samples
    av[390:, 1] = False  # after the last one
    return t, truth, cam, av


@pytest.mark.parametrize("name", ["offset-interp", "offset-hold", "camera-gapfill"])
def test_baselines_are_registered_with_docstrings(name):
    assert name in METHODS
    assert len((METHODS[name].__doc__ or "").strip()) > 100


def test_offset_interp_is_exact_for_a_linearly_drifting_chain_error():
    t, truth, cam, av = _scenario()
    drift = 0.05 + 0.1 * t[:, None, None] * np.array([1.0, -0.5, 0.2])  # linear in time
    chain = truth + drift
    cam = truth.copy()  # noise-free camera: interpolation of a linear offset is exact
    res = vision_assisted(chain, cam, av, DT, "offset-interp")
    inner = av.copy()
    inner[:5, 1] = inner[390:, 1] = True  # ends hold the offset: exact only between samples
    np.testing.assert_allclose(res.position[~inner], truth[~inner], atol=1e-12)
    np.testing.assert_array_equal(res.position[av], cam[av])
    assert np.all(res.source[av] == SOURCE_CAMERA)
    assert np.all(res.source[~av] == SOURCE_BRIDGED)
    assert not res.causal
    # before the first seen sample the first offset is held
    d0 = cam[5, 1] - chain[5, 1]
    np.testing.assert_allclose(res.position[:5, 1], chain[:5, 1] + d0, atol=1e-12)


def test_offset_hold_matches_a_plain_loop_and_is_causal():
    t, truth, cam, av = _scenario(seed=2)
    rng = np.random.default_rng(5)
    chain = truth + 0.04 + rng.normal(0, 0.01, truth.shape)
    res = vision_assisted(chain, cam, av, DT, "offset-hold")
    assert res.causal
    T, J, _ = chain.shape
    want = np.empty_like(chain)
    for j in range(J):
        seen = []
        for k in range(T):
            if av[k, j]:
                seen.append(cam[k, j] - chain[k, j])
                want[k, j] = cam[k, j]
            elif seen:
                want[k, j] = chain[k, j] + np.mean(seen[-5:], axis=0)
            else:
                want[k, j] = chain[k, j]
    np.testing.assert_allclose(res.position, want, atol=1e-12)
    assert np.all(res.source[:5, 1] == SOURCE_IMU)
    # causal: changing the future leaves the past unchanged
    chain2, cam2 = chain.copy(), cam.copy()
    chain2[250:] += 0.3
    cam2[250:] -= 0.2
    res2 = vision_assisted(chain2, cam2, av, DT, "offset-hold")
    np.testing.assert_array_equal(res2.position[:250], res.position[:250])


def test_camera_gapfill_fills_gaps_up_to_20_samples_only():
    t, truth, cam, av = _scenario(seed=3)
    chain = truth + 0.05
    res = vision_assisted(chain, cam, av, DT, "camera-gapfill")
    p = res.position
    assert not res.causal
    # 30-sample gap and the edges: no estimate; 21 samples: none either
    for j, sl in (
        (0, slice(100, 130)),
        (1, slice(0, 5)),
        (1, slice(300, 321)),
        (1, slice(390, None)),
    ):
        assert np.all(np.isnan(p[sl, j])), sl
        assert np.all(res.source[sl, j] == SOURCE_NONE)
    # the 20-sample gap: linear interpolation between samples 199 and 220
    k = np.arange(200, 220)
    w = ((k - 199) / 21.0)[:, None]
    np.testing.assert_allclose(p[200:220, 0], (1 - w) * cam[199, 0] + w * cam[220, 0], atol=1e-12)
    assert np.all(res.source[200:220, 0] == SOURCE_BRIDGED)
    np.testing.assert_array_equal(p[av], cam[av])


def test_baselines_ignore_the_camera_where_it_is_unavailable():
    t, truth, cam, av = _scenario(seed=4)
    chain = truth + 0.05
    cam2 = cam.copy()
    cam2[~av] += 0.1  # values behind available == False must not matter
    for m in ("offset-interp", "offset-hold", "camera-gapfill"):
        a = vision_assisted(chain, cam, av, DT, m).position
        b = vision_assisted(chain, cam2, av, DT, m).position
        np.testing.assert_array_equal(a, b)


def test_baselines_run_as_session_methods_and_appear_in_the_evaluation():
    from kinefuse.apps.demo import demo_recording
    from kinefuse.pipelines.run import process_recording

    rec = demo_recording()
    out = process_recording(rec, "offset-interp", {})
    assert out.label == "offset interp"
    np.testing.assert_array_equal(out.position, out.baselines["offset interp"])
    ev = out.evaluation()
    assert ev.methods[0] == "offset interp"
    assert {"offset hold", "camera gap-fill", "IMU chain"} <= set(ev.methods)
    assert ev.methods.count("offset interp") == 1


def test_joint_major_outputs_are_returned_without_a_copy():
    """``empty_output``'s arrays are joint-major views of time-major arrays: ``finish`` returns
    those arrays themselves (no transposing copy of the covariances), with the values written
    through the views."""
    from kinefuse.pipelines.fusion_context import empty_output, finish, joint_major

    _, truth, cam, av = _scenario()
    a = joint_major(2, 5, (3, 3), fill=0.0)
    assert a.shape == (2, 5, 3, 3) and np.swapaxes(a, 0, 1).flags.c_contiguous
    res = vision_assisted(truth, cam, av, DT, "offset-hold")  # written into empty_output's
    assert res.position.flags.c_contiguous and res.cov.flags.c_contiguous
    pos = joint_major(2, 400, (3,), fill=np.nan)
    pos[1, 7] = 1.5
    cov = joint_major(2, 400, (3, 3), fill=np.nan)
    src = joint_major(2, 400, dtype=np.int8, fill=SOURCE_NONE)
    ctx = type("Ctx", (), {"shape": (2, 400), "available": av.T, "joints": ("a", "b"),
                           "method": "m", "dt_s": DT, "params": res.params})()  # fmt: skip
    out = finish(ctx, pos, cov, src, causal=True)
    assert np.shares_memory(out.position, pos) and np.shares_memory(out.cov, cov)
    assert out.position[7, 1, 0] == 1.5 and out.position.shape == (400, 2, 3)
    _, c2, s2 = empty_output(ctx)
    assert np.swapaxes(c2, 0, 1).flags.c_contiguous and s2.dtype == np.int8
