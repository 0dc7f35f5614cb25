"""Camera/mocap formats (Kinect v2, Azure Kinect, MediaPipe, C3D, TRC) and the generic CSVs.

No real files of these formats are in ../shared/data, so fixtures are generated in tmp_path in
the layouts the producers write (documented in docs/formats.md).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import kinefuse.io as kio
from kinefuse.exceptions import FormatError, FormatWarning, UnitWarning
from kinefuse.io.azure_kinect import AZURE_JOINTS
from kinefuse.io.kinect_v2 import KINECT_V2_JOINTS, KINECT_V2_TO_CANONICAL
from kinefuse.io.mediapipe import MEDIAPIPE_LANDMARKS
from kinefuse.io.recording import JointStream


@pytest.fixture
def skeleton(rng):
    """(T, 25, 3) plausible camera-space joints (m) and TrackingState (T, 25)."""
    T = 12
    base = np.array([0.0, 0.0, 2.5]) + rng.normal(0, 0.3, size=(25, 3))
    pos = base + rng.normal(0, 0.01, size=(T, 25, 3))
    state = np.full((T, 25), 2)
    state[3, 5] = 1  # ElbowLeft inferred
    state[4, 9] = 0  # ElbowRight not tracked
    return np.arange(T) / 30.0, pos, state


def _write_v2_wide(path, t, pos, state, *, textual=False):
    names = {0: "NotTracked", 1: "Inferred", 2: "Tracked"}
    hdr = ["time_s"] + [
        f"{j}_{w}" for j in KINECT_V2_JOINTS for w in ("X", "Y", "Z", "TrackingState")
    ]
    rows = [",".join(hdr)]
    for k in range(len(t)):
        f = [repr(float(t[k]))]
        for j in range(25):
            f += [repr(float(v)) for v in pos[k, j]] + [
                names[state[k, j]] if textual else str(state[k, j])
            ]
        rows.append(",".join(f))
    path.write_text("\n".join(rows) + "\n")


# ------------------------------------------------------------------------------------------------
# Kinect v2
# ------------------------------------------------------------------------------------------------
def test_kinect_v2_wide(tmp_path, skeleton):
    t, pos, state = skeleton
    f = tmp_path / "k.csv"
    _write_v2_wide(f, t, pos, state)
    assert kio.detect_format(f) == "kinect_v2"
    rec = kio.load(f)
    v = rec.vision
    assert v.joints == KINECT_V2_TO_CANONICAL and v.frame == "kinect_camera"
    np.testing.assert_allclose(v.position_m, pos)
    np.testing.assert_allclose(v.t_s, t)
    assert not v.available[3, v.index("elbow_l")] and not v.available[4, v.index("elbow_r")]
    assert v.available.sum() == 12 * 25 - 2
    # configurable rule: Inferred accepted
    rec1 = kio.load(f, min_tracking_state=1)
    assert rec1.vision.available[3, 5] and not rec1.vision.available[4, 9]
    np.testing.assert_array_equal(rec.metadata["tracking_state"], state)


def test_kinect_v2_textual_states_and_long_layout(tmp_path, skeleton):
    t, pos, state = skeleton
    f = tmp_path / "k.csv"
    _write_v2_wide(f, t, pos, state, textual=True)
    a = kio.read_kinect_v2_csv(f)
    g = tmp_path / "long.csv"
    rows = ["time_ms,body,joint,x,y,z,tracking_state"]
    for k in range(len(t)):
        for body in (7, 9):
            for j in range(25):
                p = pos[k, j] + (0 if body == 7 else 1.0)
                rows.append(
                    f"{t[k] * 1e3},{body},{KINECT_V2_JOINTS[j]},{p[0]},{p[1]},{p[2]},{state[k, j]}"
                )
    g.write_text("\n".join(rows) + "\n")
    assert kio.detect_format(g) == "kinect_v2"
    b = kio.read_kinect_v2_csv(g, body=7)
    np.testing.assert_allclose(b.vision.position_m, a.vision.position_m)
    np.testing.assert_array_equal(b.vision.available, a.vision.available)
    c = kio.read_kinect_v2_csv(g, body=9)
    np.testing.assert_allclose(c.vision.position_m, pos + 1.0)


def test_kinect_v2_errors(tmp_path, skeleton):
    t, pos, state = skeleton
    f = tmp_path / "k.csv"
    _write_v2_wide(f, t, pos, state)
    text = f.read_text()
    g = tmp_path / "unknown.csv"
    g.write_text(text.replace("ElbowLeft_X", "ElbwLeft_X", 1))
    with pytest.raises(FormatError, match="unknown joint 'ElbwLeft'") as e:
        kio.read_kinect_v2_csv(g)
    assert e.value.line == 1 and e.value.field == "ElbwLeft_X"
    h = tmp_path / "nostate.csv"
    h.write_text(text.replace("WristRight_TrackingState", "WristRight_Comment", 1))
    with pytest.raises(
        FormatError, match="missing column 'WristRight_TrackingState'.*min_tracking_state=None"
    ):
        kio.read_kinect_v2_csv(h)
    assert kio.read_kinect_v2_csv(h, min_tracking_state=None).vision.available.all()
    lines = text.splitlines()
    m = tmp_path / "nonmono.csv"
    m.write_text("\n".join([lines[0], lines[1], lines[3], lines[2], *lines[4:]]))
    with pytest.raises(
        FormatError, match="line 4, field 'time_s': expected strictly increasing time, found 0.0333"
    ):
        kio.read_kinect_v2_csv(m)
    s = tmp_path / "badstate.csv"
    s.write_text("\n".join([*lines[:2], lines[2].replace(",2,", ",Trackd,", 1), *lines[3:]]))
    with pytest.raises(FormatError, match="line 3.*expected a TrackingState"):
        kio.read_kinect_v2_csv(s)


# ------------------------------------------------------------------------------------------------
# Azure Kinect
# ------------------------------------------------------------------------------------------------
def _azure_doc(rng, T=6, with_conf=True):
    frames = []
    truth = rng.normal(0, 300, size=(T, 32, 3)) + [0, 0, 2500]
    conf = np.full((T, 32), 2)
    conf[2, 7] = 1
    for k in range(T):
        bodies = [
            {
                "body_id": 1,
                "joint_positions": truth[k].tolist(),
                "joint_orientations": [[1, 0, 0, 0]] * 32,
            }
        ]
        if with_conf:
            bodies[0]["joint_confidence_levels"] = conf[k].tolist()
        if k % 2 == 0:
            bodies.append({"body_id": 4, "joint_positions": (truth[k] + 500).tolist()})
        if k == 4:
            bodies = bodies[1:]  # body 1 lost in frame 4
        frames.append(
            {
                "timestamp_usec": 1_000_000 + 33_333 * k,
                "frame_id": k,
                "num_bodies": len(bodies),
                "bodies": bodies,
            }
        )
    return (
        {"k4abt_sdk_version": "1.1.2", "joint_names": list(AZURE_JOINTS), "frames": frames},
        truth,
        conf,
    )


def test_azure_kinect(tmp_path, rng):
    doc, truth, conf = _azure_doc(rng)
    f = tmp_path / "bt.json"
    f.write_text(json.dumps(doc))
    assert kio.detect_format(f) == "azure_kinect"
    rec = kio.load(f)
    v = rec.vision
    assert v.position_m.shape == (6, 32, 3) and rec.metadata["body_id"] == 1
    np.testing.assert_allclose(v.t_s, np.arange(6) * 0.033333)
    np.testing.assert_allclose(v.position_m[0], truth[0] * 1e-3)
    assert not v.available[4].any() and np.isnan(v.position_m[4]).all()
    assert not v.available[2, v.index("wrist_l")]
    assert v.available.sum() == 5 * 32 - 1
    assert kio.load(f, min_confidence=1).vision.available.sum() == 5 * 32
    assert kio.load(f, body_id=4).vision.available[[0, 2, 4]].all()
    # without confidence levels: body present and finite (noted)
    doc2, _, _ = _azure_doc(rng, with_conf=False)
    g = tmp_path / "noconf.json"
    g.write_text(json.dumps(doc2))
    r2 = kio.load(g)
    assert r2.vision.available.sum() == 5 * 32
    assert any("no joint confidence" in n for n in r2.metadata["notes"])


def test_azure_kinect_errors(tmp_path, rng):
    doc, _, _ = _azure_doc(rng)
    text = json.dumps(doc, indent=1)
    f = tmp_path / "trunc.json"
    f.write_text(text[: len(text) // 2])
    with pytest.raises(FormatError, match=r"trunc.json, line \d+: invalid JSON .*truncated file\?"):
        kio.read_azure_kinect_json(f)
    doc["frames"][3]["bodies"][0]["joint_positions"] = doc["frames"][3]["bodies"][0][
        "joint_positions"
    ][:31]
    g = tmp_path / "short.json"
    g.write_text(json.dumps(doc))
    with pytest.raises(
        FormatError, match=r"frame 3: expected joint_positions \(32, 3\), found \(31, 3\)"
    ):
        kio.read_azure_kinect_json(g)


# ------------------------------------------------------------------------------------------------
# MediaPipe
# ------------------------------------------------------------------------------------------------
def test_mediapipe_csv_and_json_agree(tmp_path, rng):
    T = 8
    xyz = rng.normal(0, 0.4, size=(T, 33, 3))
    vis = rng.uniform(0.6, 1.0, size=(T, 33))
    vis[2, 15] = 0.2  # left wrist barely visible
    hdr = ["timestamp_ms"] + [
        f"{n}_{w}" for n in MEDIAPIPE_LANDMARKS for w in ("x", "y", "z", "visibility")
    ]
    rows = [",".join(hdr)]
    frames = []
    for k in range(T):
        f = [repr(k * 40.0)]
        for j in range(33):
            f += [repr(float(v)) for v in xyz[k, j]] + [repr(float(vis[k, j]))]
        rows.append(",".join(f))
        lms = [
            {"x": xyz[k, j, 0], "y": xyz[k, j, 1], "z": xyz[k, j, 2], "visibility": vis[k, j]}
            for j in range(33)
        ]
        frames.append({"timestamp_ms": k * 40.0, "world_landmarks": lms if k != 5 else None})
    c = tmp_path / "pose.csv"
    c.write_text("\n".join(rows) + "\n")
    j = tmp_path / "pose.json"
    j.write_text(json.dumps({"frames": frames}))
    assert kio.detect_format(c) == "mediapipe" and kio.detect_format(j) == "mediapipe"
    a, b = kio.load(c), kio.load(j)
    np.testing.assert_allclose(a.vision.t_s, np.arange(T) * 0.04)
    np.testing.assert_allclose(a.vision.position_m, xyz)
    assert a.vision.joints[15] == "wrist_l" and a.vision.joints[0] == "nose"
    assert not a.vision.available[2, 15] and a.vision.available.sum() == T * 33 - 1
    assert not b.vision.available[5].any()  # no pose in frame 5
    np.testing.assert_array_equal(a.vision.available[[0, 1, 3]], b.vision.available[[0, 1, 3]])
    assert kio.load(c, min_visibility=0.1).vision.available.all()
    # errors
    bad = tmp_path / "bad.csv"
    bad.write_text(c.read_text().replace("left_wrist_y", "left_wrist_q", 1))
    with pytest.raises(FormatError, match="missing column 'left_wrist_y'"):
        kio.read_mediapipe(bad)
    img = tmp_path / "img.json"
    img.write_text(
        json.dumps({"frames": [{"timestamp_ms": 0, "landmarks": [[0.5, 0.5, 0.0]] * 33}]})
    )
    with pytest.raises(FormatError, match="normalised image 'landmarks' only"):
        kio.read_mediapipe(img)


# ------------------------------------------------------------------------------------------------
# C3D
# ------------------------------------------------------------------------------------------------
def _write_c3d(path, labels, pts_mm, rate=100.0, residual_bad=None):
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    T = pts_mm.shape[0]
    data = np.ones((4, len(labels), T))
    data[:3] = pts_mm.transpose(2, 1, 0)
    c["data"]["points"] = data
    if residual_bad is not None:
        res = np.zeros((1, len(labels), T))
        res[0, residual_bad[1], residual_bad[0]] = -1.0
        c["data"]["meta_points"]["residuals"] = res
    c.write(str(path))


def test_c3d(tmp_path, rng):
    labels = ["RELB", "elbow_r", "LFEO", "WristRight"]
    pts = rng.normal(0, 300, size=(20, 4, 3)) + [0, 0, 1000]
    pts[7, 0] = np.nan
    f = tmp_path / "trial.c3d"
    _write_c3d(f, labels, pts)
    rec = kio.load(f)
    r = rec.reference
    assert r.joints == ("RELB", "elbow_r", "knee_l", "wrist_r") and r.frame == "c3d_lab"
    assert rec.metadata["joint_map"]["LFEO"] == "knee_l"
    assert rec.metadata["units_converted"] == ["points mm -> m"]
    np.testing.assert_allclose(
        r.position_m[np.isfinite(r.position_m)], (pts * 1e-3)[np.isfinite(pts)], rtol=1e-6
    )
    assert not r.available[7, 0] and r.available.sum() == 20 * 4 - 1
    np.testing.assert_allclose(r.t_s, np.arange(20) / 100.0)
    assert kio.load(f, role="vision").vision is not None


def test_c3d_broken(tmp_path, rng):
    pytest.importorskip("ezc3d")
    f = tmp_path / "trial.c3d"
    _write_c3d(f, ["a", "b"], rng.normal(0, 100, size=(50, 2, 3)))
    t = tmp_path / "trunc.c3d"
    t.write_bytes(f.read_bytes()[:1700])
    with pytest.raises(FormatError, match="trunc.c3d, field 'data': truncated C3D"):
        kio.read_c3d(t)
    g = tmp_path / "garbage.c3d"
    g.write_bytes(b"this is not a c3d file at all" * 30)
    with pytest.raises(FormatError, match="expected a C3D header"):
        kio.load(g)


# ------------------------------------------------------------------------------------------------
# TRC
# ------------------------------------------------------------------------------------------------
_TRC = (
    "PathFileType\t4\t(X/Y/Z)\twalk.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "60.00\t60.00\t3\t2\tmm\t60.00\t1\t3\n"
    "Frame#\tTime\tRKnee\t\t\tR.ASIS\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
    "1\t0.000\t100.0\t500.0\t20.0\t110.0\t950.0\t25.0\n"
    "2\t0.017\t101.0\t501.0\t21.0\t\t\t\n"
    "3\t0.033\t102.0\t502.0\t22.0\t112.0\t952.0\t27.0\n"
)


def test_trc_read_hand_written(tmp_path):
    f = tmp_path / "walk.trc"
    f.write_text(_TRC)
    rec = kio.load(f)
    r = rec.reference
    assert r.joints == ("knee_r", "R.ASIS") and rec.metadata["units_converted"] == [
        "positions mm -> m"
    ]
    assert rec.metadata["joint_map"] == {"RKnee": "knee_r", "R.ASIS": "R.ASIS"}
    assert kio.read_trc(f, map_names=False).reference.joints == ("RKnee", "R.ASIS")
    np.testing.assert_allclose(r.position_m[0], [[0.1, 0.5, 0.02], [0.11, 0.95, 0.025]])
    np.testing.assert_allclose(r.t_s, [0, 0.017, 0.033])
    assert r.available.tolist() == [[True, True], [True, False], [True, True]]


def test_trc_broken(tmp_path):
    f = tmp_path / "t.trc"
    f.write_text(_TRC.rsplit("\n", 2)[0] + "\n")  # last frame missing: read, as OpenSim does
    with pytest.warns(FormatWarning, match=r"NumFrames = 3 but the file has 2 data rows"):
        assert len(kio.read_trc(f).reference) == 2
    f.write_text(_TRC[:-12])  # a truncated last line is still an error
    with pytest.raises(FormatError, match=r"line 9: expected 8 fields"):
        kio.read_trc(f)
    f.write_text(_TRC.replace("mm\t60.00", "furlong\t60.00"))
    with pytest.raises(FormatError, match="line 3, field 'Units': expected Units one of"):
        kio.read_trc(f)
    f.write_text(_TRC.replace("102.0\t502.0", "102.0\tabc"))
    with pytest.raises(
        FormatError, match=r"line 9, field 'RKnee.Y': expected a number, found 'abc'"
    ):
        kio.read_trc(f)
    f.write_text(_TRC.replace("3\t0.033", "3\t0.010"))
    with pytest.raises(
        FormatError, match="line 9, field 'Time': expected strictly increasing time"
    ):
        kio.read_trc(f)


def _stream(rng, T=25, joints=("elbow_r", "wrist_r", "knee_l")):
    p = rng.normal(0, 0.5, size=(T, len(joints), 3))
    avail = np.ones((T, len(joints)), dtype=bool)
    avail[4, 1] = False
    avail[10:13, 0] = False
    return JointStream(
        t_s=np.arange(T) / 30.0 + 1.5, position_m=p, available=avail, joints=joints, frame="ENU"
    )


@pytest.mark.parametrize("units", ["m", "mm"])
def test_trc_round_trip_and_overwrite(tmp_path, rng, units):
    js = _stream(rng)
    f = tmp_path / "out.trc"
    kio.write_trc(f, js, units=units)
    back = kio.read_trc(f).reference
    assert back.joints == js.joints
    np.testing.assert_array_equal(back.available, js.available)
    np.testing.assert_allclose(back.t_s, js.t_s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        back.position(masked=True, joint="wrist_r"),
        js.position("wrist_r"),
        atol=1e-6,
        equal_nan=True,
    )
    np.testing.assert_allclose(
        np.where(js.available[..., None], back.position_m, 0),
        np.where(js.available[..., None], js.position_m, 0),
        atol=1e-6,
    )
    before = f.read_bytes()
    with pytest.raises(FileExistsError, match=r"out.trc: file exists.*force=True"):
        kio.write_trc(f, js)
    assert f.read_bytes() == before
    kio.write_trc(f, js, force=True)


# ------------------------------------------------------------------------------------------------
# generic CSV
# ------------------------------------------------------------------------------------------------
def test_joint_csv_round_trip_with_extras(tmp_path, rng):
    js = _stream(rng)
    T, J = len(js), 3
    extras = {
        "source": rng.integers(0, 4, size=(T, J)),
        "mode": rng.integers(0, 4, size=(T, J)),
        "std_m": rng.uniform(0.001, 0.05, size=(T, J, 3)),
        "nis": rng.uniform(0, 9, size=T),
        "branch": np.array(["KF", "FIR", "EM-KF"] * 9)[:T],
    }
    f = tmp_path / "fused.csv"
    kio.write_joint_csv(
        f, js, extra_columns=extras, metadata={"subject": "S02", "pipeline": "vision_assisted"}
    )
    assert kio.detect_format(f) == "joint_csv"
    rec = kio.load(f)
    back = rec.vision
    assert back.joints == js.joints and back.frame == "ENU" and rec.metadata["subject"] == "S02"
    np.testing.assert_array_equal(back.available, js.available)
    np.testing.assert_allclose(back.position_m, js.position_m, atol=1e-6)
    np.testing.assert_allclose(back.t_s, js.t_s, rtol=0, atol=0)
    ex = rec.metadata["extra_columns"]
    assert set(ex) == set(extras)
    np.testing.assert_array_equal(ex["source"], extras["source"])
    np.testing.assert_array_equal(ex["mode"], extras["mode"])
    np.testing.assert_allclose(ex["std_m"], extras["std_m"], atol=1e-6)
    np.testing.assert_allclose(ex["nis"], extras["nis"], atol=1e-6)
    np.testing.assert_array_equal(ex["branch"], extras["branch"])
    with pytest.raises(ValueError, match="reserved"):
        kio.write_joint_csv(tmp_path / "y.csv", js, extra_columns={"offset_x": np.zeros(T)})
    with pytest.raises(FileExistsError, match="fused.csv: file exists; refusing to overwrite it"):
        kio.write_joint_csv(f, js)
    with pytest.raises(ValueError, match=r"extra column 'bad': expected shape \(25,\)"):
        kio.write_joint_csv(tmp_path / "x.csv", js, extra_columns={"bad": np.zeros((3, 3))})
    assert not (tmp_path / "x.csv").exists()


def test_joint_csv_without_header_comments_and_errors(tmp_path):
    f = tmp_path / "plain.csv"
    f.write_text("t_s,elbow_r_x,elbow_r_y,elbow_r_z\n0,0.1,0.2,0.3\n0.1,0.1,,0.3\n")
    rec = kio.load(f)
    assert rec.vision.available.tolist() == [[True], [False]]
    g = tmp_path / "partial.csv"
    g.write_text("t_s,elbow_r_x,elbow_r_y\n0,0.1,0.2\n")
    with pytest.raises(FormatError, match="missing column 'elbow_r_z'"):
        kio.read_joint_csv(g)
    h = tmp_path / "notime.csv"
    h.write_text("elbow_r_x,elbow_r_y,elbow_r_z\n0.1,0.2,0.3\n")
    with pytest.raises(FormatError, match="missing time column"):
        kio.read_joint_csv(h)


def test_imu_csv_round_trip(tmp_path, shared_data):
    rec = kio.load(shared_data / "xio_imu_mocap_lower_body")
    f = tmp_path / "imu.csv"
    kio.write_imu_csv(f, rec)
    assert kio.detect_format(f) == "imu_csv"
    back = kio.load(f)
    assert list(back.imu) == list(rec.imu)
    for k, s in rec.imu.items():
        b = back.imu[k]
        np.testing.assert_allclose(b.t_s, s.t_s, rtol=0, atol=0)
        for name in ("q_world_from_sensor", "acc_m_s2", "gyr_rad_s", "mag"):
            np.testing.assert_allclose(
                getattr(b, name), getattr(s, name), rtol=1e-8, atol=1e-12, equal_nan=True
            )
    with pytest.raises(FileExistsError):
        kio.write_imu_csv(f, rec)


def test_unit_warnings(tmp_path):
    f = tmp_path / "imu_g.csv"
    rows = ["t_s,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z"] + [
        f"{k * 0.01},0.01,0.02,1.0,0,0,0.01" for k in range(20)
    ]
    f.write_text("\n".join(rows) + "\n")
    with pytest.warns(UnitWarning, match="looks like g"):
        kio.load(f)
    g = tmp_path / "imu_g_declared.csv"
    g.write_text("# acc_unit: g\n" + f.read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = kio.load(g)
    assert np.linalg.norm(r.imu["imu"].acc_m_s2[0]) == pytest.approx(9.8067, abs=0.01)
    assert r.metadata["units_converted"] == ["acc g -> m/s^2"]
    h = tmp_path / "mm.csv"
    h.write_text(
        "t_s,elbow_r_x,elbow_r_y,elbow_r_z,wrist_r_x,wrist_r_y,wrist_r_z\n0,0,0,0,250,0,0\n0.1,0,0,0,0,250,0\n"
    )
    with pytest.warns(UnitWarning, match="looks like millimetres"):
        kio.load(h)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = kio.load(h, units="mm")
    assert r.vision.position_m[0, 1, 0] == pytest.approx(0.25)


def test_imu_csv_errors(tmp_path):
    f = tmp_path / "a.csv"
    f.write_text("t_s,sensor,qw,qx,qy\n0,a,1,0,0\n")
    with pytest.raises(FormatError, match="missing column 'qz'"):
        kio.read_imu_csv(f)
    f.write_text("t_s,sensor,acc_x,acc_y,acc_z\n0,a,0,0,9.8\n0.01,a,0,0,9.8\n")
    with pytest.raises(FormatError, match="sensor 'a'.*expected an orientation"):
        kio.read_imu_csv(f)
    f.write_text(
        "t_s,sensor,qw,qx,qy,qz\n0,a,1,0,0,0\n0,b,1,0,0,0\n0.01,a,1,0,0,0\n0.005,a,1,0,0,0\n"
    )
    with pytest.raises(FormatError, match="line 5, field 't_s': expected strictly increasing time"):
        kio.read_imu_csv(f)
