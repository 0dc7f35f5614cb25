"""ASF/AMC reader on real CMU files, the Motion container and the packaged demo trial."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError
from kinefuse.io.cmu import load_motion_asf_amc, read_asf_amc
from kinefuse.io.motion import R_ENU_FROM_YUP, SEGMENT_AXIS

M_PER_UNIT = 0.0254 / 0.45  # CMU ':units length 0.45'


@pytest.fixture(scope="module")
def walk(shared_data):
    return load_motion_asf_amc(shared_data / "cmu_mocap" / "asfamc" / "02" / "02_01.amc")


def test_recording_shapes_rate_frame(shared_data):
    rec = read_asf_amc(shared_data / "cmu_mocap" / "asfamc" / "02" / "02_01.amc")
    ref = rec.reference
    assert ref.position_m.shape == (343, 22, 3)
    assert ref.frame == "ENU"
    assert ref.t_s[0] == 0.0 and ref.t_s[-1] == pytest.approx(342 / 120)
    assert np.all(ref.available)
    assert set(rec.reference_orientation) >= {
        "chest",
        "pelvis",
        "upper_arm_r",
        "forearm_r",
        "thigh_l",
        "shank_l",
    }
    assert rec.reference_orientation["thigh_l"].q_world_from_sensor.shape == (343, 4)
    assert rec.metadata["format"] == "cmu" and rec.metadata["subject"] == "02"
    assert rec.imu == {} and rec.vision is None


def test_bone_lengths_from_asf_text_and_plausible(walk):
    L = walk.segment_length_m
    # values straight from the ASF text (02.asf), converted with 0.0254 / 0.45
    assert L["upper_arm_r"] == pytest.approx(5.02649 * M_PER_UNIT, rel=1e-12)
    assert L["forearm_l"] == pytest.approx(3.35554 * M_PER_UNIT, rel=1e-12)
    assert L["thigh_l"] == pytest.approx(7.59371 * M_PER_UNIT, rel=1e-12)
    assert L["shank_r"] == pytest.approx(7.21538 * M_PER_UNIT, rel=1e-12)
    # SOURCE.md: upper arm 0.284, forearm 0.190, thigh 0.428, shank 0.407 m (adult)
    assert L["upper_arm_r"] == pytest.approx(0.284, abs=0.002)
    assert L["forearm_r"] == pytest.approx(0.190, abs=0.002)
    assert L["thigh_r"] == pytest.approx(0.428, abs=0.002)
    assert L["shank_l"] == pytest.approx(0.411, abs=0.002)
    # rigid bones: distances between joints constant over the trial
    for seg, (prox, dist) in walk.segment_joints.items():
        if dist is None:
            continue
        d = np.linalg.norm(walk.position(dist) - walk.position(prox), axis=1)
        np.testing.assert_allclose(d, L[seg], atol=1e-12)


def test_segment_axis_e2_points_from_proximal_to_distal(walk):
    for seg, (prox, dist) in walk.segment_joints.items():
        if dist is None:
            continue
        R = Rotation.from_quat(walk.orientation(seg), scalar_first=True).as_matrix()
        predicted = walk.position(prox) + walk.segment_length_m[seg] * (R @ SEGMENT_AXIS)
        np.testing.assert_allclose(predicted, walk.position(dist), atol=1e-12, err_msg=seg)
    q = walk.q_world_from_segment
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(np.sum(q[1:] * q[:-1], axis=-1) > 0)  # sign-continuous


def test_root_position_units_and_enu(walk):
    # AMC frame 1: 'root 10.4194 16.7048 -30.1003 ...' (ASF units, y up)
    expected = R_ENU_FROM_YUP @ (np.array([10.4194, 16.7048, -30.1003]) * M_PER_UNIT)
    np.testing.assert_allclose(walk.position("pelvis")[0], expected, atol=1e-12)
    # z is up: head above pelvis above ankles; SOURCE.md: the root moves 3.36 m in the walk
    z = {j: walk.position(j)[:, 2].mean() for j in ("head", "pelvis", "knee_l", "ankle_l")}
    assert z["head"] > z["pelvis"] > z["knee_l"] > z["ankle_l"]
    assert 1.2 < z["head"] - z["ankle_l"] < 1.6
    travel = np.linalg.norm(walk.position("pelvis")[-1] - walk.position("pelvis")[0])
    assert travel == pytest.approx(3.36, abs=0.02)
    # gravity is -z: the pelvis height varies little while walking
    assert np.ptp(walk.position("pelvis")[:, 2]) < 0.1
    assert walk.rate_hz == pytest.approx(120.0)


def test_other_subject_reads(shared_data):
    m = load_motion_asf_amc(shared_data / "cmu_mocap" / "asfamc" / "03" / "03_01.amc")
    assert m.position_m.shape == (432, 22, 3)
    assert m.segment_length_m["thigh_l"] == pytest.approx(7.16147 * M_PER_UNIT, rel=1e-12)


def test_window_and_to_recording(walk):
    w = walk.window(1.0, 2.0)
    assert len(w) == 120 and w.t_s[0] == pytest.approx(1.0)
    rec = w.to_recording()
    assert rec.reference.position_m.shape == (120, 22, 3)
    assert rec.metadata["segment_joints"]["forearm_r"] == ("elbow_r", "wrist_r")


# ------------------------------------------------------------------------------ broken files
@pytest.fixture
def broken(tmp_path, shared_data):
    src = shared_data / "cmu_mocap" / "asfamc" / "02"
    asf = tmp_path / "02.asf"
    asf.write_text((src / "02.asf").read_text())
    lines = (src / "02_01.amc").read_text().splitlines()

    def write(new_lines, name="02_01.amc"):
        p = tmp_path / name
        p.write_text("\n".join(new_lines) + "\n")
        return p

    return asf, lines, write


def test_truncated_amc_names_file_line_and_missing_bones(broken):
    _asf, lines, write = broken
    p = write(lines[:100])  # frame 4 cut in the middle
    with pytest.raises(FormatError) as exc:
        load_motion_asf_amc(p)
    msg = str(exc.value)
    assert "02_01.amc" in msg and "line 100" in msg and "missing" in msg and "truncated" in msg


def test_malformed_amc_values(broken):
    _asf, lines, write = broken
    bad = list(lines)
    k = next(i for i, t in enumerate(bad) if t.startswith("lfemur"))
    bad[k] = "lfemur 1.0 abc 2.0"
    with pytest.raises(FormatError, match=rf"line {k + 1}.*expected numbers for 'lfemur'"):
        load_motion_asf_amc(write(bad))
    bad[k] = "lfemur 1.0 2.0"
    with pytest.raises(FormatError, match=r"expected 3 values \(rx ry rz\) for 'lfemur', found 2"):
        load_motion_asf_amc(write(bad))
    bad[k] = "nosuchbone 1 2 3"
    with pytest.raises(FormatError, match="found 'nosuchbone'"):
        load_motion_asf_amc(write(bad))


def test_broken_or_missing_asf(broken, tmp_path):
    asf, lines, write = broken
    amc = write(lines[:200])
    text = asf.read_text().splitlines()
    cut = next(i for i, t in enumerate(text) if "name rfemur" in t)
    asf.write_text("\n".join(text[:cut]) + "\n")
    with pytest.raises(FormatError, match=r"02\.asf.*(expected 'end'|expected a ':hierarchy')"):
        load_motion_asf_amc(amc)
    with pytest.raises(FormatError, match="nothere.asf"):
        load_motion_asf_amc(amc, tmp_path / "nothere.asf")
    lone = tmp_path / "sub" / "xx_01.amc"
    lone.parent.mkdir()
    lone.write_text("\n".join(lines[:200]))
    with pytest.raises(FormatError, match="pass asf_path"):
        load_motion_asf_amc(lone)


# ------------------------------------------------------------------------------ demo data
def test_packaged_demo_trial():
    from kinefuse.data import DEMO_TRIAL, demo_motion, demo_paths

    amc, asf = demo_paths()
    assert amc.is_file() and asf.is_file() and DEMO_TRIAL == "02_08"
    attribution = (Path(amc).parent / "CMU_ATTRIBUTION.md").read_text()
    assert "obtained from mocap.cs.cmu.edu" in attribution and "NSF EIA-0196217" in attribution
    assert amc.stat().st_size + asf.stat().st_size < 1_500_000
    m = demo_motion(0.0, 1.0)
    assert m.position_m.shape == (120, 22, 3)
    assert m.segment_length_m["upper_arm_r"] == pytest.approx(0.284, abs=0.002)


def test_hand_segment_carries_the_wrist_pronation(shared_data):
    """The canonical hand is CMU's wrist bone: relative to the forearm (radius) it turns about
    the forearm's long axis only, by the AMC's ``rwrist ry`` (read here from the text)."""
    amc = shared_data / "cmu_mocap" / "asfamc" / "02" / "02_07.amc"
    m = load_motion_asf_amc(amc)
    ry = np.array(
        [float(ln.split()[1]) for ln in amc.read_text().splitlines() if ln.startswith("rwrist ")]
    )
    fa = Rotation.from_quat(m.orientation("forearm_r"), scalar_first=True)
    hand = Rotation.from_quat(m.orientation("hand_r"), scalar_first=True)
    rv = np.degrees((fa.inv() * hand).as_rotvec())
    np.testing.assert_allclose(rv[:, [0, 2]], 0.0, atol=1e-6)  # deg: rounding of composed rotations
    assert ry.size == len(m) and np.ptp(ry) > 90  # a swordplay trial: the wrist turns a lot
    np.testing.assert_allclose(np.abs(rv[:, 1]), np.abs(ry), atol=1e-6)
    assert m.segment_joints["hand_r"] == ("wrist_r", "hand_r")
