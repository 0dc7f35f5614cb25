"""Tests of the ``"kinefuse"`` fusion (IMU chain + camera, learned chain-error model)."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU
from kinefuse.pipelines.features import chain_features, imu_features, joint_segments
from kinefuse.pipelines.kinefuse_fusion import RidgeCorrection, estimate_noise, kinefuse_fusion

DT = 1 / 30


def _scenario(T=600, J=2, seed=0, cam_std=0.01, outage=(300, 360)):
    """Smooth motion; chain error = a known function of a feature; camera = truth + noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    ang = 1.2 * np.sin(2 * np.pi * 0.4 * t)[:, None] + np.arange(J)[None] * 0.5  # (T, J)
    truth = np.stack([0.3 * np.cos(ang), 0.3 * np.sin(ang), 0.1 * np.sin(0.5 * ang)], -1)
    feats = np.stack([np.cos(ang), np.sin(ang), np.cos(2 * ang)], -1)  # (T, J, 3)
    err = 0.05 * feats[..., 2:3] * np.array([1.0, -0.5, 0.3]) + 0.02  # function of a feature
    z_imu = truth - err
    z_cam = truth + rng.normal(0.0, cam_std, truth.shape)
    av = np.ones((T, J), dtype=bool)
    av[outage[0] : outage[1]] = False
    return z_imu, z_cam, av, truth, feats


def _rmse(a, b, m=None):
    e = np.sum((a - b) ** 2, -1)
    return float(np.sqrt(np.mean(e if m is None else e[m])))


def test_learned_correction_recovers_known_chain_error():
    zi, zc, av, truth, feats = _scenario()
    res = kinefuse_fusion(zi, zc, av, DT, features=feats)
    out = ~av
    raw = _rmse(zi, truth, out)
    fused = _rmse(res.position, truth, out)
    assert raw > 0.03
    assert fused < 0.2 * raw  # outage RMSE far below the raw chain
    assert np.all(res.source[out] == SOURCE_BRIDGED) and np.all(res.source[av] == SOURCE_FUSED)
    assert res.position.shape == zi.shape and res.cov.shape == (*zi.shape, 3)


def test_causal_mode_recovers_it_too():
    zi, zc, av, truth, feats = _scenario()
    res = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True)
    assert _rmse(res.position, truth, ~av) < 0.3 * _rmse(zi, truth, ~av)


def test_no_outage_output_close_to_camera():
    zi, zc, av, truth, feats = _scenario(cam_std=0.005, outage=(0, 0))
    res = kinefuse_fusion(zi, zc, av, DT, features=feats)
    assert _rmse(res.position, zc) < 0.01  # within ~2 camera noise std
    assert _rmse(res.position, truth) <= _rmse(zc, truth) * 1.05


@pytest.mark.parametrize("lag", [0, 5])
def test_causal_outputs_do_not_depend_on_the_future(lag):
    zi, zc, av, _, feats = _scenario(T=300, outage=(150, 190))
    t_cut = 170
    ref = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True, lag=lag).position
    zi2, zc2, f2 = zi.copy(), zc.copy(), feats.copy()
    rng = np.random.default_rng(5)
    zi2[t_cut + 1 :] += rng.normal(0, 0.2, zi2[t_cut + 1 :].shape)
    zc2[t_cut + 1 :] += rng.normal(0, 0.2, zc2[t_cut + 1 :].shape)
    f2[t_cut + 1 :] += rng.normal(0, 1.0, f2[t_cut + 1 :].shape)
    av2 = av.copy()
    av2[t_cut + 1 :] = ~av2[t_cut + 1 :]
    new = kinefuse_fusion(zi2, zc2, av2, DT, features=f2, causal=True, lag=lag).position
    upto = t_cut + 1 - lag
    np.testing.assert_array_equal(new[:upto], ref[:upto])
    assert not np.allclose(new[t_cut + 1 :], ref[t_cut + 1 :])


def _drifting_chain(T=900, J=2, seed=3, cam_std=0.01, cam_start=0):
    """Chain with a slowly wandering error (heading-drift-like random walk, ~5 cm) that is not a
    function of the features, plus a feature-driven part; camera = truth + white noise."""
    zi, zc, av, truth, feats = _scenario(T=T, J=J, seed=seed, cam_std=cam_std, outage=(0, 0))
    rng = np.random.default_rng(seed + 100)
    walk = np.cumsum(rng.normal(0.0, 0.004, (T, J, 3)), axis=0)
    zi = zi + walk - walk.mean(axis=0)
    av[:cam_start] = False
    return zi, zc, av, truth, feats


@pytest.mark.parametrize("cam_start", [0, 45])
def test_causal_no_drift_when_the_camera_always_sees(cam_start):
    # the chain error wanders by several cm and the camera sees every sample from cam_start:
    # the causal output must stay within about the camera's own error (here 1 cm per axis),
    # also right after a short first history (cam_start > 0: first fit on ~1 s of camera)
    zi, zc, av, truth, feats = _drifting_chain(cam_start=cam_start)
    res = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True)
    seen = av.copy()
    cam = _rmse(zc, truth, seen)
    assert _rmse(zi, truth, seen) > 2 * cam  # the chain alone is far off
    assert _rmse(res.position, truth, seen) <= 1.05 * cam
    # per 1 s window, never far from the camera (no transient drift after a refit)
    for t0 in range(cam_start, zi.shape[0] - 30, 30):
        w = np.zeros_like(seen)
        w[t0 : t0 + 30] = seen[t0 : t0 + 30]
        assert _rmse(res.position, truth, w) <= 1.5 * _rmse(zc, truth, w) + 0.002


def test_causal_short_history_start():
    # camera from sample 40 (1.3 s), first outage after 1.2 s of camera history: the causal
    # output is finite, the chain before the camera, near the camera while it sees, and in the
    # outage no worse than the raw chain
    zi, zc, av, truth, feats = _drifting_chain(T=400, cam_start=40)
    av[76:120] = False
    res = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True)
    assert np.all(np.isfinite(res.position)) and np.all(np.isfinite(res.cov))
    np.testing.assert_allclose(res.position[5:40], zi[5:40], atol=0.02)
    assert np.all(res.source[:40] == SOURCE_IMU)
    seen = av.copy()
    assert _rmse(res.position, truth, seen) <= 1.05 * _rmse(zc, truth, seen)
    out = ~av
    out[:40] = False
    assert _rmse(res.position, truth, out) <= _rmse(zi, truth, out)


def test_causal_streaming_refits_and_lag_use_the_same_filter():
    # the carried filter: with lag > 0 the output is the fixed-lag smoothing of the same
    # forward filter, so at the last sample (nothing after it) both agree exactly
    zi, zc, av, _, feats = _scenario(T=300, outage=(150, 190))
    a = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True)
    b = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True, lag=5)
    np.testing.assert_allclose(a.position[-1], b.position[-1], rtol=0, atol=1e-12)
    assert a.info["n_refits"] == b.info["n_refits"] and min(a.info["n_refits"]) >= 4
    assert np.all(np.linalg.eigvalsh(a.cov) >= 0)


def test_noise_prior_is_used_before_history():
    from kinefuse.pipelines.kinefuse_noise import _Moments

    prm = _Moments(30).noise(DT, prior_pairs=60)  # no data: the prior alone
    assert np.all(prm.var_b > 0) and np.all(prm.phi_b < 1)  # stationary chain error
    assert np.all(prm.var_c == 0)  # white camera
    np.testing.assert_allclose(prm.r_cam, 1e-3, rtol=1e-6)


def test_registered_in_vision_assisted():
    from kinefuse.pipelines import METHODS, FusionResult, VisionParams, vision_assisted

    assert "kinefuse" in METHODS
    zi, zc, av, truth, feats = _scenario()
    for causal in (False, True):
        res = vision_assisted(zi, zc, av, DT, method="kinefuse", causal=causal, features=feats)
        direct = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=causal)
        assert isinstance(res, FusionResult)
        assert res.method == "kinefuse" and res.causal is causal
        assert res.joints == ("joint_0", "joint_1")
        np.testing.assert_array_equal(res.position, direct.position)
        np.testing.assert_array_equal(res.source, direct.source)
        assert res.cov.shape == (*zi.shape, 3)
        assert res.outages[0] == ((300, 360),)
    lagged = vision_assisted(
        zi, zc, av, DT, method="kinefuse", causal=True, params=VisionParams(fixed_lag=3)
    )
    direct = kinefuse_fusion(zi, zc, av, DT, causal=True, lag=3)
    np.testing.assert_array_equal(lagged.position, direct.position)


def test_offline_is_not_causal_and_default_features_work():
    zi, zc, av, truth, _ = _scenario()
    res = kinefuse_fusion(zi, zc, av, DT)  # fallback features from the chain
    assert np.all(np.isfinite(res.position))
    assert _rmse(res.position, truth, ~av) < _rmse(zi, truth, ~av)


def test_outage_at_start_falls_back_to_chain():
    zi, zc, av, truth, feats = _scenario(outage=(0, 40))
    res = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True)
    assert np.all(np.isfinite(res.position))
    np.testing.assert_allclose(res.position[5:40], zi[5:40], atol=0.02)


def test_noise_estimation_recovers_white_noise_levels():
    rng = np.random.default_rng(1)
    T = 3000
    t = np.arange(T) * DT
    p = np.stack([0.3 * np.sin(2 * np.pi * f * t) for f in (0.3, 0.5, 0.7)], -1)
    zc = p + rng.normal(0, 0.02, p.shape)
    zi = p + rng.normal(0, 0.005, p.shape)
    prm = estimate_noise(zc, zi, np.ones(T, bool), DT, max_lag=30)
    # half the model variogram of each sensor's error, r + σ² (1 − φ^k), equals σ_white²; the
    # small chain noise is only resolved at short lags (the motion dominates the estimate's
    # variance at long lags)
    for k in (1, 30):
        vc = prm.r_cam + prm.var_c * (1 - prm.phi_c**k)
        np.testing.assert_allclose(np.sqrt(vc), 0.02, rtol=0.25)
    vi = prm.r_imu + prm.var_b * (1 - prm.phi_b)
    np.testing.assert_allclose(np.sqrt(vi), 0.005, rtol=0.6)


def test_noise_estimation_separates_a_chain_error_that_follows_the_motion():
    # the chain under-reports the motion by 10 % (an error the cross-variogram split would
    # otherwise move into the camera's variogram, as a large coloured camera error)
    rng = np.random.default_rng(3)
    T = 3000
    t = np.arange(T) * DT
    p = np.stack([0.3 * np.sin(2 * np.pi * f * t) for f in (0.3, 0.5, 0.7)], -1)
    zc = p + rng.normal(0, 0.01, p.shape)
    zi = 0.9 * p + rng.normal(0, 0.002, p.shape)
    prm = estimate_noise(zc, zi, np.ones(T, bool), DT, max_lag=30)
    # γ = γ_I − γ_V = 0.1 relative to the motion M; the fit scales the cross-variogram
    # X = 0.9 M, so γ X = 0.1 M needs γ = 0.1 / 0.9
    np.testing.assert_allclose(prm.motion_gain, 0.1 / 0.9, atol=0.01)
    # half the camera's model variogram: its white level at lag 1, and no longer the motion
    # term at lag 30 (the plain split, γ = 0, gives 0.04-0.06 m here and a perfect chain)
    vc = lambda k: np.sqrt(prm.r_cam + prm.var_c * (1 - prm.phi_c**k))  # noqa: E731
    np.testing.assert_allclose(vc(1), 0.01, rtol=0.1)
    assert np.all(vc(30) < 0.025)
    assert np.all(np.sqrt(prm.r_imu + prm.var_b * (1 - prm.phi_b**30)) > 0.005)
    # no motion-following error: γ stays 0 (up to the grid step)
    same = estimate_noise(zc, p + rng.normal(0, 0.002, p.shape), np.ones(T, bool), DT, max_lag=30)
    np.testing.assert_allclose(same.motion_gain, 0.0, atol=0.01)


def test_ridge_partial_fit_equals_fit():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(200, 4))
    Y = X @ rng.normal(size=(4, 2)) + 0.1 * rng.normal(size=(200, 2))
    a = RidgeCorrection(block=20).fit(X, Y)
    b = RidgeCorrection(block=20).partial_fit(X[:90], Y[:90], np.arange(90))
    b.partial_fit(X[90:], Y[90:], np.arange(90, 200))
    np.testing.assert_allclose(a.coef_, b.coef_, rtol=1e-9, atol=1e-12)
    assert a.alpha_ == b.alpha_
    assert np.all(np.isfinite(a.cv_error_))


def test_features_helpers():
    from kinefuse.io.recording import ImuStream
    from kinefuse.kinematics import upper_limb

    sk = upper_limb("r", lengths={"upper_arm_r": 0.3, "forearm_r": 0.25})
    assert joint_segments(sk, "elbow_r") == ("upper_arm_r", "forearm_r")
    t = np.arange(50) / 100.0
    ang = np.linspace(0, 1, 50)
    q = np.stack([np.cos(ang / 2), np.zeros(50), np.zeros(50), np.sin(ang / 2)], -1)
    streams = {s: ImuStream(t_s=t, q_world_from_sensor=q) for s in sk.segments}
    f = imu_features(streams, sk, ["elbow_r", "wrist_r"], t[::3])
    assert f.shape == (17, 2, 2 * 12 + 9)
    rate = 1.0 / 0.49  # rad/s about z
    np.testing.assert_allclose(f[1:, 0, 9:12], [[0.0, 0.0, rate]] * 16, rtol=1e-9, atol=1e-9)
    c = chain_features(np.ones((5, 2, 3)), DT, parents=[-1, 0])
    assert c.shape == (5, 2, 10) and np.all(c[0, :, -3:] == 0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"z_imu": np.zeros((10, 2))}, "shape"),
        ({"z_cam": np.zeros((10, 3, 3))}, "shape"),
        ({"available": np.ones((10, 2))}, "bool"),
        ({"dt_s": 0.0}, "dt_s"),
        ({"dt_s": "x"}, "dt_s"),
        ({"features": np.zeros((9, 2, 4))}, "features"),
        ({"lag": 3}, "lag"),
        ({"causal": "yes"}, "causal"),
    ],
)
def test_bad_input(kwargs, match):
    args = dict(
        z_imu=np.zeros((10, 2, 3)),
        z_cam=np.zeros((10, 2, 3)),
        available=np.ones((10, 2), bool),
        dt_s=DT,
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        kinefuse_fusion(
            args.pop("z_imu"), args.pop("z_cam"), args.pop("available"), args.pop("dt_s"), **args
        )


def test_bad_input_inf_and_unknown_joint():
    with pytest.raises(ValueError, match="inf"):
        kinefuse_fusion(np.full((4, 1, 3), np.inf), np.zeros((4, 1, 3)), np.ones((4, 1), bool), DT)
    from kinefuse.kinematics import upper_limb

    with pytest.raises(ValueError, match="distal"):
        joint_segments(upper_limb("r", lengths={"upper_arm_r": 0.3, "forearm_r": 0.25}), "knee_l")


def test_offline_bridge_is_the_mean_of_smoother_and_both_sided_bridges():
    from kinefuse.pipelines.offset_bridge import prequential_bridge

    zi, zc, av, truth, feats = _scenario(J=1, cam_std=0.002)
    zi = zi - np.array([0.04, -0.02, 0.03])  # plus a constant chain offset
    on = kinefuse_fusion(zi, zc, av, DT, features=feats)
    off = kinefuse_fusion(zi, zc, av, DT, features=feats, bridge=False)
    out = ~av[:, 0]
    np.testing.assert_array_equal(on.position[~out], off.position[~out])  # in view: unchanged
    base = (zi[:, 0], zi[:, 0] + on.correction[:, 0])
    fwd, _, _ = prequential_bridge(base, zc[:, 0], av[:, 0])
    bwd, _, _ = prequential_bridge([b[::-1] for b in base], zc[::-1, 0], av[::-1, 0])
    want = (off.position[:, 0] + fwd + bwd[::-1]) / 3.0
    np.testing.assert_allclose(on.position[out, 0], want[out], rtol=0, atol=1e-12)
    # each part recovers the truth here, so does the mean; its variance bounds the parts'
    assert _rmse(on.position[out, 0], truth[out, 0]) < 0.01
    var = on.cov[out, 0][:, range(3), range(3)]
    assert np.all(var > 0) and np.all(np.isfinite(var))
    assert np.all(on.source[out] == SOURCE_BRIDGED)


def test_correction_cross_validates_over_2_s_blocks_offline_and_1_s_causal():
    # blocks longer than a gait cycle keep the validation honest (module Notes); at 30 Hz:
    zi, zc, av, _, feats = _scenario()
    off = kinefuse_fusion(zi, zc, av, DT, features=feats)
    cau = kinefuse_fusion(zi, zc, av, DT, features=feats, causal=True)
    assert [p["correction"].block for p in off.params] == [60, 60]
    assert [p["correction"].block for p in cau.params] == [30, 30]
