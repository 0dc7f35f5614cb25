"""Formats added for issue 13: OpenSim tables, OpenSense .sto, Xsens MVNX, Movella DOT, x-io CSV.

Every third-party file of these formats in ``../shared/data/third_party`` (see its SOURCE.md) is
read and checked against values the file itself states (header rates, timestamps, counters,
segment geometry) or physics (unit quaternions, gravity, orientation rate = gyro); OpenSim's own
``STOFileAdapter`` (the ``opensim`` package, optional) is the oracle for ``.mot``/``.sto``.
"""

from __future__ import annotations

import re
import shutil
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import kinefuse.io as kio
from kinefuse.exceptions import FormatError, FormatWarning, InputError, UnitWarning
from kinefuse.io.opensim import read_opensim_table, write_opensense_sto
from kinefuse.io.recording import ImuStream, Recording

try:
    import opensim
except ImportError:  # optional test dependency ([test] extra)
    opensim = None

needs_opensim = pytest.mark.skipif(
    opensim is None,
    reason="OpenSim's STOFileAdapter is the oracle here: pip install opensim (in the [test] extra)",
)


@pytest.fixture(scope="module")
def tp(shared_data):
    return shared_data / "third_party"


def _rows_after_header(path, first_field: str) -> list[list[str]]:
    """Data rows of a DOT/x-io CSV, read with plain ``str.split`` (independent of the reader)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith(first_field))
    return [ln.split(",") for ln in lines[k + 1 :] if ln.strip()]


# ------------------------------------------------------------------------------------------------
# OpenSim .mot / .sto tables
# ------------------------------------------------------------------------------------------------
def test_ik_mot_content(tp):
    f = tp / "opensim" / "opensim_subject01_walk_IK.mot"
    assert kio.detect_format(f) == "opensim_table"
    rec = kio.load(f)
    tab = rec.metadata["table"]
    assert rec.imu == {} and len(tab) == 151  # nRows=151 in the header
    assert tab.columns[:3] == ("pelvis_tilt", "pelvis_tx", "pelvis_ty")
    assert len(tab.columns) + 1 == 11  # nColumns=11 counts time
    assert tab.in_degrees is True and tab.description[0] == "Coordinates"
    units = rec.metadata["units"]
    assert units["pelvis_tx"] == units["pelvis_ty"] == "m" and units["knee_angle_r"] == "deg"
    np.testing.assert_allclose(tab.t_s[[0, -1]], [0.0, 2.5], atol=1e-8)  # 150 steps at 60 Hz
    np.testing.assert_allclose(np.diff(tab.t_s), 1 / 60, atol=1e-8)
    # first data row, as printed in the file
    np.testing.assert_allclose(tab.values[0, :3], [10.32995988, 0.61213494, 1.01790250])
    knee = tab.column("knee_angle_r")
    assert -90 < knee.min() < -40 and knee.max() < 10  # a gait knee flexion curve, degrees
    si = tab.si_values()
    np.testing.assert_allclose(si[:, 4], np.deg2rad(knee))
    np.testing.assert_array_equal(si[:, 1], tab.column("pelvis_tx"))  # metres untouched


@needs_opensim
def test_ik_mot_matches_opensim_adapter(tp):
    f = tp / "opensim" / "opensim_subject01_walk_IK.mot"
    ours = read_opensim_table(f)
    theirs = opensim.TimeSeriesTable(str(f))
    assert tuple(theirs.getColumnLabels()) == ours.columns
    np.testing.assert_allclose(np.asarray(theirs.getIndependentColumn()), ours.t_s, atol=1e-12)
    matrix = theirs.getMatrix()
    np.testing.assert_allclose(matrix.to_numpy(), ours.values, atol=1e-12)
    assert theirs.getTableMetaDataAsString("inDegrees") == ours.header["inDegrees"]


def test_opensim_table_errors(tmp_path):
    f = tmp_path / "a.mot"
    f.write_text("Coordinates\nversion=1\ntime\tknee\n0\t1\n")
    with pytest.raises(FormatError, match=r"a.mot: expected an OpenSim table header ending"):
        read_opensim_table(f)
    f.write_text("nRows=3\nendheader\ntime\tknee\n0\t1\n0.1\tx\n")
    with pytest.raises(FormatError, match=r"a.mot, line 5, field 'knee': expected a number"):
        read_opensim_table(f)
    f.write_text("nRows=3\nendheader\ntime\tknee\n0\t1\n0.1\t2\n")
    with pytest.warns(FormatWarning, match="nRows=3, the table has 2"):
        assert len(read_opensim_table(f)) == 2
    f.write_text("DataType=Mat33\nendheader\ntime\tR\n0\t1\n")
    with pytest.raises(FormatError, match="unsupported DataType 'Mat33'"):
        read_opensim_table(f)
    f.write_text("endheader\ntime\tknee\n0\t1\n0\t2\n")
    with pytest.raises(FormatError, match="strictly increasing time"):
        read_opensim_table(f)


# ------------------------------------------------------------------------------------------------
# OpenSense orientation .sto: read, write, OpenSim reads what we write
# ------------------------------------------------------------------------------------------------
def test_opensense_sto_content(tp):
    f = tp / "xsens" / "opensense_walking_orientations.sto"
    assert kio.detect_format(f) == "opensense_sto"
    rec = kio.load(f)
    assert set(rec.imu) == {"chest", "pelvis", "thigh_l", "thigh_r", "shank_l", "shank_r"} | {
        "foot_l",
        "foot_r",
    }
    assert rec.metadata["segment_map"]["calcn_r_imu"] == "foot_r"
    assert rec.metadata["rate_hz"] == 100.0  # DataRate=100.000000
    for s in rec.imu.values():
        assert len(s) == 2432 and s.t_s[-1] == pytest.approx(24.31)
        assert s.rate_hz == pytest.approx(100.0)
        np.testing.assert_allclose(np.linalg.norm(s.q_world_from_sensor, axis=1), 1.0, atol=1e-6)
    # first value of the file (torso_imu at t = 0)
    np.testing.assert_allclose(
        rec.imu["chest"].q_world_from_sensor[0],
        [0.5105588968224414, 0.4570645371936038, -0.6688411554744984, 0.2882240976375608],
    )


def _opensim_quaternions(path):
    table = opensim.TimeSeriesTableQuaternion(str(path))
    flat_table = table.flatten()  # keep the table alive while its matrix is copied (SWIG views)
    matrix = flat_table.getMatrix()
    flat = np.array(matrix.to_numpy(), copy=True)
    return table, np.asarray(table.getIndependentColumn()), flat.reshape(flat.shape[0], -1, 4)


@needs_opensim
def test_opensense_sto_matches_opensim_adapter(tp):
    f = tp / "xsens" / "opensense_walking_orientations.sto"
    rec = kio.load(f)
    table, t, q = _opensim_quaternions(f)
    assert tuple(table.getColumnLabels()) == rec.metadata["table"].columns
    np.testing.assert_allclose(t, rec.imu["chest"].t_s, atol=1e-12)
    np.testing.assert_allclose(q, rec.metadata["table"].values, atol=1e-12)


@needs_opensim
def test_write_opensense_sto_read_back_by_opensim(tp, tmp_path):
    rec = kio.load(tp / "xsens" / "opensense_walking_orientations.sto")
    out = write_opensense_sto(tmp_path / "walk_orientations.sto", rec)
    table, t, q = _opensim_quaternions(out)
    assert table.getTableMetaDataAsString("DataRate") == "100.000000"  # header rate kept
    assert list(table.getColumnLabels()) == [
        "torso_imu",
        "pelvis_imu",
        "tibia_r_imu",
        "femur_r_imu",
        "tibia_l_imu",
        "femur_l_imu",
        "calcn_r_imu",
        "calcn_l_imu",
    ]
    np.testing.assert_allclose(t, rec.imu["chest"].t_s, atol=1e-6)
    expected = np.stack([s.q_world_from_sensor for s in rec.imu.values()], axis=1)
    np.testing.assert_allclose(q, expected, atol=1e-6)
    again = kio.load(out)
    assert again.metadata["rate_hz"] == 100.0 and set(again.imu) == set(rec.imu)


@needs_opensim
@pytest.mark.parametrize("in_degrees", [True, False])
def test_write_mot_read_back_by_opensim(tmp_path, rng, in_degrees):
    # issue 13: write -> OpenSim read -> compare for .mot (kinefuse's joint angles)
    from kinefuse.io import write_mot

    t = 0.5 + np.arange(40) / 120.0
    cols = {
        "elbow_r_flexion_deg": 150.0 * rng.random(40) - 10.0,
        "elbow_r_adduction_deg": rng.normal(0.0, 5.0, 40),
        "knee_l_internal_rotation_deg": rng.normal(0.0, 1e-3, 40),
    }
    cols["elbow_r_adduction_deg"][7] = np.nan  # a missing sample
    kw = {"in_degrees": in_degrees, "rate_hz": 120.0, "metadata": {"root": "shoulder_r"}}
    out = write_mot(tmp_path / "angles.mot", t, cols, **kw)
    keep = np.arange(40) != 7  # the NaN row is left out: OpenSim's Storage stops at a NaN
    table = opensim.TimeSeriesTable(str(out))
    assert list(table.getColumnLabels()) == list(cols)
    np.testing.assert_allclose(np.asarray(table.getIndependentColumn()), t[keep], atol=1e-9)
    matrix = table.getMatrix()
    values = np.array(matrix.to_numpy(), copy=True)
    np.testing.assert_allclose(values, np.column_stack(list(cols.values()))[keep], atol=1e-6)
    assert table.getTableMetaDataAsString("DataRate") == "120.000000"  # header rate kept
    assert table.getTableMetaDataAsString("inDegrees") == ("yes" if in_degrees else "no")
    assert table.getTableMetaDataAsString("root") == "shoulder_r"
    # OpenSim's Storage (what its tools load a .mot with) reads every row, honours inDegrees
    storage = opensim.Storage(str(out))
    assert storage.isInDegrees() == in_degrees and storage.getSize() == 39
    # NaN kept on request: TimeSeriesTable reads it as NaN
    kept = write_mot(tmp_path / "nan.mot", t, cols, missing="nan", **kw)
    table = opensim.TimeSeriesTable(str(kept))  # kept alive while its matrix is copied (SWIG)
    matrix = table.getMatrix()
    values = np.array(matrix.to_numpy(), copy=True)
    assert values.shape == (40, 3) and np.isnan(values[7, 1])


@needs_opensim
def test_write_opensense_sto_synthetic_rate_and_missing(tmp_path, rng):
    t = np.arange(50) / 60.0
    q = Rotation.random(50, random_state=7).as_quat(scalar_first=True)
    q[10] = np.nan  # a missing sample
    imu = {
        "upper_arm_r": ImuStream(t_s=t, q_world_from_sensor=q),
        "forearm_r": ImuStream(t_s=t, q_world_from_sensor=q[::-1].copy()),
    }
    out = write_opensense_sto(tmp_path / "o.sto", imu, rate_hz=60.0)
    table, tt, qq = _opensim_quaternions(out)
    assert table.getTableMetaDataAsString("DataRate") == "60.000000"
    assert list(table.getColumnLabels()) == ["humerus_r_imu", "radius_r_imu"]
    np.testing.assert_allclose(tt, t, atol=1e-9)
    assert np.all(np.isnan(qq[10, 0]))
    np.testing.assert_allclose(qq[:, 0], q, atol=1e-9)


@needs_opensim
def test_opensense_ik_tracks_written_orientations(tmp_path, monkeypatch):
    """End to end: OpenSense IK (IMUInverseKinematicsTool) on a kinefuse-written .sto recovers
    the orientations, and kinefuse reads the .mot OpenSim writes as OpenSim's adapter does."""
    monkeypatch.chdir(tmp_path)
    level = opensim.Logger.getLevelString()
    opensim.Logger.setLevelString("Warn")
    try:
        model = opensim.Model()
        body = opensim.Body("pelvis", 1.0, opensim.Vec3(0), opensim.Inertia(0.1, 0.1, 0.1))
        model.addBody(body)
        model.addJoint(opensim.FreeJoint("ground_pelvis", model.getGround(), body))
        body.addComponent(opensim.PhysicalOffsetFrame("pelvis_imu", body, opensim.Transform()))
        model.finalizeConnections()
        model.printToXML("one_body.osim")
        t = np.arange(30) / 30.0
        rot = Rotation.from_rotvec(
            np.column_stack([0.5 * np.sin(2 * t), 0.3 * t, -0.4 * np.cos(t)])
        )
        imu = {"pelvis": ImuStream(t_s=t, q_world_from_sensor=rot.as_quat(scalar_first=True))}
        write_opensense_sto("walk_orientations.sto", imu, rate_hz=30.0)
        tool = opensim.IMUInverseKinematicsTool()
        tool.set_model_file("one_body.osim")
        tool.set_orientations_file("walk_orientations.sto")
        tool.set_sensor_to_opensim_rotations(opensim.Vec3(0, 0, 0))
        tool.set_results_directory("ik")
        tool.set_time_range(0, 0.0)
        tool.set_time_range(1, float(t[-1]))
        tool.run(False)
    finally:
        opensim.Logger.setLevelString(level)
    mot = tmp_path / "ik" / "ik_walk_orientations.mot"
    ours = read_opensim_table(mot)
    theirs = opensim.TimeSeriesTable(str(mot))
    matrix = theirs.getMatrix()
    np.testing.assert_allclose(matrix.to_numpy(), ours.values, atol=1e-12)
    assert ours.in_degrees and ours.columns[0] == "ground_pelvis_coord_0"
    # FreeJoint rotations: body-fixed X-Y-Z, degrees (IK tolerance ~0.01 deg)
    ik_rot = Rotation.from_euler("XYZ", ours.values[:, :3], degrees=True)
    np.testing.assert_allclose(ours.t_s, t, atol=1e-9)
    assert np.degrees((rot.inv() * ik_rot).magnitude()).max() < 0.05


def test_write_opensense_sto_refusals(tmp_path):
    t = np.arange(5) / 10.0
    q = np.tile([1.0, 0, 0, 0], (5, 1))
    f = tmp_path / "o.sto"
    write_opensense_sto(f, {"pelvis": ImuStream(t_s=t, q_world_from_sensor=q)})
    with pytest.raises(FileExistsError, match="pass force=True"):
        write_opensense_sto(f, {"pelvis": ImuStream(t_s=t, q_world_from_sensor=q)})
    raw = ImuStream(t_s=t, acc_m_s2=np.zeros((5, 3)), gyr_rad_s=np.zeros((5, 3)))
    with pytest.raises(InputError, match="IMU 'pelvis' has no orientation"):
        write_opensense_sto(tmp_path / "b.sto", {"pelvis": raw})
    other = ImuStream(t_s=t + 0.01, q_world_from_sensor=q)
    with pytest.raises(InputError, match="another timeline.*resample first"):
        write_opensense_sto(
            tmp_path / "c.sto",
            Recording(imu={"pelvis": ImuStream(t_s=t, q_world_from_sensor=q), "chest": other}),
        )
    with pytest.raises(FormatError, match="expected unit quaternions, found"):
        f2 = tmp_path / "bad.sto"
        f2.write_text("DataType=Quaternion\nendheader\ntime\tpelvis_imu\n0\t2,0,0,0\n")
        kio.load(f2)


# ------------------------------------------------------------------------------------------------
# Movella / Xsens DOT CSV
# ------------------------------------------------------------------------------------------------
def test_dot_folder_content(tp):
    folder = tp / "xsens" / "dot_realtime"
    assert kio.detect_format(folder) == "xsens_dot"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no rate or unit warnings on these files
        rec = kio.load(folder)
    assert rec.metadata["segment_map"] == {
        "LFemur": "thigh_l",
        "LTibia": "shank_l",
        "Pelvis": "pelvis",
    }
    assert rec.metadata["rate_hz"] == {"thigh_l": 60.0, "shank_l": 60.0, "pelvis": 60.0}
    stf0 = min(int(_rows_after_header(f, "PacketCounter")[0][1]) for f in folder.glob("*.csv"))
    assert rec.metadata["time_origin_us"] == stf0 == 3343427885
    for f in folder.glob("*.csv"):
        rows = _rows_after_header(f, "PacketCounter")
        key = rec.metadata["segment_map"][f.name.split("_")[0]]
        s = rec.imu[key]
        stf = np.array([int(r[1]) for r in rows])
        counter = np.array([int(r[0]) for r in rows])
        assert len(s) == len(rows) and s.frame == "ENU"
        np.testing.assert_allclose(s.t_s, (stf - stf0) / 1e6, atol=1e-9)  # µs clock, shared origin
        # 16667 µs per packet at 60 Hz; dropped packets are gaps, not a slower rate
        np.testing.assert_allclose(np.diff(s.t_s) / np.diff(counter), 1 / 60, atol=2e-6)
        assert rec.metadata["dropped_packets"][key] == counter[-1] - counter[0] + 1 - len(rows)
        np.testing.assert_allclose(np.linalg.norm(s.q_world_from_sensor, axis=1), 1, atol=1e-5)
        np.testing.assert_allclose(s.q_world_from_sensor[0], [float(v) for v in rows[0][2:6]])
        assert s.acc_m_s2 is None  # free acceleration is not specific force
        np.testing.assert_allclose(
            rec.metadata["free_acc_world_m_s2"][key][-1], [float(v) for v in rows[-1][6:9]]
        )
    assert rec.metadata["dropped_packets"]["thigh_l"] == 157
    assert rec.imu["pelvis"].t_s[-1] == pytest.approx((3349778012 - stf0) / 1e6)  # 6.35 s


def test_dot_derived_specific_force_is_gravity_at_rest(tp):
    rec = kio.load(tp / "xsens" / "dot_realtime", derive_acc=True)
    for s in rec.imu.values():
        # legs moving (free acc up to a few m/s²), so the median, not every sample, is ~g
        assert np.median(np.linalg.norm(s.acc_m_s2, axis=1)) == pytest.approx(9.81, abs=0.15)
    assert any("FreeAcc" in u for u in rec.metadata["units_converted"])


_DOT_HEAD = "sep=,\nDeviceTag:,arm\nOutputRate:,{rate}Hz\nSyncStatus:,Unsynced\n\n"


def test_dot_wrap_euler_gyro_and_rate_warning(tmp_path):
    n = 40
    stf = (2**32 - 20 * 16667 + np.arange(n) * 16667) % 2**32  # wraps after 20 samples
    euler = np.column_stack([np.linspace(0, 30, n), np.linspace(-10, 10, n), np.linspace(0, 90, n)])
    gyr_dps = np.tile([10.0, -20.0, 30.0], (n, 1))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    rows = [
        "PacketCounter,SampleTimeFine,Euler_X,Euler_Y,Euler_Z,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z"
    ]
    for i in range(n):
        vals = [i + 1, int(stf[i]), *euler[i], *acc[i], *gyr_dps[i]]
        rows.append(",".join(str(v) for v in vals))
    f = tmp_path / "arm_20240101_120000.csv"
    f.write_text(_DOT_HEAD.format(rate=60) + "\n".join(rows) + "\n")
    rec = kio.load(f)
    s = rec.imu["arm"]
    np.testing.assert_allclose(s.t_s, np.arange(n) * 16667e-6, atol=1e-9)  # continuous over 2^32
    np.testing.assert_allclose(s.gyr_rad_s, np.deg2rad(gyr_dps))
    expected = Rotation.from_euler("ZYX", euler[:, ::-1], degrees=True)  # R = Rz Ry Rx
    got = Rotation.from_quat(s.q_world_from_sensor, scalar_first=True)
    assert np.degrees((expected.inv() * got).magnitude()).max() < 1e-6
    g = tmp_path / "arm_20240101_120001.csv"
    g.write_text(_DOT_HEAD.format(rate=120) + "\n".join(rows) + "\n")
    with pytest.warns(FormatWarning, match="OutputRate 120 Hz disagrees with SampleTimeFine"):
        kio.load(g)
    bad = tmp_path / "x_20240101_120002.csv"
    bad.write_text(_DOT_HEAD.format(rate=60) + rows[0] + "\n1,100,1,2\n")
    with pytest.raises(FormatError, match=r"line 7: expected 11 fields as in the header, found 4"):
        kio.load(bad)


# ------------------------------------------------------------------------------------------------
# x-io plain CSV
# ------------------------------------------------------------------------------------------------
def test_xio_csv_content(tp):
    f = tp / "x-io" / "gait-tracking_short_walk.csv"
    assert kio.detect_format(f) == "xio_csv"
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnitWarning)
        rec = kio.load(f)
    rows = np.array(_rows_after_header(f, "Time (s)"), dtype=float)
    s = rec.imu["imu"]
    dup = np.concatenate([[False], np.all(rows[1:] == rows[:-1], axis=1)])
    assert rec.metadata["duplicate_rows_dropped"] == dup.sum() == 205
    assert len(s) == len(rows) - 205
    assert s.t_s[-1] == pytest.approx(rows[-1, 0]) == pytest.approx(41.618, abs=1e-3)
    assert s.rate_hz == pytest.approx(400, rel=0.01)  # x-io's Gait-Tracking example: 400 Hz
    np.testing.assert_allclose(s.gyr_rad_s, np.deg2rad(rows[~dup, 1:4]))
    np.testing.assert_allclose(s.acc_m_s2, rows[~dup, 4:7] * 9.80665)
    assert np.median(np.linalg.norm(s.acc_m_s2, axis=1)) == pytest.approx(9.81, abs=0.3)
    assert rec.metadata["units_converted"] == ["gyr deg/s -> rad/s", "acc g -> m/s^2"]


def test_xio_csv_conflicting_duplicate(tmp_path):
    f = tmp_path / "x.csv"
    hdr = "Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),"
    hdr += "Accelerometer X (g),Accelerometer Y (g),Accelerometer Z (g)"
    f.write_text(hdr + "\n0,1,2,3,0,0,1\n0.01,1,2,3,0,0,1\n0.01,1,2,4,0,0,1\n")
    with pytest.raises(FormatError, match=r"line 4, field 'Time \(s\)': expected one row per time"):
        kio.load(f)
    f.write_text(hdr.replace("(g)", "(furlong)") + "\n0,1,2,3,0,0,1\n")
    with pytest.raises(FormatError, match="unknown unit 'furlong' of Accelerometer"):
        kio.load(f)


# ------------------------------------------------------------------------------------------------
# Xsens MVNX
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mvnx(tp):
    f = tp / "xsens" / "blender-mvnx-io_test_mocap.mvnx"
    assert kio.detect_format(f) == "mvnx"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return kio.load(f)


def test_mvnx_skeleton(mvnx):
    ref = mvnx.reference
    md = mvnx.metadata
    assert md["rate_hz"] == 60.0 and md["subject"] == "MVN System 1"  # frameRate="60"
    assert len(ref) == 112 and ref.t_s[-1] == pytest.approx(1.85, abs=1e-9)  # last time="1850"
    assert len(md["segments"]) == 23 and len(md["sensors"]) == 11  # segmentCount / sensorCount
    for j in (
        "pelvis",
        "spine_mid",
        "shoulder_r",
        "elbow_l",
        "wrist_r",
        "hand_l",
        "knee_r",
        "head",
    ):
        assert j in ref.joints
    segs = md["segments"]
    for a, b, seg, point in (
        ("shoulder_r", "elbow_r", "RightUpperArm", "jRightElbow"),
        ("elbow_l", "wrist_l", "LeftForeArm", "jLeftWrist"),
        ("hip_r", "knee_r", "RightUpperLeg", "jRightKnee"),
        ("knee_l", "ankle_l", "LeftLowerLeg", "jLeftAnkle"),
    ):
        d = np.linalg.norm(ref.position(a) - ref.position(b), axis=1)
        # every frame: the bone length is the segment's pos_b of its distal joint (MVN's model
        # lets joints give by up to ~0.2 mm, the forearm in this file)
        np.testing.assert_allclose(d, np.linalg.norm(segs[seg][point]), atol=5e-4)
        assert 0.2 < d.mean() < 0.5
    for s in mvnx.reference_orientation.values():
        np.testing.assert_allclose(np.linalg.norm(s.q_world_from_sensor, axis=1), 1, atol=1e-5)
    assert md["frames"]["jointAngle"].shape == (112, 66)  # 22 joints x 3, degrees


def test_mvnx_calibration_poses(mvnx):
    poses = mvnx.metadata["calibration_poses"]
    assert set(poses) == {"identity", "tpose", "tpose-isb"}  # the file's non-normal frames
    np.testing.assert_allclose(poses["identity"]["q_world_from_segment"], [[1, 0, 0, 0]] * 23)
    tp_ = poses["tpose"]
    p = dict(zip(tp_["joints"], tp_["position_m"], strict=True))
    for side in "rl":  # arms horizontal in the T-pose, at ~1.3 m
        assert abs(p[f"wrist_{side}"][2] - p[f"shoulder_{side}"][2]) < 0.02
        assert p[f"shoulder_{side}"][2] == pytest.approx(1.307, abs=0.01)
    assert p["pelvis"][2] == pytest.approx(0.8639, abs=1e-4)


def test_mvnx_imu_streams(mvnx):
    assert set(mvnx.imu) >= {"pelvis", "chest", "upper_arm_r", "forearm_r", "upper_arm_l"}
    assert mvnx.metadata["segment_map"]["T8"] == "chest"
    for key, s in mvnx.imu.items():
        np.testing.assert_allclose(np.linalg.norm(s.q_world_from_sensor, axis=1), 1, atol=1e-5)
        q = Rotation.from_quat(s.q_world_from_sensor, scalar_first=True)
        # derived gyro (segment angular velocity in the sensor frame) vs the orientation's own
        # rate of change: an independent check of the frame conversion
        w_fd = (q[:-1].inv() * q[1:]).as_rotvec() * 60.0
        w = 0.5 * (s.gyr_rad_s[:-1] + s.gyr_rad_s[1:])
        assert np.sqrt(np.mean((w_fd - w) ** 2)) < 0.05 + 0.1 * np.sqrt(np.mean(w**2)), key
        seg = Rotation.from_quat(
            mvnx.reference_orientation[key].q_world_from_sensor, scalar_first=True
        )
        rel = seg.inv() * q  # sensor-to-segment: nearly fixed for a strapped sensor (a forearm
        # sensor near the wrist turns ~3 degrees against MVN's forearm with pronation)
        assert np.degrees((rel[0].inv() * rel).magnitude()).max() < 5.0, key
    for key in ("pelvis", "chest", "upper_arm_r"):  # slow-moving: ~gravity
        n = np.linalg.norm(mvnx.imu[key].acc_m_s2, axis=1)
        assert np.median(n) == pytest.approx(9.81, abs=0.1)


def test_mvnx_without_derived_raw_and_bad_xml(tp, tmp_path):
    rec = kio.load(tp / "xsens" / "blender-mvnx-io_test_mocap.mvnx", derive_raw=False)
    assert all(s.acc_m_s2 is None and s.gyr_rad_s is None for s in rec.imu.values())
    assert rec.metadata["units_converted"] == []
    f = tmp_path / "cut.mvnx"
    f.write_text('<?xml version="1.0"?>\n<mvnx><subject frameRate="60"><segments>\n')
    with pytest.raises(FormatError, match="cut.mvnx, line 3: expected well-formed MVNX XML"):
        kio.load(f)


# ------------------------------------------------------------------------------------------------
# unsupported files: say what it looks like and what kinefuse reads
# ------------------------------------------------------------------------------------------------
def test_unsupported_messages(tmp_path, tp):
    cases = {
        "rec.mvn": (b"MVN\x00\x01binary", "an Xsens MVN Analyze recording.*export it to MVNX"),
        "table.csv": (b"a,b,c\n1,2,3\n", r"a text table whose columns \('a', 'b', 'c'\)"),
        "model.xml": (b"<OpenSimDocument Version='40000'>", "an OpenSim setup or model XML"),
        "blob.bin": (b"\x00\x01\x02\x03", r"a binary file \(.bin\)"),
    }
    for name, (content, what) in cases.items():
        f = tmp_path / name
        f.write_bytes(content)
        with pytest.raises(FormatError) as e:
            kio.load(f)
        msg = str(e.value)
        assert f"{name}: unsupported format: this looks like " in msg
        assert re.search(what, msg), msg
        assert "kinefuse reads: " in msg and ", mvnx, " in msg and ", trc, " in msg
        assert len(msg) < 600, msg  # one readable line: the reader names, not their descriptions
    with pytest.raises(
        FormatError,
        match=r"a folder \(4 .trc\) that is not one recording; kinefuse reads what is in it one "
        r"at a time \(opensim_rajagopal_motion_capture_walk.trc: trc, .*\); pass one of them",
    ):
        kio.load(tp / "trc")


@pytest.mark.filterwarnings("ignore:.*NumFrames")  # the pyomeca file's header (tested elsewhere)
def test_folder_around_one_recording_reads_it(tmp_path, tp):
    # the AMC is the folder's one readable file (its ASF, beside it, is the skeleton it reads)
    assert kio.detect_format(tp / "asf_amc") == "cmu"
    a, b = kio.load(tp / "asf_amc"), kio.load(tp / "asf_amc" / "gsimchoni_backflip.amc")
    np.testing.assert_array_equal(a.reference.position_m, b.reference.position_m)
    # a dataset folder: one recording next to its README and licence (and a hidden file)
    d = tmp_path / "dataset"
    d.mkdir()
    shutil.copy(tp / "trc" / "pyomeca_markers.trc", d / "markers.trc")
    (d / "README.md").write_text("# markers\n")
    (d / "LICENSE.txt").write_text("MIT License\n")
    (d / ".hidden.trc").write_text("not read\n")
    one = kio.load(d)
    np.testing.assert_array_equal(
        one.reference.position_m, kio.load(d / "markers.trc").reference.position_m
    )
    assert kio.load(d, format="trc").reference.joints == one.reference.joints
    # two recordings: which one is the user's to say
    shutil.copy(d / "markers.trc", d / "again.trc")
    with pytest.raises(FormatError, match=r"not one recording.*again.trc: trc, markers.trc: trc"):
        kio.load(d)
    with pytest.raises(
        FormatError, match=r"format 'trc' reads one file; this is a folder \(3 .trc"
    ):
        kio.load(d, format="trc")
    # a dataset's top folder (README, licence) whose recordings sit in a sub-folder: named
    top = tmp_path / "study"
    top.mkdir()
    (top / "README.md").write_text("# study\n")
    shutil.move(d, top / "trials")
    with pytest.raises(
        FormatError,
        match=r"its sub-folder trials/ holds files kinefuse reads \(trc\), e.g. "
        r"trials/again.trc; pass one of them",
    ):
        kio.load(top)


@needs_opensim
def test_vec3_table_matches_opensim_adapter(tmp_path):
    f = tmp_path / "acc.sto"
    f.write_text(
        "DataRate=100.000000\nDataType=Vec3\nversion=3\nOpenSimVersion=4.1\nendheader\n"
        "time\tpelvis_imu\ttorso_imu\n"
        "0\t0.1,-9.8,0.25\t1e-3,2,3\n0.01\t0.2,-9.7,NaN\t4,5,6\n"
    )
    ours = read_opensim_table(f)
    assert ours.data_type == "Vec3" and ours.values.shape == (2, 2, 3) and ours.rate_hz == 100.0
    theirs = opensim.TimeSeriesTableVec3(str(f))
    flat_table = theirs.flatten()
    matrix = flat_table.getMatrix()
    np.testing.assert_allclose(
        np.array(matrix.to_numpy()).reshape(2, 2, 3), ours.values, atol=1e-12, equal_nan=True
    )
    assert tuple(theirs.getColumnLabels()) == ours.columns


def test_sensor_maps_and_writer_names(tp, tmp_path):
    rec = kio.load(tp / "xsens" / "dot_realtime", sensor_map={"Yao": "chest"})  # a DeviceTag
    assert set(rec.imu) == {"thigh_l", "shank_l", "chest"}
    sto = kio.load(
        tp / "xsens" / "opensense_walking_orientations.sto", sensor_map={"torso_imu": "trunk"}
    )
    assert "trunk" in sto.imu and "chest" not in sto.imu
    out = write_opensense_sto(
        tmp_path / "o.sto", {"pelvis": sto.imu["pelvis"]}, names={"pelvis": "pelvis_imu"}
    )
    assert out.read_text().splitlines()[4] == "time\tpelvis_imu"


def test_dot_synced_clock_wrapping_between_sensors(tmp_path):
    head = _DOT_HEAD.format(rate=60).replace("Unsynced", "Synced")
    cols = "PacketCounter,SampleTimeFine,Quat_W,Quat_X,Quat_Y,Quat_Z\n"
    starts = {"LFemur": 2**32 - 16667, "LTibia": 2**32 - 16667 + 2 * 16667 - 2**32}
    for name, s0 in starts.items():
        rows = [f"{i + 1},{(s0 + i * 16667) % 2**32},1,0,0,0" for i in range(5)]
        (tmp_path / f"{name}_20240101_120000.csv").write_text(head + cols + "\n".join(rows) + "\n")
    rec = kio.load(tmp_path)
    np.testing.assert_allclose(rec.imu["thigh_l"].t_s, np.arange(5) * 16667e-6, atol=1e-9)
    np.testing.assert_allclose(rec.imu["shank_l"].t_s, (2 + np.arange(5)) * 16667e-6, atol=1e-9)


def test_dot_delta_quantities(tmp_path):
    """``dq``/``dv`` (orientation and velocity increments per sample) -> rates, as the DOT manual
    defines them (acceleration = dv / dt, dt = 1 / output rate)."""
    n, rate = 10, 60.0
    w = np.array([0.5, -1.0, 2.0])  # rad/s
    a = np.array([0.1, 0.2, 9.8])  # m/s^2
    dq = Rotation.from_rotvec(np.tile(w / rate, (n, 1))).as_quat(scalar_first=True)
    rows = ["PacketCounter,SampleTimeFine,dq_W,dq_X,dq_Y,dq_Z,dv_X,dv_Y,dv_Z"]
    for i in range(n):
        rows.append(",".join(str(v) for v in [i + 1, 1000 + i * 16667, *dq[i], *(a / rate)]))
    f = tmp_path / "wrist_20240101_120000.csv"
    f.write_text(_DOT_HEAD.format(rate=60) + "\n".join(rows) + "\n")
    s = kio.load(f).imu["wrist"]
    np.testing.assert_allclose(s.gyr_rad_s, np.tile(w, (n, 1)), atol=1e-9)
    np.testing.assert_allclose(s.acc_m_s2, np.tile(a, (n, 1)), atol=1e-9)
