"""Sensor-to-segment calibration (static, reference window, alignment), Kabsch, chain positions."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.io.recording import ImuStream, JointStream, Recording
from kinefuse.kinematics import (
    calibrate,
    chain_positions,
    heading_rotation,
    kabsch_rotation,
    lower_body,
    upper_limb,
)

FS = 100.0
LENGTHS = {"thigh_l": 0.42, "shank_l": 0.40, "thigh_r": 0.41, "shank_r": 0.39}


def mountings():
    """Known sensor mountings: R_segment_from_sensor per segment (segment axis = segment -z)."""
    return {
        s: Rotation.from_euler("xyz", [20 * i + 5, -30 + 15 * i, 60 * i], degrees=True)
        for i, s in enumerate(LENGTHS)
    }


def legs(T: int, *, rich: bool, seed: int = 0):
    """World-from-segment rotations of 4 leg segments; ``rich`` adds rotation about all axes."""
    t = np.arange(T) / FS
    rng = np.random.default_rng(seed)
    out = {}
    for i, s in enumerate(LENGTHS):
        ph = rng.uniform(0, 2 * np.pi, 3)
        amp = np.array([0.5, 0.35, 0.6]) if rich else np.array([0.5, 0.0, 0.0])
        rv = amp * np.sin(2 * np.pi * np.array([0.9, 0.6, 0.4]) * t[:, None] * (1 + 0.1 * i) + ph)
        out[s] = Rotation.from_rotvec(rv)
    return out


def make_recording(
    T=300, *, rich=True, R_ref_from_world=None, noise_m=0.0, ref_rate=FS, seed=0, frame="ENU"
):
    seg = legs(T, rich=rich, seed=seed)
    mount = mountings()
    t = np.arange(T) / FS
    hips = {"hip_l": np.tile([-0.1, 0.0, 0.95], (T, 1)), "hip_r": np.tile([0.1, 0.0, 0.95], (T, 1))}
    hips["hip_l"][:, 1] += 0.8 * t
    hips["hip_r"][:, 1] += 0.8 * t
    pos = dict(hips)
    for side in "lr":
        pos[f"knee_{side}"] = pos[f"hip_{side}"] + LENGTHS[f"thigh_{side}"] * seg[
            f"thigh_{side}"
        ].apply([0, 0, -1])
        pos[f"ankle_{side}"] = pos[f"knee_{side}"] + LENGTHS[f"shank_{side}"] * seg[
            f"shank_{side}"
        ].apply([0, 0, -1])
    imu = {
        s: ImuStream(
            t_s=t,
            q_world_from_sensor=(seg[s] * mount[s]).as_quat(scalar_first=True),
            name=s,
            frame="ENU",
        )
        for s in LENGTHS
    }
    joints = ("hip_l", "knee_l", "ankle_l", "hip_r", "knee_r", "ankle_r")
    P = np.stack([pos[j] for j in joints], axis=1)
    truth = JointStream(t_s=t, position_m=P.copy(), joints=joints)
    if R_ref_from_world is not None:
        P = P @ R_ref_from_world.T
    rng = np.random.default_rng(seed + 100)
    P = P + noise_m * rng.standard_normal(P.shape)
    step = int(round(FS / ref_rate))
    ref = JointStream(t_s=t[::step] + 0.0, position_m=P[::step], joints=joints, frame=frame)
    expected_axes = {s: mount[s].inv().apply([0, 0, -1]) for s in LENGTHS}
    return Recording(imu=imu, reference=ref), truth, expected_axes


def angle_deg(a, b):
    return float(
        np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
    )


# ---------------------------------------------------------------- Kabsch
def test_kabsch_matches_scipy_align_vectors(rng):
    P = rng.standard_normal((30, 3))
    R_true = Rotation.random(random_state=5)
    Q = R_true.apply(P) + 0.01 * rng.standard_normal((30, 3))
    w = rng.random(30)
    R = kabsch_rotation(P, Q, w)
    np.testing.assert_allclose(
        R, Rotation.align_vectors(Q, P, weights=w)[0].as_matrix(), atol=1e-10
    )
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(kabsch_rotation(P, R_true.apply(P)), R_true.as_matrix(), atol=1e-12)
    # reflection-prone data still gives a proper rotation
    assert np.linalg.det(kabsch_rotation(P, -P)) == pytest.approx(1.0)


def test_heading_rotation_recovers_yaw(rng):
    P = rng.standard_normal((50, 3))
    Rz = Rotation.from_euler("z", 37, degrees=True)
    R = heading_rotation(P, Rz.apply(P) + 0.001 * rng.standard_normal((50, 3)))
    assert np.degrees((Rotation.from_matrix(R) * Rz.inv()).magnitude()) < 0.1
    with pytest.raises(InputError, match=r"same shape \(N, 3\), got \(50, 3\) and \(49, 3\)"):
        heading_rotation(P, P[:-1])


def test_kabsch_warns_on_collinear_vectors():
    P = np.tile([1.0, 0, 0], (5, 1))
    with pytest.warns(NumericalWarning, match="not unique"):
        kabsch_rotation(P, P)


# ---------------------------------------------------------------- static calibration
def test_static_n_pose_recovers_mounting():
    T = 100
    mount = mountings()
    t = np.arange(T) / FS
    rng = np.random.default_rng(1)
    imu = {}
    for s in LENGTHS:
        # segment hangs straight down (segment axis -z), heading arbitrary, slow postural sway
        # of 0.005 rad (white jitter would not pass the still-window test, by design)
        ph = rng.uniform(0, 2 * np.pi, 3)
        sway = Rotation.from_rotvec(0.005 * np.sin(2 * np.pi * 0.3 * t[:, None] + ph))
        seg = Rotation.from_euler("z", rng.uniform(-180, 180), degrees=True) * sway
        imu[s] = ImuStream(t_s=t, q_world_from_sensor=(seg * mount[s]).as_quat(scalar_first=True))
    cal = calibrate(Recording(imu=imu), lower_body(lengths=LENGTHS), "static", window_s=1.0)
    for s in LENGTHS:
        assert angle_deg(cal.axes[s], mount[s].inv().apply([0, 0, -1])) < 0.5
        assert cal.residual_deg[s] < 2.0
    assert cal.R_world_from_camera is None and cal.lengths_m == {}


def test_static_t_pose_arms():
    mount = Rotation.from_euler("xyz", [10, 70, -20], degrees=True)
    facing = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    right = np.cross(facing, [0, 0, 1])
    # segment frame with its -z along the right arm
    seg = Rotation.align_vectors([right], [[0, 0, -1.0]])[0]
    n = int(0.5 * FS)  # a static calibration needs the pose held for 0.25 s at least
    q = (seg * mount).as_quat(scalar_first=True)[None].repeat(n, 0)
    rec = Recording(imu={"upper_arm_r": ImuStream(t_s=np.arange(n) / FS, q_world_from_sensor=q)})
    cal = calibrate(
        rec,
        upper_limb("r", height_m=1.7),
        "static",
        window_s=0.5,
        pose="t",
        facing=facing,
        segments=["upper_arm_r"],
    )
    assert angle_deg(cal.axes["upper_arm_r"], mount.inv().apply([0, 0, -1])) < 1e-6


# ---------------------------------------------------------------- reference-window calibration
def _with_trunk(rec, mounts):
    """``rec`` (make_recording: hips fixed, right = world +x) plus pelvis and chest IMUs
    mounted as ``mounts`` (``R_sensor_from_segment``, ISB: X anterior, Y up, Z right) on a trunk
    pitching about the hips' axis, and the shoulders in the reference."""
    ref = rec.reference
    t = ref.t_s
    G0 = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # X->+y, Y->+z, Z->+x
    G = Rotation.from_rotvec(0.3 * np.sin(2 * np.pi * 0.5 * t)[:, None] * [1.0, 0, 0])
    G = G * Rotation.from_matrix(G0)
    mid = 0.5 * (ref.position("hip_l") + ref.position("hip_r"))
    sh = {s: mid + G.apply([0.0, 0.5, z]) for s, z in (("shoulder_l", -0.18), ("shoulder_r", 0.18))}
    joints = (*ref.joints, *sh)
    P = np.concatenate([ref.position_m, np.stack(list(sh.values()), axis=1)], axis=1)
    imu = dict(rec.imu)
    for s, M in mounts.items():  # world_from_sensor = world_from_segment @ segment_from_sensor
        q = (G * Rotation.from_matrix(M).inv()).as_quat(scalar_first=True)
        imu[s] = ImuStream(t_s=t, q_world_from_sensor=q, name=s, frame="ENU")
    return Recording(imu=imu, reference=JointStream(t_s=t, position_m=P, joints=joints))


def test_reference_calibration_gives_the_trunk_frames_from_shoulders_and_hips():
    """With a reference holding both shoulders and hips, the chest and pelvis IMUs get their
    ISB frame (right along the shoulder or hip line, up from mid-hip to mid-shoulder) instead
    of the sensor taken as right-front-up. Oracle: the mounting the data were made with."""
    rec, _, _ = make_recording()
    mounts = {
        "pelvis": Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix(),
        "chest": Rotation.from_euler("zyx", [-80, 20, 160], degrees=True).as_matrix(),
    }
    cal = calibrate(_with_trunk(rec, mounts), lower_body(height_m=1.75), "reference", window_s=1.0)
    for s, M in mounts.items():
        np.testing.assert_allclose(cal.frames[s], M, atol=1e-9)
    # without the shoulders the trunk frames stay unknown (not guessed)
    cal = calibrate(rec, lower_body(height_m=1.75), "reference", window_s=1.0)
    assert not cal.frames


def test_reference_window_recovers_axis_under_noise():
    rec, truth, expected = make_recording(noise_m=0.005, rich=False)
    sk = lower_body(height_m=1.75)
    cal = calibrate(rec, sk, "reference", window_s=1.0)
    assert cal.align == "none" and cal.R_world_from_camera is None
    for s in LENGTHS:
        assert angle_deg(cal.axes[s], expected[s]) < 1.0
        assert cal.lengths_m[s] == pytest.approx(LENGTHS[s], abs=0.005)
    js = chain_positions(rec, sk, cal, root=("hip_l", "hip_r"))
    err = js.position("ankle_l") - truth.position("ankle_l")
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.012


def test_chain_positions_noise_free_and_resampled():
    rec, truth, _ = make_recording(ref_rate=25.0)  # reference at 25 Hz, IMUs at 100 Hz
    sk = lower_body(height_m=1.75)
    cal = calibrate(rec, sk, "reference", window_s=1.0)
    js = chain_positions(rec, sk, cal)  # default roots: the hips, from the reference
    assert js.joints[:2] == ("hip_l", "hip_r") and len(js) == len(rec.reference)
    for j in ("knee_l", "ankle_r"):
        np.testing.assert_allclose(js.position(j), truth.position(j)[::4], atol=2e-4)


@pytest.mark.parametrize("align", ["rotation", "heading"])
def test_reference_alignment_recovered(align):
    R = Rotation.from_euler(
        "zyx", [50, 0, 0] if align == "heading" else [50, -20, 100], degrees=True
    )
    rec, truth, expected = make_recording(
        R_ref_from_world=R.as_matrix(), noise_m=0.002, frame="vicon"
    )
    sk = lower_body(height_m=1.75)
    cal = calibrate(
        rec, sk, "reference", window_s=2.0, align="auto" if align == "rotation" else align
    )
    assert cal.align == align
    err = Rotation.from_matrix(cal.R_world_from_camera) * R
    assert np.degrees(err.magnitude()) < 1.0
    for s in LENGTHS:
        assert angle_deg(cal.axes[s], expected[s]) < 1.5
    js = chain_positions(rec, sk, cal)
    assert js.frame == "vicon"
    np.testing.assert_allclose(
        js.position("ankle_r"), truth.position("ankle_r") @ R.as_matrix().T, atol=0.02
    )


def test_alignment_warns_when_poorly_determined():
    rec, _, _ = make_recording(rich=False, frame="vicon")  # planar swing: tilt about x unobservable
    with pytest.warns(NumericalWarning, match="poorly determined"):
        calibrate(rec, lower_body(height_m=1.75), "reference", window_s=1.0, align="rotation")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        calibrate(rec, lower_body(height_m=1.75), "reference", window_s=1.0, align="none")


def test_q_sensor_from_segment_maps_segment_axis():
    rec, _, expected = make_recording()
    cal = calibrate(rec, lower_body(height_m=1.75), "reference")
    q = cal.q_sensor_from_segment("thigh_l", "-e3")
    v = Rotation.from_quat(q, scalar_first=True).apply([0, 0, -1])
    np.testing.assert_allclose(v, cal.axes["thigh_l"], atol=1e-12)


# ---------------------------------------------------------------- bad input
def test_calibration_bad_input():
    rec, _, _ = make_recording(T=50)
    sk = lower_body(height_m=1.75)
    with pytest.raises(InputError, match="unknown calibration method 'kinect'"):
        calibrate(rec, sk, "kinect")
    with pytest.raises(
        InputError, match=r"missing IMU for segment 'upper_arm_r' \(calibration\).*\['shank_l'"
    ):
        calibrate(rec, upper_limb("r", height_m=1.7), "static")
    with pytest.raises(InputError, match=r"unknown segment 'foot_l'; this skeleton has"):
        calibrate(rec, sk, "static", segments=["foot_l"])
    with pytest.raises(InputError, match="has no vision joint stream"):
        calibrate(rec, sk, "vision")
    with pytest.raises(InputError, match="expected a window with samples"):
        calibrate(rec, sk, "reference", start_s=10.0)
    ref = rec.reference.subset(["hip_l", "knee_l", "hip_r", "knee_r", "ankle_r"])
    rec2 = Recording(imu=rec.imu, reference=ref)
    with pytest.raises(
        InputError,
        match=r"segment 'shank_l': expected joints \['ankle_l'\] in the reference stream",
    ):
        calibrate(rec2, sk, "reference")
    with pytest.raises(
        InputError, match=r"root joint\(s\) \['pelvis'\] not in the reference stream"
    ):
        chain_positions(rec, sk, root="pelvis")
    with pytest.raises(
        InputError, match=r"expected root 'hip_l' with shape \(T, 3\) = \(50, 3\), got \(49, 3\)"
    ):
        chain_positions(rec, sk, root={"hip_l": np.zeros((49, 3)), "hip_r": np.zeros((50, 3))})


@settings(max_examples=60, deadline=None)
@given(
    psi=st.floats(-720.0, 720.0, allow_nan=False),
    seed=st.integers(0, 2**32 - 1),
    scale=st.floats(0.5, 2.0),
)
def test_turn_heading_is_scipys_composition_with_rz(psi, seed, scale):
    """`turn_heading(q, ψ)` is scipy's ``Rotation.from_matrix(R_z(ψ)) * Rotation.from_quat(q)``
    (the heading matrix the calibration reports) for rows that are not exactly unit, up to the
    quaternion's sign (scipy's ``from_matrix`` picks one; ``turn_heading`` keeps ``q``'s at
    ψ = 0); NaN rows stay NaN. Components are bounded by 1: 1e-12 is far above rounding."""
    from kinefuse.kinematics.calibration_result import turn_heading
    from kinefuse.kinematics.forward import rotation_z

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(50, 4)) * scale
    q[7] = np.nan
    got = turn_heading(q, psi)
    ok = np.ones(50, bool)
    ok[7] = False
    H = Rotation.from_matrix(rotation_z(np.radians(psi)))
    want = (H * Rotation.from_quat(q[ok], scalar_first=True)).as_quat(scalar_first=True)
    sign = np.sign(np.sum(got[ok] * want, axis=1))[:, None]
    np.testing.assert_allclose(got[ok], sign * want, atol=1e-12)
    np.testing.assert_allclose(
        turn_heading(q[ok], 0.0),
        q[ok] / np.linalg.norm(q[ok], axis=1)[:, None],
        rtol=1e-15,
        atol=1e-15,
    )
    assert np.isnan(got[7]).all()


def _still_arm(n):
    q = Rotation.from_euler("xyz", [10, 70, -20], degrees=True).as_quat(scalar_first=True)
    st = ImuStream(t_s=np.arange(n) / FS, q_world_from_sensor=q[None].repeat(n, 0))
    return Recording(imu={"upper_arm_r": st})


def test_static_calibration_refuses_a_recording_too_short_to_hold_a_pose():
    """A few samples (0.02 s) cannot show stillness: an error saying how long the sensors
    share and what is needed, not a calibration over 20 ms."""
    with pytest.raises(InputError, match=r"share only 0\.02 s, too short to hold a pose"):
        calibrate(_still_arm(3), upper_limb("r", height_m=1.7), "static", segments=["upper_arm_r"])


def test_static_calibration_warns_when_the_recording_is_shorter_than_its_window():
    sk = upper_limb("r", height_m=1.7)
    with pytest.warns(NumericalWarning, match=r"shorter than the still window of 1 s.*0\.59 s"):
        calibrate(_still_arm(60), sk, "static", segments=["upper_arm_r"])
    with warnings.catch_warnings():  # 100 samples at 100 Hz fill a 1-s window: no warning
        warnings.simplefilter("error", NumericalWarning)
        calibrate(_still_arm(100), sk, "static", segments=["upper_arm_r"])


def test_reference_calibration_refuses_quaternions_that_are_not_unit():
    """Norm-2 quaternions were blended (and so normalised) by SLERP before any check: the
    reference calibration accepted what the static one and chain_positions refuse."""
    from dataclasses import replace

    rec, _, _ = make_recording()
    st = rec.imu["thigh_l"]
    imu = {**rec.imu, "thigh_l": replace(st, q_world_from_sensor=2.0 * st.q_world_from_sensor)}
    with pytest.raises(InputError, match="IMU 'thigh_l' orientation as unit quaternions"):
        calibrate(replace(rec, imu=imu), lower_body(height_m=1.75), "reference", window_s=1.0)
