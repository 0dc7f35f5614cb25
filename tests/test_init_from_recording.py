"""`kinefuse init-session --from RECORDING`: a session filled from the user's own recording."""

from __future__ import annotations

import html
import json
import re
import textwrap

import pytest
from typer.testing import CliRunner

from conftest import cli_stderr
from kinefuse import cli
from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import ConfigError
from kinefuse.io._names import canonical_segment
from kinefuse.kinematics.skeleton import ANTHROPOMETRIC_RATIOS
from kinefuse.pipelines.run import run_session
from kinefuse.session_file import load_session
from kinefuse.session_file.from_recording import NO_HEIGHT_RATIO, sketch_recording

runner = CliRunner()


def _init(path, recording, *extra):
    return runner.invoke(cli.app, ["init-session", str(path), "--from", str(recording), *extra])


def test_ximu3_folder_becomes_a_session_that_runs(shared_data, tmp_path):
    """The x-IMU3 lower-body folder: the reader, the path and the seven sensors found by name;
    the feet (no body-height ratio) mapped for the ankle angles, with what their length would
    add; pelvis root, static calibration, IMU only; `kinefuse run` then gives the knees and
    ankles with anatomical knee flexion, and the ankle angles."""
    rec = shared_data / "xio_imu_mocap_lower_body"
    session = tmp_path / "walk.toml"
    res = _init(session, rec)
    assert res.exit_code == 0, (res.output, cli_stderr(res))
    assert "thigh_l = Left_Upper_Leg_64F61CC4" in " ".join(res.output.split())
    cfg = load_session(session)
    assert cfg.imu.format == "ximu3" and cfg.imu.path == rec.resolve()
    assert cfg.imu.segments == {
        "pelvis": "pelvis_64F0EDBF",
        "thigh_l": "Left_Upper_Leg_64F61CC4",
        "thigh_r": "Right_Upper_Leg_64F61C2E",
        "shank_l": "Left_Lower_Leg_64F61CB3",
        "shank_r": "Right_Lower_Leg_64F61B2A",
        "foot_l": "Left_Foot_64F0EBCE",
        "foot_r": "Right_Foot_64F619FB",
    }
    text = session.read_text(encoding="utf-8")
    assert 'foot_l = "Left_Foot_64F0EBCE"  # the ankle angles; [skeleton.lengths] foot_l' in text
    assert cfg.skeleton.root == "pelvis" and cfg.method.name == "imu-only"
    assert cfg.calibration.settings["method"] == "static"
    assert cfg.camera is None and cfg.reference is None
    summary = run_session(session, tmp_path / "out")
    assert set(summary.coverage) == {"knee_l", "knee_r", "ankle_l", "ankle_r"}
    for side in "lr":
        knee = summary.angles_deg[f"knee_{side}"]
        assert -10 <= knee["flexion_min"] and knee["flexion_max"] <= 150, knee
        assert knee["flexion_max"] > 90  # the recording squats and kneels
    assert {"ankle_l", "ankle_r"} <= set(summary.angles_deg)
    assert any("foot_l, foot_r: IMUs used for the ankle angles only" in n for n in summary.notes)
    assert not [w for w in summary.warnings if "in the calibration pose" in w]


def test_a_walk_without_a_still_pose_gets_functional_calibration_and_runs(shared_data, tmp_path):
    """The Neura walk starts moving at once: a static calibration would stop with "no still
    window", so the template chooses functional calibration and says why, and maps the feet
    (their IMUs locate the ankles). Its Vicon reference is filled for evaluation only. The
    session then runs as written (before: the user had to edit the calibration and the feet)."""
    rec = shared_data / "neura_sparse_sample"
    session = tmp_path / "neura.toml"
    res = _init(session, rec)
    assert res.exit_code == 0, (res.output, cli_stderr(res))
    assert "functional calibration: no still window of 2 s" in " ".join(res.output.split())
    cfg = load_session(session)
    assert cfg.imu.format == "neura" and cfg.reference is not None
    assert cfg.reference.path == rec.resolve() and cfg.reference.align == "none"
    assert cfg.skeleton.root == "pelvis"  # not the reference: evaluation only by default
    assert cfg.calibration.settings["method"] == "functional"
    assert {"foot_l", "foot_r"} <= set(cfg.imu.segments)
    text = session.read_text(encoding="utf-8")
    assert 'method = "functional"  # no still window of 2 s for a static calibration' in text
    summary = run_session(session, tmp_path / "out")
    assert set(summary.coverage) == {"knee_l", "knee_r", "ankle_l", "ankle_r"}
    assert all(c["available"] > 0.9 * c["samples"] for c in summary.coverage.values())


def test_a_still_pose_keeps_static_calibration_and_feet_lengths_add_toes(shared_data, tmp_path):
    """The other side of the choice above: x-IMU3 holds still at the start. With the feet's
    lengths measured, as the template's comment says, the run adds the toes to the ankle
    angles (dorsiflexion positive, zero in the pose, within a plausible range: the recording
    squats and kneels)."""
    session = tmp_path / "x.toml"
    assert _init(session, shared_data / "xio_imu_mocap_lower_body").exit_code == 0
    assert load_session(session).calibration.settings["method"] == "static"
    text = session.read_text(encoding="utf-8")
    assert "no still window" not in text
    assert "the ankle angles; [skeleton.lengths] foot_l (ankle to toe) adds the toe" in text
    lengths = "[skeleton.lengths]\nfoot_l = 0.15\nfoot_r = 0.15\n#"
    session.write_text(text.replace("# [skeleton.lengths]", lengths), encoding="utf-8")
    summary = run_session(session, tmp_path / "out")
    assert {"foot_l", "foot_r"} <= set(summary.coverage)
    for side in "lr":
        ankle = summary.angles_deg[f"ankle_{side}"]
        assert -60 <= ankle["flexion_min"] < -5 and 5 < ankle["flexion_max"] <= 40, ankle
    assert not any("ankle" in w for w in summary.warnings), summary.warnings


def test_hand_imus_are_segments_that_locate_the_wrist(shared_data, tmp_path):
    """A hand IMU (Xsens suits, qmt) maps to hand_l/hand_r; with functional calibration it
    locates the wrist centre and is not an output segment (nothing locates the fingertips).
    Before, [imu.segments] refused 'hand_r' while the calibration asked for it."""
    assert canonical_segment("LeftHand") == "hand_l"
    assert canonical_segment("hand_right") == "hand_r"
    qmt = shared_data / "qmt_full_body_example" / "full_body_example_data.mat"
    session = tmp_path / "arm.toml"
    session.write_text(
        textwrap.dedent(f"""\
            [session]
            name = "arm"
            [imu]
            format = "qmt"
            path = "{qmt.as_posix()}"
            [imu.segments]
            upper_arm_r = "upper_arm_right"
            forearm_r = "forearm_right"
            hand_r = "hand_right"
            [skeleton]
            root = "fixed"
            root_position_m = [0.0, 0.0, 1.40]
            [skeleton.lengths]
            upper_arm_r = 0.30
            forearm_r = 0.26
            [calibration]
            method = "functional"
            [method]
            name = "imu-only"
            """),
        encoding="utf-8",
    )
    summary = run_session(session, tmp_path / "out")
    assert set(summary.coverage) == {"elbow_r", "wrist_r"}
    assert summary.coverage["wrist_r"]["available"] == summary.coverage["wrist_r"]["samples"]
    assert any("hand_r: IMUs used for the wrist centres only" in n for n in summary.notes)


def test_an_angle_off_zero_in_the_calibration_pose_is_a_warning(shared_data, tmp_path):
    """The DOT data as converted for MT Manager (both legs): the knees' flexion axes imply
    facings 148 deg apart, so the facing stays north and the pelvis frame disagrees with the
    left thigh's: hip_l reads -150 deg of rotation in the pose, where every angle is zero by
    construction. That is said; the x-IMU3 walk (test above) says nothing of the kind."""
    rec = shared_data / "third_party" / "xsens" / "dot_transformed_mtmanager"
    session = tmp_path / "dot.toml"
    assert _init(session, rec).exit_code == 0
    summary = run_session(session, tmp_path / "out")
    said = [w for w in summary.warnings if "in the calibration pose" in w]
    assert len(said) == 1 and re.match(r"hip_l reads internal rotation -15\d deg", said[0]), said
    # nearly backwards: what a swapped thigh/shank pair gives (LFemur and LTibia are swapped
    # in this recording: mapped the other way round, both knees agree on the facing)
    assert "are the sensors of thigh_l and shank_l swapped in [imu.segments]" in said[0]
    assert 'heading = "static"' in said[0]


def test_both_arms_get_the_mid_shoulder_point_as_their_root(shared_data, tmp_path):
    """Xsens MVNX (trunk, both arms and hands): root 'fixed' is the mid-shoulder point, the
    shoulders hang from the chest IMU (tests/test_trunk_shoulders.py) and the template says so."""
    mvnx = shared_data / "third_party" / "xsens" / "blender-mvnx-io_test_mocap.mvnx"
    session = tmp_path / "ub.toml"
    res = _init(session, mvnx)
    assert res.exit_code == 0, (res.output, cli_stderr(res))
    text = session.read_text(encoding="utf-8")
    assert 'chest = "T8"' in text and 'root = "fixed"' in text
    assert "the mid-shoulder point, m; the shoulders hang from the chest IMU" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("chest = "))
    assert line.endswith("# the shoulders hang from it"), line  # functional: no angles there


def test_one_leg_with_the_pelvis_places_only_its_hip(shared_data, tmp_path):
    """Xsens DOT: pelvis + left thigh and shank only. The pelvis root used to place both hips
    and the chain refused the unknown hip_r; now the session runs for the left leg."""
    rec = shared_data / "third_party" / "xsens" / "dot_realtime"
    session = tmp_path / "dot.toml"
    assert _init(session, rec).exit_code == 0
    assert set(load_session(session).imu.segments) == {"pelvis", "thigh_l", "shank_l"}
    summary = run_session(session, tmp_path / "out")
    assert set(summary.coverage) == {"knee_l", "ankle_l"}
    # the reader's count of dropped packets reaches the terminal (it was in metadata only)
    assert any(
        w.startswith("imu: LFemur (thigh_l): 157 packets dropped") for w in summary.warnings
    ), summary.warnings
    assert all(c["available"] > 0 for c in summary.coverage.values())


def test_one_thigh_without_the_pelvis_starts_at_its_hip(shared_data, tmp_path):
    """A single Xsens DOT on the right thigh: the chain starts at hip_r, whose position the
    fixed root gives (as paper A's shoulder). Before, the run refused it ("the hips are placed
    from the pelvis IMU") although one measured position fixes a single chain."""
    rec = shared_data / "third_party" / "xsens" / "dot_transformed_mtmanager"
    session = tmp_path / "thigh.toml"
    res = _init(session, rec / "XSDot_20210820_202113_RFemur.txt")
    assert res.exit_code == 0
    # the file is one sensor of a five-sensor recording: the message says how to map them all
    assert f"one sensor of the recording in {rec}: --from that folder" in " ".join(
        res.output.split()
    )
    assert "the measured root joint (hip_r), m" in session.read_text(encoding="utf-8")
    summary = run_session(session, tmp_path / "out")
    assert summary.coverage["knee_r"]["available"] == summary.coverage["knee_r"]["samples"] > 0
    assert (
        "# frame: xsens_global_z_up, relative to hip_r"
        in (tmp_path / "out" / "thigh_joints.csv").read_text()
    )
    # two thighs without the pelvis: one position cannot place both hips (refused, with how)
    legs = tmp_path / "legs.toml"
    assert _init(legs, shared_data / "xio_imu_mocap_lower_body").exit_code == 0
    text = legs.read_text(encoding="utf-8").replace('pelvis = "pelvis_64F0EDBF"\n', "")
    legs.write_text(text.replace('root = "pelvis"', 'root = "fixed"'), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"hips \['hip_l', 'hip_r'\] are placed from the pelvis"):
        run_session(legs, tmp_path / "out2")


def test_a_sensor_without_a_segment_name_is_left_for_the_user_to_map(shared_data, tmp_path):
    """x-io's single-sensor CSV: the sensor's name says no segment; the template lists it
    commented and the message says what to do before `kinefuse run` (which refuses)."""
    rec = shared_data / "third_party" / "x-io" / "gait-tracking_short_walk.csv"
    session = tmp_path / "one.toml"
    res = _init(session, rec)
    assert res.exit_code == 0, (res.output, cli_stderr(res))
    said = " ".join(res.output.split())
    assert "segments none; not recognised: gait-tracking_short_walk" in said
    assert "Name each sensor's segment in [imu.segments]" in said and "Check it" not in said
    assert '# ??? = "gait-tracking_short_walk"  # not recognised' in session.read_text()


def test_functional_lengths_are_checked_against_the_body_height_lengths(shared_data, tmp_path):
    """The warning for a functional length far from the expected one quotes the length the
    session gives (here body height 1.0 m: thigh 0.245 m), not the placeholder the chain was
    built with before the calibration (0.300 m for every segment)."""
    session = tmp_path / "x.toml"
    assert _init(session, shared_data / "xio_imu_mocap_lower_body").exit_code == 0
    text = session.read_text(encoding="utf-8").replace('method = "static"', 'method = "functional"')
    text = text.replace("body_height_m = 1.75", "body_height_m = 1.0")  # the feet are mapped
    session.write_text(text, encoding="utf-8")
    summary = run_session(session, tmp_path / "out")
    said = " ".join(summary.warnings + summary.notes)
    assert "segment 'thigh_l' spans" in said and "the skeleton says 0.245 m" in said
    assert "the skeleton says 0.300 m" not in said


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--format", "ximu3"], ["--format is for --from RECORDING"]),
        (["--from", "nowhere.csv"], ["--from nowhere.csv: file or folder not found"]),
        (["--from", "{kinect}"], ["no IMU stream in this kinect_v2 recording", "[camera] path"]),
        (["--from", "{trc}"], ["no IMU stream in this trc recording", "[reference] path"]),
        (["--from", "{kinect}", "--format", "nope"], ["--format: unknown reader 'nope'"]),
    ],
)
def test_bad_input_is_one_line(args, needles, shared_data, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    kinect = shared_data / "third_party" / "kinect_v2" / "lslkinect_MoCap.csv"
    trc = shared_data / "third_party" / "trc" / "opensim_subject01_walk1.trc"
    args = [a.replace("{kinect}", str(kinect)).replace("{trc}", str(trc)) for a in args]
    res = runner.invoke(cli.app, ["init-session", "s.toml", *args])
    assert res.exit_code == 2, (res.output, cli_stderr(res))
    err = cli_stderr(res).strip()
    assert len(err.splitlines()) == 1 and all(n in err for n in needles), err
    assert not (tmp_path / "s.toml").exists()


def test_no_height_ratio_is_the_skeleton_s():
    """session_file cannot import kinematics: its list of segments without a body-height
    ratio must match kinematics.skeleton.ANTHROPOMETRIC_RATIOS."""
    limbs = [s for s in SEGMENTS if s not in ("chest", "pelvis")]
    assert set(NO_HEIGHT_RATIO) == {s for s in limbs if s[:-2] not in ANTHROPOMETRIC_RATIOS}


def test_sketch_paths_are_relative_below_the_session_else_absolute(shared_data, tmp_path):
    rec = shared_data / "xio_imu_mocap_lower_body"
    assert sketch_recording(rec, rec.parent).path == "xio_imu_mocap_lower_body"
    assert sketch_recording(rec, tmp_path).path == str(rec.resolve())


@pytest.mark.parametrize(
    "kind", ["Inertial/a9_s1_t1_inertial.mat", "Skeleton/a9_s1_t1_skeleton.mat"]
)
def test_a_utd_mhad_trial_from_either_file_names_both_and_runs(kind, shared_data, tmp_path):
    """A UTD-MHAD trial is two files read as a pair: from either one, the session names the
    inertial file in [imu] and the skeleton file in [camera], and `kinefuse run` reads them
    (the camera section had the inertial file: 'missing variable d_skel')."""
    utd = shared_data / "utd_mhad"
    session = tmp_path / "utd.toml"
    res = _init(session, utd / kind)
    assert res.exit_code == 0, (res.output, cli_stderr(res))
    cfg = load_session(session)
    assert cfg.imu.path == (utd / "Inertial/a9_s1_t1_inertial.mat").resolve()
    assert cfg.camera.path == (utd / "Skeleton/a9_s1_t1_skeleton.mat").resolve()
    summary = run_session(session, tmp_path / "out")
    assert "wrist_r" in summary.coverage


def test_a_reference_without_the_output_joints_is_said_not_scored(shared_data, tmp_path):
    """BROAD: the reference is the optical rigid body 'imu', not a joint the chain outputs.
    The run says once that nothing is scored and why (it said the reference covered 0 % of
    the samples and that the metrics were computed on that part, then gave frame advice)."""
    rec = shared_data / "broad" / "data_mat" / "04_undisturbed_slow_rotation_with_breaks_A.mat"
    session = tmp_path / "b.toml"
    assert _init(session, rec).exit_code == 0
    text = session.read_text(encoding="utf-8")
    session.write_text(text.replace("[imu.segments]\n", '[imu.segments]\nforearm_r = "imu"\n', 1))
    summary = run_session(session, tmp_path / "out")
    said = [w for w in summary.warnings if "not scored" in w or "covers only" in w]
    assert said == [
        "not scored: the reference has none of the output joints (wrist_r); it has ['imu']"
    ]
    assert summary.evaluation is None


def test_6d_limbs_read_zero_in_the_pose(shared_data, tmp_path):
    """qmt full body (6-D, sensors strapped with different headings): each limb is turned to
    its fitted flexion axis (heading auto = static), so no shoulder or hip reads a rotation in
    the pose (they read 69, -125, -41 and 128 deg when the sensors' headings were taken as
    alike on the body), and the right knee's axis is fitted robustly."""
    session = tmp_path / "q.toml"
    assert _init(session, shared_data / "qmt_full_body_example").exit_code == 0
    summary = run_session(session, tmp_path / "out")
    said = [w for w in summary.warnings if "in the calibration pose" in w]
    assert not said, said
    # the right leg reads within the anatomical ranges (least squares alone: knee_r's axis
    # 58 deg tilted by the walk's outliers, then -90 to 71 deg of flexion)
    assert not [w for w in summary.warnings if w.startswith(("knee_r", "ankle_r", "hip_r"))]
    assert not [w for w in summary.warnings if "flexion axis of knee_r" in w]
    prov = json.loads((tmp_path / "out" / "provenance.json").read_text(encoding="utf-8"))
    assert set(prov["limb_heading_deg"]) == {"elbow_l", "elbow_r", "knee_l", "knee_r"}
    # the run's warnings: in the report's warnings box, not repeated in its notes
    page = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    box, notes = page.split("<h2>Notes</h2>")
    assert summary.warnings and 'class="warnings"' in box
    assert all(html.escape(w) in box and html.escape(w) not in notes for w in summary.warnings)
    # the coverage per joint: a table in the report, not eight notes
    assert "<h2>Coverage</h2>" in notes and "coverage knee_l:" not in notes
    assert any(n.startswith("coverage knee_l:") for n in summary.notes)  # still in the result


def test_a_file_holding_every_sensor_is_not_called_one_sensor(shared_data, tmp_path):
    """The qmt example's one .mat holds all 16 sensors (its folder reads the same file): no
    advice to pass the folder instead. The DOT case (one file per sensor) keeps it (above)."""
    rec = shared_data / "qmt_full_body_example" / "full_body_example_data.mat"
    res = _init(tmp_path / "qmt.toml", rec)
    assert res.exit_code == 0, (res.output, cli_stderr(res))
    assert "one sensor of the recording" not in " ".join(res.output.split())


def test_init_session_names_a_folder_path_before_asking_for_force(shared_data, tmp_path):
    rec = shared_data / "xio_imu_mocap_lower_body"
    res = _init(tmp_path, rec)
    assert res.exit_code == 2
    err = " ".join(cli_stderr(res).split())
    assert f"PATH {tmp_path}: is a folder, expected a file name" in err, err


def test_init_session_errors_name_the_recording(tmp_path):
    """A recording kinefuse reads but cannot sketch (one sample: no time span for the still
    window): the error names the file and no internal function."""
    csv = tmp_path / "one.csv"
    csv.write_text(
        "# kinefuse-imu-csv 1\nt_s,sensor,qw,qx,qy,qz\n0.0,thigh_r,1,0,0,0\n0.0,shank_r,1,0,0,0\n",
        encoding="utf-8",
    )
    res = _init(tmp_path / "s.toml", csv)
    err = " ".join(cli_stderr(res).split())
    assert res.exit_code == 2 and "share no time span" in err, err
    assert "find_still_window" not in err and err.startswith(f"kinefuse: error: {csv}:"), err
