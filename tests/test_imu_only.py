"""The IMU-only path: still windows, static calibration, heading, joint angles, lengths, roots, .mot,
and `kinefuse run` / `evaluate` / `init-session` on real IMU-only recordings (x-IMU3, qmt)."""

from __future__ import annotations

import ast
import json
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import tomllib
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from kinefuse import cli
from kinefuse.exceptions import ConfigError, InputError, NumericalWarning
from kinefuse.io import FORMATS, ImuStream, Recording, read_joint_csv, read_trc, write_mot
from kinefuse.kinematics import (
    ANTHROPOMETRIC_RATIOS,
    calibrate,
    find_still_window,
    joint_angles,
    lower_body,
    segment_lengths,
    segment_orientations,
    upper_limb,
)
from kinefuse.pipelines.run import run_session
from kinefuse.session_file import METHODS

SESSIONS = Path(__file__).parent / "data" / "sessions"
runner = CliRunner()
FS = 100.0


def _err(result) -> str:
    try:
        return result.stderr
    except ValueError:
        return result.output


def _rz(deg):
    return Rotation.from_euler("z", deg, degrees=True)


# ------------------------------------------------------------------ still window
def _stream(rot: Rotation, t, *, gyro=True, acc_noise=0.0, seed=0):
    """An ImuStream whose gyro is the body rate of ``rot`` (finite differences)."""
    q = rot.as_quat(scalar_first=True)
    rng = np.random.default_rng(seed)
    g_world = np.array([0.0, 0.0, 9.81])
    acc = rot.inv().apply(g_world) + acc_noise * rng.standard_normal((t.size, 3))
    gyr = None
    if gyro:
        d = (rot[:-1].inv() * rot[1:]).as_rotvec() * FS
        gyr = np.vstack([d, d[-1:]])
    return ImuStream(t_s=t, q_world_from_sensor=q, acc_m_s2=acc, gyr_rad_s=gyr)


def _moving_then_still(T=600, still_from_s=3.0, amp=0.6):
    t = np.arange(T) / FS
    env = np.where(t < still_from_s, 1.0, 0.0)
    rv = amp * env[:, None] * np.sin(2 * np.pi * 1.2 * t)[:, None] * np.array([1.0, 0.3, 0.0])
    return t, Rotation.from_rotvec(rv)


@pytest.mark.parametrize("gyro", [True, False])
def test_still_window_is_the_earliest_still_one(gyro):
    t, rot = _moving_then_still()
    st = _stream(rot, t, gyro=gyro)
    w = find_still_window({"thigh_l": st, "shank_l": st}, 1.0)
    assert w.still and 3.0 - 1e-9 <= w.start_s <= 3.3, w
    assert w.signal == ("gyroscope" if gyro else "orientation change")
    assert w.rate_rad_s < 1e-6 and w.acc_std_m_s2 < 1e-6


def test_no_still_window_names_the_stillest_candidate():
    t, rot = _moving_then_still(still_from_s=99.0)
    rec = Recording(imu={"upper_arm_r": _stream(rot, t), "forearm_r": _stream(rot, t)})
    with pytest.raises(InputError, match=r"no still window of 1 s.*stillest candidate is") as info:
        calibrate(rec, upper_limb("r", height_m=1.7), "static", window_s=1.0)
    msg = str(info.value)
    # the motion level of the stillest candidate is printed (|rate| of this motion ~ 1-5 rad/s)
    rate = float(msg.split("stillest candidate is")[1].split("mean angular rate ")[1].split(" ")[0])
    assert 0.1 < rate < 6.0, msg


# ------------------------------------------------------------------ static calibration
def _arm_pose_recording(mounts, T=200, heading_deg=(0.0, 0.0), flex_deg=None):
    """Upper arm + forearm hanging still for 1 s, then the elbow flexes.

    ``mounts`` = R_segment_from_sensor per segment; ``heading_deg`` rotates each sensor's world
    frame (6-D fusion); ``flex_deg`` (T,) flexes the elbow after the still second.
    """
    t = np.arange(T) / FS
    flex = np.zeros(T) if flex_deg is None else flex_deg
    seg = {
        "upper_arm_r": Rotation.identity(T),
        # elbow flexion = rotation about the ISB +Z (right) axis, world east for a subject facing
        # north (the default facing): the forearm's end moves anteriorly
        "forearm_r": Rotation.from_euler("x", flex[:, None], degrees=True),
    }
    imu = {}
    for (s, R), h in zip(seg.items(), heading_deg, strict=True):
        q = (_rz(h) * R * mounts[s]).as_quat(scalar_first=True)
        imu[s] = ImuStream(t_s=t, q_world_from_sensor=q, name=s)
    return Recording(imu=imu)


MOUNTS = {
    "upper_arm_r": Rotation.from_euler("xyz", [10, 80, -30], degrees=True),
    "forearm_r": Rotation.from_euler("xyz", [-40, 20, 65], degrees=True),
}


def test_static_frames_give_known_elbow_flexion():
    T = 300
    flex = np.where(np.arange(T) < 100, 0.0, np.linspace(0, 120, T))
    rec = _arm_pose_recording(MOUNTS, T, flex_deg=flex)
    cal = calibrate(rec, upper_limb("r", height_m=1.7), "static", window_s=0.5)
    assert cal.window_s[0] == pytest.approx(0.0) and cal.still.still
    ang = joint_angles(segment_orientations(rec, cal, rec.imu["forearm_r"].t_s))["elbow_r"]
    np.testing.assert_allclose(ang[:, 0], flex, atol=1e-6)
    np.testing.assert_allclose(ang[:, 1:], 0.0, atol=1e-6)


def test_static_foot_frame_is_the_shank_s_and_gives_known_dorsiflexion():
    """A foot's static frame is its shank's carried into the foot sensor in the pose (ISB
    neutral, Wu et al. 2002): the ankle dorsiflexed by a known angle about the shank's Z (east
    for the default facing north) after the still half second reads as that ankle flexion
    (positive: toes up) and nothing else, whatever the sensor mountings; the foot's long axis
    points forward in the pose (it used to point down, like the shank's)."""
    from kinefuse.pipelines.run import build_chain

    T = 300
    t = np.arange(T) / FS
    dorsi = np.where(np.arange(T) < 100, 0.0, 25.0 * np.sin(np.linspace(0.0, 3 * np.pi, T)))
    mounts = {
        "thigh_r": Rotation.from_euler("xyz", [10, 80, -30], degrees=True),
        "shank_r": Rotation.from_euler("xyz", [-40, 20, 65], degrees=True),
        "foot_r": Rotation.from_euler("xyz", [95, -15, 140], degrees=True),
    }
    seg = {"thigh_r": Rotation.identity(T), "shank_r": Rotation.identity(T),
           "foot_r": Rotation.from_euler("x", dorsi[:, None], degrees=True)}  # fmt: skip
    rec = Recording(imu={
        s: ImuStream(t_s=t, q_world_from_sensor=(seg[s] * mounts[s]).as_quat(scalar_first=True))
        for s in seg
    })  # fmt: skip
    sk, _ = build_chain(list(seg), {"thigh_r": 0.4, "shank_r": 0.4, "foot_r": 0.15}, {})
    cal = calibrate(rec, sk, "static", window_s=0.5)
    ang = joint_angles(segment_orientations(rec, cal, t))
    np.testing.assert_allclose(ang["ankle_r"][:, 0], dorsi, atol=1e-6)
    np.testing.assert_allclose(ang["ankle_r"][:, 1:], 0.0, atol=1e-6)
    np.testing.assert_allclose(ang["knee_r"], 0.0, atol=1e-6)
    forward = mounts["foot_r"].apply(cal.axes["foot_r"])  # in the world, in the pose
    np.testing.assert_allclose(forward, [0.0, 1.0, 0.0], atol=1e-9)
    # the knee flexes too, and the facing given is wrong (east): the knee's flexion axis comes
    # from the movement, and the foot follows its shank's frame, not the wrong pose frame
    knee = np.where(np.arange(T) < 100, 0.0, 60.0 * np.sin(np.linspace(0.0, 2 * np.pi, T)) ** 2)
    seg["shank_r"] = Rotation.from_euler("x", -knee[:, None], degrees=True)
    seg["foot_r"] = seg["shank_r"] * Rotation.from_euler("x", dorsi[:, None], degrees=True)
    imu = {s: ImuStream(t_s=t, q_world_from_sensor=(seg[s] * mounts[s]).as_quat(scalar_first=True))
           for s in seg}  # fmt: skip
    rec = Recording(imu=imu)
    cal = calibrate(
        rec, sk, "static", window_s=0.5, facing=(1.0, 0.0, 0.0), flexion_axes="movement"
    )
    ang = joint_angles(segment_orientations(rec, cal, t))
    np.testing.assert_allclose(ang["knee_r"][:, 0], knee, atol=1e-5)
    np.testing.assert_allclose(ang["ankle_r"][:, 0], dorsi, atol=1e-5)
    np.testing.assert_allclose(ang["ankle_r"][:, 1:], 0.0, atol=1e-5)


def test_static_heading_brings_6d_frames_together():
    # forearm sensor world frame off by 40 deg heading: without the correction the relative
    # rotation is wrong, with heading="static" the flexion is exact (same mounting heading)
    T = 300
    flex = np.where(np.arange(T) < 100, 0.0, np.linspace(0, 90, T))
    same = {s: Rotation.from_euler("xyz", [0, 90, 0], degrees=True) for s in MOUNTS}
    rec = _arm_pose_recording(same, T, heading_deg=(0.0, 40.0), flex_deg=flex)
    sk = upper_limb("r", height_m=1.7)
    cal = calibrate(rec, sk, "static", window_s=0.5, heading="static")
    assert cal.world_heading_deg["forearm_r"] == pytest.approx(-40.0, abs=1e-6)
    ang = joint_angles(segment_orientations(rec, cal, rec.imu["forearm_r"].t_s))["elbow_r"]
    np.testing.assert_allclose(ang[:, 0], flex, atol=1e-6)
    raw = calibrate(rec, sk, "static", window_s=0.5)
    bad = joint_angles(segment_orientations(rec, raw, rec.imu["forearm_r"].t_s))["elbow_r"]
    assert np.max(np.abs(bad[:, 0] - flex)) > 5.0


def _elbow_2dof_recording(facing_deg, heading_deg, T=800):
    """Still N-pose for 1 s, then shoulder swing, elbow flexion and forearm pronation.

    The subject faces ``facing_deg`` (about the vertical from north); each sensor's world frame
    is off by its ``heading_deg`` (6-D fusion). Returns the recording, flexion and pronation.
    """
    t = np.arange(T) / FS
    m = np.clip(t - 1.0, 0.0, None)
    flex = 60.0 * (1.0 - np.cos(1.3 * m))  # 0..120 deg
    pron = 40.0 * np.sin(0.7 * m)
    shoulder = Rotation.from_euler(
        "xy", np.stack([25.0 * np.sin(0.9 * m), 15.0 * np.sin(0.5 * m)], 1), degrees=True
    )
    body = _rz(facing_deg)
    seg = {
        "upper_arm_r": body * shoulder,
        # flexion about body east (ISB Z, right), pronation about the forearm's long axis (Y)
        "forearm_r": body
        * shoulder
        * Rotation.from_euler("x", flex[:, None], degrees=True)
        * Rotation.from_euler("z", pron[:, None], degrees=True),
    }
    imu = {}
    for (s, R), h in zip(seg.items(), heading_deg, strict=True):
        q = (_rz(h) * R * MOUNTS[s]).as_quat(scalar_first=True)
        imu[s] = ImuStream(t_s=t, q_world_from_sensor=q, name=s)
    return Recording(imu=imu), flex, pron


def test_hinge_flexion_axis_from_movement_needs_no_facing():
    # 6-D sensors (headings 0 and 55 deg), subject facing 70 deg from the assumed north, sensors
    # mounted differently: the pose frames misassign the flexion axis, the movement finds it
    rec, flex, pron = _elbow_2dof_recording(70.0, (0.0, 55.0))
    sk = upper_limb("r", height_m=1.7)
    t = rec.imu["forearm_r"].t_s
    pose = calibrate(rec, sk, "static", window_s=0.5, heading="static", flexion_axes="pose")
    bad = joint_angles(segment_orientations(rec, pose, t))["elbow_r"][:, 0]
    assert np.max(np.abs(bad - flex)) > 10.0
    cal = calibrate(rec, sk, "static", window_s=0.5, heading="static")  # "auto": movement
    assert set(cal.hinge_residual_rad_s) == {"elbow_r"}
    ang = joint_angles(segment_orientations(rec, cal, t))["elbow_r"]
    # finite-difference rates and the weak heading prior: a fraction of a degree
    np.testing.assert_allclose(ang[:, 0], flex, atol=0.5)
    np.testing.assert_allclose(ang[:, 2], pron, atol=0.5)
    np.testing.assert_allclose(ang[:, 1], 0.0, atol=0.5)


def test_facing_auto_is_estimated_from_the_hinges():
    """9-D sensors (shared north), subject facing 70 deg from north: the declared default
    facing misassigns the flexion axis; ``facing="auto"`` fits it to the movement and takes the
    facing from it (closed form: the body's rotation applied to north)."""
    rec, flex, pron = _elbow_2dof_recording(70.0, (0.0, 0.0))
    sk = upper_limb("r", height_m=1.7)
    t = rec.imu["forearm_r"].t_s
    north = calibrate(rec, sk, "static", window_s=0.5)
    assert north.facing_from == "declared" and np.allclose(north.facing, [0.0, 1.0, 0.0])
    bad = joint_angles(segment_orientations(rec, north, t))["elbow_r"][:, 0]
    assert np.max(np.abs(bad - flex)) > 10.0
    cal = calibrate(rec, sk, "static", window_s=0.5, facing="auto")
    assert cal.facing_from == "hinges"
    want = _rz(70.0).apply([0.0, 1.0, 0.0])
    assert np.degrees(np.arccos(np.clip(cal.facing @ want, -1, 1))) < 1.0
    ang = joint_angles(segment_orientations(rec, cal, t))["elbow_r"]
    np.testing.assert_allclose(ang[:, 0], flex, atol=0.5)
    np.testing.assert_allclose(ang[:, 2], pron, atol=0.5)
    # nothing to estimate it from (the elbow never moves): north, said so
    still = _arm_pose_recording(MOUNTS, 300)
    with pytest.warns(NumericalWarning, match="hardly moved"):
        cal0 = calibrate(still, sk, "static", window_s=0.5, facing="auto")
    assert cal0.facing_from == "default" and np.allclose(cal0.facing, [0.0, 1.0, 0.0])
    with pytest.raises(InputError, match="facing"):
        calibrate(rec, sk, "static", window_s=0.5, facing="north")
    # in a T-pose the arms' static axes follow the assumed facing: the elbow cannot tell it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)  # the arm hangs: off the T-pose
        tp = calibrate(rec, sk, "static", window_s=0.5, pose="t", facing="auto")
    assert tp.facing_from == "default"


def test_hinge_flexion_sign_by_anatomy():
    # the same motion seen with the elbow axis sign flipped by a mirrored mounting still reads
    # as flexion (positive), not extension
    rec, flex, _ = _elbow_2dof_recording(-120.0, (10.0, -80.0))
    cal = calibrate(rec, upper_limb("r", height_m=1.7), "static", window_s=0.5, heading="static")
    fl = joint_angles(segment_orientations(rec, cal, rec.imu["forearm_r"].t_s))["elbow_r"][:, 0]
    assert np.percentile(fl, 99) > 100.0 and np.percentile(fl, 1) > -1.0


def test_static_warns_naming_a_segment_off_the_pose():
    rec = _arm_pose_recording(MOUNTS, 100)
    sk = upper_limb("r", height_m=1.7)
    true_axis = MOUNTS["upper_arm_r"].inv().apply([0.0, 0.0, -1.0])  # the sensor axis pointing down
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal = calibrate(rec, sk, "static", mounting={"upper_arm_r": true_axis})
    assert cal.pose_residual_deg["upper_arm_r"] < 1e-6
    with pytest.warns(NumericalWarning, match=r"segment 'forearm_r' is \d+ deg from the assumed"):
        calibrate(rec, sk, "static", mounting={"forearm_r": "+e3"})


# ------------------------------------------------------------------ joint angles (closed forms)
def test_joint_angles_match_constructed_rotations(rng):
    T = 50
    Rp = Rotation.random(T, random_state=3)
    a, b, c = rng.uniform(-60, 60, (3, T))
    rel = Rotation.from_euler("ZXY", np.stack([a, b, c], 1), degrees=True)
    ori = {
        "thigh_r": Rp.as_matrix(),
        "shank_r": (Rp * rel).as_matrix(),
        "thigh_l": Rp.as_quat(scalar_first=True),
        "shank_l": (Rp * rel).as_quat(scalar_first=True),
        "upper_arm_r": Rp.as_matrix(),
        "forearm_r": (Rp * rel).as_matrix(),
    }
    ang = joint_angles(ori)
    assert set(ang) == {"knee_l", "knee_r", "elbow_r"}
    np.testing.assert_allclose(ang["knee_r"], np.stack([-a, b, c], 1), atol=1e-8)
    np.testing.assert_allclose(ang["knee_l"], np.stack([-a, -b, -c], 1), atol=1e-8)
    np.testing.assert_allclose(ang["elbow_r"], np.stack([a, b, c], 1), atol=1e-8)


def test_joint_angle_signs_are_anatomical():
    # knee bent: the shank's distal end moves posteriorly (-X) -> flexion positive
    shank = Rotation.align_vectors([[-np.sin(0.5), -np.cos(0.5), 0.0]], [[0.0, -1.0, 0.0]])[0]
    knee = joint_angles({"thigh_r": np.eye(3)[None], "shank_r": shank.as_matrix()[None]})
    assert knee["knee_r"][0, 0] == pytest.approx(np.degrees(0.5))
    # left hip: thigh's distal end towards the midline (+Z = right) -> adduction positive
    thigh = Rotation.align_vectors([[0.0, -np.cos(0.3), np.sin(0.3)]], [[0.0, -1.0, 0.0]])[0]
    hip = joint_angles({"pelvis": np.eye(3)[None], "thigh_l": thigh.as_matrix()[None]})
    assert hip["hip_l"][0, 1] == pytest.approx(np.degrees(0.3))
    with pytest.raises(InputError, match=r"joint 'elbow_l' needs .*missing \['forearm_l'\]"):
        joint_angles({"upper_arm_l": np.eye(3)[None]}, ["elbow_l"])


# ------------------------------------------------------------------ lengths
def test_segment_lengths_order_and_sources():
    L, how = segment_lengths(
        ["thigh_l", "thigh_r", "shank_l"],
        measured={"thigh_l": 0.41},
        height_m=1.80,
        derived={"thigh_r": (0.40, "REFERENCE")},
    )
    assert L == pytest.approx({"thigh_l": 0.41, "thigh_r": 0.40, "shank_l": 0.246 * 1.80})
    assert how["thigh_l"] == "measured" and how["thigh_r"] == "REFERENCE"
    assert "Winter 2009" in how["shank_l"] and ANTHROPOMETRIC_RATIOS["shank"] == 0.246
    L, how = segment_lengths(["foot_l"], functional={"foot_l": 0.2})
    assert how["foot_l"] == "functional calibration"
    with pytest.raises(InputError, match=r"no length for segment\(s\) \['forearm_r'\]"):
        segment_lengths(["forearm_r"])
    assert lower_body(height_m=1.6).length("thigh_l") == pytest.approx(0.245 * 1.6)


# ------------------------------------------------------------------ .mot
def test_write_mot_layout(tmp_path):
    t = np.arange(4) / 50.0
    p = write_mot(
        tmp_path / "a.mot",
        t,
        {"knee_r_flexion": [0.0, 1.5, np.nan, 3.0]},
        metadata={"root": "pelvis"},
    )
    lines = p.read_text().splitlines()
    head = lines[: lines.index("endheader")]
    assert head[0] == "a" and {"version=1", "nRows=3", "nColumns=2", "inDegrees=yes"} <= set(head)
    assert "root=pelvis" in head and any(h.startswith("rows_omitted=1 ") for h in head)
    assert lines[lines.index("endheader") + 1].split("\t") == ["time", "knee_r_flexion"]
    data = np.genfromtxt(lines[lines.index("endheader") + 2 :], delimiter="\t")
    np.testing.assert_allclose(data[:, 0], t[[0, 1, 3]])  # the NaN row left out (default)
    np.testing.assert_allclose(data[:, 1], [0.0, 1.5, 3.0])
    kept = write_mot(tmp_path / "n.mot", t, {"k": [0.0, 1.5, np.nan, 3.0]}, missing="nan")
    assert "NaN" in kept.read_text().splitlines()[-2]
    with pytest.raises(FileExistsError):
        write_mot(p, t, {"x": t})
    with pytest.raises(InputError, match=r"column 'x' with shape \(T,\) = \(4,\), got \(3,\)"):
        write_mot(tmp_path / "b.mot", t, {"x": t[:3]})


# ------------------------------------------------------------------ sessions on real data
def test_ximu3_lower_body_imu_only_session(shared_data, tmp_path):
    out = tmp_path / "x3"
    res = runner.invoke(
        cli.app, ["run", str(SESSIONS / "ximu3_lower_body.toml"), "--out", str(out)]
    )
    assert res.exit_code == 0, (res.output, _err(res))
    stem = "ximu3-lower-body"
    for f in ("_joints.csv", "_joints.trc", "_angles.csv", "_angles.mot"):
        assert (out / f"{stem}{f}").is_file(), f
    assert (out / "report.html").is_file()
    html = (out / "report.html").read_text()
    assert "Range of motion per joint" in html and "Winter 2009" in html
    rec = read_joint_csv(out / f"{stem}_joints.csv")
    assert rec.vision.frame == "ENU, relative to the pelvis (mid-hip)"
    assert rec.metadata["header"]["root"].startswith("pelvis (mid-hip)")
    # no filter ran: the header says what the -1 modes and the empty std columns mean
    assert "-1=no filter" in rec.metadata["header"]["mode_codes"]
    assert rec.metadata["header"]["std_m"].endswith("empty: imu-only gives none")
    assert "root: pelvis" in (out / f"{stem}_joints.trc").read_text().splitlines()[0]
    read_trc(out / f"{stem}_joints.trc")
    # both thighs (and shanks) the same length, from body height
    st = rec.vision
    hip_w = ANTHROPOMETRIC_RATIOS["hip_joint_spacing"] * 1.75
    for side in "lr":
        knee, ankle = st.position(f"knee_{side}"), st.position(f"ankle_{side}")
        shank = np.linalg.norm(ankle - knee, axis=1)
        np.testing.assert_allclose(shank[np.isfinite(shank)], 0.246 * 1.75, atol=1e-5)
        # thigh = |knee - hip|, with |hip| = half the hip width from the mid-hip origin
        assert np.nanmax(np.linalg.norm(knee, axis=1)) <= 0.245 * 1.75 + hip_w / 2 + 1e-5
    # the x-IMU3s drop packets (20-27 single-sample gaps of 40 ms per sensor at 50 Hz): bridged,
    # so every joint is available on all but the edge sample (strict 1.5-step gaps left 86 %)
    for j in ("knee_l", "knee_r", "ankle_l", "ankle_r"):
        assert np.isfinite(st.position(j)).all(axis=1).mean() > 0.99, j
    assert "are backed by the inputs" not in res.output  # no coverage warning
    ang = np.genfromtxt(out / f"{stem}_angles.csv", delimiter=",", names=True, skip_header=6)
    for side in "lr":
        flex = ang[f"knee_{side}_flexion_deg"]
        flex = flex[np.isfinite(flex)]
        assert flex.size > 800 and -10.0 <= flex.min() and flex.max() <= 150.0
        assert flex.max() > 60.0  # the recording bends the knees
        # the terminal's angle table shows the written file's extremes (flexion min, max first)
        after = res.output[res.output.index("Joint angles over the recording (deg)") :]
        row = next(ln for ln in after.splitlines() if ln.strip().startswith(f"knee_{side} "))
        shown = [float(v) for v in row.split()[1:3]]
        np.testing.assert_allclose(shown, [flex.min(), flex.max()], atol=0.051)
    mot = (out / f"{stem}_angles.mot").read_text().splitlines()
    assert "inDegrees=yes" in mot and mot[mot.index("endheader") + 1].startswith("time\tknee_l_")
    assert any(ln.startswith("root=pelvis") for ln in mot[: mot.index("endheader")])


def test_a_pose_declared_wrong_is_said_with_what_to_check(shared_data, tmp_path):
    """The qmt right arm held in an N-pose but declared a T-pose: the run says which segments
    are far from the T-pose direction (the calibration's own warnings) and, for the elbow that
    then reads flexed in the pose, that the pose held may not be the declared one."""
    text = (SESSIONS / "qmt_right_arm.toml").read_text(encoding="utf-8")
    data = shared_data / "qmt_full_body_example" / "full_body_example_data.mat"
    lines = [
        f'path = "{data.as_posix()}"' if ln.startswith("path = ") else ln
        for ln in text.replace('pose = "n"', 'pose = "t"').splitlines()
    ]
    session = tmp_path / "t.toml"
    session.write_text("\n".join(lines) + "\n", encoding="utf-8")
    summary = run_session(session, tmp_path / "out")
    far = [w for w in summary.warnings if "from the assumed T-pose direction" in w]
    assert {w.split("'")[1] for w in far} == {"upper_arm_r", "forearm_r"}, summary.warnings
    (elbow,) = [w for w in summary.warnings if w.startswith("elbow_r reads flexion")]
    assert "the pose held was not the declared [calibration] pose" in elbow


def test_qmt_right_arm_paper_a_setting(shared_data, tmp_path):
    out = tmp_path / "qa"
    res = runner.invoke(cli.app, ["run", str(SESSIONS / "qmt_right_arm.toml"), "--out", str(out)])
    assert res.exit_code == 0, (res.output, _err(res))
    st = read_joint_csv(out / "qmt-right-arm_joints.csv").vision
    assert st.joints == ("elbow_r", "wrist_r")
    shoulder = np.array([0.0, 0.0, 1.40])
    l1 = np.linalg.norm(st.position("elbow_r") - shoulder, axis=1)
    l2 = np.linalg.norm(st.position("wrist_r") - st.position("elbow_r"), axis=1)
    assert np.nanmax(np.abs(l1 - 0.30)) < 1e-3 and np.nanmax(np.abs(l2 - 0.26)) < 1e-3
    ang = np.genfromtxt(out / "qmt-right-arm_angles.csv", delimiter=",", names=True, skip_header=6)
    flex = ang["elbow_r_flexion_deg"]
    assert np.all(np.isfinite(flex))
    # 6-D data: the flexion axis comes from the movement, not from the unknown facing (the pose
    # frames gave -124..24 deg); the range is flexion. Measured 1st-99th percentile -13.6..130.3
    # deg: the N-pose was held with the elbow a few degrees flexed (zero = the pose), so full
    # extension reads slightly negative and the report warns about the -10 deg bound
    html = (out / "report.html").read_text()
    assert "flexion axes of elbow_r from the movement" in html
    lo, hi = np.percentile(flex, [1, 99])
    assert -15.0 <= lo and 100.0 <= hi <= 160.0 and np.median(flex) > 0.0
    inside = -10.0 <= lo and hi <= 160.0
    assert inside or ('class="warnings"' in html and "elbow_r flexion spans" in html)
    # the report names window, stillness and heading handling
    assert "stillness" in html and "heading: 6-D orientations" in html
    # the calibrated sensor orientations for OpenSense IK (issue 13), heading-corrected
    from kinefuse.io import load

    sto = load(out / "qmt-right-arm_orientations.sto")
    assert set(sto.imu) == {"upper_arm_r", "forearm_r"} and "OpenSense: " in html
    q = sto.imu["forearm_r"].q_world_from_sensor
    assert q.shape == (st.t_s.size, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-9)


# ------------------------------------------------------------------ refusals
OPENSENSE = """\
    [session]
    name = "opensense"
    [imu]
    format = "opensense"
    path = "{data}/opensense_example_imu"
    [imu.segments]
    pelvis = "00B42279"
    thigh_r = "00B4227C"
    shank_r = "00B4227D"
    thigh_l = "00B421EE"
    shank_l = "00B421ED"
    [skeleton]
    body_height_m = 1.75
    root = "pelvis"
    [calibration]
    method = "static"
    [method]
    name = "imu-only"
"""


def test_opensense_walk_facing_from_the_knees(shared_data, tmp_path):
    """OpenSim's OpenSense example (9-D Xsens, subject facing about south): with the facing not
    declared, knees and hips read as walking does (knee flexion 0..70 deg, hip flexion -15..30:
    e.g. Perry & Burnfield 2010); the north default read the knees -69..7 deg (issue 10)."""
    p = _session(tmp_path, OPENSENSE.format(data=shared_data))
    res = runner.invoke(cli.app, ["run", str(p), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, (res.output, _err(res))
    assert "flexion spans" not in _err(res)  # no range warning
    prov = json.loads((tmp_path / "o" / "provenance.json").read_text())
    assert prov["facing_from"] == "hinges" and prov["facing"][1] < -0.9  # about south
    ang = np.genfromtxt(
        tmp_path / "o" / "opensense_angles.csv", delimiter=",", names=True, skip_header=6
    )
    for side in "lr":
        knee, hip = ang[f"knee_{side}_flexion_deg"], ang[f"hip_{side}_flexion_deg"]
        assert -12 < np.nanmin(knee) and 55 < np.nanmax(knee) < 80, side
        assert -20 < np.nanmin(hip) < -5 and 20 < np.nanmax(hip) < 40, side


def test_a_mapped_sensor_nothing_reads_is_said(shared_data, tmp_path):
    """The OpenSense example's chest IMU, mapped with the legs: a static calibration reads it
    for the trunk angles (the chest in the pelvis). With one leg on a fixed root and no pelvis
    IMU nothing reads it (it would place the shoulders): the notes say so instead of ignoring
    it silently."""
    body = OPENSENSE.replace('pelvis = "00B42279"', 'pelvis = "00B42279"\n    chest = "00B42268"')
    summary = run_session(_session(tmp_path, body.format(data=shared_data)), tmp_path / "o")
    assert not any(n.startswith("chest: mapped in") for n in summary.notes)
    ang = np.genfromtxt(
        tmp_path / "o" / "opensense_angles.csv", delimiter=",", names=True, skip_header=6
    )
    flex = ang["trunk_flexion_deg"]  # walking: the trunk leans forward a little on the pelvis
    assert 0 < np.nanmedian(flex) < 15 and np.nanmax(np.abs(ang["trunk_axial_rotation_deg"])) < 25
    one_leg = body.replace('pelvis = "00B42279"\n', "").replace('thigh_l = "00B421EE"\n', "")
    one_leg = one_leg.replace('shank_l = "00B421ED"\n', "")
    one_leg = one_leg.replace('root = "pelvis"', 'root = "fixed"\n    root_position_m = [0, 0, 1]')
    assert "pelvis =" not in one_leg and "thigh_l" not in one_leg and "chest =" in one_leg
    summary = run_session(_session(tmp_path, one_leg.format(data=shared_data)), tmp_path / "f")
    assert any(n.startswith("chest: mapped in [imu.segments] but not used") for n in summary.notes)


NEURA_FUNCTIONAL = """\
    [session]
    name = "nf"
    [imu]
    format = "neura"
    path = "{data}/neura_sparse_sample"
    [imu.segments]
    pelvis = "Pelvis"
    thigh_l = "L_UpLeg"
    thigh_r = "R_UpLeg"
    shank_l = "L_LowLeg2"
    shank_r = "R_LowLeg2"
    foot_l = "L_Foot"
    foot_r = "R_Foot"
    [skeleton]
    root = "reference"
    [skeleton.lengths]
    thigh_l = 0.417
    thigh_r = 0.395
    shank_l = 0.389
    shank_r = 0.409
    [reference]
    format = "neura"
    path = "{data}/neura_sparse_sample/vicon/S02-Trial-Walk-1.csv"
    [calibration]
    method = "functional"
    [method]
    name = "imu-only"
"""


def test_functional_session_uses_the_measured_lengths_and_feet_for_ankles(shared_data, tmp_path):
    """Functional calibration in a session: the feet's IMUs locate the ankles (no error asking
    for a toe), and the tape lengths win over the functional estimates in the chain, as the
    provenance says (the chain used the estimates: shank_l 0.409 m instead of 0.389)."""
    p = _session(tmp_path, NEURA_FUNCTIONAL.format(data=shared_data))
    res = runner.invoke(cli.app, ["run", str(p), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, (res.output, _err(res))
    rec = read_joint_csv(tmp_path / "o" / "nf_joints.csv")
    st = rec.vision
    assert st.joints == ("knee_l", "knee_r", "ankle_l", "ankle_r")
    for side, want in (("l", 0.389), ("r", 0.409)):
        shank = np.linalg.norm(st.position(f"ankle_{side}") - st.position(f"knee_{side}"), axis=1)
        np.testing.assert_allclose(shank[np.isfinite(shank)], want, atol=1e-5)
    prov = json.loads((tmp_path / "o" / "metrics.json").read_text())["provenance"]
    assert prov["segment_lengths"]["shank_l"] == {"m": 0.389, "source": "measured"}
    report = (tmp_path / "o" / "report.html").read_text()
    assert "foot_l, foot_r: IMUs used for the ankle centres only" in report
    # the OpenSense orientations hold every mapped sensor (they share the data set's world
    # frame), the pelvis and the feet too: OpenSense IK reads its pelvis IMU first
    sto = (tmp_path / "o" / "nf_orientations.sto").read_text().splitlines()
    header = next(ln for ln in sto if ln.startswith("time")).split("\t")
    assert set(header[1:]) == {
        "pelvis_imu", "femur_l_imu", "femur_r_imu", "tibia_l_imu", "tibia_r_imu",
        "calcn_l_imu", "calcn_r_imu",
    }  # fmt: skip


def _session(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(textwrap.dedent(body), encoding="utf-8")
    return p


NEURA_IMU = """\
    [session]
    name = "walk"
    [imu]
    format = "neura"
    path = "{data}/neura_sparse_sample"
    [imu.segments]
    {segments}
    [skeleton]
    {skeleton}
    [method]
    name = "{method}"
"""


@pytest.mark.parametrize(
    ("case", "needle"),
    [
        ("no still window", "no still window of 2 s.*stillest candidate is .* rad/s"),
        ("missing length", r"no length for segment\(s\) \['shank_l'\]"),
        ("camera method", "method 'kinefuse' needs a camera"),
    ],
)
def test_bad_input_refused_with_one_line(shared_data, tmp_path, monkeypatch, case, needle):
    seg = 'pelvis = "Pelvis"\n    thigh_l = "L_UpLeg"\n    shank_l = "L_LowLeg2"'
    skel = "body_height_m = 1.75"
    method = "imu-only"
    if case == "missing length":
        skel = 'root = "pelvis"\n    [skeleton.lengths]\n    thigh_l = 0.40'
    if case == "camera method":
        method = "kinefuse"
        from kinefuse.pipelines.run import write as ps

        def _no_work(*a, **k):
            raise AssertionError("work started before the refusal")

        monkeypatch.setattr(ps, "load_streams", _no_work)
    p = _session(
        tmp_path,
        NEURA_IMU.format(data=shared_data, segments=seg, skeleton=skel, method=method),
    )
    res = runner.invoke(cli.app, ["run", str(p), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2, (res.output, _err(res))
    lines = [ln for ln in _err(res).splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("kinefuse: error:"), lines
    import re

    assert re.search(needle, lines[0]), lines[0]
    assert not (tmp_path / "out").exists()


def test_reference_is_evaluation_only_unless_asked(shared_data, tmp_path):
    # Neura IMUs + Vicon reference, lengths measured, static calibration asked: the walk has no
    # still pose, so nothing silently falls back to the reference
    body = (
        NEURA_IMU.format(
            data=shared_data,
            segments='pelvis = "Pelvis"\n    thigh_l = "L_UpLeg"\n    shank_l = "L_LowLeg2"',
            skeleton="body_height_m = 1.75\n    [skeleton.lengths]\n    thigh_l = 0.40\n    shank_l = 0.40",
            method="imu-only",
        )
        + '[reference]\nformat = "neura"\n'
        + f'path = "{shared_data}/neura_sparse_sample/vicon/S02-Trial-Walk-1.csv"\n'
    )
    p = _session(tmp_path, body)
    with pytest.raises(InputError, match="no still window"):
        run_session(p, tmp_path / "out")
    with pytest.raises(ConfigError, match="'vision' needs a \\[camera\\]"):
        run_session(_session(tmp_path, body + '[calibration]\nmethod = "vision"\n'), tmp_path)


# ------------------------------------------------------------------ template, evaluate
def test_template_comments_are_true(tmp_path):
    from kinefuse.session_file import CALIBRATIONS, CAMERA_METHODS, METHODS, ROOTS

    p = tmp_path / "session.toml"
    assert runner.invoke(cli.app, ["init-session", str(p)]).exit_code == 0
    text = p.read_text()
    doc = tomllib.loads(text)
    assert doc["imu"]["format"] in FORMATS
    for m in METHODS:
        assert f"# {m} " in text
    for r in ROOTS:
        assert f"#   {r} " in text
    for c in CALIBRATIONS:
        assert f"#   {c} " in text
    assert "kinefuse" in CAMERA_METHODS and f"Needed by {', '.join(CAMERA_METHODS)}." in text
    fmt_line = next(ln for ln in text.splitlines() if ln.startswith("format = "))
    assert set(fmt_line.split("one of ")[1].split(", ")) == set(FORMATS)
    assert "used by kinefuse when present" not in text


def test_evaluate_takes_folders_and_format(shared_data):
    folder = shared_data / "neura_sparse_sample"
    args = ["evaluate", str(folder), "--format", "neura", "--method", "imu-only"]
    res = runner.invoke(cli.app, [*args, "--calibration", "reference", "--json", "-"])
    assert res.exit_code == 0, (res.output, _err(res))
    assert "[calibrated on reference, lengths from reference, root from reference]" in res.output
    res = runner.invoke(cli.app, [*args[:2], "--format", "nosuch", "--method", "imu-only"])
    assert res.exit_code == 2 and "unknown format 'nosuch'" in _err(res)
    res = runner.invoke(
        cli.app,
        ["evaluate", str(shared_data / "xio_imu_mocap_lower_body"), "--method", "imu-only"],
    )
    assert res.exit_code == 2 and "no reference" in _err(res), _err(res)
    # a camera method on a recording with a reference and no camera: refused before any work,
    # without a session's advice ("add a [camera] section") that evaluate cannot take
    res = runner.invoke(cli.app, [*args[:4], "--method", "elm-fir"])
    assert res.exit_code == 2, _err(res)
    assert "needs a camera, and this recording has none (only a reference" in _err(res)
    assert "[camera]" not in _err(res)
    # advice in session terms gets evaluate's own option beside it
    utd = shared_data / "utd_mhad" / "Skeleton" / "a3_s1_t1_skeleton.mat"
    res = runner.invoke(cli.app, ["evaluate", str(utd), "--method", "imu-only"])
    assert res.exit_code == 2 and "--calibration reference calibrates from the reference" in _err(
        res
    )


def test_calibration_docs_example_runs(shared_data, monkeypatch, capsys):
    root = Path(__file__).parent.parent
    text = (root / "docs" / "calibration.md").read_text(encoding="utf-8")
    blocks = [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]
    code = next(b for b in blocks if '"static"' in b)  # the static example (functional: its test)
    monkeypatch.chdir(root)
    exec(compile(code, "docs/calibration.md", "exec"), {})
    out = capsys.readouterr().out
    assert "mean angular rate" in out and "knee_l" in out
    peaks = ast.literal_eval(out.strip().splitlines()[-1])  # the printed peak flexion per joint
    assert all(np.isfinite(v) and 40 < v < 150 for v in peaks.values()), peaks
    assert "tests/data/sessions/ximu3_lower_body.toml" in text  # the CLI example is tested above


class _WorkStarted(Exception):
    pass


@pytest.mark.parametrize("inputs", ["imu", "imu+camera", "imu+reference", "imu+camera+reference"])
@pytest.mark.parametrize("method", METHODS)
def test_every_method_and_input_runs_or_is_refused_before_work(
    tmp_path, monkeypatch, method, inputs
):
    """The contract of the method registry: a combination is refused with one line saying what
    it needs before any file is read, or it proceeds to reading the files."""
    from kinefuse import methods
    from kinefuse.pipelines.run import write as ps
    from kinefuse.session_file import CAMERA_METHODS

    for f in ("imu.csv", "camera.csv", "truth.csv"):
        (tmp_path / f).write_text("x\n")
    body = f"""\
        [session]
        name = "combo"
        [imu]
        format = "imu_csv"
        path = "imu.csv"
        [imu.segments]
        forearm_r = "IMU 2"
        [skeleton]
        body_height_m = 1.75
        [method]
        name = "{method}"
    """
    if "camera" in inputs:
        body += '[camera]\nformat = "joint_csv"\npath = "camera.csv"\n'
    if "reference" in inputs:
        body += '[reference]\nformat = "joint_csv"\npath = "truth.csv"\n'

    def _work(*a, **k):
        raise _WorkStarted

    monkeypatch.setattr(ps, "load_streams", _work)
    p = _session(tmp_path, body)
    refused = method in CAMERA_METHODS and "camera" not in inputs
    if refused:
        res = runner.invoke(cli.app, ["run", str(p), "--out", str(tmp_path / "out")])
        assert res.exit_code == 2, (res.output, _err(res))
        line = [ln for ln in _err(res).splitlines() if ln.strip()]
        assert len(line) == 1 and f"needs a camera (it uses {methods.get(method).uses})" in line[0]
    else:
        with pytest.raises(_WorkStarted):
            ps.run_session(p, tmp_path / "out")


def test_fixed_root_positions_closed_form():
    """Paper A's chain from a fixed, measured shoulder: positions in closed form."""
    from kinefuse.pipelines.run import process_recording

    T = 300
    flex = np.where(np.arange(T) < 100, 0.0, np.minimum(np.linspace(-50, 130, T), 90.0))
    rec = _arm_pose_recording(MOUNTS, T, flex_deg=flex)
    out = process_recording(
        rec,
        "imu-only",
        {"root_position_m": {"shoulder_r": [1.0, 2.0, 3.0]}, "calibration_window_s": 0.5},
        lengths={"upper_arm_r": 0.30, "forearm_r": 0.26},
    )
    assert (
        out.joints == ("elbow_r", "wrist_r") and "fixed shoulder_r at [1.0, 2.0, 3.0]" in out.root
    )
    elbow, wrist = out.position[:, 0], out.position[:, 1]
    np.testing.assert_allclose(elbow, np.tile([1.0, 2.0, 2.70], (T, 1)), atol=1e-9)
    th = np.radians(flex)  # forearm swings forward (north, the declared facing) as it flexes
    expect = np.stack([np.ones(T), 2.0 + 0.26 * np.sin(th), 2.70 - 0.26 * np.cos(th)], -1)
    np.testing.assert_allclose(wrist, expect, atol=1e-9)
    np.testing.assert_allclose(out.angles["elbow_r"][:, 0], flex, atol=1e-6)
    assert out.provenance["segment_lengths"]["forearm_r"]["source"] == "measured"
    assert out.reference is None and out.tag == ""


def test_default_facing_note_says_why():
    """North by default has two reasons: nothing moved, or the hinges' flexion axes gave no
    common facing (e.g. 6-D sensors whose headings differ). The note names the right one."""
    from types import SimpleNamespace

    from kinefuse.pipelines.run.calibration import _static_notes

    def note(hinges):
        cal = SimpleNamespace(facing=None, facing_from="default", hinge_residual_rad_s=hinges,
                              frames={"thigh_r": None, "shank_r": None}, world_heading_deg={})  # fmt: skip
        notes, prov = [], {}
        _static_notes(cal, False, ["thigh_r"], notes, prov)
        (line,) = [n for n in notes if n.startswith("facing:")]
        return line

    assert "no elbow or knee moved enough" in note({})
    moved = note({"knee_l": 0.5, "knee_r": 0.6})
    assert "knee_l, knee_r gave no common one" in moved and "moved enough" not in moved


def test_api_arguments_that_would_be_misread_are_refused(shared_data):
    """Found by a sweep of the Python API: a name given as a bare string was iterated letter
    by letter ("unknown segment 't'"); a low-pass cutoff of NaN or above Nyquist switched the
    filter off (thigh 0.097 m instead of 0.356); a zero or negative still-window step searched
    only the first window; a tiny one asked for 63 GiB."""
    from kinefuse.io import load
    from kinefuse.kinematics import find_still_window, joint_angles
    from kinefuse.kinematics.functional import functional_calibration

    rec = load(shared_data / "neura_sparse_sample")
    sk = lower_body(height_m=1.75)
    with pytest.raises(InputError, match=r"segments as a sequence of names, e.g. \['thigh_l'\]"):
        calibrate(rec, sk, "functional", segments="thigh_l")
    with pytest.raises(InputError, match="expected segments with at least one segment name"):
        calibrate(rec, sk, "functional", segments=[])
    with pytest.raises(InputError, match=r"joints as a sequence of names, e\.g\. \['knee_l'\]"):
        joint_angles({}, joints="knee_l")
    for bad in (np.nan, 0.0, 49.9, True):
        with pytest.raises(InputError, match=r"expected cutoff_hz in \(0, 45\) Hz"):
            functional_calibration(rec, sk, cutoff_hz=bad)
    for bad in (-1.0, 0.0, np.nan):
        with pytest.raises(InputError, match="expected step_s finite and > 0"):
            find_still_window(rec.imu, step_s=bad)
    with pytest.raises(InputError, match="candidate windows"):
        find_still_window(rec.imu, step_s=1e-9)
