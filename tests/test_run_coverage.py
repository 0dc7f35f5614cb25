"""Coverage is data (issue 12, cases 1-4 and 11): every output sample of `kinefuse run` says
which input backed it; samples no input covers are predictions, never "available"; Inf in an
input is an error naming file, column and row; a missing orientation is never substituted
silently; streams that do not overlap or hold one sample get an error saying so."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import test_session_run as _base
from kinefuse import cli
from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_PREDICTED
from kinefuse.exceptions import ConfigError, InputError
from kinefuse.io import read_imu_csv, read_joint_csv, read_trc, write_imu_csv, write_joint_csv
from kinefuse.pipelines.run import run_session

synthetic_files = _base.synthetic_files  # the module-scoped fixture of the synthetic session

NO_CAMERA = """\
[session]
name = "synthetic"
[imu]
format = "csv"
path = "{imu}"
[imu.segments]
upper_arm_r = "IMU 1"
forearm_r = "IMU 2"
[skeleton]
body_height_m = 1.75
root = "reference"
[reference]
format = "joint-csv"
path = "{ref}"
[calibration]
method = "reference"
window_s = {window}
[method]
name = "{method}"
[method.parameters]
{extra}
"""


def _imu_variant(folder: Path, name: str, sensors=("IMU 2",), **edit) -> str:
    """imu.csv with ``sensors`` cut (``t_end``) or reduced to ``n`` samples."""
    imu = dict(read_imu_csv(folder / "imu.csv").imu)
    for sensor in sensors:
        st = imu[sensor]
        keep = st.t_s <= edit["t_end"] if "t_end" in edit else np.arange(st.t_s.size) < edit["n"]
        fields = ("t_s", "q_world_from_sensor", "acc_m_s2", "gyr_rad_s", "mag")
        imu[sensor] = dataclasses.replace(
            st, **{f: getattr(st, f)[keep] for f in fields if getattr(st, f) is not None}
        )
    write_imu_csv(folder / name, imu, force=True)
    return name


def _edit_imu_text(folder: Path, name: str, columns, value: str, rows=None) -> str:
    """imu.csv with ``columns`` of IMU 2 set to ``value`` (in every row, or the given ones)."""
    lines = (folder / "imu.csv").read_text().splitlines()
    h = next(i for i, line in enumerate(lines) if line.startswith("t_s,"))
    cols = lines[h].split(",")
    mine = [i for i in range(h + 1, len(lines)) if lines[i].split(",")[1] == "IMU 2"]
    for i in mine if rows is None else [mine[r] for r in rows]:
        parts = lines[i].split(",")
        for c in columns:
            parts[cols.index(c)] = value
        lines[i] = ",".join(parts)
    (folder / name).write_text("\n".join(lines) + "\n")
    return name


def _check_written(summary, joint: str):
    rec = read_joint_csv(summary["outputs"][0])
    st = rec.vision
    j = st.joints.index(joint)
    extra = rec.metadata["extra_columns"]
    source = np.asarray(extra["source"], dtype=float)[:, j]
    trc = read_trc(summary["outputs"][1]).reference
    return st, j, source, trc, extra


# ------------------------------------------------------------------------------------ case 1
def test_imu_ending_early_is_predicted_not_available(synthetic_files, tmp_path):
    imu = _imu_variant(synthetic_files, "imu_short.csv", t_end=3.0)
    p = _base._good(synthetic_files, imu=imu)
    summary = run_session(p, tmp_path / "out")
    st, j, source, trc, extra = _check_written(summary, "wrist_r")
    late = st.t_s > 3.05
    assert late.sum() > 80
    assert not np.any(st.available[late, j])  # used to be available = 1
    assert np.all(source[late] == SOURCE_PREDICTED)
    assert np.all(np.isnan(trc.position_m[late, j]))  # TRC: missing markers
    assert np.all(st.available[st.t_s < 2.9, j])
    cov = np.asarray(extra["imu_forearm_r_covered"], dtype=float)
    assert np.all(cov[late] == 0) and np.all(cov[st.t_s < 2.9] == 1)
    counts = summary["coverage"]["wrist_r"]
    assert counts["predicted"] == np.sum(source == SOURCE_PREDICTED) >= late.sum()
    assert counts["available"] == st.available[:, j].sum()
    assert summary["coverage"]["elbow_r"]["available"] == st.t_s.size  # upper arm IMU is whole
    (w,) = [w for w in summary["warnings"] if w.startswith("wrist_r: only")]
    assert "forearm_r IMU" in w and f"{counts['predicted']} predicted" in w
    page = (tmp_path / "out" / "report.html").read_text()
    table = page.split("<h2>Coverage</h2>")[1].split("</section>")[0]  # the report's table
    row = table.split("<td>wrist_r</td>")[1].split("</tr>")[0]
    assert f">{counts['predicted']}</td>" in row
    # the metrics score what is output as available, never the predictions
    assert any("predicted joint samples" in n and "excluded" in n for n in summary["notes"])
    ev = summary["evaluation"]
    assert np.all(ev.mean_rmse[0] < 0.1), ev.mean_rmse  # would be dominated by 3 s of drift


def test_coverage_warning_reaches_the_cli(synthetic_files, tmp_path):
    imu = _imu_variant(synthetic_files, "imu_short.csv", t_end=3.0)
    p = _base._good(synthetic_files, imu=imu)
    res = _base.runner.invoke(cli.app, ["run", str(p), "--out", str(tmp_path / "o"), "-q"])
    assert res.exit_code == 0, _base._err(res)
    assert "warning: wrist_r: only" in _base._err(res)


# ------------------------------------------------------------------------------------ case 2
@pytest.mark.parametrize("sensors", [("IMU 2",), ("IMU 1", "IMU 2")], ids=["one", "all"])
def test_imu_of_two_samples_is_not_extrapolated(synthetic_files, tmp_path, sensors):
    imu = _imu_variant(synthetic_files, f"imu_two_{len(sensors)}.csv", sensors, n=2)
    summary = run_session(_base._good(synthetic_files, imu=imu), tmp_path / "out")
    for joint in ("wrist_r", "elbow_r") if len(sensors) == 2 else ("wrist_r",):
        st, j, source, trc, _ = _check_written(summary, joint)
        assert st.available[:, j].sum() <= 2  # used to be 9.5 s of predictions marked 1
        assert np.sum(source == SOURCE_PREDICTED) >= st.t_s.size - 2
        assert np.sum(np.isfinite(trc.position_m[:, j, 0])) <= 2
        assert any(w.startswith(f"{joint}: only") for w in summary["warnings"])
    if len(sensors) == 2:  # the elbow's warning names its own input, not the forearm's
        (w,) = [w for w in summary["warnings"] if w.startswith("elbow_r: only")]
        assert "upper_arm_r IMU" in w and "forearm_r" not in w


# ------------------------------------------------------------------------------ case 3
def test_inf_in_an_input_names_file_column_and_line(synthetic_files, tmp_path):
    imu = _edit_imu_text(synthetic_files, "imu_inf.csv", ["qx"], "inf", rows=[40])
    with pytest.raises(ConfigError, match=r"imu_inf.csv, line \d+, field 'qx'.*'inf'"):
        run_session(_base._good(synthetic_files, imu=imu), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_inf_from_a_non_table_reader_is_an_error(monkeypatch, tmp_path, synthetic_files):
    import kinefuse.io
    from kinefuse.pipelines.run import streams

    real = kinefuse.io.load

    def load_with_inf(path, format=None):
        rec = real(path, format=format)
        if rec.imu:
            st = rec.imu["IMU 2"]
            q = st.q_world_from_sensor.copy()
            q[7, 2] = -np.inf
            rec.imu["IMU 2"] = dataclasses.replace(st, q_world_from_sensor=q)
        return rec

    monkeypatch.setattr(streams, "load", load_with_inf)  # the reader load_streams calls
    with pytest.raises(ConfigError, match=r"sensor 'IMU 2', column qy: infinite value at sample 7"):
        run_session(_base._good(synthetic_files), tmp_path / "out")


def test_empty_quaternions_of_one_sensor_are_not_replaced_silently(synthetic_files, tmp_path):
    imu = _edit_imu_text(synthetic_files, "imu_noq.csv", ["qw", "qx", "qy", "qz"], "")
    p = _base._good(synthetic_files, imu=imu)
    with pytest.raises(InputError, match="no orientation for forearm_r.*estimate_orientation"):
        run_session(p, tmp_path / "out")
    # the explicit policy: estimated, and said so in the summary and the report
    body = p.read_text() + "estimate_orientation = true\n"
    p = _base._write_session(synthetic_files, body, name="estimate.toml")
    summary = run_session(p, tmp_path / "out2")
    assert any("no orientation for forearm_r" in w and "VQF" in w for w in summary["warnings"])
    assert "estimated from acc + gyr with VQF" in (tmp_path / "out2" / "report.html").read_text()


# ------------------------------------------------------------------------------------ case 4
def _short_reference(folder: Path, name: str, keep) -> str:
    ref = read_joint_csv(folder / "truth.csv").reference
    k = keep(ref.t_s)
    cut = dataclasses.replace(
        ref, t_s=ref.t_s[k], position_m=ref.position_m[k], available=ref.available[k]
    )
    write_joint_csv(folder / name, cut, role="reference", force=True)
    return name


def test_short_reference_does_not_cut_the_output(synthetic_files, tmp_path):
    ref = _short_reference(synthetic_files, "truth_1s.csv", lambda t: t <= 1.0)
    body = NO_CAMERA.format(imu="imu.csv", ref=ref, method="paper-a", window=0.8, extra="")
    p = _base._write_session(synthetic_files, body, name="short_ref.toml")
    summary = run_session(p, tmp_path / "out")
    st, j, source, _, _ = _check_written(summary, "wrist_r")
    assert st.t_s[-1] > 5.9  # the whole IMU recording, not 1 s (used to be 30 rows)
    assert not np.any(st.available[st.t_s > 2.1, j])  # no root (hips/shoulder) there
    assert np.all(source[st.t_s > 2.1] == SOURCE_PREDICTED)
    assert any("reference covers only" in w for w in summary["warnings"])


# ----------------------------------------------------------------------------------- case 11
def test_streams_that_do_not_overlap_say_so(synthetic_files, tmp_path):
    ref = _short_reference(synthetic_files, "truth_late.csv", lambda t: t > -1.0)
    late = read_joint_csv(synthetic_files / ref).reference
    write_joint_csv(
        synthetic_files / ref,
        dataclasses.replace(late, t_s=late.t_s + 100.0),
        role="reference",
        force=True,
    )
    body = NO_CAMERA.format(imu="imu.csv", ref=ref, method="paper-a", window=2.0, extra="")
    p = _base._write_session(synthetic_files, body, name="late_ref.toml")
    with pytest.raises(InputError, match="do not overlap in time") as err:
        run_session(p, tmp_path / "out")
    assert "calibration" not in str(err.value)


def test_single_sample_stream_says_so(synthetic_files, tmp_path):
    imu = _imu_variant(synthetic_files, "imu_one.csv", n=1)
    with pytest.raises(ConfigError, match="single valid sample") as err:
        run_session(_base._good(synthetic_files, imu=imu), tmp_path / "out")
    assert "calibration" not in str(err.value)


def _camera_gap(folder: Path, name: str, t0: float, t1: float) -> str:
    cam = read_joint_csv(folder / "camera.csv").vision
    avail = cam.available.copy()
    avail[(cam.t_s > t0) & (cam.t_s < t1)] = False
    pos = np.where(avail[..., None], cam.position_m, np.nan)
    write_joint_csv(
        folder / name, dataclasses.replace(cam, position_m=pos, available=avail), force=True
    )
    return name


@pytest.mark.parametrize(("gap_s", "available"), [(0.5, True), (2.0, False)])
def test_root_gap_is_bridged_or_predicted(synthetic_files, tmp_path, gap_s, available):
    # paper A with the shoulder from the camera: a short camera gap is interpolated (the
    # samples say "bridged"), a long one leaves the chain without a root (predicted)
    cam = _camera_gap(synthetic_files, f"camera_gap{gap_s}.csv", 3.0, 3.0 + gap_s)
    body = _base._good(synthetic_files).read_text().replace("camera.csv", cam)
    p = _base._write_session(synthetic_files, body, name=f"gap{gap_s}.toml")
    summary = run_session(p, tmp_path / "out")
    st, j, source, _, extra = _check_written(summary, "elbow_r")
    inside = (st.t_s > 3.05) & (st.t_s < 2.95 + gap_s)
    root = np.asarray(extra["root_covered"], dtype=float)[:, j]
    assert np.all(root[inside] == 0) and np.all(root[st.t_s < 2.9] == 1)
    assert np.all(st.available[inside, j] == available)
    want = SOURCE_BRIDGED if available else SOURCE_PREDICTED
    assert np.all(source[inside] == want)
    assert summary["coverage"]["elbow_r"]["bridged" if available else "predicted"] >= inside.sum()


def test_dropped_imu_packets_leave_no_hole_in_the_output_frames():
    """An IMU-only output follows the first sensor's clock; where that sensor dropped packets
    the frames stay uniform (TRC/.mot readers expect a constant rate), and a short gap is
    bridged, so those frames are available and exact (the arm hangs still)."""
    from scipy.spatial.transform import Rotation

    from kinefuse.io import ImuStream, Recording
    from kinefuse.pipelines.run import process_recording

    t = np.arange(300) / 100.0
    keep = np.ones(t.size, bool)
    keep[[120, 121, 200]] = False  # a 30 ms and a 20 ms hole in the upper arm's stream
    q = np.tile(Rotation.identity().as_quat(scalar_first=True), (t.size, 1))
    acc = np.tile([0.0, 0.0, 9.81], (t.size, 1))
    imu = {
        "upper_arm_r": ImuStream(t_s=t[keep], q_world_from_sensor=q[keep], acc_m_s2=acc[keep]),
        "forearm_r": ImuStream(t_s=t, q_world_from_sensor=q, acc_m_s2=acc),
    }
    params = {"root": "fixed", "root_position_m": [0.0, 0.0, 1.4], "calibration": "static"}
    out = process_recording(Recording(imu=imu), "imu-only", params, body_height_m=1.75)
    np.testing.assert_allclose(out.t_s, t, atol=1e-9)
    assert out.available.all()
    assert np.isnan(out.run_time_s)  # no filter ran: no "0.000 s" run-time table
    np.testing.assert_allclose(out.position, np.broadcast_to(out.position[:1], out.position.shape))
