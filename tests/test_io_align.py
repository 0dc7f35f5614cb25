"""Time alignment: SLERP vs scipy, NaN in gaps and outside, common timeline, clock offsets."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

import kinefuse.io as kio
from kinefuse.io.align import (
    common_timeline,
    estimate_clock_offset,
    resample_coverage,
    resample_orientation,
    resample_positions,
)
from kinefuse.io.recording import ImuStream, JointStream, Recording


def _random_rotations(rng, n):
    rv = np.cumsum(rng.normal(0, 0.2, size=(n, 3)), axis=0)
    return Rotation.from_rotvec(rv)


def test_slerp_matches_scipy(rng):
    t = np.cumsum(rng.uniform(0.005, 0.015, size=60))
    r = _random_rotations(rng, 60)
    q = r.as_quat(scalar_first=True)
    t_new = np.sort(rng.uniform(t[0], t[-1], size=200))
    out = resample_orientation(t, q, t_new, max_gap_s=1.0)
    ref = Slerp(t, r)(t_new)
    err = (Rotation.from_quat(out, scalar_first=True) * ref.inv()).magnitude()
    assert err.max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    # exact at source times, sign-independent (q and -q are the same rotation)
    q_flip = q.copy()
    q_flip[::2] *= -1
    at = resample_orientation(t, q_flip, t, max_gap_s=1.0)
    np.testing.assert_allclose(np.abs(np.sum(at * q, axis=1)), 1.0, atol=1e-12)


def test_slerp_nan_outside_and_in_gaps(rng):
    t = np.arange(50) * 0.01
    q = _random_rotations(rng, 50).as_quat(scalar_first=True)
    q[20:25] = np.nan  # a 60 ms hole
    t_new = np.arange(-0.02, 0.52, 0.0025)
    out = resample_orientation(t, q, t_new)  # default max gap = 1.5 * 10 ms
    bad = ~np.all(np.isfinite(out), axis=1)
    assert bad[t_new < 0].all() and bad[t_new > t[-1] + 1e-12].all()
    hole = (t_new > t[19] + 1e-12) & (t_new < t[25] - 1e-12)
    assert bad[hole].all()
    inside = (t_new >= 0) & (t_new <= t[19]) | (t_new >= t[25]) & (t_new <= t[-1])
    assert not bad[inside].any()
    # a larger max gap bridges the hole
    out2 = resample_orientation(t, q, t_new, max_gap_s=0.1)
    assert np.all(np.isfinite(out2[hole]))


def test_positions_linear_and_availability(rng):
    t = np.arange(40) / 30.0
    p = rng.normal(size=(40, 2, 3))
    avail = np.ones((40, 2), dtype=bool)
    avail[10:14, 1] = False
    t_new = np.arange(0, 40 / 30.0, 0.01)
    out, a = resample_positions(t, p, t_new, available=avail)
    for ax in range(3):
        np.testing.assert_allclose(
            out[a[:, 0], 0, ax], np.interp(t_new, t, p[:, 0, ax])[a[:, 0]], atol=1e-12
        )
    gap = (t_new > t[9] + 1e-12) & (t_new < t[14] - 1e-12)
    assert not a[gap, 1].any() and np.isnan(out[gap, 1]).all()
    assert a[~gap & (t_new <= t[-1]), 1].all()
    assert not a[t_new > t[-1]].any()
    # 2-D input keeps its shape
    o2, a2 = resample_positions(t, p[:, 0], t_new)
    assert o2.shape == (t_new.size, 3) and a2.shape == (t_new.size,)
    with pytest.raises(ValueError, match="strictly increasing t_src"):
        resample_positions(t[::-1], p, t_new)


@pytest.mark.parametrize("max_gap_s", [None, 0.05, 0.2])
def test_resample_coverage_follows_its_definition(rng, max_gap_s):
    """Oracle, a loop over the targets: a target is covered when it is a usable source time, or
    lies between two consecutive usable source times at most ``max_gap_s`` apart (default 1.5
    source steps); and it is where resample_positions gives a value."""
    t = np.cumsum(rng.uniform(0.01, 0.03, 300))
    usable = rng.random(300) > 0.15
    usable[40:50] = False  # a long gap
    t_new = np.concatenate([rng.uniform(t[0] - 0.1, t[-1] + 0.1, 700), t[::7]])
    t_new = np.unique(t_new)
    got = resample_coverage(t, usable, t_new, max_gap_s=max_gap_s)
    gap = 1.5 * np.median(np.diff(t)) if max_gap_s is None else max_gap_s
    tv = t[usable]
    want = np.zeros(t_new.size, bool)
    for i, x in enumerate(t_new):
        if x in tv:
            want[i] = True
            continue
        for a, b in zip(tv[:-1], tv[1:], strict=True):
            if a < x < b:
                want[i] = b - a <= gap
                break
    np.testing.assert_array_equal(got, want)
    p = np.where(usable[:, None], rng.normal(size=(300, 3)), np.nan)
    np.testing.assert_array_equal(resample_positions(t, p, t_new, max_gap_s=max_gap_s)[1], want)
    with pytest.raises(ValueError, match="usable with shape"):
        resample_coverage(t, usable[:-1], t_new)


def test_common_timeline_overlap():
    t1 = np.arange(0, 2, 0.01)
    t2 = np.arange(0.3, 2.5, 0.02)
    acc = np.tile([0, 0, 9.81], (t1.size, 1))
    q2 = np.tile([1.0, 0, 0, 0], (t2.size, 1))
    v = JointStream(
        t_s=np.arange(0.1, 1.9, 1 / 30), position_m=np.zeros((54, 1, 3)), joints=("wrist_r",)
    )
    rec = Recording(
        imu={
            "forearm_r": ImuStream(t_s=t1, acc_m_s2=acc, gyr_rad_s=np.zeros_like(acc)),
            "upper_arm_r": ImuStream(t_s=t2, q_world_from_sensor=q2),
        },
        vision=v,
    )
    out = common_timeline(rec)
    t = out.vision.t_s
    assert out.metadata["timeline"]["rate_hz"] == pytest.approx(30.0)
    assert t[0] == pytest.approx(0.3) and t[-1] <= 1.9 - 1e-3 + 1 / 30
    for s in out.imu.values():
        np.testing.assert_array_equal(s.t_s, t)
    assert np.all(np.isfinite(out.imu["forearm_r"].acc_m_s2)) and np.all(
        np.isfinite(out.imu["upper_arm_r"].q_world_from_sensor)
    )
    union = common_timeline(rec, rate_hz=50.0, span="union")
    assert union.imu["forearm_r"].t_s[0] == 0.0
    assert np.isnan(union.imu["upper_arm_r"].q_world_from_sensor[0]).all()
    assert not union.vision.available[0].any()


def test_clock_offset_synthetic(rng):
    # smooth "angular rate" with structure at several time scales
    t_true = np.arange(0, 30, 0.005)
    w = np.stack(
        [np.convolve(rng.normal(size=t_true.size), np.hanning(81), "same") for _ in range(3)],
        axis=1,
    )
    offset = 0.437
    t_a = t_true[::2]  # 100 Hz on clock a
    sig_a = w[::2]
    keep = slice(3, None, 6)  # ~33 Hz on clock b, which reads t - offset
    t_b = t_true[keep] - offset
    sig_b = w[keep] + rng.normal(0, 0.05, size=w[keep].shape)
    res = estimate_clock_offset(t_a, sig_a, t_b, sig_b, max_lag_s=2.0)
    assert res.offset_s == pytest.approx(offset, abs=0.004)
    assert res.correlation > 0.9
    res2 = estimate_clock_offset(t_b, sig_b, t_a, sig_a, max_lag_s=2.0)
    assert res2.offset_s == pytest.approx(-offset, abs=0.004)


def test_clock_offset_broad_gyro_vs_optical(shared_data):
    """Real data: IMU angular rate vs. the OptiTrack-derived rate (independent systems)."""
    rec = kio.load(shared_data / "broad" / "data_mat" / "01_undisturbed_slow_rotation_A.mat")
    fs = 285.714
    n = int(40 * fs)
    imu, ref = rec.imu["imu"], rec.reference_orientation["imu"]
    t = imu.t_s[:n]
    r = Rotation.from_quat(
        np.nan_to_num(ref.q_world_from_sensor[:n], nan=0.0)
        + np.where(np.isnan(ref.q_world_from_sensor[:n]), [1, 0, 0, 0], 0),
        scalar_first=True,
    )
    w_opt = (r[:-1].inv() * r[1:]).as_rotvec() * fs
    ok = np.all(np.isfinite(ref.q_world_from_sensor[:n]), axis=1)
    w_opt[~(ok[:-1] & ok[1:])] = np.nan
    t_opt = 0.5 * (t[:-1] + t[1:])
    # the dataset is synchronised: offset ~ 0
    res0 = estimate_clock_offset(t, imu.gyr_rad_s[:n], t_opt, w_opt, max_lag_s=1.0, rate_hz=100.0)
    assert abs(res0.offset_s) < 0.015 and res0.correlation > 0.9
    # inject a known offset: the optical clock runs 0.25 s behind
    res = estimate_clock_offset(
        t, imu.gyr_rad_s[:n], t_opt - 0.25, w_opt, max_lag_s=1.0, rate_hz=100.0
    )
    assert res.offset_s == pytest.approx(0.25 + res0.offset_s, abs=0.005)


def test_clock_offset_errors():
    t = np.arange(10.0)
    with pytest.raises(ValueError, match="max_lag_s > 0"):
        estimate_clock_offset(t, t, t, t, max_lag_s=0)
    with pytest.raises(ValueError, match="no lag within max_lag_s"):
        estimate_clock_offset(t, np.sin(t), t + 100.0, np.sin(t), max_lag_s=1.0)
