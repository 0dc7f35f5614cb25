"""kinefuse.io.load: format registry, detection, clear errors."""

from __future__ import annotations

import pytest

import kinefuse.io as kio
from kinefuse.exceptions import FormatError, InputError


def test_formats_listing():
    for name in (
        "utd_mhad",
        "opensense",
        "qmt",
        "ximu3",
        "broad",
        "c3d",
        "trc",
        "kinect_v2",
        "azure_kinect",
        "mediapipe",
        "imu_csv",
        "joint_csv",
        "neura",
        "cmu",
        "bvh",
    ):
        assert name in kio.FORMATS and kio.FORMATS[name]
    assert (
        callable(kio.read_trc)
        and callable(kio.write_joint_csv)
        and callable(kio.estimate_clock_offset)
    )
    with pytest.raises(AttributeError):
        kio.read_nonexistent  # noqa: B018


def test_unknown_format_lists_known(tmp_path):
    f = tmp_path / "x.csv"
    f.write_text("a,b\n1,2\n")
    with pytest.raises(
        ValueError, match=r"unknown format 'vicon_x'; known formats: azure_kinect, broad, bvh, c3d"
    ):
        kio.load(f, format="vicon_x")


def test_undetectable_and_missing(tmp_path):
    f = tmp_path / "notes.xyz"
    f.write_text("hello\n")
    with pytest.raises(
        FormatError,
        match=r"notes.xyz: unsupported format: this looks like a text file without a recognisable "
        r"header \(.xyz\); kinefuse reads: .*, trc, .*--format NAME \(Python: format=NAME\)",
    ):
        kio.load(f)
    with pytest.raises(FileNotFoundError, match="nope.csv: no such file"):
        kio.load(tmp_path / "nope.csv")
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(FormatError, match="unsupported format: this looks like an empty file"):
        kio.load(empty)
    with pytest.raises(FormatError, match="empty or truncated"):
        kio.load(empty, format="joint_csv")


def test_dataset_root_and_asf_hints(shared_data):
    with pytest.raises(FormatError, match="UTD-MHAD dataset root; pass one trial's file"):
        kio.load(shared_data / "utd_mhad")
    asf = shared_data / "cmu_mocap" / "asfamc" / "02" / "02.asf"
    with pytest.raises(FormatError, match=r"pass the motion \(.amc\) file"):
        kio.load(asf)


def test_explicit_format_and_options(shared_data):
    f = shared_data / "utd_mhad" / "Inertial" / "a1_s1_t1_inertial.mat"
    rec = kio.load(f, format="utd_mhad", skeleton_rate_hz=30.0, segment="forearm_r")
    assert rec.vision.t_s[1] == pytest.approx(1 / 30)
    assert rec.metadata["units_converted"] == ["acc g -> m/s^2", "gyr deg/s -> rad/s"]
    assert {"subject", "source", "format", "units_converted"} <= set(rec.metadata)


def test_load_names_a_wrong_path_type_and_unknown_reader_options(shared_data):
    """load(5) raised a TypeError from pathlib; load(path, foo=1) one naming read_neura."""
    with pytest.raises(InputError, match="expected path as a file or folder path, got int"):
        kio.load(5)
    with pytest.raises(InputError, match=r"unknown option\(s\) \['foo'\] for the 'neura' reader"):
        kio.load(shared_data / "neura_sparse_sample", foo=1)


def test_writers_refuse_what_their_readers_would_refuse(shared_data, tmp_path):
    """write_trc wrote DataRate 'abc' (read_trc then refused the file); decimals=-1 failed
    in a format string."""
    from kinefuse.io.trc import write_trc

    ref = kio.load(shared_data / "neura_sparse_sample").reference
    with pytest.raises(InputError, match=r"DataRate='abc': expected a rate > 0"):
        write_trc(tmp_path / "a.trc", ref, header={"DataRate": "abc"})
    with pytest.raises(InputError, match="expected decimals as an integer from 0 to 17, got -1"):
        write_trc(tmp_path / "b.trc", ref, decimals=-1)
    assert not (tmp_path / "a.trc").exists() and not (tmp_path / "b.trc").exists()


def test_write_mot_refuses_a_file_its_reader_would_refuse(tmp_path):
    import numpy as np

    from kinefuse.io.mot import write_mot

    t = np.arange(5) / 100.0
    with pytest.raises(InputError, match="at least one column besides time"):
        write_mot(tmp_path / "a.mot", t, {})
    with pytest.raises(InputError, match="expected name as one non-empty line"):
        write_mot(tmp_path / "b.mot", t, {"knee_flexion": t}, name="a\nb")
