"""Readers on the real files of ../shared/data, checked against independent loads and physics."""

from __future__ import annotations

import importlib
import shutil

import numpy as np
import pytest
import scipy.io
from scipy.spatial.transform import Rotation

import kinefuse.io as kio
from kinefuse.conventions import GRAVITY_M_S2 as G
from kinefuse.exceptions import FormatError

DEG = np.pi / 180


def _rest_norm(acc, gyr, thr=0.3):
    """|acc| over samples with low angular rate (quasi-static)."""
    still = np.linalg.norm(gyr, axis=1) < thr
    return np.linalg.norm(acc[still], axis=1)


# ------------------------------------------------------------------------------------------------
# UTD-MHAD
# ------------------------------------------------------------------------------------------------
def test_utd_mhad_wrist_trial(shared_data):
    f = shared_data / "utd_mhad" / "Inertial" / "a3_s1_t1_inertial.mat"
    rec = kio.load(f)
    x = scipy.io.loadmat(f)["d_iner"]
    s = scipy.io.loadmat(shared_data / "utd_mhad" / "Skeleton" / "a3_s1_t1_skeleton.mat")["d_skel"]
    assert rec.metadata["format"] == "utd_mhad"
    assert rec.metadata["subject"] == "s1" and rec.metadata["action"] == 3
    assert set(rec.metadata["units_converted"]) == {"acc g -> m/s^2", "gyr deg/s -> rad/s"}
    imu = rec.imu["forearm_r"]
    assert imu.acc_m_s2.shape == (184, 3) and imu.q_world_from_sensor is None
    np.testing.assert_allclose(imu.acc_m_s2, x[:, :3] * G)
    np.testing.assert_allclose(imu.gyr_rad_s, x[:, 3:] * DEG)
    assert imu.rate_hz == pytest.approx(50.0)
    # physics: gravity magnitude while nearly still
    rest = _rest_norm(imu.acc_m_s2, imu.gyr_rad_s)
    assert rest.size >= 3 and np.median(rest) == pytest.approx(G, abs=0.8)
    assert np.median(np.linalg.norm(imu.acc_m_s2, axis=1)) == pytest.approx(G, abs=1.2)
    v = rec.vision
    assert v.position_m.shape == (72, 20, 3) and v.frame == "kinect_v1_camera"
    np.testing.assert_allclose(v.position("elbow_r"), s[9].T)
    np.testing.assert_allclose(v.position("head")[0], s[0, :, 0])
    assert v.available.all()  # SOURCE.md: no all-zero joints in this data
    # stretched over the inertial duration
    assert v.t_s[0] == 0.0 and v.t_s[-1] == pytest.approx(imu.t_s[-1])
    # bone lengths plausible (m)
    forearm = np.linalg.norm(v.position("elbow_r") - v.position("wrist_r"), axis=1)
    upper = np.linalg.norm(v.position("shoulder_r") - v.position("elbow_r"), axis=1)
    assert 0.18 < np.median(forearm) < 0.32 and 0.2 < np.median(upper) < 0.4
    # the subject faces the camera: right shoulder at +x (x toward the sensor's left)
    assert np.median(v.position("shoulder_r")[:, 0] - v.position("shoulder_l")[:, 0]) > 0.2


def test_utd_mhad_thigh_from_skeleton_file_and_pair(shared_data):
    skel = shared_data / "utd_mhad" / "Skeleton" / "a23_s2_t1_skeleton.mat"
    iner = shared_data / "utd_mhad" / "Inertial" / "a23_s2_t1_inertial.mat"
    rec = kio.load(skel)  # partner found by name
    assert list(rec.imu) == ["thigh_r"]
    rec2 = kio.load((skel, iner))  # a pair in either order
    np.testing.assert_array_equal(rec.imu["thigh_r"].acc_m_s2, rec2.imu["thigh_r"].acc_m_s2)
    np.testing.assert_array_equal(rec.vision.position_m, rec2.vision.position_m)


def test_utd_mhad_broken_files(shared_data, tmp_path):
    src = shared_data / "utd_mhad" / "Inertial" / "a3_s1_t1_inertial.mat"
    trunc = tmp_path / "a3_s1_t1_inertial.mat"
    trunc.write_bytes(src.read_bytes()[:150])
    with pytest.raises(FormatError, match="a3_s1_t1_inertial.mat"):
        kio.read_utd_mhad(trunc)
    wrong = tmp_path / "a4_s1_t1_inertial.mat"
    scipy.io.savemat(wrong, {"d_iner": np.zeros((10, 5))})
    with pytest.raises(
        FormatError, match=r"expected d_iner with shape \(N>=2, 6\), found \(10, 5\)"
    ):
        kio.read_utd_mhad(wrong)
    missing = tmp_path / "a5_s1_t1_inertial.mat"
    scipy.io.savemat(missing, {"acc": np.zeros((10, 6))})
    with pytest.raises(FormatError, match="missing variable 'd_iner'") as e:
        kio.read_utd_mhad(missing)
    assert e.value.field == "d_iner"


def test_utd_mhad_zero_joint_unavailable(shared_data, tmp_path):
    s = scipy.io.loadmat(shared_data / "utd_mhad" / "Skeleton" / "a3_s1_t1_skeleton.mat")[
        "d_skel"
    ].copy()
    s[10, :, 5] = 0.0  # wrist_r lost in frame 5 (Kinect v1 exports zeros)
    f = tmp_path / "a3_s1_t1_skeleton.mat"
    scipy.io.savemat(f, {"d_skel": s})
    with pytest.warns(UserWarning, match="inertial partner file not found"):
        rec = kio.load(f)
    assert not rec.vision.available[5, rec.vision.index("wrist_r")]
    assert rec.vision.available.sum() == 72 * 20 - 1
    assert rec.imu == {}


# ------------------------------------------------------------------------------------------------
# OpenSense / Xsens
# ------------------------------------------------------------------------------------------------
def _xsens_independent(fn):
    lines = open(fn).read().split("\n")
    nh = sum(ln.startswith("//") for ln in lines)
    cols = lines[nh].split("\t")
    data = np.array(
        [
            [float(v) if v else np.nan for v in ln.split("\t")]
            for ln in lines[nh + 1 :]
            if ln.strip()
        ]
    )
    acc = data[:, cols.index("Acc_X") : cols.index("Acc_X") + 3]
    R = (
        data[:, cols.index("Mat[1][1]") : cols.index("Mat[1][1]") + 9]
        .reshape(-1, 3, 3)
        .transpose(0, 2, 1)
    )
    return data[:, 0], acc, R


def test_opensense_folder(shared_data):
    folder = shared_data / "opensense_example_imu"
    rec = kio.load(folder)
    assert rec.metadata["format"] == "opensense"
    assert set(rec.imu) == {
        "chest",
        "pelvis",
        "thigh_l",
        "thigh_r",
        "shank_l",
        "shank_r",
        "foot_l",
        "foot_r",
    }
    s = rec.imu["thigh_r"]
    counter, acc, R = _xsens_independent(folder / "MT_012005D6_009-001_00B4227C.txt")
    assert s.name == "00B4227C" and len(s) == 2474 and s.rate_hz == pytest.approx(100.0)
    np.testing.assert_allclose(s.acc_m_s2, acc)
    Rq = Rotation.from_quat(s.q_world_from_sensor, scalar_first=True).as_matrix()
    np.testing.assert_allclose(Rq, R, atol=5e-6)
    # aligned by packet counter: t = (counter - c0) / 100 with c0 the earliest first counter
    c0 = rec.metadata["packet_counter_origin"]
    np.testing.assert_allclose(s.t_s, (counter - c0) / 100.0)
    assert min(x.t_s[0] for x in rec.imu.values()) == 0.0
    # physics: the world-frame specific force is +g along z on average
    f_world = np.einsum("nij,nj->ni", Rq, s.acc_m_s2)
    np.testing.assert_allclose(np.median(f_world, axis=0), [0, 0, G], atol=0.35)


def test_opensense_broken(shared_data, tmp_path):
    src = shared_data / "opensense_example_imu" / "MT_012005D6_009-001_00B4227C.txt"
    lines = src.read_text().split("\n")
    # missing column: drop Acc_Y from header and rows
    hdr = 5
    i = lines[hdr].split("\t").index("Acc_Y")
    bad = [
        "\t".join(f for k, f in enumerate(ln.split("\t")) if k != i) if n >= hdr and ln else ln
        for n, ln in enumerate(lines)
    ]
    f1 = tmp_path / "MT_x_00B4227C.txt"
    f1.write_text("\n".join(bad))
    with pytest.raises(FormatError, match="missing column 'Acc_Y'") as e:
        kio.read_opensense(f1)
    assert e.value.field == "Acc_Y" and e.value.line == 6
    # truncated: last line cut in the middle
    f2 = tmp_path / "MT_y_00B4227C.txt"
    f2.write_text("\n".join(lines[:40]) + "\n" + lines[40][:30])
    with pytest.raises(
        FormatError,
        match=r"line 41: expected 26 fields as in the header, found \d+ \(truncated line\?\)",
    ):
        kio.read_opensense(f2)
    # non-monotonic packet counter
    swapped = lines[:20] + [lines[21], lines[20]] + lines[22:]
    f3 = tmp_path / "MT_z_00B4227C.txt"
    f3.write_text("\n".join(swapped))
    with pytest.raises(FormatError, match="strictly increasing") as e:
        kio.read_opensense(f3)
    assert e.value.line == 22 and e.value.field == "PacketCounter"
    # wrong type
    f4 = tmp_path / "MT_w_00B4227C.txt"
    f4.write_text("\n".join(lines[:30] + [lines[30].replace("\t9.", "\tx9.", 1)] + lines[31:]))
    with pytest.raises(FormatError, match="line 31, field 'Acc_X': expected a number, found 'x9"):
        kio.read_opensense(f4)


# ------------------------------------------------------------------------------------------------
# qmt
# ------------------------------------------------------------------------------------------------
def test_qmt(shared_data, tmp_path):
    f = shared_data / "qmt_full_body_example" / "full_body_example_data.mat"
    rec = kio.load(f)
    d = scipy.io.loadmat(f, squeeze_me=True, struct_as_record=False)
    assert rec.metadata["format"] == "qmt" and len(rec.imu) == 16
    for seg, name in [
        ("upper_arm_r", "upper_arm_right"),
        ("forearm_l", "forearm_left"),
        ("thigh_l", "upper_leg_left"),
        ("shank_r", "lower_leg_right"),
        ("pelvis", "hip"),
        ("chest", "upper_back"),
        ("hand_l", "hand_left"),  # a segment since hand IMUs locate the wrists (functional)
    ]:
        assert rec.metadata["segment_map"][name] == seg
        np.testing.assert_array_equal(rec.imu[seg].acc_m_s2, d[name].acc)
        np.testing.assert_array_equal(rec.imu[seg].gyr_rad_s, d[name].gyr)
    assert "head" in rec.imu and "lower_back" in rec.imu  # unknown sensors keep their names
    s = rec.imu["forearm_r"]
    assert (
        s.t_s[0] == pytest.approx(40.0)
        and s.rate_hz == pytest.approx(100.0)
        and s.q_world_from_sensor is None
    )
    assert np.median(_rest_norm(s.acc_m_s2, s.gyr_rad_s)) == pytest.approx(G, abs=0.5)
    # broken: a struct without gyr
    bad = tmp_path / "bad.mat"
    scipy.io.savemat(bad, {"t": np.arange(5.0), "arm": {"acc": np.zeros((5, 3))}})
    with pytest.raises(FormatError, match="struct 'arm': missing field 'gyr'"):
        kio.read_qmt(bad)


# ------------------------------------------------------------------------------------------------
# x-IMU3
# ------------------------------------------------------------------------------------------------
def test_ximu3(shared_data):
    root = shared_data / "xio_imu_mocap_lower_body"
    rec = kio.load(root)
    assert rec.metadata["format"] == "ximu3"
    assert set(rec.imu) == {
        "pelvis",
        "thigh_l",
        "thigh_r",
        "shank_l",
        "shank_r",
        "foot_l",
        "foot_r",
    }
    assert "quaternion earth frame NWU -> ENU" in rec.metadata["units_converted"]
    a = np.genfromtxt(
        root / "Right_Upper_Leg_64F61C2E" / "Inertial.csv", delimiter=",", skip_header=1
    )
    s = rec.imu["thigh_r"]
    np.testing.assert_allclose(s.gyr_rad_s, a[:, 1:4] * DEG)
    np.testing.assert_allclose(s.acc_m_s2, a[:, 4:7] * G)
    np.testing.assert_allclose(s.t_s, (a[:, 0] - rec.metadata["t0_us"]) * 1e-6, atol=1e-9)
    assert s.rate_hz == pytest.approx(50.0, abs=0.3)
    for seg, st in rec.imu.items():
        R = Rotation.from_quat(st.q_world_from_sensor, scalar_first=True)
        np.testing.assert_allclose(np.linalg.norm(st.q_world_from_sensor, axis=1), 1.0, atol=1e-9)
        f_world = np.median(R.apply(st.acc_m_s2), axis=0)
        np.testing.assert_allclose(f_world, [0, 0, G], atol=0.3, err_msg=seg)
        # ENU check: the horizontal magnetic field points north (+y), not east
        ok = np.all(np.isfinite(st.mag), axis=1)
        assert ok.mean() > 0.9  # the magnetometer log has dropped packets (gaps of ~2 intervals)
        m = R[ok].apply(st.mag[ok])
        mx, my = np.median(m[:, 0]), np.median(m[:, 1])
        assert my > 0.2 and abs(mx) < 0.5 * my, (seg, mx, my)


def test_ximu3_broken(shared_data, tmp_path):
    src = shared_data / "xio_imu_mocap_lower_body" / "pelvis_64F0EDBF"
    dst = tmp_path / "pelvis_1234ABCD"
    shutil.copytree(src, dst)
    text = (dst / "Inertial.csv").read_text().splitlines()
    (dst / "Inertial.csv").write_text("\n".join(text[:10] + [text[10][:20]]))
    with pytest.raises(FormatError, match=r"Inertial.csv, line 11: expected 7 fields"):
        kio.load(dst)
    hdr = text[0].replace("Accelerometer X (g)", "Accelerometer X (furlong)")
    (dst / "Inertial.csv").write_text("\n".join([hdr, *text[1:]]))
    with pytest.raises(FormatError, match="expected one unit for Accelerometer X/Y/Z"):
        kio.load(dst)
    (dst / "Inertial.csv").write_text(
        "\n".join([text[0].replace("Gyroscope Y", "Gyro Y"), *text[1:]])
    )
    with pytest.raises(FormatError, match=r"missing column 'Gyroscope Y \(\.\.\.\)'"):
        kio.load(dst)


# ------------------------------------------------------------------------------------------------
# BROAD
# ------------------------------------------------------------------------------------------------
def test_broad(shared_data, tmp_path):
    f = shared_data / "broad" / "data_mat" / "01_undisturbed_slow_rotation_A.mat"
    rec = kio.load(f)
    d = scipy.io.loadmat(f, squeeze_me=True)
    s = rec.imu["imu"]
    assert len(s) == 56940 and s.rate_hz == pytest.approx(285.714, abs=1e-3)
    np.testing.assert_array_equal(s.gyr_rad_s, d["imu_gyr"])
    np.testing.assert_array_equal(s.mag, d["imu_mag"])
    ref = rec.reference_orientation["imu"]
    np.testing.assert_array_equal(ref.q_world_from_sensor, d["opt_quat"])
    assert rec.metadata["optical_valid_fraction"] == pytest.approx(0.997, abs=0.002)
    assert rec.reference.position_m.shape == (56940, 1, 3)
    assert rec.metadata["movement"].dtype == bool
    assert np.median(_rest_norm(s.acc_m_s2, s.gyr_rad_s, 0.05)) == pytest.approx(G, abs=0.2)
    # physics: the optical body-frame angular rate matches the gyro (first 60 s)
    n = int(60 * 285.714)
    q = ref.q_world_from_sensor[:n]
    ok = np.all(np.isfinite(q[:-1]), axis=1) & np.all(np.isfinite(q[1:]), axis=1)
    r = Rotation.from_quat(q[:-1][ok], scalar_first=True)
    r1 = Rotation.from_quat(q[1:][ok], scalar_first=True)
    w_opt = (r.inv() * r1).as_rotvec() * 285.714
    g = 0.5 * (s.gyr_rad_s[: n - 1] + s.gyr_rad_s[1:n])[ok]
    for k in range(3):
        assert np.corrcoef(w_opt[:, k], g[:, k])[0, 1] > 0.9
    bad = tmp_path / "bad.mat"
    scipy.io.savemat(bad, {"imu_gyr": np.zeros((4, 3)), "imu_acc": np.zeros((4, 3))})
    with pytest.raises(FormatError, match="missing variable 'imu_mag'"):
        kio.read_broad(bad)


# ------------------------------------------------------------------------------------------------
# other engineers' readers through load()
# ------------------------------------------------------------------------------------------------
def test_load_dispatches_to_neura(shared_data):
    importlib.import_module("kinefuse.io.neura")  # fails, never skips, if it is broken
    folder = shared_data / "neura_sparse_sample"
    assert kio.detect_format(folder) == "neura"
    rec = kio.load(folder)
    assert rec.reference is not None and "pelvis" in rec.imu


def test_load_dispatches_to_cmu_and_bvh(shared_data):
    for mod in ("kinefuse.io.cmu", "kinefuse.io.bvh"):  # fail, never skip, if broken
        importlib.import_module(mod)
    amc = shared_data / "cmu_mocap" / "asfamc" / "02" / "02_01.amc"
    bvh = shared_data / "cmu_mocap" / "bvh_131_scaled" / "scaled_131_01.bvh"
    assert kio.detect_format(amc) == "cmu" and kio.detect_format(bvh) == "bvh"
    assert isinstance(kio.load(amc), kio.Recording)
    assert isinstance(kio.load(bvh), kio.Recording)


def test_utd_mhad_pair_of_two_trials_is_refused(shared_data):
    """The inertial file of one trial with the skeleton of another was read as one recording."""
    d = shared_data / "utd_mhad"
    with pytest.raises(FormatError, match="is the skeleton of trial a10_s1_t2, given with the"):
        kio.load(
            (d / "Inertial" / "a10_s1_t1_inertial.mat", d / "Skeleton" / "a10_s1_t2_skeleton.mat")
        )
