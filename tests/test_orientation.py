"""Orientation: VQF adapter (batch == vqf, stream == batch), gyro integration, SLERP resampling, BROAD."""

from __future__ import annotations

import re

import numpy as np
import pytest
import vqf
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError
from kinefuse.orientation import (
    MAX_GAP_S,
    OrientationEstimator,
    default_max_gap_s,
    estimate,
    integrate_gyro,
    rate_from_orientation,
    slerp_resample,
)

FS = 100.0


@pytest.fixture
def imu(rng):
    """Noisy, smoothly rotating synthetic IMU (6 s at 100 Hz) from a known orientation trajectory."""
    T = 600
    t = np.arange(T + 1) / FS
    rotvec = np.stack(
        [0.6 * np.sin(1.1 * t), 0.4 * np.sin(0.7 * t + 1), 1.5 * np.sin(0.3 * t)], axis=1
    )
    q = Rotation.from_rotvec(rotvec).as_quat(scalar_first=True)
    gyr = rate_from_orientation(q, 1 / FS)
    R = Rotation.from_quat(q[1:], scalar_first=True)
    acc = R.inv().apply([0.0, 0.0, 9.81]) + 0.05 * rng.standard_normal((T, 3))
    mag = R.inv().apply([0.0, 20.0, -40.0]) + 0.2 * rng.standard_normal((T, 3))
    return {"acc": acc, "gyr": gyr + 0.002 * rng.standard_normal((T, 3)), "mag": mag, "q": q[1:]}


# ---------------------------------------------------------------- estimate == vqf
@pytest.mark.parametrize("use_mag", [False, True])
def test_estimate_equals_vqf_bit_for_bit(imu, use_mag):
    mag = imu["mag"] if use_mag else None
    q = estimate(imu["acc"], imu["gyr"], mag, rate_hz=FS)
    out = vqf.VQF(1 / FS).updateBatch(imu["gyr"], imu["acc"], mag)
    np.testing.assert_array_equal(q, out["quat9D" if use_mag else "quat6D"])
    assert q.shape == (600, 4)


def test_estimate_offline_and_params_equal_vqf(imu):
    params = {"tauAcc": 1.5, "magDistRejectionEnabled": False}
    q = estimate(imu["acc"], imu["gyr"], imu["mag"], rate_hz=FS, offline=True, params=params)
    np.testing.assert_array_equal(
        q, vqf.offlineVQF(imu["gyr"], imu["acc"], imu["mag"], 1 / FS, params)["quat9D"]
    )
    q = estimate(imu["acc"], imu["gyr"], rate_hz=FS, params=params)
    np.testing.assert_array_equal(
        q, vqf.VQF(1 / FS, **params).updateBatch(imu["gyr"], imu["acc"])["quat6D"]
    )


def test_estimate_frame_is_enu_with_sensor_to_world(imu):
    q = estimate(imu["acc"], imu["gyr"], imu["mag"], rate_hz=FS)
    # 9D: heading referenced to the magnetic field (north = +y): after convergence close to truth
    err = (
        Rotation.from_quat(q, scalar_first=True)
        * Rotation.from_quat(imu["q"], scalar_first=True).inv()
    ).magnitude()
    assert np.degrees(np.median(err[300:])) < 3.0
    # 6D: the sensor z axis in the world frame follows the true inclination
    q6 = estimate(imu["acc"], imu["gyr"], rate_hz=FS)
    up_est = Rotation.from_quat(q6, scalar_first=True).inv().apply([0, 0, 1])
    up_true = Rotation.from_quat(imu["q"], scalar_first=True).inv().apply([0, 0, 1])
    assert np.degrees(np.median(np.arccos(np.clip(np.sum(up_est * up_true, 1), -1, 1))[300:])) < 2.0


@pytest.mark.parametrize("use_mag", [False, True])
def test_stream_equals_batch_and_checkpoint(imu, use_mag):
    batch = estimate(imu["acc"], imu["gyr"], imu["mag"] if use_mag else None, rate_hz=FS)
    est = OrientationEstimator(FS)
    out = []
    for k in range(200):
        if k == 120:
            saved = est.state
        out.append(est.update(imu["acc"][k], imu["gyr"][k], imu["mag"][k] if use_mag else None))
    np.testing.assert_array_equal(np.array(out), batch[:200])
    # restore the checkpoint and resume: identical continuation
    est.state = saved
    again = [
        est.update(imu["acc"][k], imu["gyr"][k], imu["mag"][k] if use_mag else None)
        for k in range(120, 200)
    ]
    np.testing.assert_array_equal(np.array(again), batch[120:200])
    est.reset()
    np.testing.assert_array_equal(
        est.update(imu["acc"][0], imu["gyr"][0]),
        estimate(imu["acc"][:1], imu["gyr"][:1], rate_hz=FS)[0],
    )
    assert est.bias_rad_s.shape == (3,)


def test_estimate_bad_input(imu):
    acc, gyr = imu["acc"], imu["gyr"]
    with pytest.raises(InputError, match=r"gyr with shape \(T, 3\) = \(600, 3\).*\(599, 3\)"):
        estimate(acc, gyr[:-1], rate_hz=FS)
    with pytest.raises(ValueError, match=r"acc with shape \(T, 3\), got \(600, 4\)"):
        estimate(np.zeros((600, 4)), gyr, rate_hz=FS)
    bad = acc.copy()
    bad[7, 1] = np.nan
    with pytest.raises(InputError, match="finite acc.*sample 7"):
        estimate(bad, gyr, rate_hz=FS)
    with pytest.raises(InputError, match="float array"):
        estimate(acc.astype(int), gyr, rate_hz=FS)
    with pytest.raises(InputError, match="unknown orientation method 'madgwick'"):
        estimate(acc, gyr, rate_hz=FS, method="madgwick")
    with pytest.raises(InputError, match=r"unknown VQF parameter\(s\) \['tau_acc'\]"):
        estimate(acc, gyr, rate_hz=FS, params={"tau_acc": 1.0})
    with pytest.raises(InputError, match="rate_hz finite and > 0"):
        estimate(acc, gyr, rate_hz=0.0)
    # VQF asserts these in C++: without the check the Python process aborted (exit 134)
    for bad_params, msg in (
        ({"tauAcc": -1.0}, "'tauAcc': expected a finite number > 0, got -1.0"),
        ({"restFilterTau": 0.0}, "'restFilterTau': expected a finite number > 0"),
        ({"tauAcc": "x"}, "'tauAcc': expected a number, got 'x'"),
        ({"restBiasEstEnabled": 1}, "'restBiasEstEnabled': expected True or False"),
        ({"biasClip": np.nan}, "'biasClip': expected a finite number"),
    ):
        for offline in (False, True):
            with pytest.raises(InputError, match=re.escape(msg)):
                estimate(acc, gyr, rate_hz=FS, params=bad_params, offline=offline)
    with pytest.raises(InputError, match=r"acc with shape \(3,\)"):
        OrientationEstimator(FS).update(acc[:2], gyr[0])


# ---------------------------------------------------------------- gyro integration
def test_integrate_gyro_constant_rate_matches_scipy():
    q0 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_quat(scalar_first=True)
    w = np.tile([0.0, 0.0, np.pi / 2], (100, 1))  # 90 deg/s about sensor z for 1 s
    q = integrate_gyro(q0, w, 0.01)
    assert q.shape == (101, 4)
    expected = Rotation.from_quat(q0, scalar_first=True) * Rotation.from_rotvec([0, 0, np.pi / 2])
    assert (Rotation.from_quat(q[-1], scalar_first=True) * expected.inv()).magnitude() < 1e-12


def test_integrate_gyro_inverts_rate_from_orientation(rng):
    r = Rotation.from_rotvec(np.cumsum(0.05 * rng.standard_normal((301, 3)), axis=0))
    q = r.as_quat(scalar_first=True)
    dt = 0.005 + 0.01 * rng.random(300)
    w = rate_from_orientation(q, dt)
    q_back = integrate_gyro(q[0], w, dt)
    assert np.max((Rotation.from_quat(q_back, scalar_first=True) * r.inv()).magnitude()) < 1e-10


def test_integrate_gyro_bad_input():
    with pytest.raises(InputError, match=r"dt_s as a scalar or with shape \(T,\) = \(5,\)"):
        integrate_gyro([1.0, 0, 0, 0], np.zeros((5, 3)), np.ones(4))
    with pytest.raises(InputError, match="unit quaternions"):
        integrate_gyro([2.0, 0, 0, 0], np.zeros((5, 3)), 0.01)


# ---------------------------------------------------------------- SLERP resampling
def test_slerp_resample_midpoint_and_gaps():
    """A constant-rate rotation: SLERP is exact (closed form). At 10 Hz one missing sample
    leaves 0.2 s (<= MAX_GAP_S = 0.25 s: bridged by default, a dropped packet), two leave
    0.3 s (missing); an explicit ``max_gap_s`` wins."""
    t = np.arange(10) * 0.1
    q = Rotation.from_rotvec(np.outer(t, [0, 0, 1.0])).as_quat(scalar_first=True)
    q[3] = np.nan
    q[6:8] = np.nan
    dst = np.array([0.05, 0.15, 0.25, 0.65, 0.95])
    out = slerp_resample(t, q, dst)
    ang = Rotation.from_quat(out[:3], scalar_first=True).as_rotvec()[:, 2]
    np.testing.assert_allclose(ang, [0.05, 0.15, 0.25], atol=1e-12)
    assert np.all(np.isnan(out[3:]))  # inside the 0.3 s gap, and past the end
    strict = slerp_resample(t, q, dst, max_gap_s=0.15)
    assert np.isfinite(strict[:2]).all() and np.isnan(strict[2]).all()
    assert default_max_gap_s(t) == MAX_GAP_S == 0.25
    assert default_max_gap_s(np.arange(3) * 0.5) == 0.75  # sparse: 1.5 steps
    np.testing.assert_array_equal(slerp_resample(t, q, t), q)


@pytest.mark.parametrize("step_rad", [0.05, 0.8])
def test_slerp_resample_equals_scipy_slerp(step_rad):
    """Oracle: scipy's Slerp over the whole series (same interval rule and output sign), on
    unnormalised quaternions with random sign flips, a repeated orientation, targets on and
    between the source times and at both ends; more targets than one of slerp_pairs' chunks."""
    from scipy.spatial.transform import Slerp

    rng = np.random.default_rng(7)
    T = 400
    t = np.cumsum(rng.uniform(0.005, 0.02, T))
    q = Rotation.from_rotvec(np.cumsum(rng.normal(0, step_rad, (T, 3)), 0)).as_quat(
        scalar_first=True
    )
    q[rng.random(T) < 0.3] *= -1
    q[10] = q[9]
    q *= rng.uniform(0.5, 2.0, (T, 1))
    t_dst = np.concatenate([rng.uniform(t[0], t[-1], 9000), t, [t[0], t[-1]]])
    want = Slerp(t, Rotation.from_quat(q, scalar_first=True))(t_dst).as_quat(scalar_first=True)
    got = slerp_resample(t, q, t_dst, max_gap_s=np.inf)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)  # unit quaternions: ~1e-16 each


def test_slerp_resample_source_times_across_a_gap_are_kept():
    """A target on a valid source time is that sample even where the interval before it is a
    gap (np.isin over the valid times is the oracle for which targets are used)."""
    t = np.arange(10) * 0.1
    q = Rotation.from_rotvec(np.outer(t, [0, 0, 1.0])).as_quat(scalar_first=True)
    q[4] = np.nan  # valid times 0.3 -> 0.5: a gap of 2 steps (longer than max_gap_s)
    t_dst = np.array([t[0], t[3], 0.35, 0.4, 0.45, t[5], 0.55, t[9], 0.95])
    out = slerp_resample(t, q, t_dst, max_gap_s=0.15)
    used = np.isfinite(out).all(axis=1)
    want = np.isin(t_dst, t[np.isfinite(q).all(axis=1)]) | (t_dst == 0.55)
    np.testing.assert_array_equal(used, want)
    np.testing.assert_allclose(out[5], q[5], atol=1e-15)


def test_slerp_resample_refuses_unordered_times():
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    with pytest.raises(InputError, match="strictly increasing"):
        slerp_resample([0.0, 0.2, 0.1, 0.3], q, [0.15])


# ---------------------------------------------------------------- BROAD (real data)
BROAD_TRIALS = {  # 9D total RMSE during motion (deg), VQF defaults, BROAD's error convention
    "03_undisturbed_slow_rotation_C": 1.93,
    "12_undisturbed_slow_translation_C": 1.36,
}


@pytest.mark.parametrize("trial", sorted(BROAD_TRIALS))
def test_broad_estimate_equals_vqf_and_accuracy(shared_data, trial):
    sio = pytest.importorskip("scipy.io")
    path = shared_data / "broad" / "data_mat" / f"{trial}.mat"
    if not path.is_file():
        pytest.skip(f"missing {path}")
    d = sio.loadmat(path, squeeze_me=True)
    acc = np.ascontiguousarray(d["imu_acc"])
    gyr = np.ascontiguousarray(d["imu_gyr"])
    mag = np.ascontiguousarray(d["imu_mag"])
    fs = float(d["sampling_rate"])
    q = estimate(acc, gyr, mag, rate_hz=fs)
    np.testing.assert_array_equal(q, vqf.VQF(1 / fs).updateBatch(gyr, acc, mag)["quat9D"])
    q6 = estimate(acc, gyr, rate_hz=fs, offline=True)
    np.testing.assert_array_equal(q6, vqf.offlineVQF(gyr, acc, None, 1 / fs, None)["quat6D"])
    # accuracy against the optical reference (earth-frame error, scipy as the independent oracle)
    ok = np.all(np.isfinite(d["opt_quat"]), axis=1) & d["movement"].astype(bool)
    err = (
        Rotation.from_quat(q[ok], scalar_first=True)
        * Rotation.from_quat(d["opt_quat"][ok], scalar_first=True).inv()
    )
    rmse = np.degrees(np.sqrt(np.mean(err.magnitude() ** 2)))
    assert rmse == pytest.approx(BROAD_TRIALS[trial], abs=0.01)


def test_slerp_resample_refuses_times_that_are_not_times():
    """A NaN source time made every output NaN, the valid part too; a negative max_gap_s
    did the same: both are errors, not missing data."""
    from kinefuse.orientation.resample import slerp_resample

    t = np.arange(10) / 10.0
    q = np.tile([1.0, 0.0, 0.0, 0.0], (10, 1))
    bad = t.copy()
    bad[4] = np.nan
    with pytest.raises(InputError, match="expected t_src_s finite, got nan at sample 4"):
        slerp_resample(bad, q, t[:5] + 0.05)
    with pytest.raises(InputError, match="expected t_dst_s finite"):
        slerp_resample(t, q, bad)
    with pytest.raises(InputError, match="max_gap_s >= 0"):
        slerp_resample(t, q, t + 0.05, max_gap_s=-1.0)
    np.testing.assert_allclose(slerp_resample(t, q, t[:-1] + 0.05), q[:-1])
