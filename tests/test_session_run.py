"""`kinefuse run` / `kinefuse evaluate` back-ends: real sessions, a synthetic one, bad sessions."""

from __future__ import annotations

import json
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from kinefuse import cli
from kinefuse.exceptions import ConfigError, InputError
from kinefuse.io import read_joint_csv, read_trc, write_imu_csv, write_joint_csv
from kinefuse.pipelines.run import RunResult, build_chain, evaluate_recording, run_session

SESSIONS = Path(__file__).parent / "data" / "sessions"
runner = CliRunner()


def _err(result) -> str:
    try:
        return result.stderr
    except ValueError:
        return result.output


# ------------------------------------------------------------------------------------------
# a synthetic session (no shared data): virtual forearm IMU + camera joints, CSV files
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def synthetic_files(tmp_path_factory):
    from kinefuse.data import demo_motion
    from kinefuse.sim import CameraConfig, virtual_recording

    d = tmp_path_factory.mktemp("synthetic")
    rec = virtual_recording(
        demo_motion(0.0, 6.0),
        camera=CameraConfig(occlusion_rate_per_min=0.0, dropout_rate_per_min=0.0),
        segments=("upper_arm_r", "forearm_r"),
        seed=5,
    )
    write_imu_csv(d / "imu.csv", {"IMU 1": rec.imu["upper_arm_r"], "IMU 2": rec.imu["forearm_r"]})
    write_joint_csv(d / "camera.csv", rec.vision.subset(["shoulder_r", "elbow_r", "wrist_r"]))
    write_joint_csv(
        d / "truth.csv",
        rec.reference.subset(["shoulder_r", "elbow_r", "wrist_r"]),
        role="reference",
    )
    return d


def _write_session(folder: Path, body: str, name: str = "s.toml") -> Path:
    p = folder / name
    p.write_text(textwrap.dedent(body), encoding="utf-8")
    return p


GOOD = """\
    [session]
    name = "synthetic"
    [imu]
    format = "{fmt}"
    path = "{imu}"
    [imu.segments]
    upper_arm_r = "IMU 1"
    forearm_r = "{sensor}"
    [skeleton]
    body_height_m = 1.75
    [camera]
    format = "joint-csv"
    path = "camera.csv"
    [reference]
    format = "joint-csv"
    path = "truth.csv"
    [method]
    name = "{method}"
    [method.parameters]
    calibration_window_s = 3.0
"""


def _good(folder, fmt="csv", imu="imu.csv", sensor="IMU 2", method="paper-a") -> Path:
    return _write_session(folder, GOOD.format(fmt=fmt, imu=imu, sensor=sensor, method=method))


def test_synthetic_session_writes_csv_trc_report(synthetic_files, tmp_path):
    p = _good(synthetic_files)
    out = tmp_path / "out"
    summary = run_session(p, out)
    csv, trc, sto = summary["outputs"]
    assert csv.name == "synthetic_joints.csv" and trc.name == "synthetic_joints.trc"
    assert sto.name == "synthetic_orientations.sto"  # calibrated sensor orientations, OpenSense
    rec = read_joint_csv(csv)
    assert rec.vision.joints == ("elbow_r", "wrist_r")
    extra = rec.metadata["extra_columns"]
    assert {"source", "mode", "std_m"} <= set(extra)
    assert np.all(np.asarray(extra["mode"], dtype=float) >= 0)  # the filter ran everywhere
    assert np.all(np.isfinite(np.asarray(extra["std_m"], dtype=float)))
    tr = read_trc(trc)
    np.testing.assert_allclose(tr.reference.position_m, rec.vision.position_m, atol=2e-6)
    ev = summary["evaluation"]
    assert ev.methods[:2] == ("EM-KF/FIR", "IMU chain")
    # the IMU chain of virtual sensors (camera shoulder) is within a few cm of the truth (VQF
    # orientation, soft tissue, calibrated against a Kinect-like camera: real chains are ~5 cm off)
    assert np.all(ev.mean_rmse[1] < 0.06), ev.mean_rmse
    assert summary["report"].is_file()
    # a typed result that still reads as the mapping `--json` writes (same keys, same order)
    assert isinstance(summary, RunResult) and summary.report == summary["report"]
    keys = ["outputs", "notes", "provenance", "coverage", "warnings", "tables", "angles_deg",
            "evaluation", "report"]  # fmt: skip
    assert list(summary) == [k for k in keys if k != "angles_deg" or summary.angles_deg]
    assert dict(summary)["evaluation"] is ev and summary.get("nosuch") is None
    # never overwrite without force; nothing written in that case
    before = csv.stat().st_mtime_ns
    with pytest.raises(FileExistsError, match="--force"):
        run_session(p, out)
    assert csv.stat().st_mtime_ns == before
    run_session(p, out, force=True)


def test_synthetic_session_camera_method_through_cli(synthetic_files, tmp_path):
    p = _good(synthetic_files, method="elm-kf")
    out = tmp_path / "cli"
    res = runner.invoke(
        cli.app, ["run", str(p), "--out", str(out), "--json", str(tmp_path / "s.json")]
    )
    assert res.exit_code == 0, (res.output, _err(res))
    data = json.loads((tmp_path / "s.json").read_text())
    assert "ELM/KF" in data["evaluation"]["methods"]
    assert (out / "report.html").is_file() and (out / "synthetic_joints.trc").is_file()


# ------------------------------------------------------------------------------------------
# bad sessions -> one clear error (ConfigError / InputError), CLI exit 2
# ------------------------------------------------------------------------------------------


def _bad_imu_csv(folder: Path, kind: str) -> Path:
    t = np.arange(50) / 50.0
    q = np.tile([1.0, 0.0, 0.0, 0.0], (50, 1))
    p = folder / f"imu_{kind}.csv"
    head = "# kinefuse-imu-csv 1\n# acc_unit: m/s^2\n# gyr_unit: rad/s\n"
    if kind == "g":
        rows = [f"{x},IMU 2,0,0,1.0,0.01,0,0" for x in t]
        p.write_text(head + "t_s,sensor,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z\n" + "\n".join(rows))
    elif kind == "acc-only":
        rows = [f"{x},IMU 2,0,0,9.81" for x in t]
        p.write_text(head + "t_s,sensor,acc_x,acc_y,acc_z\n" + "\n".join(rows))
    elif kind == "nan":
        rows = [f"{x},IMU 2,,,," for x in t] + [f"{x},IMU 1,{','.join(map(str, q[0]))}" for x in t]
        p.write_text(head + "t_s,sensor,qw,qx,qy,qz\n" + "\n".join(rows))
    return p


@pytest.mark.parametrize(
    ("case", "needle"),
    [
        ("missing file", "not found"),
        ("unknown format", "unknown format"),
        ("wrong units", "units"),
        ("unknown segment", "unknown segment"),
        ("no orientation or raw data", "IMU 2"),
        ("nan-only stream", "IMU 2"),
        ("unknown sensor", "nosuch"),
    ],
)
def test_bad_sessions_raise_one_line_errors(synthetic_files, tmp_path, case, needle):
    import shutil

    for f in ("imu.csv", "camera.csv", "truth.csv"):
        shutil.copy(synthetic_files / f, tmp_path / f)
    kw = {}
    if case == "missing file":
        kw["imu"] = "nope.csv"
    elif case == "unknown format":
        kw["fmt"] = "xsens-binary"
    elif case == "wrong units":
        kw["imu"] = _bad_imu_csv(tmp_path, "g").name
    elif case == "no orientation or raw data":
        kw["imu"] = _bad_imu_csv(tmp_path, "acc-only").name
    elif case == "nan-only stream":
        kw["imu"] = _bad_imu_csv(tmp_path, "nan").name
    elif case == "unknown sensor":
        kw["sensor"] = "nosuch"
    p = _good(tmp_path, **kw)
    if case == "unknown segment":
        p.write_text(p.read_text().replace("forearm_r =", "lower_arm_r ="))
    with pytest.raises(InputError) as info:
        run_session(p, tmp_path / "out")
    msg = str(info.value)
    assert isinstance(info.value, (ConfigError, InputError))
    assert "\n" not in msg and needle in msg, msg
    # the CLI shows it as one red line, exit 2
    res = runner.invoke(cli.app, ["run", str(p), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2, (res.output, _err(res))
    lines = [ln for ln in _err(res).splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("kinefuse: error:"), lines
    assert not (tmp_path / "out").exists()


def test_unknown_method_parameter_is_a_config_error(synthetic_files, tmp_path):
    p = _good(synthetic_files)
    p.write_text(p.read_text() + "calibraton = 'static'\n")
    with pytest.raises(ConfigError, match="did you mean 'calibration'"):
        run_session(p, tmp_path / "out")


def test_build_chain_roots():
    sk, roots = build_chain(
        ["shank_l", "thigh_l", "thigh_r", "shank_r"],
        dict.fromkeys(["thigh_l", "shank_l", "thigh_r", "shank_r"], 0.4),
    )
    assert roots == ("hip_l", "hip_r")
    parent = {
        s: (sk.segments[i] if i >= 0 else None)
        for s, i in zip(sk.segments, sk.parents, strict=True)
    }
    assert parent == {"thigh_l": None, "thigh_r": None, "shank_l": "thigh_l", "shank_r": "thigh_r"}
    sk, roots = build_chain(["forearm_r"], {"forearm_r": 0.25})
    assert roots == ("elbow_r",) and sk.distal == ("wrist_r",)


# ------------------------------------------------------------------------------------------
# real data: Neura (IMU + Vicon) and UTD-MHAD (wrist IMU + Kinect)
# ------------------------------------------------------------------------------------------


def test_neura_session(shared_data, tmp_path):
    summary = run_session(SESSIONS / "neura_walk.toml", tmp_path)
    ev = summary["evaluation"]
    assert ev.joints == ("knee_l", "knee_r", "ankle_l", "ankle_r")
    tag = " [calibrated on reference, lengths from reference, root from reference]"
    assert ev.methods == ("EM-KF/FIR" + tag, "IMU chain" + tag)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["provenance"]["calibration"] == "reference"
    assert metrics["provenance"]["labels"] == tag.strip()
    chain = ev.mean_rmse[1]
    # real Xsens chain from the Vicon hips: about 1-2 cm (regression bound, not tuned)
    assert np.all(chain < 0.04), chain
    assert np.all(ev.mean_rmse[0] < 0.06), ev.mean_rmse[0]
    rec = read_joint_csv(summary["outputs"][0])
    assert rec.vision.frame == "vicon" and len(rec.vision) == ev.n_steps
    assert summary["report"].is_file()


def test_utd_mhad_session(shared_data, tmp_path):
    summary = run_session(SESSIONS / "utd_mhad_a9_s1_t1.toml", tmp_path)
    ev = summary["evaluation"]
    assert ev.joints == ("wrist_r",)
    # wrist = Kinect elbow + real forearm IMU; reference = Kinect wrist. The session
    # calibrates on the camera, which is the reference's own data, and starts the chain at its
    # elbow: every score says so
    tag = (
        " [calibrated on camera = reference, lengths from camera = reference, "
        "root from camera = reference]"
    )
    assert ev.methods == ("EM-KF/FIR" + tag, "IMU chain" + tag)
    # paper A scores the IMU wrist against the Kinect wrist: no warning; a camera method
    # scored against its own camera gets one
    assert not any("reference's own data" in w for w in summary["warnings"])
    text = (SESSIONS / "utd_mhad_a9_s1_t1.toml").read_text()
    text = text.replace("../../../../shared/data", str(shared_data)).replace(
        'name = "paper-a"', 'name = "camera-only"'
    )
    (tmp_path / "cam.toml").write_text(text)
    cam = run_session(tmp_path / "cam.toml", tmp_path / "cam")
    assert any("reference's own data" in w for w in cam["warnings"])
    assert ev.mean_rmse[ev.methods.index("IMU chain" + tag), 0] < 0.05
    assert (tmp_path / "utd-mhad-a9-s1-t1_joints.trc").is_file()


def test_evaluate_recording_neura(shared_data):
    path = shared_data / "neura_sparse_sample" / "vicon" / "S02-Trial-Walk-1.csv"
    # the reference is evaluation-only: no lengths from it unless asked ...
    with pytest.raises(InputError, match=r"no length for segment\(s\) \['thigh_l'"):
        evaluate_recording(path, "imu-only", calibration="static")
    # ... body height sizes the legs (the feet, which it cannot size, serve the ankle angles),
    # and a static calibration then needs the still pose this walk lacks
    with pytest.raises(InputError, match=r"no still window of 2 s"):
        evaluate_recording(path, "imu-only", calibration="static", body_height_m=1.75)
    # by default the walk (no still pose) gets functional calibration from its IMUs, and says so
    ev = evaluate_recording(path, "imu-only")
    assert ev.methods == ("IMU only [functional calibration (auto), root from reference]",)
    assert set(ev.joints) == {"knee_l", "knee_r", "ankle_l", "ankle_r"}
    assert np.all(ev.mean_rmse < 0.06), ev.mean_rmse
    # calibrating on the reference must be asked for, and is labelled
    ev = evaluate_recording(path, "imu-only", calibration="reference")
    tag = " [calibrated on reference, lengths from reference, root from reference]"
    assert ev.methods == ("IMU only" + tag,)
    # every limb IMU of the recording: thighs, shanks and feet (toe points from Vicon)
    assert set(ev.joints) == {"knee_l", "knee_r", "ankle_l", "ankle_r", "foot_l", "foot_r"}
    legs = [ev.joints.index(j) for j in ("knee_l", "knee_r", "ankle_l", "ankle_r")]
    assert np.all(ev.mean_rmse[0, legs] < 0.04), ev.mean_rmse
    assert np.all(ev.mean_rmse < 0.1), ev.mean_rmse
    res = runner.invoke(
        cli.app,
        ["evaluate", str(path), "--method", "paper-a", "--calibration", "reference", "--json", "-"],
    )
    assert res.exit_code == 0, (res.output, _err(res))
    data = json.loads(res.output)
    assert data["methods"][0] == "EM-KF/FIR" + tag


def test_evaluate_recording_camera_method_without_camera(shared_data):
    path = shared_data / "neura_sparse_sample" / "vicon" / "S02-Trial-Walk-1.csv"
    with pytest.raises(InputError, match="needs a camera"):
        evaluate_recording(path, "elm-fir")


def test_every_method_of_a_recording_is_scored_where_the_reference_measured(shared_data):
    """UTD-MHAD's Kinect (camera = reference) runs at about 15 Hz; a camera method's output is
    on a 30-Hz grid, IMU-only on the Kinect's own frames. Both are scored at the same
    instants, one per Kinect frame (before: the camera methods also on the reference values
    interpolated between frames, twice as many samples, not comparable)."""
    import kinefuse.io as kio
    from kinefuse.pipelines.run import process_recording

    rec = kio.load(shared_data / "utd_mhad" / "Inertial" / "a1_s1_t1_inertial.mat")
    rec = replace(rec, reference=rec.vision)  # as the UTD-MHAD sessions: the Kinect is both
    params = {"calibration": "vision", "calibration_window_s": 10.0}
    imu = process_recording(rec, "imu-only", params, body_height_m=1.75).evaluation()
    cam = process_recording(rec, "kinefuse", params, body_height_m=1.75).evaluation()
    n_frames = 48  # the trial's Kinect frames (SOURCE.md: no timestamps, 14.8 Hz effective)
    assert imu.n_steps == n_frames and cam.n_steps == 2 * n_frames
    chain_imu = imu.methods.index(next(m for m in imu.methods if m.startswith("IMU only")))
    chain_cam = cam.methods.index(next(m for m in cam.methods if m.startswith("IMU chain")))
    assert imu.n_samples[chain_imu, 0] == cam.n_samples[chain_cam, 0] == n_frames
