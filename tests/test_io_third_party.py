"""Readers on real files written by other tools (``../shared/data/third_party``, see its SOURCE.md).

Each test pins what a correct reader does with one file (issue 13's defects 1-14) against values
stated in the file itself or in SOURCE.md, and, where OpenSim's Python package is installed (the
``[test]`` extra), against OpenSim's own ``TRCFileAdapter`` as an independent oracle.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import kinefuse.io as kio
from kinefuse.exceptions import FormatError, FormatWarning, UnitWarning
from kinefuse.io._names import KINECT_LIMB_JOINTS
from kinefuse.io.recording import JointStream


@pytest.fixture(scope="session")
def tp(shared_data):
    d = shared_data / "third_party"
    if not d.is_dir():
        pytest.skip(f"third-party sample files not found in {d}")
    return d


@pytest.fixture(scope="session")
def opensim():
    """OpenSim's Python package (the independent oracle), or a visible skip."""
    try:
        import opensim as osim
    except ImportError as e:
        pytest.skip(
            f"OpenSim oracle tests need the 'opensim' package (pip install opensim; part of "
            f"kinefuse[test]): {e}"
        )
    osim.Logger.setLevelString("error")
    return osim


def _osim_trc(osim, path):
    """(time (T,), values (T, M, 3) in the file's units, labels, metadata) via OpenSim.

    ``TimeSeriesTableVec3(path)`` reads a ``.trc`` with OpenSim's ``TRCFileAdapter``.
    """
    tab = osim.TimeSeriesTableVec3(str(path))
    flat = tab.flatten()
    m = flat.getMatrix().to_numpy()
    t = np.asarray(tab.getIndependentColumn())
    labels = list(tab.getColumnLabels())
    meta = {k: tab.getTableMetaDataAsString(k) for k in tab.getTableMetaDataKeys() if k != "header"}
    return t, m.reshape(len(t), len(labels), 3), labels, meta


def _quiet(fn, *a, **kw):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = fn(*a, **kw)
    return out, [str(x.message) for x in w]


# ------------------------------------------------------------------------------------------------
# TRC (defects 5, 6, 7, 14)
# ------------------------------------------------------------------------------------------------
_TRC_FILES = {
    # file: (DataRate, units factor to m, frames, markers)
    "opensim_subject01_walk1.trc": (60.0, 1e-3, 151, 41),
    "opensim_rajagopal_motion_capture_walk.trc": (100.0, 1e-3, 238, 41),
    "pose2sim_Standing_for_Scaling.trc": (60.0, 1.0, 25, 21),
}


@pytest.mark.parametrize("name", sorted(_TRC_FILES))
def test_trc_third_party_matches_opensim(tp, opensim, name):
    """Defects 5 and 6: kinefuse reads what OpenSim's TRCFileAdapter reads, value for value."""
    path = tp / "trc" / name
    rate, factor, T, M = _TRC_FILES[name]
    rec, _ = _quiet(kio.read_trc, path, map_names=False)
    r = rec.reference
    t, vals, labels, meta = _osim_trc(opensim, path)
    assert (len(r), len(r.joints)) == (T, M) == (len(t), len(labels))
    assert list(r.joints) == labels
    assert rec.metadata["rate_hz"] == float(meta["DataRate"]) == rate
    np.testing.assert_allclose(r.t_s, t, rtol=0, atol=1e-12)
    zero = np.all(vals == 0.0, axis=-1)
    np.testing.assert_allclose(
        r.position_m[~zero], vals[~zero] * factor, rtol=0, atol=1e-12, equal_nan=True
    )
    assert not r.available[zero].any()  # defect 14: OpenSim keeps 0,0,0; kinefuse = missing


def test_trc_repeated_tabs_in_header(tp):
    """Defect 5: the Rajagopal header values row has repeated tabs (empty tokens dropped)."""
    rec = kio.read_trc(tp / "trc" / "opensim_rajagopal_motion_capture_walk.trc")
    h = rec.metadata["header"]
    assert (h["DataRate"], h["CameraRate"], h["NumFrames"], h["Units"]) == (
        "100.0",
        "100.0",
        "238",
        "mm",
    )
    r = rec.reference
    assert r.t_s[-1] == pytest.approx(2.37) and len(r) == 238
    # positions in m: markers spread over a body (pelvis to toes ~ 1 m), not millimetres
    spread = np.nanmax(r.position_m[0], axis=0) - np.nanmin(r.position_m[0], axis=0)
    assert 0.5 < spread.max() < 2.5


def test_trc_numframes_exceeds_rows(tp):
    """Defect 6: NumFrames 50, 25 rows: read the 25 rows and warn about the header."""
    with pytest.warns(FormatWarning, match=r"NumFrames = 50 but the file has 25 data rows"):
        rec = kio.read_trc(tp / "trc" / "pose2sim_Standing_for_Scaling.trc")
    r = rec.reference
    assert len(r) == 25 and rec.metadata["rate_hz"] == 60.0
    np.testing.assert_allclose(r.t_s, np.arange(1, 26) / 60.0, atol=1e-12)
    # metres; a standing subject: head above the ankles by 1.3-2 m (vertical axis y)
    head, ankle = r.position("head")[0], r.position("ankle_r")[0]
    assert 1.3 < head[1] - ankle[1] < 2.0


def test_trc_comma_separated_variant(tp):
    """pyomeca's comma-separated TRC is read (with a note) and its truncation is reported."""
    with pytest.warns(FormatWarning, match="NumFrames = 652 but the file has 93"):
        rec = kio.read_trc(tp / "trc" / "pyomeca_markers.trc")
    r = rec.reference
    assert len(r) == 93 and len(r.joints) == 51 and rec.metadata["rate_hz"] == 100.0
    assert any("comma-separated" in n for n in rec.metadata["notes"])
    np.testing.assert_allclose(r.position_m[0, 0], [0.7337041, 0.0809832, 0.1918668], atol=1e-12)
    np.testing.assert_allclose(np.diff(r.t_s), 0.01, atol=1e-9)


def test_trc_header_survives_round_trip(tp, tmp_path):
    """Defect 7: DataRate 60, OrigDataRate, OrigDataStartFrame survive read -> write -> read even
    though the Time column is rounded to 0.017 s (the median step would say 58.82 Hz)."""
    src = tp / "trc" / "opensim_subject01_walk1.trc"
    rec = kio.read_trc(src)
    out = kio.write_trc(
        tmp_path / "w.trc", rec.reference, header=rec.metadata["header"], units="mm"
    )
    back = kio.read_trc(out)
    for k in ("DataRate", "CameraRate", "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"):
        assert float(back.metadata["header"][k]) == float(rec.metadata["header"][k]), k
    assert back.metadata["rate_hz"] == 60.0
    # without a header: the rate from the time span, snapped (60, not 58.823529)
    out2 = kio.write_trc(tmp_path / "w2.trc", rec.reference)
    assert kio.read_trc(out2).metadata["header"]["DataRate"] == "60"
    js = JointStream(
        t_s=np.arange(50) / 120.0 + 1e-9 * np.sin(np.arange(50)),
        position_m=np.ones((50, 1, 3)),
        joints=("a",),
    )
    out3 = kio.write_trc(tmp_path / "w3.trc", js)
    assert kio.read_trc(out3).metadata["header"]["DataRate"] == "120"
    out4 = kio.write_trc(tmp_path / "w4.trc", js, rate_hz=119.5)
    assert kio.read_trc(out4).metadata["rate_hz"] == 119.5


@pytest.mark.parametrize("units", ["m", "mm"])
def test_trc_written_is_read_by_opensim(tp, tmp_path, opensim, units):
    """Every TRC kinefuse writes is read back by OpenSim with the same values and header rate."""
    rec = kio.read_trc(tp / "trc" / "opensim_rajagopal_motion_capture_walk.trc", map_names=False)
    js = rec.reference
    rng = np.random.default_rng(7)
    avail = js.available & (rng.random(js.available.shape) > 0.02)  # some missing samples
    js = JointStream(t_s=js.t_s, position_m=js.position_m, available=avail, joints=js.joints)
    out = kio.write_trc(tmp_path / "k.trc", js, units=units, header=rec.metadata["header"])
    t, vals, labels, meta = _osim_trc(opensim, out)
    assert labels == list(js.joints) and meta["DataRate"] == "100.0" and meta["Units"] == units
    np.testing.assert_allclose(t, js.t_s, rtol=0, atol=1e-12)
    scale = {"m": 1.0, "mm": 1e3}[units]
    expected = np.where(avail[..., None], js.position_m, np.nan) * scale
    np.testing.assert_allclose(vals, expected, rtol=0, atol=1e-6 * scale, equal_nan=True)
    # a stream of kinefuse's own (odd rate, negative and tiny values) written without a header
    T = 40
    p = rng.normal(0, 0.4, size=(T, 3, 3))
    p[5, 1] = np.nan
    js2 = JointStream(
        t_s=0.25 + np.arange(T) / 37.5, position_m=p, joints=("elbow_r", "wrist_r", "x")
    )
    out2 = kio.write_trc(tmp_path / "k2.trc", js2)
    t2, vals2, _, meta2 = _osim_trc(opensim, out2)
    assert float(meta2["DataRate"]) == 37.5
    np.testing.assert_allclose(t2, js2.t_s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(vals2, p, rtol=0, atol=1e-6, equal_nan=True)


def test_trc_all_zero_marker_is_missing(tmp_path):
    """Defect 14: an all-zero marker is missing (one rule; zero_is_missing=False keeps it)."""
    text = (
        "PathFileType\t4\t(X/Y/Z)\tz.trc\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
        "100\t100\t2\t2\tmm\t100\t1\t2\n"
        "Frame#\tTime\tA\t\t\tB\t\t\n"
        "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n\n"
        "1\t0.00\t0.000\t0.000\t0.000\t10\t0\t0\n"
        "2\t0.01\t1.0\t2.0\t3.0\t0\t0\t0\n"
    )
    f = tmp_path / "z.trc"
    f.write_text(text)
    rec = kio.read_trc(f)
    assert rec.reference.available.tolist() == [[False, True], [True, False]]
    assert (
        rec.metadata["n_zero_samples"] == 2 and "all exactly 0" in rec.metadata["availability_rule"]
    )
    assert kio.read_trc(f, zero_is_missing=False).reference.available.all()


# ------------------------------------------------------------------------------------------------
# C3D (defects 1-4, 14; analog channels)
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ezc3d():
    try:
        import ezc3d as mod
    except ImportError as e:
        pytest.skip(f"C3D tests need ezc3d (pip install 'kinefuse[c3d]'): {e}")
    return mod


def _segment_m(js, a, b):
    d = np.linalg.norm(js.position(a) - js.position(b), axis=-1)
    return float(np.nanmedian(d))


def test_c3d_labels_longer_than_used(tp, ezc3d):
    """Defect 1: POINT:LABELS has 48 entries, POINT:USED 26: the first 26 labels are read."""
    rec = kio.read_c3d(tp / "c3d" / "btk_c3d.org_sample01_Eb015pi.c3d")
    r = rec.reference
    assert (
        len(r.joints) == 26 and r.joints[:3] == ("RFT1", "RFT2", "RFT3") and r.joints[-1] == "pv4"
    )
    assert len(r) == 450 and rec.metadata["rate_hz"] == 50.0
    assert r.t_s[-1] == pytest.approx(449 / 50)
    assert any("first USED = 26" in n for n in rec.metadata["notes"])
    p = np.where(r.available[..., None], r.position_m, np.nan)
    assert 0.3 < np.nanmedian(np.linalg.norm(p, axis=-1)) < 5.0  # metres, not mm
    a = rec.metadata["analog"]  # analog channels exposed, not joints
    assert a["values"].shape == (1800, 16) and a["rate_hz"] == 200.0
    assert a["labels"][:3] == ("FX1", "FY1", "FZ1") and a["t_s"][-1] == pytest.approx(1799 / 200)


def test_c3d_header_last_frame_disagrees(tp, ezc3d):
    """Defect 2: header and POINT:FRAMES announce 1149 frames, the data section holds exactly 29
    whole frames (what ezc3d reads): read them with a warning, no false "truncated" error."""
    with pytest.warns(FormatWarning, match="announces 1149 frames but the data section holds 29"):
        rec = kio.read_c3d(tp / "c3d" / "ezc3d_Optotrak.c3d")
    r = rec.reference
    c = ezc3d.c3d(str(tp / "c3d" / "ezc3d_Optotrak.c3d"))
    assert len(r) == 29 == c["parameters"]["POINT"]["FRAMES"]["value"][0]
    assert rec.metadata["rate_hz"] == 30.0 and r.joints[0] == "Marker_1" and len(r.joints) == 54
    np.testing.assert_allclose(
        r.position_m[r.available],
        np.transpose(c["data"]["points"][:3], (2, 1, 0))[r.available] / 1e3,
    )
    assert rec.metadata["analog"] is None


def test_c3d_plug_in_gait_outputs_are_not_joints(tp, ezc3d):
    """Defect 3: angles/forces/moments/powers stored as points are kept apart, not scaled to m."""
    rec = kio.read_c3d(tp / "c3d" / "btk_c3d.org_sample09_PlugInC3D.c3d")
    r = rec.reference
    other = rec.metadata["c3d_other_points"]
    for grp, n, unit in (
        ("ANGLES", 10, "deg"),
        ("FORCES", 8, "N"),
        ("MOMENTS", 8, "Nmm"),
        ("POWERS", 6, "W"),
    ):
        assert len(other[grp]["labels"]) == n and other[grp]["unit"] == unit
        assert not set(other[grp]["labels"]) & set(r.joints)
    assert len(r.joints) == 86 - 32 and "LKneeAngles" not in r.joints
    knee = other["ANGLES"]["values"][:, other["ANGLES"]["labels"].index("LKneeAngles"), 0]
    assert 30 < np.nanmax(knee) - np.nanmin(knee) < 90  # knee flexion range over gait, degrees
    # Plug-in-Gait joint centres: thigh (hip -> knee) 0.3-0.55 m, shank (knee -> ankle) 0.3-0.6 m
    assert 0.3 < _segment_m(r, "hip_l", "knee_l") < 0.55
    assert 0.3 < _segment_m(r, "knee_r", "ankle_r") < 0.6
    assert rec.metadata["analog"]["values"].shape == (5620, 36)


def test_c3d_empty_label_can_be_written_to_trc(tp, ezc3d, tmp_path):
    """Defect 4: an empty label is named point_<n>, and the result writes to TRC."""
    rec = kio.read_c3d(tp / "c3d" / "btk_c3d.org_sample24_MotionMonitorC3D.c3d")
    r = rec.reference
    assert r.joints == ("point_1", "M1", "M2", "M3", "M4", "M5", "M6", "M7") and "" not in r.joints
    assert (
        len(r) == 840 and rec.metadata["rate_hz"] == 140.0 and rec.metadata["units_converted"] == []
    )
    out = kio.write_trc(tmp_path / "mm.trc", r)
    back = kio.read_trc(out, map_names=False)
    assert back.reference.joints == r.joints and back.metadata["rate_hz"] == 140.0
    assert rec.metadata["analog"]["values"].shape == (5880, 16)


def test_c3d_duplicate_labels_get_distinct_names(tp, ezc3d, tmp_path):
    rec = kio.read_c3d(tp / "c3d" / "btk_others_Gait.c3d")
    r = rec.reference
    assert len(r.joints) == 33 and len(set(r.joints)) == 33
    for lab in ("RKNE", "RANK", "LKNE", "LANK", "RFOO", "LFOO"):
        assert lab in r.joints and f"{lab}_2" in r.joints
    assert len(r) == 487 and rec.metadata["rate_hz"] == 100.0
    kio.write_trc(tmp_path / "gait.trc", r)


def test_c3d_qualisys_keeps_working(tp, ezc3d):
    rec = kio.read_c3d(tp / "c3d" / "ezc3d_Qualisys.c3d")
    r = rec.reference
    assert (len(r), len(r.joints), rec.metadata["rate_hz"]) == (340, 55, 200.0)
    assert r.joints[:2] == ("L_IAS", "L_IPS") and r.available.all()
    # pelvis width (left to right anterior iliac spine) 0.2-0.35 m
    assert 0.2 < _segment_m(r, "L_IAS", "R_IAS") < 0.35
    assert rec.metadata["analog"]["values"].shape == (3400, 69)


def test_c3d_all_zero_marker_is_missing(tmp_path, ezc3d):
    """Defect 14 for C3D: a point written as 0, 0, 0 is missing."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("a", "b")
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    data = np.ones((4, 2, 5))
    data[:3, 1, 2] = 0.0
    c["data"]["points"] = data
    c.write(str(tmp_path / "z.c3d"))
    rec = kio.read_c3d(tmp_path / "z.c3d")
    assert rec.reference.available.sum() == 9 and not rec.reference.available[2, 1]
    assert kio.read_c3d(tmp_path / "z.c3d", zero_is_missing_points=False).reference.available.all()


def test_c3d_to_trc_read_by_opensim(tp, ezc3d, opensim, tmp_path):
    """A TRC kinefuse writes from a C3D is read by OpenSim with the same values and rate."""
    r = kio.read_c3d(tp / "c3d" / "btk_others_Gait.c3d").reference
    out = kio.write_trc(tmp_path / "g.trc", r, units="mm")
    t, vals, labels, meta = _osim_trc(opensim, out)
    assert labels == list(r.joints) and float(meta["DataRate"]) == 100.0
    expected = np.where(r.available[..., None], r.position_m, np.nan) * 1e3
    np.testing.assert_allclose(vals, expected, rtol=0, atol=1e-3 * 0.5 + 1e-9, equal_nan=True)


# ------------------------------------------------------------------------------------------------
# BVH (defects 8-10) and ASF/AMC
# ------------------------------------------------------------------------------------------------
def _bvh_channels(path, joint, frame):
    """The 6 channel values of ``joint`` at ``frame`` of a Bandai file (every joint has 6)."""
    lines = path.read_text().splitlines()
    order = [ln.split()[1] for ln in lines if ln.split()[:1] in (["ROOT"], ["JOINT"])]
    k = lines.index("MOTION")
    vals = np.array(lines[k + 3 + frame].split(), float)
    i = order.index(joint)
    return vals[6 * i : 6 * i + 6]


def test_bvh_bandai_position_channels_replace_offset(tp):
    """Defect 8 (and 9, 10): non-root position channels replace the OFFSET; cm detected;
    Bandai naming mapped (thigh ~0.39 m, hips ~0.9 m high)."""
    path = tp / "bvh" / "bandai1_walk_normal_001.bvh"
    with pytest.warns(
        UserWarning, match=r"naming 'bandai': no joint found for \['hand_l', 'hand_r'\]"
    ):
        rec = kio.read_bvh(path)
    md, r = rec.metadata, rec.reference
    assert md["joint_naming"] == "bandai" and md["length_unit_m"] == 0.01
    assert len(r) == 195 and md["rate_hz"] == pytest.approx(30.0, rel=1e-5)
    # thigh = |LowerLeg_L position channels| in cm, per the file (not OFFSET + channels)
    thigh_file = np.linalg.norm(_bvh_channels(path, "LowerLeg_L", 0)[:3]) * 0.01
    assert md["segment_length_m"]["thigh_l"] == pytest.approx(thigh_file, rel=1e-6)
    assert md["segment_length_m"]["thigh_l"] == pytest.approx(0.39, abs=0.01)
    d = np.linalg.norm(r.position("knee_l") - r.position("hip_l"), axis=-1)
    np.testing.assert_allclose(d, thigh_file, rtol=1e-6)  # rigid bone every frame
    assert np.median(r.position("pelvis")[:, 2]) == pytest.approx(0.9, abs=0.05)
    assert 1.3 < np.median(r.position("head")[:, 2]) < 1.9  # m, not 278 "m"
    assert set(r.joints) >= set(KINECT_LIMB_JOINTS) - {"hand_l", "hand_r"}
    assert {"thigh_l", "shank_r", "upper_arm_l", "forearm_r", "pelvis"} <= set(
        rec.reference_orientation
    )
    for s in rec.reference_orientation.values():
        np.testing.assert_allclose(np.linalg.norm(s.q_world_from_sensor, axis=1), 1.0, atol=1e-9)


def _bandai_fk(path, frame, target):
    """Independent FK of a Bandai file (6 channels per joint, position channels replace the
    OFFSET below the root), in file units and y-up; written apart from the reader."""
    lines = path.read_text().splitlines()
    parent, stack, name, order = {}, [], None, []
    for ln in lines[: lines.index("MOTION")]:
        tok = ln.split()
        if tok[:1] in (["ROOT"], ["JOINT"]):
            name = tok[1]
            parent[name] = stack[-1] if stack else None
            order.append(name)
        elif tok[:1] == ["End"]:
            name = None
        elif tok[:1] == ["{"]:
            stack.append(name)
        elif tok[:1] == ["}"]:
            stack.pop()
    chain = [target]
    while parent[chain[-1]] is not None:
        chain.append(parent[chain[-1]])
    R, p = np.eye(3), np.zeros(3)
    for j in reversed(chain):
        v = _bvh_channels(path, j, frame)  # X/Y/Zposition, Z/X/Yrotation
        p = p + R @ v[:3]  # root OFFSET is 0 in this file
        c, s_ = np.cos(np.radians(v[3:])), np.sin(np.radians(v[3:]))
        Rz = np.array([[c[0], -s_[0], 0], [s_[0], c[0], 0], [0, 0, 1]])
        Rx = np.array([[1, 0, 0], [0, c[1], -s_[1]], [0, s_[1], c[1]]])
        Ry = np.array([[c[2], 0, s_[2]], [0, 1, 0], [-s_[2], 0, c[2]]])
        R = R @ Rz @ Rx @ Ry
    return p


@pytest.mark.parametrize("frame", [0, 97, 194])
def test_bvh_bandai_matches_independent_fk(tp, frame):
    from kinefuse.io.motion import R_ENU_FROM_YUP

    path = tp / "bvh" / "bandai1_walk_normal_001.bvh"
    with pytest.warns(UserWarning, match="no joint found"):
        r = kio.read_bvh(path).reference
    for joint, bvh_name in (("ankle_l", "Foot_L"), ("wrist_r", "Hand_R"), ("head", "Head")):
        expected = R_ENU_FROM_YUP @ _bandai_fk(path, frame, bvh_name) * 0.01
        np.testing.assert_allclose(r.position(joint)[frame], expected, atol=1e-9)


def test_bvh_motionbuilder_naming(tp):
    """Defect 9: CMU clip in MotionBuilder naming: LeftShoulder is the clavicle, LeftArm the
    shoulder joint; every limb joint found, no warning."""
    path = tp / "bvh" / "fairmotion_01_01.bvh"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = kio.read_bvh(path)
    md, r = rec.metadata, rec.reference
    assert md["joint_naming"] == "motionbuilder" and md["joint_source"]["shoulder_l"] == "LeftArm"
    assert set(KINECT_LIMB_JOINTS) <= set(r.joints)
    width = np.linalg.norm(r.position("shoulder_l") - r.position("shoulder_r"), axis=-1)
    assert 0.25 < np.median(width) < 0.5  # not 0.0
    # CMU's ASF unit (1/0.45 inch) detected: shank 7.49 units in the file -> 0.42 m
    assert md["length_unit_m"] == pytest.approx(0.0254 / 0.45)
    shank = np.hypot(2.56220, 7.03959) * 0.0254 / 0.45
    assert md["segment_length_m"]["shank_l"] == pytest.approx(shank, rel=1e-6)
    assert len(r) == 2752 and md["rate_hz"] == pytest.approx(1 / 0.0083333)


def test_bvh_units_checked(tp):
    """Defect 10: a wrong given unit warns; check_units calls centimetres centimetres."""
    path = tp / "bvh" / "bandai1_walk_normal_001.bvh"
    with pytest.warns(UnitWarning, match=r"length_unit_m=1.0 the figure is 133 m"):
        with pytest.warns(UserWarning, match="no joint found"):
            rec = kio.read_bvh(path, length_unit_m=1.0)
    with pytest.warns(UnitWarning, match="looks like centimetres"):
        from kinefuse.io._checks import check_units

        check_units(rec)


def test_asf_amc_backflip_keeps_working(tp):
    rec = kio.load(tp / "asf_amc" / "gsimchoni_backflip.amc")
    r, md = rec.reference, rec.metadata
    assert md["format"] == "cmu" and set(KINECT_LIMB_JOINTS) <= set(r.joints)
    assert len(r) == 247
    assert (
        0.3 < md["segment_length_m"]["thigh_l"] < 0.55
        and 0.3 < md["segment_length_m"]["shank_r"] < 0.55
    )
    assert md["rate_hz"] == pytest.approx(120.0)


# ------------------------------------------------------------------------------------------------
# x-IMU3 (defect 11)
# ------------------------------------------------------------------------------------------------
def test_ximu3_on_plain_xio_csv_is_not_a_bare_file_not_found(tp):
    """Defect 11: format='ximu3' on x-io's plain CSV (not Inertial.csv in a sensor folder) says
    what the file is, or hands it to the plain-CSV reader when the installation has one."""
    path = tp / "x-io" / "gait-tracking_short_walk.csv"
    try:
        rec, _ = _quiet(kio.load, path, format="ximu3")
    except FormatError as e:
        assert "x-io's plain CSV export" in str(
            e
        ) and "gait-tracking_short_walk.csv, line 1" in str(e)
        return
    (imu,) = rec.imu.values()
    assert imu.t_s[-1] - imu.t_s[0] == pytest.approx(41.618, abs=0.01)  # last "Time (s)"
    assert 9.0 < np.median(np.linalg.norm(imu.acc_m_s2, axis=1)) < 10.6  # g -> m/s^2
    assert np.percentile(np.linalg.norm(imu.gyr_rad_s, axis=1), 99) < 35  # deg/s -> rad/s


def test_ximu3_inertial_csv_under_another_name(shared_data, tmp_path):
    """An x-IMU3 Inertial.csv exported under another name is read as one sensor."""
    src = shared_data / "xio_imu_mocap_lower_body" / "pelvis_64F0EDBF"
    f = tmp_path / "pelvis_export.csv"
    f.write_bytes((src / "Inertial.csv").read_bytes())
    (one,) = kio.read_ximu3(f).imu.values()
    ref = kio.read_ximu3(src).imu["pelvis"]
    np.testing.assert_array_equal(one.gyr_rad_s, ref.gyr_rad_s)
    np.testing.assert_array_equal(one.acc_m_s2, ref.acc_m_s2)
    assert one.q_world_from_sensor is None
    bad = tmp_path / "other.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(FormatError, match=r"other.csv, line 1: expected an x-IMU3 Inertial.csv"):
        kio.read_ximu3(bad)


# ------------------------------------------------------------------------------------------------
# Kinect v2 recorder CSV (defect 12)
# ------------------------------------------------------------------------------------------------
def test_kinect_v2_lsl_kinect_export(tp):
    """Defect 12: preamble line without '#', TimeSpan (Unix ms) time column, '_Conf' columns."""
    path = tp / "kinect_v2" / "lslkinect_MoCap.csv"
    rec = kio.load(path)
    v, md = rec.vision, rec.metadata
    assert md["format"] == "kinect_v2" and md["time_column"] == "TimeSpan"
    assert len(v) == 358 and len(v.joints) == 25 and v.joints[:2] == ("spine_base", "spine_mid")
    # first/last TimeSpan of the file: 1604056708714.7141, 1604056720622.563 ms
    assert md["t0_unix_s"] == pytest.approx(1604056708.7147141, abs=1e-6)
    assert v.t_s[0] == 0.0 and v.t_s[-1] == pytest.approx(11.907849, abs=1e-5)
    assert md["preamble"]["stream nominal rate"] == "15"
    assert any("nominal rate" in n and "29.8 Hz" in n for n in md["notes"])
    # confidences: 7155 x 1 (Tracked), 1795 x 0.5 (Inferred) in the file
    assert v.available.sum() == 7155
    assert kio.load(path, min_tracking_state=1).vision.available.sum() == 7155 + 1795
    upper_arm = np.linalg.norm(v.position("shoulder_l") - v.position("elbow_l"), axis=-1)
    assert 0.2 < np.nanmedian(upper_arm) < 0.35  # metres
    same = kio.read_kinect_v2_csv(path, time_column="TimeSpan", time_unit="ms")
    np.testing.assert_array_equal(same.vision.t_s, v.t_s)
    allin = kio.read_kinect_v2_csv(path, confidence_states={0.5: 2, 1.0: 2})
    assert allin.vision.available.sum() == 7155 + 1795


def test_kinect_v2_reader_arguments_errors(tp, tmp_path):
    path = tp / "kinect_v2" / "lslkinect_MoCap.csv"
    with pytest.raises(FormatError, match="time_column='Stamp' not found"):
        kio.read_kinect_v2_csv(path, time_column="Stamp")
    with pytest.raises(
        FormatError,
        match=r"line 52, field 'ElbowLeft_Conf': expected a confidence among \[1.0\].*found 0.5",
    ):
        kio.read_kinect_v2_csv(path, confidence_states={1.0: 2})
    f = tmp_path / "k.csv"
    f.write_text("Recorder v1, nominal rate 30\nframe,foo,bar\n1,2,3\n")
    with pytest.raises(
        FormatError, match="k.csv: expected a header line with column names, found none"
    ):
        kio.read_kinect_v2_csv(f)
    g = tmp_path / "g.csv"
    g.write_text(
        "Stamp,SpineBase_X,SpineBase_Y,SpineBase_Z,SpineBase_Conf\n10,0,1,2,1\n20,0,1,2,1\n"
    )
    r = kio.read_kinect_v2_csv(g, time_column="Stamp", time_unit="ms")
    np.testing.assert_allclose(r.vision.t_s, [0.01, 0.02])
    with pytest.raises(FormatError, match="unknown unit of time column 'Stamp'; pass time_unit="):
        kio.read_kinect_v2_csv(g, time_column="Stamp")


# ------------------------------------------------------------------------------------------------
# Xsens MT Manager text / OpenSense (defect 13)
# ------------------------------------------------------------------------------------------------
def test_mtmanager_dot_times_from_sample_time_fine(tp):
    """Defect 13: SampleTimeFine (µs, DOT) gives the times and disagrees with 'Update Rate:
    100Hz' (warned); free acceleration is recognised, not taken for specific force."""
    folder = tp / "xsens" / "dot_transformed_mtmanager"
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        rec = kio.load(folder)
    msgs = [str(x.message) for x in w]
    assert not [m for m in msgs if "looks like g" in m]
    fmt = [str(x.message) for x in w if issubclass(x.category, FormatWarning)]
    assert len(fmt) == 5 and all("Update Rate says 100 Hz" in m for m in fmt)
    md = rec.metadata
    assert md["time_source"] == "SampleTimeFine" and set(rec.imu) == {
        "pelvis", "thigh_l", "thigh_r", "shank_l", "shank_r"
    }  # fmt: skip
    tib = rec.imu["shank_l"]
    # LTibia: 381 rows, SampleTimeFine 16667 µs apart -> 60 Hz, 6.33 s (not 3.8 s at 100 Hz)
    lines = (folder / "XSDot_20210820_202113_LTibia.txt").read_text().splitlines()
    rows = [ln.split("\t") for ln in lines[6:] if ln.strip()]
    fine = np.array([float(r[1]) for r in rows])
    assert len(tib) == len(rows) == 381
    np.testing.assert_allclose(tib.t_s - tib.t_s[0], (fine - fine[0]) * 1e-6, atol=1e-9)
    assert tib.rate_hz == pytest.approx(60.0, rel=1e-3) and tib.t_s[-1] - tib.t_s[
        0
    ] == pytest.approx(6.333, abs=1e-3)
    # free acceleration (world frame) kept; specific force rebuilt: R f - g e_z == free acc
    free = np.array([[float(v) for v in r[14:17]] for r in rows])
    np.testing.assert_allclose(md["free_acc_m_s2"]["shank_l"], free)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(tib.q_world_from_sensor, scalar_first=True)
    np.testing.assert_allclose(R.apply(tib.acc_m_s2) - [0, 0, 9.80665], free, atol=1e-9)
    for s in rec.imu.values():
        np.testing.assert_allclose(np.linalg.norm(s.q_world_from_sensor, axis=1), 1.0, atol=1e-6)
        assert 9.0 < np.median(np.linalg.norm(s.acc_m_s2, axis=1)) < 10.6


def test_mtmanager_sample_time_fine_wraps_and_ticks(tmp_path):
    """SampleTimeFine wraps at 2^32; MTi's 10 kHz ticks agree with a 100 Hz Update Rate."""
    start = 2**32 - 250
    rows = [
        "\t".join([str(k + 1), str((start + 100 * k) % 2**32), "0.1", "0.2", "9.8", "0", "0", "0"])
        for k in range(6)
    ]
    f = tmp_path / "MT_x_00B4227C.txt"
    header = "PacketCounter\tSampleTimeFine\tAcc_X\tAcc_Y\tAcc_Z\tGyr_X\tGyr_Y\tGyr_Z"
    f.write_text("// Update Rate: 100.0Hz\n" + header + "\n" + "\n".join(rows) + "\n")
    from kinefuse.io.opensense import read_xsens_txt

    p = read_xsens_txt(f)
    np.testing.assert_allclose(
        p["sample_time_s"] - p["sample_time_s"][0], np.arange(6) * 0.01, atol=1e-12
    )
    assert p["sample_time_note"] == "SampleTimeFine in 10 kHz ticks (MTi)"


def test_opensense_example_keeps_packet_counter_times(shared_data):
    """The OpenSense example has an empty SampleTimeFine: times from PacketCounter / 100 Hz."""
    rec = kio.load(shared_data / "opensense_example_imu")
    assert rec.metadata["time_source"] == "PacketCounter / Update Rate"
    assert rec.metadata["free_acc_m_s2"] == {}
    for s in rec.imu.values():
        assert s.rate_hz == pytest.approx(100.0)
        assert 9.0 < np.median(np.linalg.norm(s.acc_m_s2, axis=1)) < 10.6


def test_all_zero_rule_in_camera_readers(tmp_path):
    """Defect 14: the same all-zero rule in the Kinect v2 and MediaPipe readers."""
    g = tmp_path / "k.csv"
    g.write_text(
        "t_s,SpineBase_X,SpineBase_Y,SpineBase_Z,SpineBase_TrackingState\n0,0,0,0,2\n0.1,0.1,0.2,2.0,2\n"
    )
    r = kio.read_kinect_v2_csv(g)
    assert r.vision.available[:, 0].tolist() == [False, True]
    assert r.metadata["n_zero_samples"] == 1 and "all exactly 0" in r.metadata["availability_rule"]
    m = tmp_path / "mp.csv"
    m.write_text("t_s,nose_x,nose_y,nose_z,nose_visibility\n0,0,0,0,0.9\n0.1,0.1,0.2,0.3,0.9\n")
    assert kio.read_mediapipe(m).vision.available[:, 0].tolist() == [False, True]


def test_trc_comma_variant_is_refused_by_opensim(tp, opensim):
    """Why pyomeca's comma-separated TRC is not compared with OpenSim: OpenSim refuses it."""
    with pytest.raises(RuntimeError, match="TRCFileAdapter"):
        _osim_trc(opensim, tp / "trc" / "pyomeca_markers.trc")


def test_bvh_unit_undecidable_asks_for_it(tmp_path):
    """A figure no candidate unit makes person-sized: the nearest is used, with a UnitWarning."""
    text = (
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition "
        "Zrotation Yrotation Xrotation\n JOINT LeftUpLeg\n {\n  OFFSET 1 0 0\n  CHANNELS 3 Zrotation "
        "Yrotation Xrotation\n  JOINT LeftLeg\n  {\n   OFFSET 0 -5 0\n   CHANNELS 3 Zrotation Yrotation "
        "Xrotation\n   End Site\n   {\n    OFFSET 0 -5 0\n   }\n  }\n }\n}\nMOTION\nFrames: 2\n"
        "Frame Time: 0.01\n" + "0 0 0 0 0 0 0 0 0 0 0 0\n" * 2
    )
    f = tmp_path / "tiny.bvh"
    f.write_text(text)
    with pytest.warns(UnitWarning, match=r"figure measures 5 BVH units and none of m, cm.*assumed"):
        with pytest.warns(UserWarning, match="no joint found"):
            guess = kio.read_bvh(f)
    assert guess.metadata["length_unit_m"] == 1.0  # 5 m is nearer to 1.5 m than 0.28 m (CMU unit)
    with pytest.warns(UserWarning, match="no joint found"):
        rec = kio.read_bvh(f, length_unit_m=0.2)  # 1 m figure: accepted without a UnitWarning
    assert rec.metadata["segment_length_m"]["thigh_l"] == pytest.approx(1.0)


def test_ximu3_sibling_csv_is_detected(shared_data):
    """Any CSV of an x-IMU3 sensor folder loads the sensor (Magnetometer.csv, HighG...)."""
    rec = kio.load(
        shared_data / "xio_imu_mocap_lower_body" / "pelvis_64F0EDBF" / "Magnetometer.csv"
    )
    assert rec.metadata["format"] == "ximu3" and list(rec.imu) == ["pelvis"]


def test_session_reader_options_reach_the_reader(tp, shared_data, tmp_path):
    """Defect 12 via a session: [camera.reader] names the time column and the confidence map."""
    from kinefuse.exceptions import ConfigError
    from kinefuse.pipelines.run import load_streams
    from kinefuse.session_file import load_session

    cam = tp / "kinect_v2" / "lslkinect_MoCap.csv"
    imu = shared_data / "xio_imu_mocap_lower_body"
    text = f"""
[session]
name = "s"
[imu]
format = "ximu3"
path = "{imu}"
[imu.segments]
pelvis = "pelvis_64F0EDBF"
[skeleton]
body_height_m = 1.8
[camera]
format = "kinect_v2"
path = "{cam}"
[camera.reader]
time_column = "TimeSpan"
time_unit = "ms"
confidence_states = {{"0" = 0, "0.5" = 2, "1" = 2}}
[method]
name = "imu-only"
"""
    p = tmp_path / "s.toml"
    p.write_text(text)
    cfg = load_session(p)
    assert cfg.camera.reader["time_unit"] == "ms"
    rec, _ = _quiet(load_streams, cfg, strict_units=False)
    rec = rec[0] if isinstance(rec, tuple) else rec
    assert rec.vision.available.sum() == 7155 + 1795  # Inferred accepted by the mapping
    p.write_text(text.replace('time_unit = "ms"', 'time_units = "ms"'))
    with pytest.raises(
        ConfigError,
        match=r"\[camera.reader\]: unknown option\(s\) \['time_units'\] for the 'kinect_v2' "
        r"reader; it takes \[.*'time_unit'",
    ):
        load_streams(load_session(p), strict_units=False)
