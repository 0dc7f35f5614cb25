"""BVH reader on the real (metre-scaled) CMU BVH clips, checked against an independent FK."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import FormatError
from kinefuse.io.bvh import load_motion_bvh, read_bvh
from kinefuse.io.motion import R_ENU_FROM_YUP, SEGMENT_AXIS


@pytest.fixture(scope="module")
def bvh_path(shared_data):
    return shared_data / "cmu_mocap" / "bvh_131_scaled" / "scaled_131_01.bvh"


@pytest.fixture(scope="module")
def motion(bvh_path):
    return load_motion_bvh(bvh_path)


def test_shapes_rate_lengths(bvh_path, motion):
    rec = read_bvh(bvh_path)
    assert rec.reference.position_m.shape == (995, 22, 3)
    assert motion.rate_hz == pytest.approx(1 / 0.008333)
    assert rec.metadata["format"] == "bvh"
    L = motion.segment_length_m
    # offsets in the file, metres: LeftKnee 0.140731 -0.386656 0 ; LeftElbow 0 -0.239947 0
    assert L["thigh_l"] == pytest.approx(np.hypot(0.140731, 0.386656), rel=1e-9)
    assert L["upper_arm_l"] == pytest.approx(0.239947, rel=1e-9)
    assert 0.35 < L["shank_r"] < 0.45 and 0.15 < L["forearm_r"] < 0.25
    head = motion.position("head")[:, 2] - motion.position("ankle_l")[:, 2]
    assert 1.0 < np.median(head) < 1.6


def test_segment_axis_identity(motion):
    for seg, (prox, dist) in motion.segment_joints.items():
        if dist is None:
            continue
        R = Rotation.from_quat(motion.orientation(seg), scalar_first=True).as_matrix()
        np.testing.assert_allclose(
            motion.position(prox) + motion.segment_length_m[seg] * (R @ SEGMENT_AXIS),
            motion.position(dist),
            atol=1e-12,
        )


def _rot(axis, deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _independent_fk(path, frame, target):
    """Minimal BVH FK written separately from the reader: position of ``target`` at ``frame``."""
    lines = path.read_text().splitlines()
    joints, stack, n_ch = {}, [], 0
    name = None
    for i, line in enumerate(lines):
        tok = line.split()
        if not tok:
            continue
        if tok[0] in ("ROOT", "JOINT"):
            name = tok[1]
            joints[name] = {"parent": stack[-1] if stack else None}
        elif tok[0] == "End":
            name = None
        elif tok[0] == "{":
            stack.append(name)
        elif tok[0] == "}":
            stack.pop()
        elif tok[0] == "OFFSET" and name is not None:
            joints[name]["offset"] = np.array(tok[1:4], float)
        elif tok[0] == "CHANNELS":
            joints[name]["channels"] = tok[2:]
            joints[name]["start"] = n_ch
            n_ch += int(tok[1])
        elif tok[0] == "MOTION":
            values = np.array(lines[i + 3 + frame].split(), float)
            break
    chain = [target]
    while joints[chain[-1]]["parent"] is not None:
        chain.append(joints[chain[-1]]["parent"])
    R, p = np.eye(3), np.zeros(3)
    for j in reversed(chain):
        info = joints[j]
        v = values[info["start"] : info["start"] + len(info["channels"])]
        p = p + R @ info["offset"]
        local = np.eye(3)
        for ch, val in zip(info["channels"], v, strict=True):
            if ch.endswith("position"):
                p = p + R @ (np.eye(3)["XYZ".index(ch[0])] * val)
            else:
                local = local @ _rot(ch[0], val)
        R = R @ local
    return p


@pytest.mark.parametrize("frame", [0, 500, 994])
def test_left_wrist_matches_independent_fk(bvh_path, motion, frame):
    expected = R_ENU_FROM_YUP @ _independent_fk(bvh_path, frame, "LeftWrist")
    np.testing.assert_allclose(motion.position("wrist_l")[frame], expected, atol=1e-9)
    expected = R_ENU_FROM_YUP @ _independent_fk(bvh_path, frame, "RightAnkle")
    np.testing.assert_allclose(motion.position("ankle_r")[frame], expected, atol=1e-9)


def test_broken_bvh(bvh_path, tmp_path):
    lines = bvh_path.read_text().splitlines()
    p = tmp_path / "t.bvh"
    p.write_text("\n".join(lines[:500]) + "\n")
    with pytest.raises(
        FormatError, match=r"t\.bvh, line 500: expected 995 frame lines.*found 313 \(truncated"
    ):
        load_motion_bvh(p)
    bad = list(lines)
    bad[4] = "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Wrotation"
    p.write_text("\n".join(bad) + "\n")
    with pytest.raises(FormatError, match=r"line 5: expected a channel among .* found 'Wrotation'"):
        load_motion_bvh(p)
    bad = list(lines)
    bad[190] = bad[190].replace(" ", " x ", 1)
    p.write_text("\n".join(bad) + "\n")
    with pytest.raises(FormatError, match=r"line 191: frame 3: expected \d+ channel values"):
        load_motion_bvh(p)
    p.write_text("\n".join(lines[:100]) + "\n")
    with pytest.raises(FormatError, match="MOTION"):
        load_motion_bvh(p)
