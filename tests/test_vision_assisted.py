"""Tests of the paper-B pipeline (kinefuse.pipelines.vision_assisted; SPEC §10.3)."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_CAMERA, SOURCE_FUSED, SOURCE_IMU
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.models import constant_velocity
from kinefuse.pipelines import (
    METHODS,
    SOURCE_NONE,
    FusionResult,
    VisionParams,
    register_method,
    vision_assisted,
)
from kinefuse.pipelines._outages import find_episodes, interpolate_gaps

DT = 1 / 30


def make_scenario(seed: int = 3, T: int = 900, J: int = 3, f_max: float = 0.25):
    """Smooth 3-D trajectories; IMU = truth + slowly varying offset + noise; camera with outages."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    truth = np.zeros((T, J, 3))
    offset = np.zeros((T, J, 3))
    for j in range(J):
        for k in range(3):
            f = rng.uniform(0.05, f_max, 3)
            ph = rng.uniform(0, 2 * np.pi, 3)
            a = rng.uniform(0.05, 0.2, 3)
            truth[:, j, k] = (a * np.sin(2 * np.pi * f * t[:, None] + ph)).sum(axis=1)
            offset[:, j, k] = 0.06 * rng.choice([-1, 1]) + 0.02 * np.sin(
                2 * np.pi * t / 200 + rng.uniform(0, 6)
            )
    z_imu = truth + offset + rng.normal(0, 0.01, (T, J, 3))
    z_cam = truth + rng.normal(0, 0.02, (T, J, 3))
    available = np.ones((T, J), dtype=bool)
    for j in range(J):
        for s in (320 + 90 * j, 650 + 40 * j):
            available[s : s + 45, j] = False
    return truth, z_imu, z_cam, available


@pytest.fixture(scope="module")
def scenario():
    return make_scenario()


def fir1_positions(z_imu, params=None):
    params = VisionParams() if params is None else params
    model = constant_velocity(DT, params.q, params.r_imu)
    _, res = UFIRFilter(model, horizon=params.horizon).filter(
        np.ascontiguousarray(z_imu.transpose(1, 0, 2))
    )
    return res.position.transpose(1, 0, 2)


# ------------------------------------------------------------------------------ outage bookkeeping
def test_episode_merge_rule_back_to_back():
    av = np.ones(200, dtype=bool)
    av[50:60] = False
    av[70:80] = False  # 10 available samples between: fewer than N = 20 -> one episode
    av[120:130] = False
    av[150:160] = False  # exactly 20 available samples between: two episodes
    eps = find_episodes(av, 20)
    assert eps == [(50, 100, 80, True), (120, 150, 130, True), (150, 180, 160, True)]


def test_episode_without_recovery_runs_to_end():
    av = np.ones(100, dtype=bool)
    av[:5] = False
    av[90:] = False
    assert find_episodes(av, 20) == [(0, 25, 5, True), (90, 100, 100, False)]


def test_interpolate_gaps_closed_form():
    v = np.array([[np.nan] * 3, [0.0, 0, 0], [np.nan] * 3, [np.nan] * 3, [3.0, 6, 9], [np.nan] * 3])
    av = np.all(np.isfinite(v), axis=1)
    out, filled = interpolate_gaps(v, av)
    assert np.all(np.isnan(out[0]))
    np.testing.assert_allclose(out[1:], [[0, 0, 0], [1, 2, 3], [2, 4, 6], [3, 6, 9], [3, 6, 9]])
    np.testing.assert_array_equal(filled, [False, False, True, True, False, True])


# ------------------------------------------------------------------------------ methods
def test_camera_only_interpolation_and_sources():
    T = 10
    z = np.zeros((T, 1, 3))
    z[:, 0, 0] = np.arange(T, dtype=float)
    z[:, 0, 1] = 2.0 * np.arange(T)
    av = np.ones((T, 1), dtype=bool)
    av[:2] = False  # before the first camera sample: NaN
    av[4:7] = False  # gap: linear between t = 3 and t = 7
    av[9:] = False  # after the last: held
    zc = z.copy()
    zc[~av] = 123.0  # ignored where unavailable
    r = vision_assisted(np.zeros_like(z), zc, av, DT, "camera-only")
    assert np.all(np.isnan(r.position[:2]))
    np.testing.assert_allclose(r.position[2:9, 0, 0], np.arange(2, 9, dtype=float))
    np.testing.assert_allclose(r.position[2:9, 0, 1], 2.0 * np.arange(2, 9))
    np.testing.assert_allclose(r.position[9, 0], z[8, 0])
    expected = (
        [SOURCE_NONE] * 2
        + [SOURCE_CAMERA] * 2
        + [SOURCE_BRIDGED] * 3
        + [SOURCE_CAMERA] * 2
        + [SOURCE_BRIDGED]
    )
    np.testing.assert_array_equal(r.source[:, 0], expected)
    assert r.causal is False


def test_imu_only_equals_fir1(scenario):
    _, zi, zc, av = scenario
    r = vision_assisted(zi, zc, av, DT, "imu-only")
    np.testing.assert_allclose(r.position, fir1_positions(zi), rtol=0, atol=1e-12)
    assert np.all(r.source == SOURCE_IMU)
    assert r.cov.shape == (*zi.shape, 3)


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
def test_sources_and_diagnostics(scenario, method):
    _, zi, zc, av = scenario
    r = vision_assisted(zi, zc, av, DT, method, joints=("a", "b", "c"))
    assert isinstance(r, FusionResult)
    T, J, _ = zi.shape
    assert r.position.shape == (T, J, 3) and r.cov.shape == (T, J, 3, 3)
    assert r.source.shape == (T, J) and r.source.dtype == np.int8
    assert r.mu.shape == (T, J, 2) and r.joints == ("a", "b", "c")
    in_ep = np.zeros((T, J), dtype=bool)
    for j in range(J):
        for ep in r.episodes[j]:
            in_ep[ep.start : ep.stop, j] = True
            assert ep.mode == "bridged"
    np.testing.assert_array_equal(r.source[~in_ep], SOURCE_FUSED)
    np.testing.assert_array_equal(r.source[in_ep], SOURCE_BRIDGED)
    assert np.all(av[~in_ep])  # every unavailable sample lies in an episode
    assert np.all(np.isnan(r.mu[~av])) and np.allclose(r.mu[av].sum(-1), 1.0)
    assert np.all(np.isfinite(r.position)) and np.all(np.isfinite(r.cov))
    assert r.outages[0] == ((320, 365), (650, 695))
    # first episode of joint 0: 320 available samples before it, all used (< W = 600)
    ep0 = r.episodes[0][0]
    assert (ep0.start, ep0.stop, ep0.train_start, ep0.n_train) == (320, 385, 0, 320)
    assert ep0.n_train_elm2 == 320 and not ep0.elm2_skipped


def test_outage_errors_well_below_raw_offset(scenario):
    truth, zi, zc, av = scenario
    raw = np.sqrt(np.mean(np.sum((zi - truth)[~av] ** 2, axis=-1)))
    imu_only = vision_assisted(zi, zc, av, DT, "imu-only")
    e_imu = np.sqrt(np.mean(np.sum((imu_only.position - truth)[~av] ** 2, axis=-1)))
    assert e_imu > 0.8 * raw  # FIR-1 keeps the IMU offset
    for method in ("elm-fir", "elm-kf"):
        r = vision_assisted(zi, zc, av, DT, method)
        err = np.sqrt(np.mean(np.sum((r.position - truth)[~av] ** 2, axis=-1)))
        assert err < 0.5 * raw, (method, err, raw)
        fused = np.sqrt(
            np.mean(np.sum((r.position - truth)[r.source == SOURCE_FUSED] ** 2, axis=-1))
        )
        assert fused < 0.03  # camera noise 2 cm per axis, smoothed


def test_outage_at_start_is_imu_only_and_flagged(scenario):
    _, zi, zc, av = scenario
    av = av.copy()
    av[:60, 0] = False
    r = vision_assisted(zi, zc, av, DT, "elm-fir")
    ep = r.episodes[0][0]
    assert (ep.start, ep.stop, ep.mode) == (0, 80, "imu-fallback")
    assert np.all(r.source[:80, 0] == SOURCE_IMU) and np.all(r.imu_fallback[:80, 0])
    assert not np.any(r.imu_fallback[80:, 0]) and not np.any(r.imu_fallback[:, 1:])
    np.testing.assert_allclose(r.position[:80, 0], fir1_positions(zi)[:80, 0], atol=1e-12)
    assert r.source[80, 0] == SOURCE_FUSED


def test_back_to_back_outages_merge_into_one_episode(scenario):
    _, zi, zc, av = scenario
    av = av.copy()
    av[:, 1] = True
    av[400:430, 1] = False
    av[440:470, 1] = False  # 10 < N available samples between
    r = vision_assisted(zi, zc, av, DT, "elm-fir")
    eps = r.episodes[1]
    assert [(e.start, e.stop, e.recovery_start) for e in eps] == [(400, 490, 470)]
    assert np.all(r.source[400:490, 1] == SOURCE_BRIDGED)
    assert r.source[399, 1] == SOURCE_FUSED and r.source[490, 1] == SOURCE_FUSED
    # FIR-2 and the IMM were fed during the available samples inside the episode
    assert np.all(np.isfinite(r.mu[430:440, 1]))


def test_too_short_segment_skips_elm2(scenario):
    _, zi, zc, av = scenario
    av = av.copy()
    av[:, 2] = True
    av[300:330, 2] = False
    av[400:430, 2] = False  # segment before onset 400 has 70 samples < 200
    r = vision_assisted(zi, zc, av, DT, "elm-fir")
    ep = r.episodes[2][1]
    assert ep.start == 400 and ep.elm2_skipped and ep.n_train_elm2 == 70
    assert np.all(r.elm2_skipped[400:450, 2]) and not np.any(r.elm2_skipped[:400, 2])
    assert np.all(r.source[400:450, 2] == SOURCE_BRIDGED)


def test_all_outage_joint(scenario):
    _, zi, zc, av = scenario
    av = av.copy()
    av[:, 1] = False
    r = vision_assisted(zi, zc, av, DT, "elm-fir")
    assert np.all(r.source[:, 1] == SOURCE_IMU) and np.all(r.imu_fallback[:, 1])
    np.testing.assert_allclose(r.position[:, 1], fir1_positions(zi)[:, 1], atol=1e-12)
    assert np.all(np.isnan(r.mu[:, 1]))
    assert np.all(r.source[:, 0] != SOURCE_IMU)


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
@pytest.mark.parametrize("t_cut", [340, 500])  # inside an episode / inside an available stretch
def test_causal_mode_never_reads_future(scenario, method, t_cut):
    _, zi, zc, av = scenario
    r = vision_assisted(zi, zc, av, DT, method, causal=True)
    assert r.causal
    rng = np.random.default_rng(11)
    zi2, zc2, av2 = zi.copy(), zc.copy(), av.copy()
    zi2[t_cut + 1 :] += rng.normal(0, 0.3, zi2[t_cut + 1 :].shape)
    zc2[t_cut + 1 :] += rng.normal(0, 0.3, zc2[t_cut + 1 :].shape)
    av2[t_cut + 1 :] = rng.random(av2[t_cut + 1 :].shape) < 0.5
    r2 = vision_assisted(zi2, zc2, av2, DT, method, causal=True)
    sl = slice(0, t_cut + 1)
    np.testing.assert_array_equal(r.position[sl], r2.position[sl])
    np.testing.assert_array_equal(r.cov[sl], r2.cov[sl])
    np.testing.assert_array_equal(r.source[sl], r2.source[sl])
    np.testing.assert_array_equal(r.mu[sl], r2.mu[sl])
    # the offline mode does read the future (RTS): the same perturbation changes the past
    o1 = vision_assisted(zi, zc, av, DT, method)
    o2 = vision_assisted(zi2, zc2, av2, DT, method)
    assert not o1.causal and not np.array_equal(o1.position[sl], o2.position[sl])


def test_causal_fixed_lag_is_delayed(scenario):
    _, zi, zc, av = scenario
    r = vision_assisted(zi, zc, av, DT, "elm-fir", causal=True, params=VisionParams(fixed_lag=10))
    f = vision_assisted(zi, zc, av, DT, "elm-fir", causal=True)
    assert not r.causal
    fused = r.source == SOURCE_FUSED
    assert not np.allclose(r.position[fused], f.position[fused])
    np.testing.assert_array_equal(r.source, f.source)


def test_elm2_input_and_linear_skip_options_run(scenario):
    truth, zi, zc, av = scenario
    for p in (VisionParams(elm2_input="fir3_out"), VisionParams(linear_skip=True, alpha=1e-3)):
        r = vision_assisted(zi, zc, av, DT, "elm-fir", params=p)
        assert np.all(np.isfinite(r.position)) and np.all(r.source[~av] == SOURCE_BRIDGED)


def test_features_extend_elm1_input(scenario):
    _, zi, zc, av = scenario
    feats = np.zeros((*zi.shape[:2], 2))
    r = vision_assisted(zi, zc, av, DT, "elm-fir", features=feats)
    assert np.all(np.isfinite(r.position))
    with pytest.raises(ValueError, match=r"expected features .*\(900, 3, F\).*got \(900, 2, 2\)"):
        vision_assisted(zi, zc, av, DT, "elm-fir", features=feats[:, :2])


def test_register_method_extension_point(scenario):
    _, zi, zc, av = scenario

    def constant(ctx):
        J, T = ctx.shape
        return FusionResult(
            position=np.zeros((T, J, 3)),
            cov=np.zeros((T, J, 3, 3)),
            source=np.zeros((T, J), np.int8),
            joints=ctx.joints,
            method=ctx.method,
        )

    register_method("test-constant", constant)
    try:
        r = vision_assisted(zi, zc, av, DT, "test-constant")
        assert r.method == "test-constant" and np.all(r.position == 0)
        with pytest.raises(ValueError, match="already registered"):
            register_method("test-constant", constant)
    finally:
        METHODS.pop("test-constant", None)


# ------------------------------------------------------------------------------ bad input
def test_bad_input_names_expected_and_actual(scenario):
    _, zi, zc, av = scenario
    with pytest.raises(
        ValueError, match=r"expected z_cam with the shape of z_imu \(900, 3, 3\).*got \(900, 2, 3\)"
    ):
        vision_assisted(zi, zc[:, :2], av, DT)
    with pytest.raises(
        ValueError, match=r"expected available with shape \(T, J\) = \(900, 3\), got \(899, 3\)"
    ):
        vision_assisted(zi, zc, av[1:], DT)
    with pytest.raises(ValueError, match=r"expected z_imu with shape \(T, J, 3\), got \(900, 3\)"):
        vision_assisted(zi[:, 0], zc[:, 0], av[:, 0], DT)
    with pytest.raises(ValueError, match=r"expected available as a bool array .* got dtype"):
        vision_assisted(zi, zc, av.astype(float), DT)
    with pytest.raises(ValueError, match=r"unknown method 'elm-svm'; expected one of"):
        vision_assisted(zi, zc, av, DT, "elm-svm")
    for dt in (0.0, -1 / 30, float("nan")):
        with pytest.raises(ValueError, match=r"expected dt_s finite and > 0, got"):
            vision_assisted(zi, zc, av, dt)
    with pytest.raises(ValueError, match=r"expected 3 joint names"):
        vision_assisted(zi, zc, av, DT, joints=("a", "b"))
    bad = zi.copy()
    bad[:, 2] = np.nan
    with pytest.raises(ValueError, match=r"at least one finite sample per joint.*\[2\]"):
        vision_assisted(bad, zc, av, DT)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"q": -1.0}, "expected q finite and >= 0"),
        ({"r_imu": 0.0}, "expected r_imu finite and > 0"),
        ({"r_cam": np.eye(2)}, r"expected r_cam as a scalar or shape \(3, 3\), got \(2, 2\)"),
        ({"horizon": 3}, "expected horizon as an int >= 7"),
        ({"transition": [[0.9, 0.2], [0.1, 0.9]]}, "expected transition rows summing to 1"),
        ({"elm2_input": "rts"}, "expected elm2_input in"),
        ({"clip_factor": 0}, "expected clip_factor finite and > 0"),
        ({"train_window": 1.5}, "expected train_window as an int"),
        ({"fixed_lag": -1}, "expected fixed_lag as an int >= 0"),
    ],
)
def test_vision_params_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        VisionParams(**kwargs)


def test_vision_params_defaults():
    p = VisionParams()
    assert p.min_samples() == 200 and VisionParams(linear_skip=True).min_samples() == 240
    np.testing.assert_array_equal(p.r_imu, 0.01 * np.eye(3))
    assert not p.r_cam.flags.writeable


# ------------------------------------------------------------------------------ recordings
def test_from_recording_on_virtual_cmu():
    import kinefuse.sim as sim
    from kinefuse.data import demo_motion
    from kinefuse.pipelines import vision_assisted_from_recording

    rec = sim.virtual_recording(demo_motion(), seed=1)
    out = vision_assisted_from_recording(rec, method="elm-fir")
    r = out.result
    T = rec.vision.t_s.size
    assert r.position.shape == (T, 8, 3) and out.reference.shape == (T, 8, 3)
    assert r.joints[0] == "elbow_l"
    # camera frame ENU; estimated from VQF 9D orientations and a Kinect-like camera: a few degrees
    np.testing.assert_allclose(out.R_world_from_camera, np.eye(3), atol=0.1)
    err = np.linalg.norm(r.position - out.reference, axis=-1)
    fused = r.source == SOURCE_FUSED
    # the virtual Kinect's tracking error alone is 3 cm per axis (kinefuse.sim.camera)
    assert np.sqrt(np.mean(err[fused] ** 2)) < 0.10
    assert set(np.unique(r.source)) <= {SOURCE_FUSED, SOURCE_BRIDGED, SOURCE_IMU}
    raw = np.linalg.norm(out.z_imu - out.reference, axis=-1)
    assert np.sqrt(np.mean(raw**2)) < 0.07  # IMU chain: VQF orientation, soft tissue, mounting
