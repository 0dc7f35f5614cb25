"""Virtual IMUs and camera driven by real CMU motion: exactness, error statistics, determinism."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.conventions import GRAVITY_ENU_M_S2, JOINTS
from kinefuse.io.cmu import load_motion_asf_amc
from kinefuse.io.motion import Motion
from kinefuse.sim import PAPER_B_SEGMENTS, CameraConfig, ImuConfig, virtual_recording


@pytest.fixture(scope="module")
def walk(shared_data):
    return load_motion_asf_amc(shared_data / "cmu_mocap" / "asfamc" / "02" / "02_01.amc")


def _integrate(q0, gyr, dt):
    """q_k = q_k-1 ⊗ exp(gyr_k dt), starting from q0 at sample 0 (gyr_0 unused)."""
    rots = [Rotation.from_quat(q0, scalar_first=True)]
    for w in gyr[1:]:
        rots.append(rots[-1] * Rotation.from_rotvec(w * dt))
    return Rotation.concatenate(rots)


def _angle_deg(r1, r2):
    return np.degrees((r1.inv() * r2).magnitude())


def _sensor_twist(motion, seg, fraction=0.5):
    """A forearm sensor's turn with pronation at the mocap samples, rotation (independent of
    kinefuse.sim): ``fraction`` of the hand's twist about the forearm's y axis, minus its mean."""
    if not seg.startswith("forearm"):
        return Rotation.identity(len(motion))
    fa = Rotation.from_quat(motion.orientation(seg), scalar_first=True)
    hand = Rotation.from_quat(motion.orientation("hand" + seg[7:]), scalar_first=True)
    w, y = (fa.inv() * hand).as_quat(scalar_first=True)[:, [0, 2]].T
    phi = np.unwrap(2 * np.arctan2(y, w))
    return Rotation.from_rotvec(np.outer(fraction * (phi - phi.mean()), [0.0, 1.0, 0.0]))


@pytest.mark.parametrize("lowpass", [None, 15.0])
def test_integrated_gyro_reproduces_orientation(walk, lowpass):
    rec = virtual_recording(
        walk,
        imu=ImuConfig.ideal(motion_lowpass_hz=lowpass),
        camera=None,
        segments=("forearm_r", "shank_l"),
        knee_secondary=0.0,  # the shank as the mocap moves it (compared with the mocap below)
    )
    for seg in ("forearm_r", "shank_l"):
        s = rec.imu[seg]
        est = _integrate(s.q_world_from_sensor[0], s.gyr_rad_s, 0.01)
        truth = Rotation.from_quat(
            rec.metadata["imu_truth"][seg]["q_world_from_sensor"], scalar_first=True
        )
        assert _angle_deg(est, truth).max() < 0.1
        # ideal AHRS output = truth; with raw mocap also the mocap samples at common times (every
        # 5th): the bone, turned with pronation on the forearm
        np.testing.assert_allclose(
            np.abs(np.sum(s.q_world_from_sensor * truth.as_quat(scalar_first=True), axis=1)),
            1.0,
            atol=1e-12,
        )
        if lowpass is None:
            bone = Rotation.from_quat(walk.orientation(seg), scalar_first=True)
            mocap = (bone * _sensor_twist(walk, seg))[::6]
            assert _angle_deg(est[::5][: len(mocap)], mocap[: len(est[::5])]).max() < 0.1


def _fd_specific_force(walk, seg):
    prox, dist = walk.segment_joints[seg]
    p = 0.5 * (walk.position(prox) + walk.position(dist))  # segment midpoint
    a = (p[2:] - 2 * p[1:-1] + p[:-2]) * walk.rate_hz**2
    R = Rotation.from_quat(walk.orientation(seg), scalar_first=True) * _sensor_twist(walk, seg)
    return R[1:-1].inv().apply(a - GRAVITY_ENU_M_S2)


def test_accelerometer_equals_specific_force_of_true_motion(walk):
    # at the mocap rate the scheme is exactly the central second difference of the midpoint
    rec = virtual_recording(
        walk,
        imu=ImuConfig.ideal(rate_hz=120.0, motion_lowpass_hz=None),
        camera=None,
        knee_secondary=0.0,  # the motion as given: the finite differences below are of ``walk``
    )
    for seg in PAPER_B_SEGMENTS:
        np.testing.assert_allclose(
            rec.imu[seg].acc_m_s2[1:-1], _fd_specific_force(walk, seg), atol=1e-6
        )
    # at 100 Hz, the samples at common times (t = 0.05 k) equal it too
    rec = virtual_recording(
        walk, imu=ImuConfig.ideal(motion_lowpass_hz=None), camera=None, segments=("thigh_r",)
    )
    f = _fd_specific_force(walk, "thigh_r")  # at mocap samples 1..T-2
    acc = rec.imu["thigh_r"].acc_m_s2[5::5]  # t = 0.05, 0.10, ... = mocap samples 6, 12, ...
    n = min(len(acc), len(f[5::6]))
    np.testing.assert_allclose(acc[:n], f[5::6][:n], atol=1e-6)
    # with the default motion low-pass the walking thigh reads about 1 g on average
    smooth = virtual_recording(walk, imu=ImuConfig.ideal(), camera=None, segments=("thigh_r",))
    assert np.median(np.linalg.norm(smooth.imu["thigh_r"].acc_m_s2, axis=1)) == pytest.approx(
        9.8, abs=1.5
    )


def test_imu_noise_std_matches_config(walk):
    cfg = ImuConfig.ideal(gyr_noise_dps_sqrt_hz=0.015, acc_noise_ug_sqrt_hz=230.0)
    rec = virtual_recording(walk, imu=cfg, camera=None, seed=3)
    truth = rec.metadata["imu_truth"]
    gyr = np.concatenate([rec.imu[s].gyr_rad_s - truth[s]["gyr_rad_s"] for s in PAPER_B_SEGMENTS])
    acc = np.concatenate([rec.imu[s].acc_m_s2 - truth[s]["acc_m_s2"] for s in PAPER_B_SEGMENTS])
    assert np.degrees(gyr.std()) == pytest.approx(0.015 * np.sqrt(50.0), rel=0.05)
    assert acc.std() == pytest.approx(230e-6 * 9.80665 * np.sqrt(50.0), rel=0.05)


def test_default_imu_errors_within_datasheet_bounds(walk):
    rec = virtual_recording(walk, camera=None, seed=1)
    errs = []
    for seg in PAPER_B_SEGMENTS:
        t = rec.metadata["imu_truth"][seg]
        assert np.all(np.abs(np.degrees(t["gyr_error"]["turn_on_bias"])) <= 5.0)
        assert np.all(np.abs(t["acc_error"]["turn_on_bias"]) <= 0.05 * 9.80665)
        M = t["gyr_error"]["sensitivity_matrix"]
        assert np.all(np.abs(np.diag(M) - 1) <= 0.015 + 1e-12)
        mount = Rotation.from_quat(t["q_segment_from_sensor"], scalar_first=True).magnitude()
        assert np.degrees(mount) < 15.0
        errs.append(
            _angle_deg(
                Rotation.from_quat(rec.imu[seg].q_world_from_sensor, scalar_first=True),
                Rotation.from_quat(t["q_world_from_sensor"], scalar_first=True),
            )
        )
    # VQF on the raw signals: degrees off, as on real sensors (BROAD: 1-8 deg), never exact
    assert 0.2 < np.median(np.concatenate(errs)) < 10.0


def test_orientation_is_vqf_on_the_raw_signals(walk):
    from kinefuse.orientation import estimate

    for orientation, use_mag in (("vqf", True), ("vqf-6d", False)):
        cfg = ImuConfig(warmup_s=0.0, orientation=orientation)
        rec = virtual_recording(walk, imu=cfg, camera=None, segments=("thigh_l",), seed=4)
        s = rec.imu["thigh_l"]
        q = estimate(s.acc_m_s2, s.gyr_rad_s, s.mag if use_mag else None, rate_hz=s.rate_hz)
        np.testing.assert_allclose(s.q_world_from_sensor, q, atol=1e-9)
        assert s.frame == ("ENU" if use_mag else "VQF-6D")


def _pose_trajectory(omega=2.0, amp=0.3, rate_hz=200.0, seconds=4.0):
    """Rotation about z at omega rad/s, position amp·sin(omega t) along x (closed forms)."""
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    q = Rotation.from_rotvec(np.outer(omega * t, [0.0, 0.0, 1.0])).as_quat(scalar_first=True)
    p = np.column_stack([amp * np.sin(omega * t), np.zeros_like(t), np.zeros_like(t)])
    return t, q, p


def test_raw_signals_match_closed_forms():
    from kinefuse.sim import simulate_imu_from_pose

    omega, amp = 2.0, 0.3
    t, q, p = _pose_trajectory(omega, amp)
    cfg = ImuConfig.ideal(rate_hz=100.0)
    t_out = np.arange(20, 380) / 100.0  # inside the trajectory, away from the spline ends
    st, truth = simulate_imu_from_pose(t, q, p, cfg, np.random.default_rng(0), t_out)
    # gyro: constant rate about the sensor z axis (exact for a fixed-axis rotation)
    np.testing.assert_allclose(st.gyr_rad_s, np.tile([0.0, 0.0, omega], (t_out.size, 1)), atol=1e-9)
    # accelerometer: R^T (a - g); a = central second difference (step h = 1/200 s) of the spline,
    # which for a sine is -amp (2 - 2 cos(omega h)) / h^2 sin(omega t); spline error O(h^4)
    h = 1.0 / 200.0
    R = Rotation.from_rotvec(np.outer(omega * t_out, [0.0, 0.0, 1.0]))
    a = np.column_stack(
        [-amp * (2 - 2 * np.cos(omega * h)) / h**2 * np.sin(omega * t_out), 0 * t_out, 0 * t_out]
    )
    np.testing.assert_allclose(st.acc_m_s2, R.inv().apply(a - GRAVITY_ENU_M_S2), atol=1e-4)
    # magnetometer: R^T m_earth (no disturbance in the ideal config)
    np.testing.assert_allclose(st.mag, R.inv().apply(cfg.mag_earth_ut), atol=1e-9)
    assert np.linalg.norm(cfg.mag_earth_ut) == pytest.approx(44.0)
    # integrating the gyro reproduces the orientation
    est = _integrate(st.q_world_from_sensor[0], st.gyr_rad_s, 0.01)
    assert _angle_deg(est, R).max() < 1e-6


def test_soft_tissue_artefact_bounded_by_configured_amplitude(walk):
    from kinefuse.sim import STA_AMPLITUDE

    cfg = ImuConfig.ideal(soft_tissue_scale=1.5)
    rec = virtual_recording(walk, imu=cfg, camera=None, segments=("thigh_r", "forearm_l"), seed=9)
    for seg, kind in (("thigh_r", "thigh"), ("forearm_l", "forearm")):
        tr = rec.metadata["imu_truth"][seg]
        a_tr, a_rot = tr["sta_amplitude"]
        assert a_tr == pytest.approx(1.5e-3 * STA_AMPLITUDE[kind][0])
        assert a_rot == pytest.approx(1.5 * np.radians(STA_AMPLITUDE[kind][1]))
        s = np.linalg.norm(tr["sta_drive_rad"], axis=1)
        d = np.linalg.norm(tr["sta_translation_m"], axis=1)
        r = np.linalg.norm(tr["sta_rotvec_rad"], axis=1)
        # |M s| <= |s| (spectral norm <= 1); splines between samples overshoot a little
        assert np.all(d <= a_tr * s * 1.02 + 1e-4) and np.all(r <= a_rot * s * 1.02 + 1e-4)
        # and not much smaller: M has rank 3 and the drive 3m components (6 on the thigh, 9 on a
        # forearm with a hand: hip/shoulder or elbow, wrist), so the part of the drive in M's null
        # space moves nothing; a random M keeps about sqrt(3 / 3m) of it, times σ >= 0.5
        assert d.max() > 0.15 * a_tr * s.max() and r.max() > 0.15 * a_rot * s.max()
        # the sensor is off the bone by exactly that rotation (and the rigid mounting)
        seg_rot = Rotation.from_quat(tr["q_world_from_segment"], scalar_first=True)
        sen_rot = Rotation.from_quat(tr["q_world_from_sensor"], scalar_first=True)
        twist = Rotation.from_rotvec(np.outer(tr["twist_rad"], [0.0, 1.0, 0.0]))
        expect = seg_rot * twist * Rotation.from_rotvec(tr["sta_rotvec_rad"])
        assert _angle_deg(expect, sen_rot).max() < 0.05
        # noise-free gyro integrates to the moving sensor's orientation
        est = _integrate(tr["q_world_from_sensor"][0], rec.imu[seg].gyr_rad_s, 0.01)
        assert _angle_deg(est, sen_rot).max() < 0.1
    # the thigh of a walk moves by millimetres to centimetres, within the literature's 10-30 mm
    d_thigh = np.linalg.norm(rec.metadata["imu_truth"]["thigh_r"]["sta_translation_m"], axis=1)
    assert 0.002 < d_thigh.max() < 0.045


def test_magnetic_disturbance_only_inside_episodes():
    from kinefuse.sim import simulate_imu_from_pose

    t, q, p = _pose_trajectory(seconds=120.0, rate_hz=50.0)
    cfg = ImuConfig.ideal(
        rate_hz=50.0,
        mag_disturbance_per_min=4.0,
        mag_disturbance_ut=30.0,
        mag_disturbance_duration_s=4.0,
    )
    _, truth = simulate_imu_from_pose(t, q, p, cfg, np.random.default_rng(3))
    dev = np.linalg.norm(truth["mag_world_ut"] - cfg.mag_earth_ut, axis=1)
    tt = t[0] + np.arange(dev.size) / 50.0
    inside = np.zeros(dev.size, dtype=bool)
    for t0, t1 in truth["mag_episodes"]:
        inside |= (tt >= t0) & (tt <= t1)
    assert len(truth["mag_episodes"]) >= 2
    assert np.all(dev[~inside] < 1e-9)
    assert dev.max() <= 30.0 * len(truth["mag_episodes"]) and dev.max() > 7.5


def test_mount_magnet_is_a_sensor_frame_field_over_its_span():
    """A magnet on the sensor's mount: the noise-free reading gains a constant sensor-frame vector
    (the given direction, normalised) from the fraction ``from`` to ``to`` of the recorded span
    (warm-up excluded), 1 s ramps, nothing elsewhere; the world field is untouched."""
    from kinefuse.sim import simulate_imu_from_pose

    t, q, p = _pose_trajectory(seconds=60.0, rate_hz=50.0)
    base = dict(rate_hz=50.0, orientation="vqf", warmup_s=2.0, mag_inhomogeneity_ut=1.0)
    plain = ImuConfig.ideal(**base)
    magnet = ImuConfig.ideal(
        **base,
        mag_mount_magnet_ut=40.0,
        mag_mount_magnet_from=0.25,
        mag_mount_magnet_to=0.75,
        mag_mount_magnet_dir=(0.0, 3.0, 4.0),
    )
    st0, tr0 = simulate_imu_from_pose(t, q, p, plain, np.random.default_rng(5))
    st1, tr1 = simulate_imu_from_pose(t, q, p, magnet, np.random.default_rng(5))
    np.testing.assert_array_equal(tr1["mag_world_ut"], tr0["mag_world_ut"])
    diff = tr1["mag_ut"] - tr0["mag_ut"]
    ts = st1.t_s
    a = ts[0] + 0.25 * (ts[-1] - ts[0])
    b = ts[0] + 0.75 * (ts[-1] - ts[0])
    full = (ts >= a + 1.0) & (ts <= b - 1.0)
    off = (ts <= a) | (ts >= b)
    np.testing.assert_allclose(diff[full], np.broadcast_to([0.0, 24.0, 32.0], diff[full].shape),
                               rtol=0, atol=1e-9)  # fmt: skip
    assert np.all(np.abs(diff[off]) < 1e-9)
    assert np.all(np.linalg.norm(diff, axis=1) <= 40.0 + 1e-9)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"mag_mount_magnet_from": 0.8, "mag_mount_magnet_to": 0.2},
        {"mag_mount_magnet_to": 1.5},
        {"mag_mount_magnet_dir": (0.0, 0.0, 0.0)},
        {"mag_mount_magnet_dir": (1.0, 2.0)},
    ],
)
def test_mount_magnet_bad_settings(kwargs):
    from kinefuse.exceptions import InputError

    with pytest.raises(InputError, match="ImuConfig.mag_mount_magnet"):
        ImuConfig(**kwargs)


def test_camera_tracking_error_std():
    motion = _static_motion(minutes=4.0)
    cfg = CameraConfig.ideal(tracking_error_std_m=0.03)
    rec = virtual_recording(motion, imu=None, camera=cfg, seed=2)
    err = rec.metadata["camera_truth"]["tracking_error_m"]
    assert err.std() == pytest.approx(0.03, rel=0.1)
    np.testing.assert_allclose(rec.vision.position_m - rec.reference.position_m, err, atol=1e-12)


def test_reference_at_camera_timestamps(walk):
    rec = virtual_recording(
        walk, imu=ImuConfig.ideal(), camera=CameraConfig(), seed=0, knee_secondary=0.0
    )
    assert np.diff(rec.vision.t_s) == pytest.approx(1 / 30.0) and rec.imu[
        "chest"
    ].rate_hz == pytest.approx(100.0)
    np.testing.assert_array_equal(rec.reference.t_s, rec.vision.t_s)
    np.testing.assert_allclose(
        rec.reference.position_m, walk.position_m[::4][: len(rec.reference)], atol=1e-12
    )
    imu_ref = rec.metadata["reference_imu_rate"]
    np.testing.assert_array_equal(imu_ref.t_s, rec.imu["chest"].t_s)
    np.testing.assert_allclose(
        imu_ref.position_m[::5], walk.position_m[::6][: len(imu_ref.t_s[::5])], atol=1e-12
    )


def test_camera_noise_std_and_camera_frame(walk):
    cfg = CameraConfig.ideal(noise_std_m=(0.01, 0.02, 0.03), frame="camera", heading_deg=40.0)
    rec = virtual_recording(walk, imu=None, camera=cfg, seed=5)
    R, c = rec.metadata["R_world_from_camera"], rec.metadata["camera_position_m"]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert rec.vision.frame == "camera" and np.all(rec.vision.available)
    truth_cam = (rec.reference.position_m - c) @ R
    err = (rec.vision.position_m - truth_cam).reshape(-1, 3)
    np.testing.assert_allclose(err.std(axis=0), [0.01, 0.02, 0.03], rtol=0.05)
    # heading alignment is recoverable: Kabsch on noise-free data gives R_world_from_camera
    clean = virtual_recording(
        walk, imu=None, camera=CameraConfig.ideal(frame="camera", heading_deg=40.0)
    )
    a = clean.vision.position_m.reshape(-1, 3)
    b = clean.reference.position_m.reshape(-1, 3)
    a0, b0 = a - a.mean(0), b - b.mean(0)
    U, _, Vt = np.linalg.svd(b0.T @ a0)
    R_est = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    np.testing.assert_allclose(R_est, R, atol=1e-9)


def _static_motion(minutes=10.0, rate_hz=30.0):
    """A long motionless skeleton (only the outage processes matter here)."""
    T = int(minutes * 60 * rate_hz)
    rng = np.random.default_rng(0)
    base = rng.normal(size=(1, len(JOINTS), 3))
    q = np.zeros((T, 1, 4))
    q[..., 0] = 1.0
    return Motion(
        t_s=np.arange(T) / rate_hz,
        q_world_from_segment=q,
        segments=("pelvis",),
        position_m=np.repeat(base, T, axis=0),
        joints=JOINTS,
        segment_joints={"pelvis": ("pelvis", None)},
        segment_length_m={},
    )


def test_occlusion_and_dropout_statistics():
    motion = _static_motion(minutes=12.0)
    cfg = CameraConfig(occlusion_rate_per_min=6.0, dropout_rate_per_min=6.0, bone_length_std=0.0)
    rec = virtual_recording(motion, imu=None, camera=cfg, seed=11)
    truth = rec.metadata["camera_truth"]
    occl, drop = truth["occluded"], truth["dropout"]
    mean_d = 0.5 * (0.3 + 3.0)
    expected = lambda lam: lam * mean_d / (60.0 + lam * mean_d)  # noqa: E731
    assert occl.mean() == pytest.approx(expected(6.0), rel=0.15)
    assert drop.mean() == pytest.approx(expected(6.0), rel=0.35)
    avail = rec.vision.available
    np.testing.assert_array_equal(avail, ~(occl | drop[:, None]))
    assert np.all(np.isnan(rec.vision.position_m[~avail]))
    # independent per joint: occlusion correlation between joints is small
    c = np.corrcoef(occl.T.astype(float))
    assert np.abs(c[np.triu_indices_from(c, 1)]).mean() < 0.1
    # every completed outage lasts 0.3-3 s
    for mask in [*occl.T, drop]:
        edges = np.diff(np.r_[0, mask.astype(int), 0])
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        full = stops < mask.size  # not cut by the end of the recording
        dur = (stops - starts)[full] / 30.0
        assert dur.size > 0 and dur.min() >= 0.3 - 1e-9 and dur.max() <= 3.0 + 1e-9


def test_bone_length_variation_std():
    motion = _static_motion(minutes=2.0)
    rec = virtual_recording(
        motion, imu=None, camera=CameraConfig.ideal(bone_length_std=0.05), seed=2
    )
    scale = rec.metadata["camera_truth"]["bone_scale"]
    assert scale.std() == pytest.approx(0.05, rel=0.1)
    v = rec.vision
    L = np.linalg.norm(v.position("elbow_l") - v.position("shoulder_l"), axis=1)
    L0 = np.linalg.norm(
        rec.reference.position("elbow_l") - rec.reference.position("shoulder_l"), axis=1
    )
    assert np.std(L / L0) == pytest.approx(0.05, rel=0.3)


def test_same_seed_same_output(walk):
    a = virtual_recording(walk, seed=7)
    b = virtual_recording(walk, seed=7)
    c = virtual_recording(walk, seed=8)
    for seg in a.imu:
        for f in ("acc_m_s2", "gyr_rad_s", "mag", "q_world_from_sensor"):
            np.testing.assert_array_equal(getattr(a.imu[seg], f), getattr(b.imu[seg], f))
        assert not np.allclose(a.imu[seg].acc_m_s2, c.imu[seg].acc_m_s2)
    np.testing.assert_array_equal(a.vision.position_m, b.vision.position_m)
    np.testing.assert_array_equal(a.vision.available, b.vision.available)
    # adding a sensor or removing the camera leaves the other streams unchanged
    d = virtual_recording(walk, seed=7, camera=None, segments=("chest", "foot_l"))
    np.testing.assert_array_equal(d.imu["chest"].acc_m_s2, a.imu["chest"].acc_m_s2)


def test_bad_arguments(walk):
    from kinefuse.exceptions import InputError

    with pytest.raises(InputError, match="unknown segment 'wing'"):
        virtual_recording(walk, segments=("wing",))
    with pytest.raises(InputError, match="ImuConfig.rate_hz"):
        ImuConfig(rate_hz=0.0)
    with pytest.raises(InputError, match="CameraConfig.frame"):
        CameraConfig(frame="NED")
    with pytest.raises(InputError, match="expected motion"):
        virtual_recording(np.zeros((3, 3)))


def test_reference_at_refuses_times_outside_the_motion():
    """A cubic spline extrapolated the truth: 7 s past a 2.85-s clip the wrist was 4e5 m away,
    marked available."""
    from kinefuse.data import demo_motion
    from kinefuse.exceptions import InputError
    from kinefuse.sim.camera import reference_at

    m = demo_motion()
    with pytest.raises(InputError, match="expected t_s inside the motion's span"):
        reference_at(m, np.array([m.t_s[-1] + 7.0]))
    assert np.all(np.isfinite(reference_at(m, m.t_s[[0, -1]]).position_m))
