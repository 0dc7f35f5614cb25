"""Neura sparse (gaittoolbox) reader, and the issue's Neura check: real Xsens thighs/shanks + Vicon hips.

The Neura trial is evaluation-only data (SOURCE.md): nothing is tuned on it. The chain uses the
documented procedure only: Vicon hip centres as roots, per-segment axis and length from the first
second against the Vicon joint centres (``calibrate(..., "reference", window_s=1.0)``); IMUs and
Vicon share a world frame (SOURCE.md: the IMU orientations are yaw-fixed into it), so
``align="auto"`` resolves to no alignment.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from kinefuse.exceptions import FormatError
from kinefuse.io.neura import read_neura
from kinefuse.kinematics import Skeleton, calibrate, chain_positions

TRIAL = "S02-Trial-Walk-1"
JOINTS = ("knee_l", "knee_r", "ankle_l", "ankle_r")


@pytest.fixture(scope="module")
def neura_dir(shared_data):
    d = shared_data / "neura_sparse_sample"
    if not (d / "vicon" / f"{TRIAL}.csv").is_file():
        pytest.skip(f"missing {d}")
    return d


@pytest.fixture(scope="module")
def rec(neura_dir):
    return read_neura(neura_dir)


def plain_csv(path):
    """Independent loader (SOURCE.md recipe): header names and a float table."""
    rows = [line for line in open(path) if not line.startswith("//")]
    cols = rows[0].strip().split(",")
    return cols, np.array([[float(v) for v in r.strip().split(",")] for r in rows[1:] if r.strip()])


# ---------------------------------------------------------------- reader
def test_reader_shapes_units_and_values(rec, neura_dir):
    assert set(rec.imu) == {
        "pelvis", "thigh_l", "thigh_r", "shank_l", "shank_r", "shank_distal_l", "shank_distal_r", "foot_l", "foot_r",
    }  # fmt: skip
    assert rec.imu["shank_l"].name == "L_LowLeg2" and rec.imu["shank_distal_r"].name == "R_LowLeg"
    ref = rec.reference
    assert ref.position_m.shape == (955, 9, 3) and ref.frame == "vicon"
    assert ref.joints == (
        "pelvis",
        "hip_l",
        "hip_r",
        "knee_l",
        "knee_r",
        "ankle_l",
        "ankle_r",
        "foot_l",
        "foot_r",
    )
    np.testing.assert_allclose(ref.t_s[[0, 1, -1]], [0.0, 0.01, 9.54])
    assert rec.imu["thigh_r"].rate_hz == pytest.approx(100.0)
    for s in rec.imu.values():
        assert (
            s.q_world_from_sensor.shape == (955, 4)
            and s.gyr_rad_s.shape == (955, 3)
            and s.frame == "vicon"
        )
    # units: metres (pelvis about 0.97 m high), gravity about 9.8 m/s² in the acc norm at rest-ish start
    assert np.median(ref.position("pelvis")[:, 2]) == pytest.approx(0.97, abs=0.03)
    assert np.median(np.linalg.norm(rec.imu["pelvis"].acc_m_s2, axis=1)) == pytest.approx(
        9.8, abs=0.5
    )
    # values against the independent loader
    vc, v = plain_csv(neura_dir / "vicon" / f"{TRIAL}.csv")
    knee_r = v[:, [vc.index(f"RFEO_{k}") for k in (1, 2, 3)]]
    np.testing.assert_array_equal(ref.position("knee_r"), knee_r)
    np.testing.assert_allclose(
        knee_r[0], [-0.0980976734104866, 1.34427138991412, 0.492429824761657]
    )
    ic, imu = plain_csv(neura_dir / "imu" / f"{TRIAL}-R_UpLeg.csv")
    np.testing.assert_array_equal(
        rec.imu["thigh_r"].gyr_rad_s, imu[:, [ic.index(f"gyr_{k}") for k in (1, 2, 3)]]
    )
    np.testing.assert_allclose(rec.imu["thigh_r"].gyr_rad_s[0], [0.278266, 0.143086, 0.043875])
    ic, imu = plain_csv(neura_dir / "imu" / f"{TRIAL}-L_LowLeg2.csv")
    q = imu[:, [ic.index(f"ori_{k}") for k in (1, 2, 3, 4)]]
    np.testing.assert_allclose(
        rec.imu["shank_l"].q_world_from_sensor, q / np.linalg.norm(q, axis=1)[:, None]
    )
    np.testing.assert_allclose(
        np.linalg.norm(rec.reference_orientation["thigh_l"].q_world_from_sensor, axis=1), 1.0
    )
    assert rec.metadata["subject"] == "S02" and rec.metadata["format"] == "neura"


def test_reader_accepts_files(neura_dir):
    a = read_neura(neura_dir / "vicon" / f"{TRIAL}.csv")
    b = read_neura(neura_dir / "imu" / f"{TRIAL}-L_LowLeg2.csv")
    np.testing.assert_array_equal(a.reference.position_m, b.reference.position_m)


@pytest.fixture
def copy_dir(neura_dir, tmp_path):
    dst = tmp_path / "neura"
    (dst / "imu").mkdir(parents=True)
    shutil.copytree(neura_dir / "vicon", dst / "vicon")
    for sensor in ("L_UpLeg", "L_LowLeg2"):
        shutil.copy(neura_dir / "imu" / f"{TRIAL}-{sensor}.csv", dst / "imu")
    return dst


def _edit(path, fn):
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(fn(lines)))


def test_broken_files_raise_format_error(copy_dir):
    assert set(read_neura(copy_dir).imu) == {"thigh_l", "shank_l"}
    vicon = copy_dir / "vicon" / f"{TRIAL}.csv"
    original = vicon.read_text()

    def bad_value(lines):  # line 8 = third data row (5 header lines + column names)
        f = lines[7].split(",")
        f[19] = "abc"
        lines[7] = ",".join(f)
        return lines

    _edit(vicon, bad_value)
    with pytest.raises(
        FormatError,
        match=r"S02-Trial-Walk-1.csv, line 8, field 'RFEO_2': expected a number, got 'abc'",
    ):
        read_neura(copy_dir)
    vicon.write_text(original)
    _edit(vicon, lambda lines: lines[:-1])
    with pytest.raises(FormatError, match="nSamples=955, got 954 data rows"):
        read_neura(copy_dir)
    vicon.write_text(original)
    _edit(vicon, lambda lines: [*lines[:9], lines[9].rsplit(",", 1)[0] + "\n", *lines[10:]])
    with pytest.raises(FormatError, match="line 10: expected 55 comma-separated values, got 54"):
        read_neura(copy_dir)
    vicon.write_text(original)
    imu = copy_dir / "imu" / f"{TRIAL}-L_UpLeg.csv"
    _edit(imu, lambda lines: [ln.replace("ori_4", "ori_x") for ln in lines])
    with pytest.raises(
        FormatError, match=r"L_UpLeg.csv, field 'ori_4': expected columns .*missing \['ori_4'\]"
    ):
        read_neura(copy_dir)
    with pytest.raises(FormatError, match="no such file or folder"):
        read_neura(copy_dir / "missing.csv")
    shutil.rmtree(copy_dir / "vicon")
    with pytest.raises(FormatError, match="'imu/' and 'vicon/' subfolders"):
        read_neura(copy_dir)
    assert issubclass(FormatError, ValueError)


# ---------------------------------------------------------------- the Neura check
def test_neura_chain_accuracy(rec):
    sk = Skeleton.from_joint_stream(rec.reference, "lower_body", window_s=1.0)
    cal = calibrate(rec, sk, "reference", window_s=1.0)
    assert cal.align == "none" and cal.window_s == (0.0, 0.99)
    est = chain_positions(rec, sk, cal, root=("hip_l", "hip_r"))
    rmse_3d, rmse_axes = {}, {}
    for j in JOINTS:
        e = est.position(j) - rec.reference.position(j)
        rmse_3d[j] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
        rmse_axes[j] = float(np.mean(np.sqrt(np.mean(e**2, axis=0))))  # papers' "Mean" column
    print("3-D RMSE (cm):", {j: round(100 * v, 2) for j, v in rmse_3d.items()})
    print("mean of per-axis RMSE (cm):", {j: round(100 * v, 2) for j, v in rmse_axes.items()})
    assert np.mean(list(rmse_3d.values())) <= 0.040
    assert max(rmse_3d.values()) <= 0.050
    # regression on the figures (deterministic)
    assert np.mean(list(rmse_3d.values())) == pytest.approx(0.0399, abs=0.0005)
    assert np.mean(list(rmse_axes.values())) == pytest.approx(0.0206, abs=0.0005)


def test_example_runs(neura_dir, capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "neura_chain.py"
    spec = importlib.util.spec_from_file_location("neura_chain_example", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = mod.main([str(neura_dir)])
    assert set(out) == set(JOINTS)
    assert "mean" in capsys.readouterr().out
