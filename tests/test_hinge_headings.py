"""Static calibration with flexion axes from the movement: the limbs' headings (6-D), a fitted
axis that contradicts the pose, and a swapped pair of sensors (closed-form synthetic data)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import NumericalWarning
from kinefuse.io import ImuStream, Recording
from kinefuse.kinematics import (
    calibrate,
    joint_angles,
    lower_body,
    segment_orientations,
    upper_limb,
)
from kinefuse.pipelines.run.calibration import _joint_angles

FS = 100.0
LEGS = ("pelvis", "thigh_l", "shank_l", "thigh_r", "shank_r")
#: R_segment_from_sensor: every sensor sits on its segment with its own heading (on the side, at
#: the front, at the back...), unlike the assumption of a common sensor heading on the body
MOUNTS = {
    "pelvis": Rotation.from_euler("xyz", [5, 10, 0], degrees=True),
    "thigh_l": Rotation.from_euler("xyz", [-20, 100, 15], degrees=True),
    "shank_l": Rotation.from_euler("xyz", [30, -60, 160], degrees=True),
    "thigh_r": Rotation.from_euler("xyz", [10, -120, -25], degrees=True),
    "shank_r": Rotation.from_euler("xyz", [-15, 45, 70], degrees=True),
    "foot_l": Rotation.from_euler("xyz", [5, -10, 75], degrees=True),  # on the top of the foot
    "foot_r": Rotation.from_euler("xyz", [-8, 6, -110], degrees=True),
    "upper_arm_r": Rotation.from_euler("xyz", [10, 80, -30], degrees=True),
    "forearm_r": Rotation.from_euler("xyz", [-40, 20, 65], degrees=True),
}


def _legs(headings_deg, T=1200, swap_left=False, pelvis_tilt=0.0, pelvis_yaw=0.0, mounts=None):
    """Still N-pose for 1 s, then hips and knees flex (about the body's right axis, world east
    for a subject facing north); each sensor's world frame is turned by its heading (6-D).
    ``pelvis_tilt``: amplitude of a pelvic tilt (about the right axis), deg; ``pelvis_yaw``: the
    pelvis sensor turned on the body about the vertical, deg; ``mounts``: instead of
    :data:`MOUNTS`."""
    t = np.arange(T) / FS
    m = np.clip(t - 1.0, 0.0, None)
    ang = {}
    for side, w in (("l", 1.1), ("r", 1.7)):
        hip = 30.0 * (1.0 - np.cos(w * m)) + 5.0 * np.sin(2.3 * w * m)  # 0..65 deg
        knee = 45.0 * (1.0 - np.cos(1.3 * w * m))  # 0..90 deg
        # about north (ISB X): adduction of the right leg, abduction of the left; it also
        # leaves the hinge nothing to mistake a heading turned half a turn for (planar motion)
        abd = 12.0 * np.sin(0.9 * w * m)
        ang[side] = (hip, knee, abd)
    tilt = pelvis_tilt * np.stack(
        [np.sin(2.2 * m), 0.5 * np.sin(3.1 * m), 0.3 * np.sin(2.7 * m)], 1
    )
    seg = {"pelvis": Rotation.from_euler("xyz", tilt, degrees=True)}  # tilt, obliquity, turn
    for side in "lr":
        hip, knee, abd = ang[side]
        seg[f"thigh_{side}"] = seg["pelvis"] * Rotation.from_euler(
            "XY", np.stack([hip, abd], axis=1), degrees=True
        )  # Grood & Suntay order: flexion, then the floating axis
        seg[f"shank_{side}"] = seg[f"thigh_{side}"] * Rotation.from_euler(
            "x", -knee[:, None], degrees=True
        )
    for side, w in (("l", 1.1), ("r", 1.7)):  # dorsiflexion, then the foot's axial rotation
        dorsi = 15.0 * np.sin(2.1 * w * m) - 5.0 * (1.0 - np.cos(0.6 * w * m))
        axial = 8.0 * np.sin(1.4 * w * m)
        seg[f"foot_{side}"] = seg[f"shank_{side}"] * Rotation.from_euler(
            "XZ", np.stack([dorsi, axial], axis=1), degrees=True
        )
        ang[f"ankle_{side}"] = (dorsi, axial)
    if swap_left:  # the sensors of the left thigh and shank mapped to each other's segment
        seg["thigh_l"], seg["shank_l"] = seg["shank_l"], seg["thigh_l"]
    imu = {}
    for s in (*LEGS, "foot_l", "foot_r") if "foot_l" in headings_deg else LEGS:
        mounts = MOUNTS if mounts is None else mounts
        mount = mounts[{"thigh_l": "shank_l", "shank_l": "thigh_l"}.get(s, s) if swap_left else s]
        if s == "pelvis":
            mount = Rotation.from_euler("z", pelvis_yaw, degrees=True) * mount
        R = Rotation.from_euler("z", headings_deg[s], degrees=True) * seg[s] * mount
        imu[s] = ImuStream(t_s=t, q_world_from_sensor=R.as_quat(scalar_first=True), name=s,
                           **_inertial(seg, s, mount, t))  # fmt: skip
    return Recording(imu=imu), t, ang


def _inertial(seg, s, mount, t):
    """The accelerometer and gyroscope of sensor ``s`` (pelvis and thighs; others none): the
    pelvis turning about a fixed point, hip centres 9 cm to each side and 8 cm down, the pelvis
    sensor 12 cm behind that point, a thigh's 20 cm down its thigh and 7 cm to the side."""
    if not (s == "pelvis" or s.startswith("thigh_")):
        return {}
    P = seg["pelvis"]
    if s == "pelvis":
        p = P.apply([0.0, -0.12, 0.0])
    else:
        side = 1.0 if s.endswith("_r") else -1.0
        p = P.apply([0.09 * side, 0.0, -0.08]) + seg[s].apply([0.07 * side, 0.0, -0.20])
    dt = float(t[1] - t[0])
    acc_w = np.gradient(np.gradient(p, dt, axis=0), dt, axis=0) + [0.0, 0.0, 9.81]
    R = seg[s] * mount  # the sensor's true world-from-sensor (no 6-D heading)
    d = (R[2:] * R[:-2].inv()).as_rotvec() / (2.0 * dt)  # world rate, central differences
    w_w = np.concatenate([d[:1], d, d[-1:]])
    return {"acc_m_s2": R.inv().apply(acc_w), "gyr_rad_s": R.inv().apply(w_w)}


def _legs_skeleton():
    from dataclasses import replace

    return replace(lower_body(height_m=1.75), root_segment="pelvis")


def test_6d_limbs_face_as_the_trunk_in_the_pose():
    """6-D sensors mounted with different headings on the body: the hips read zero in the
    pose and the exact hip and knee angles after, although the sensors' headings disagree
    (before: the hips read the mounting differences as internal rotation)."""
    headings = {"pelvis": 0.0, "thigh_l": 35.0, "shank_l": -70.0, "thigh_r": 120.0, "shank_r": 10.0}
    rec, t, ang = _legs(headings)
    cal = calibrate(rec, _legs_skeleton(), "static", window_s=0.5, heading="static",
                    facing="auto", segments=list(LEGS))  # fmt: skip
    assert set(cal.limb_heading_deg) == {"knee_l", "knee_r"}
    assert cal.world_heading_deg["pelvis"] == 0.0  # the first segment keeps its heading
    out = joint_angles(segment_orientations(rec, cal, t))
    for side in "lr":
        hip, knee, abd = ang[side]
        np.testing.assert_allclose(out[f"hip_{side}"][:, 0], hip, atol=0.5)
        np.testing.assert_allclose(
            out[f"hip_{side}"][:, 1], abd * (1 if side == "r" else -1), atol=0.5
        )
        np.testing.assert_allclose(out[f"hip_{side}"][:, 2], 0.0, atol=0.5)
        np.testing.assert_allclose(out[f"knee_{side}"][:, 0], knee, atol=0.5)
        np.testing.assert_allclose(out[f"knee_{side}"][:, 1:], 0.0, atol=0.5)
    notes, warns = [], []
    _joint_angles(rec, cal, t, notes, warns)
    assert not any("by construction" in w for w in warns), warns


def test_fitted_axis_that_contradicts_the_pose_is_not_used():
    """The 'pose' holds the upper arm abducted 45 deg: the elbow's flexion axis fitted to the
    movement is 45 deg from perpendicular to the pose's long axis: warned, pose frames kept."""
    T = 600
    t = np.arange(T) / FS
    m = np.clip(t - 1.0, 0.0, None)
    flex = 60.0 * (1.0 - np.cos(1.3 * m))
    arm = Rotation.from_euler("y", np.full((T, 1), -45.0), degrees=True)  # about north: abduction
    seg = {
        "upper_arm_r": arm,
        "forearm_r": arm * Rotation.from_euler("x", flex[:, None], degrees=True),
    }
    imu = {
        s: ImuStream(t_s=t, q_world_from_sensor=(R * MOUNTS[s]).as_quat(scalar_first=True), name=s)
        for s, R in seg.items()
    }
    rec = Recording(imu=imu)
    with pytest.warns(
        NumericalWarning, match=r"flexion axis of elbow_r .* 45 deg from perpendicular"
    ):
        cal = calibrate(rec, upper_limb("r", height_m=1.7), "static", window_s=0.5, facing="auto")
    assert "elbow_r" not in cal.hinge_residual_rad_s


def test_swapped_sensors_are_named():
    """9-D (shared headings): the left thigh and shank sensors swapped reverse knee_l's fitted
    axis; the facing warning and the hip's pose-angle warning name the pair to check."""
    rec, t, _ = _legs(dict.fromkeys(LEGS, 0.0), swap_left=True)
    with pytest.warns(NumericalWarning, match=r"thigh_l and shank_l \(knee_l\).*swapped"):
        cal = calibrate(rec, _legs_skeleton(), "static", window_s=0.5, facing="auto",
                        segments=list(LEGS))  # fmt: skip
    notes, warns = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        _joint_angles(rec, cal, t, notes, warns)
    hip = [w for w in warns if w.startswith("hip_l reads")]
    assert hip and "sensors of thigh_l and shank_l swapped" in hip[0], warns


def _elbow(T: int):
    """An elbow flexing 0..120 deg while the upper arm sways, 6-D: the forearm sensor's world
    turned 40 deg. Returns ``t``, ``R_A``, ``R_B`` (T, 3, 3), both sensor-frame long axes
    (proximal -> distal) and the true flexion axis in the upper-arm sensor (world x)."""
    t = np.arange(T) / FS
    m = np.clip(t - 1.0, 0.0, None)
    flex = 60.0 * (1.0 - np.cos(1.3 * m))
    arm = Rotation.from_euler("zx", np.stack([20.0 * np.sin(0.7 * m), 15.0 * np.sin(m)], 1), True)
    R_A = (arm * MOUNTS["upper_arm_r"]).as_matrix()
    fore = arm * Rotation.from_euler("x", flex[:, None], degrees=True) * MOUNTS["forearm_r"]
    R_B = (Rotation.from_euler("z", 40.0, degrees=True) * fore).as_matrix()
    axis_a = MOUNTS["upper_arm_r"].inv().apply([0.0, 0.0, -1.0])
    axis_b = MOUNTS["forearm_r"].inv().apply([0.0, 0.0, -1.0])
    return t, R_A, R_B, axis_a, axis_b, MOUNTS["upper_arm_r"].inv().apply([1.0, 0.0, 0.0])


def _off_deg(j1, truth) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(j1 @ truth))))))


def test_perpendicular_fit_recovers_a_perpendicular_axis_exactly():
    """The refit with the flexion axis held perpendicular to the proximal long axis: on an elbow
    whose axis is perpendicular (closed-form motion, 6-D headings 40 deg apart), it finds that
    axis and the heading as the free fit does, with a residual near zero."""
    from kinefuse.kinematics.hinge import _fit_flexion_axis, _world_rate

    t, R_A, R_B, axis_a, axis_b, truth = _elbow(600)
    args = (R_A, R_B, _world_rate(R_A, t), _world_rate(R_B, t), axis_a, axis_b, True)
    for perpendicular in (False, True):
        j1, dpsi, rms = _fit_flexion_axis(*args, perpendicular=perpendicular)
        # rates from finite differences of the orientations (half a sample late) and the weak
        # heading prior: a fraction of a degree, not zero
        off = _off_deg(j1, truth)
        assert off < 0.5 and rms < 0.01, (perpendicular, off, rms)
        assert np.degrees(dpsi) == pytest.approx(-40.0, abs=0.5)
        if perpendicular:
            assert abs(j1 @ axis_a) < 1e-12


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_hinge_fit_is_robust_to_knocks(seed):
    """An elbow (6-D, headings 40 deg apart) whose forearm rates carry 0.05 rad/s noise and, on
    5 % of the samples, knocks of 2 rad/s: the robust (Cauchy) refinement finds the flexion axis
    within 1.5 deg and the heading within 1.5 deg. Least squares alone, measured on the same
    data: 1.3, 36 and 10.5 deg off for seeds 5, 6, 7."""
    from kinefuse.kinematics.hinge import _fit_flexion_axis, _world_rate

    T = 1200
    t, R_A, R_B, axis_a, axis_b, truth = _elbow(T)
    rng = np.random.default_rng(seed)
    wB = _world_rate(R_B, t) + rng.normal(0.0, 0.05, (T, 3))
    knocked = rng.choice(T, T // 20, replace=False)
    wB[knocked] += rng.normal(0.0, 2.0, (knocked.size, 3))
    j1, dpsi, _ = _fit_flexion_axis(R_A, R_B, _world_rate(R_A, t), wB, axis_a, axis_b, True)
    assert _off_deg(j1, truth) < 1.5
    assert np.degrees(dpsi) == pytest.approx(-40.0, abs=1.5)


@pytest.mark.parametrize("refine_heading", [True, False])
def test_rate_constraint_jacobian_equals_finite_differences(refine_heading):
    """The hinge fit's analytic Jacobian (azimuth, elevation, heading) against scipy's central
    differences of the same residual, at random points on random rotations and rates; the
    tolerance is the differences' truncation error (step ~6e-6 rad, curvature ~1e2)."""
    from scipy.optimize._numdiff import approx_derivative

    from kinefuse.kinematics.hinge import _rate_constraint

    rng = np.random.default_rng(7)
    K = 400
    R = Rotation.random(K, random_state=8).as_matrix()
    b, wA, wB = rng.normal(size=(3, K, 3))
    res, jac = _rate_constraint(R[:, :, 0], R[:, :, 1], R[:, :, 2], b, wA, wB, 0.3, refine_heading)
    for x in rng.uniform(-np.pi, np.pi, size=(6, 3)):
        J = jac(x)
        assert J.shape == (K + 1, 3)
        np.testing.assert_allclose(J, approx_derivative(res, x, method="3-point"), atol=1e-4)
        if not refine_heading:  # the heading turns nothing: only its prior depends on it
            assert np.all(J[:K, 2] == 0.0)


def test_6d_foot_sensors_get_their_heading_from_the_ankle():
    """6-D foot sensors on the top of the feet, turned 75 and -110 deg about the vertical from
    the shank sensors' common-heading assumption: the exact ankle angles (dorsiflexion, no
    adduction, the foot's axial rotation) once each foot's heading is fitted to its ankle;
    the common-heading assumption alone was up to 31 (left) and 85 deg (right) off in adduction
    here."""
    headings = {"pelvis": 0.0, "thigh_l": 35.0, "shank_l": -70.0, "thigh_r": 120.0,
                "shank_r": 10.0, "foot_l": -150.0, "foot_r": 60.0}  # fmt: skip
    rec, t, ang = _legs(headings)
    from kinefuse.pipelines.run.chain import build_chain

    limbs = [*LEGS[1:], "foot_l", "foot_r"]
    skeleton, _ = build_chain(limbs, dict.fromkeys(limbs, 0.4))
    cal = calibrate(rec, skeleton, "static", window_s=0.5, heading="static", facing="auto",
                    segments=["pelvis", *limbs])  # fmt: skip
    assert set(cal.foot_heading_deg) == {"ankle_l", "ankle_r"}
    out = joint_angles(segment_orientations(rec, cal, t))
    for side in "lr":
        dorsi, axial = ang[f"ankle_{side}"]
        a = out[f"ankle_{side}"]
        # the rates are finite differences of the orientations: a fraction of a degree
        np.testing.assert_allclose(a[:, 0], dorsi, atol=0.5)
        np.testing.assert_allclose(a[:, 1], 0.0, atol=0.5)
        np.testing.assert_allclose(np.abs(a[:, 2]), np.abs(axial), atol=0.5)
        np.testing.assert_allclose(out[f"knee_{side}"][:, 0], ang[side][1], atol=0.5)


@pytest.mark.parametrize(("yaw", "dropped"), [(0.0, False), (70.0, False), (70.0, True)])
def test_6d_pelvis_sensor_turned_on_the_body_is_turned_back(yaw, dropped):
    """6-D, the pelvis tilting (25 deg), tipping and turning as the hips flex, every sensor
    facing as the others but the pelvis's, turned by ``yaw`` on the body (the common-heading
    assumption fails for it): the hips' movement turns it back, and the hip angles are exact;
    without the turn they were up to 30 deg off. Its heading comes from
    the assumption only when another segment's sensor is the reference (the first segment).
    ``dropped``: 5 % of the pelvis and left thigh samples missing (NaN), as dropped packets."""
    headings = {"pelvis": 0.0, "thigh_l": 35.0, "shank_l": -70.0, "thigh_r": 120.0, "shank_r": 10.0}
    front = {s: Rotation.from_euler("x", 10.0 * k, degrees=True) for k, s in enumerate(LEGS)}
    rec, t, ang = _legs(headings, pelvis_tilt=25.0, pelvis_yaw=yaw, mounts=front)
    if dropped:
        rng = np.random.default_rng(3)
        for s in ("pelvis", "thigh_l"):
            st = rec.imu[s]
            rows = rng.choice(np.arange(100, t.size), t.size // 20, replace=False)
            q, acc, gyr = (np.array(v) for v in (st.q_world_from_sensor, st.acc_m_s2, st.gyr_rad_s))
            q[rows], acc[rows], gyr[rows] = np.nan, np.nan, np.nan
            rec.imu[s] = ImuStream(
                t_s=t, q_world_from_sensor=q, acc_m_s2=acc, gyr_rad_s=gyr, name=s
            )
    cal = calibrate(rec, _legs_skeleton(), "static", window_s=0.5, heading="static",
                    facing="auto", segments=[*LEGS[1:], "pelvis"])  # fmt: skip
    found = cal.pelvis_heading_deg
    assert set(found["rates"]) == set(found["accelerations"]) == {"hip_l", "hip_r"}
    assert found["turn"] == pytest.approx(yaw, abs=3.0), found
    out = joint_angles(segment_orientations(rec, cal, t))
    for side in "lr":
        hip, _, abd = ang[side]
        expected = np.stack([hip, abd * (1 if side == "r" else -1), np.zeros_like(hip)], 1)
        # a turn 2 deg off (the hips' abduction, which the rate model leaves out) reads the
        # 25 deg pelvic tilt about an axis 2 deg off: about 1 deg at the hips; dropped samples
        # are missing (NaN) there, nowhere else
        seen = np.all(np.isfinite(out[f"hip_{side}"]), axis=1)
        assert seen.all() or (dropped and seen.mean() > 0.85)
        np.testing.assert_allclose(out[f"hip_{side}"][seen], expected[seen], atol=1.5)


def test_6d_pelvis_turn_that_the_accelerations_cannot_place_is_warned_not_applied():
    """The same pelvis sensor turned 70 deg on the body, its accelerometer and gyroscope
    missing (orientations only): the rates give 70 deg only modulo a half turn, nothing can
    choose the half, so nothing is applied and a warning names both halves and says which
    angles are unreliable."""
    headings = {"pelvis": 0.0, "thigh_l": 35.0, "shank_l": -70.0, "thigh_r": 120.0, "shank_r": 10.0}
    front = {s: Rotation.from_euler("x", 10.0 * k, degrees=True) for k, s in enumerate(LEGS)}
    rec, t, _ = _legs(headings, pelvis_tilt=25.0, pelvis_yaw=70.0, mounts=front)
    st = rec.imu["pelvis"]
    rec.imu["pelvis"] = ImuStream(t_s=t, q_world_from_sensor=st.q_world_from_sensor, name="pelvis")
    with pytest.warns(NumericalWarning, match=r"pelvis heading: .* by (-?\d+) or (-?\d+) deg") as w:
        cal = calibrate(rec, _legs_skeleton(), "static", window_s=0.5, heading="static",
                        facing="auto", segments=[*LEGS[1:], "pelvis"])  # fmt: skip
    msg = next(str(x.message) for x in w if "pelvis heading" in str(x.message))
    assert "cannot tell which" in msg and "hip and trunk angles" in msg, msg
    assert not cal.pelvis_heading_deg
