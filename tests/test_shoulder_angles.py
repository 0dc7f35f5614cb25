"""Shoulder and trunk angles: the upper arm in the chest's frame, the chest in the pelvis's
(ISB axes, Z-X-Y as the other joints).

Closed-form oracle: a synthetic upper body whose trunk turns and leans while each upper arm is
set in the chest's ISB frame by known flexion, adduction and internal rotation
(``R = R_Z(α) R_X(β) R_Y(γ)``; ISB signs, mirrored on the left), and (with a pelvis) the chest
in the pelvis by known trunk flexion, lateral bending and axial rotation. The calibration sees
only the sensors (mounted at arbitrary angles) in a still pose; the angles it gives back must
be the ones the body was built from, offline and live.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.io import ImuStream, Recording
from kinefuse.kinematics import joint_angles
from kinefuse.pipelines.run import process_recording
from kinefuse.streaming.config import stream_config_from_session
from kinefuse.streaming.engine_types import IMU_FRESH
from kinefuse.streaming.offline import offline_causal
from kinefuse.streaming.runner import build_engine
from test_trunk_shoulders import MOUNTS as ARM_MOUNTS  # chest, upper arms, forearms
from test_trunk_shoulders import _run_session  # kinefuse run, chain.json and its computation

pytestmark = pytest.mark.filterwarnings("ignore:.*has no online form:UserWarning")

FS = 100.0
H = 1.75
#: ISB axes of the body facing north in the world (x east, y north, z up): columns X anterior
#: (north), Y superior (up), Z right (east)
B = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
MOUNTS = {**ARM_MOUNTS, "pelvis": Rotation.from_euler("xyz", [0, 10, -70], degrees=True)}
PARAMS = {"root": "fixed", "root_position_m": [0.0, 0.0, 1.4], "calibration": "static",
          "facing": [0.0, 1.0, 0.0]}  # fmt: skip


def _zxy(angles_deg: np.ndarray) -> Rotation:
    """``R_Z(α) R_X(β) R_Y(γ)`` in ISB segment axes, as a rotation of the world (facing north)."""
    R = Rotation.from_euler("ZXY", angles_deg, degrees=True).as_matrix()
    return Rotation.from_matrix(B @ R @ B.T)


def _upper_body(T: int = 900, pose: str = "n", pelvis: bool = False):
    """Segment orientations (world from segment; identity = N-pose facing north), the shoulder
    (and trunk) angles they were built from (ISB signs) and the recording of the sensors."""
    t = np.arange(T) / FS
    m = np.clip(t - 2.5, 0.0, None)  # still for 2.5 s (the default window: 2 s)
    trunk = Rotation.from_euler(
        "zx", np.stack([35.0 * np.sin(0.8 * m), -20.0 * (1 - np.cos(0.6 * m))], 1), degrees=True
    )
    seg, want = {"chest": trunk}, {}
    if pelvis:  # the pelvis turns; the chest bends forward, sideways and turns on it
        seg["pelvis"] = Rotation.from_euler("z", 25.0 * np.sin(0.5 * m)[:, None], degrees=True)
        flex, bend = 20.0 * (1 - np.cos(0.7 * m)), 15.0 * np.sin(0.9 * m)
        turn = 25.0 * np.sin(1.1 * m)
        want["trunk"] = np.stack([flex, bend, turn], 1)
        # flexion is -α (the chest's superior axis tilting forward); bending β, rotation γ
        trunk = seg["pelvis"] * _zxy(np.stack([-flex, bend, turn], 1))
        seg["chest"] = trunk
    for side, k, mirror in (("l", 1.0, -1.0), ("r", 1.4, 1.0)):
        flex = 75.0 * (1 - np.cos(0.9 * k * m))  # 0 ... 150 deg
        add = -35.0 * (1 - np.cos(0.5 * k * m))  # abduction 0 ... 70 deg
        rot = 40.0 * np.sin(1.3 * k * m)
        if pose == "t":  # the arms horizontal to the side in the still part, then lowered
            add = -90.0 + 60.0 * (1 - np.cos(0.7 * k * m)) / 2
            flex, rot = 50.0 * np.sin(0.4 * k * m), 0.0 * m
        want[f"shoulder_{side}"] = np.stack([flex, add, rot], 1)
        # ISB: adduction and internal rotation mirrored on the left (β and γ change sign)
        arm = trunk * _zxy(np.stack([flex, mirror * add, mirror * rot], 1))
        seg[f"upper_arm_{side}"] = arm
        el = Rotation.from_euler("x", 50.0 * (1 - np.cos(1.4 * k * m))[:, None], degrees=True)
        seg[f"forearm_{side}"] = arm * el
    imu = {
        s: ImuStream(t_s=t, q_world_from_sensor=(R * MOUNTS[s]).as_quat(scalar_first=True), name=s)
        for s, R in seg.items()
    }
    return want, Recording(imu=imu)


def test_shoulder_angles_equal_the_angles_the_body_was_built_from():
    want, rec = _upper_body()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no gimbal-lock or pose warning on good data
        out = process_recording(rec, "imu-only", dict(PARAMS), body_height_m=H)
    for j in ("shoulder_l", "shoulder_r"):
        # exact data: only the calibration's least squares (cf. tests/test_trunk_shoulders.py)
        np.testing.assert_allclose(out.angles[j], want[j], atol=1e-5, err_msg=j)
    assert np.ptp(out.angles["shoulder_r"][:, 0]) > 140.0  # the test spans the range
    assert any("shoulder_l" in n for n in out.notes if n.startswith("joint angles"))


def test_trunk_angles_equal_the_angles_the_body_was_built_from():
    want, rec = _upper_body(pelvis=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = process_recording(rec, "imu-only", dict(PARAMS), body_height_m=H)
    for j in ("trunk", "shoulder_l", "shoulder_r"):
        np.testing.assert_allclose(out.angles[j], want[j], atol=1e-5, err_msg=j)
    assert min(np.ptp(out.angles["trunk"], axis=0)) > 29.0  # each angle moves


def test_the_isb_signs_of_a_plain_trunk_flexion_bending_and_turn():
    """Independent of the decomposition: bending forward is flexion, to the right is positive
    lateral bending, turning to the left (seen from above) positive axial rotation."""
    pelvis = np.broadcast_to(np.eye(3), (1, 3, 3))
    for rotvec, k in (([0, 0, -1], 0), ([1, 0, 0], 1), ([0, 1, 0], 2)):  # ISB X ant., Y up, Z right
        chest = Rotation.from_rotvec(np.radians(20.0) * np.array(rotvec, float)).as_matrix()[None]
        a = joint_angles({"pelvis": pelvis, "chest": chest})["trunk"][0]
        np.testing.assert_allclose(a, 20.0 * np.eye(3)[k], atol=1e-9)
        y, x = chest[0][:, 1], chest[0][:, 0]  # the chest's superior and anterior axes
        assert {0: y[0] > 0.3, 1: y[2] > 0.3, 2: x[2] < -0.3}[k]  # forward, right, left


def test_the_isb_signs_of_a_plain_flexion_and_abduction():
    """Independent of the decomposition: the arm forward is flexion, out to the side is
    abduction (negative adduction), on both sides."""
    chest = np.broadcast_to(np.eye(3), (1, 3, 3))
    fwd = Rotation.from_rotvec([0.0, 0.0, np.pi / 3]).as_matrix()[None]  # about Z (right)
    out = joint_angles({"chest": chest, "upper_arm_l": fwd, "upper_arm_r": fwd})
    for j in ("shoulder_l", "shoulder_r"):
        np.testing.assert_allclose(out[j][0], [60.0, 0.0, 0.0], atol=1e-9)
    # right arm out to the right: the humerus's superior axis (elbow -> shoulder) points left
    right_out = Rotation.from_rotvec([-np.pi / 4, 0.0, 0.0]).as_matrix()[None]
    left_out = Rotation.from_rotvec([np.pi / 4, 0.0, 0.0]).as_matrix()[None]
    out = joint_angles({"chest": chest, "upper_arm_l": left_out, "upper_arm_r": right_out})
    for j, R in (("shoulder_r", right_out), ("shoulder_l", left_out)):
        np.testing.assert_allclose(out[j][0], [0.0, -45.0, 0.0], atol=1e-9)
        y = R[0][:, 1]  # the humerus's superior axis in chest axes (X ant., Y sup., Z right)
        assert np.sign(y[2]) == (-1.0 if j == "shoulder_r" else 1.0)  # towards the midline


def test_a_t_pose_calibration_reads_the_abducted_arms_without_warnings():
    want, rec = _upper_body(pose="t")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no gimbal-lock (SciPy) nor pose-angle warning
        out = process_recording(rec, "imu-only", dict(PARAMS, pose="t"), body_height_m=H)
    assert not [w for w in out.warnings if "shoulder" in w], out.warnings
    t = out.t_s
    for j in ("shoulder_l", "shoulder_r"):
        a = out.angles[j]
        np.testing.assert_allclose(a[t < 2.0, 1], -90.0, atol=1e-4)  # abducted in the pose
        away = np.abs(want[j][:, 1] + 90.0) > 10.0  # flexion and rotation defined there
        assert away.mean() > 0.5
        np.testing.assert_allclose(a[away], want[j][away], atol=1e-4, err_msg=j)


def test_the_pose_check_expects_the_poses_own_shoulder_angles():
    """A T-pose shoulder reads adduction -90 by construction, and its flexion and rotation are
    undefined there: only an adduction away from -90 is named."""
    from kinefuse.kinematics.calibration_result import Calibration
    from kinefuse.kinematics.still import StillWindow
    from kinefuse.pipelines.run.calibration import _pose_angle_check

    t = np.arange(300) / FS
    cal = Calibration(axes={}, window_s=(0.0, 2.0), still=StillWindow(0.0, 2.0, 0.0, 0.0, "chest", "chest", "gyr", True),
                      pose_angles_deg={"shoulder_r": np.array([0.0, -90.0, 0.0]),
                                       "elbow_r": np.zeros(3)})  # fmt: skip

    def check(shoulder, elbow=(0.0, 0.0, 0.0)):
        a = {"shoulder_r": np.tile(shoulder, (t.size, 1)), "elbow_r": np.tile(elbow, (t.size, 1))}
        return _pose_angle_check(a, t, cal)

    assert check([-40.0, -89.0, 30.0]) == []
    (msg,) = check([0.0, -60.0, 0.0])
    assert msg.startswith("shoulder_r reads adduction -60 deg") and "adduction -90" in msg, msg
    (msg,) = check([0.0, -90.0, 0.0], elbow=[25.0, 0.0, 0.0])
    assert msg.startswith("elbow_r reads flexion 25 deg") and "reads zero by construction" in msg


def test_the_live_shoulder_and_trunk_angles_are_kinefuse_runs(tmp_path):
    """Oracle: kinefuse run's angles on the same samples; chain.json carries the chest's
    and the pelvis's frames, so the engine computes the shoulders and the trunk live."""
    _, rec = _upper_body(T=600, pelvis=True)
    chain, cfg, rec2, out = _run_session(
        tmp_path, rec, 'root = "fixed"\nroot_position_m = [0, 0, 1.4]'
    )
    engine = build_engine(stream_config_from_session(cfg, chain), camera=False,
                          camera_rate_hz=30.0, imu_rate_hz=FS)  # fmt: skip
    assert {"shoulder_l", "shoulder_r", "trunk"} <= set(engine.config.angle_joints)
    imu = {s: (st.t_s, st.q_world_from_sensor) for s, st in rec2.imu.items()}
    off = offline_causal(engine.config, engine.processor, imu, None, frame_times=out.t_s)
    fresh = np.all(off.imu_status == IMU_FRESH, axis=1)  # every segment (the chest too)
    assert fresh.mean() > 0.95
    for a, j in enumerate(engine.config.angle_joints):
        ok = fresh & np.all(np.isfinite(out.angles[j]), axis=-1)
        np.testing.assert_allclose(off.angles_deg[ok, a], out.angles[j][ok], atol=1e-6, err_msg=j)
    header = (tmp_path / "out").glob("*angles.csv")
    head = [p.read_text().splitlines()[6] for p in header]
    assert any("shoulder_r_flexion_deg" in h and "trunk_lateral_bending_deg" in h for h in head)
