"""`kinefuse experiment realism`: virtual sensors next to real ones (quick configuration)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.apps.experiments import EXPERIMENTS, run_experiment
from kinefuse.apps.realism import (
    REPORT,
    TOLERANCE,
    TUNING,
    knee_off_axis_share,
    orientation_error_deg,
)
from kinefuse.exceptions import InputError


def test_orientation_error_matches_scipy_angle():
    a = Rotation.random(50, random_state=1)
    b = Rotation.random(50, random_state=2)
    qa, qb = a.as_quat(scalar_first=True), b.as_quat(scalar_first=True)
    qb[3] = np.nan
    qa[5] *= -1.0  # q and -q are the same rotation
    e = orientation_error_deg(qa, qb)
    ref = np.degrees((a * b.inv()).magnitude())
    assert np.isnan(e[3])
    np.testing.assert_allclose(np.delete(e, 3), np.delete(ref, 3), atol=1e-6)


def test_knee_off_axis_share_is_near_zero_for_a_hinge_and_not_for_real_knees(shared_data):
    """Measure (iv): CMU's own 1-DoF knees seen by ideal sensors are hinges (share near 0); the
    simulator's knees (secondary rotations, kinefuse.sim.knee) are not; the real x-IMU3 knees
    move off their flexion axis (the realism check prints 0.41)."""
    from kinefuse.io import load
    from kinefuse.io.cmu import load_motion_asf_amc
    from kinefuse.sim import ImuConfig, virtual_recording

    root = shared_data / "cmu_mocap" / "asfamc" / "02"
    motion = load_motion_asf_amc(root / "02_01.amc", root / "02.asf")
    legs = ("pelvis", "thigh_l", "thigh_r", "shank_l", "shank_r", "foot_l", "foot_r")
    hinge = virtual_recording(
        motion, imu=ImuConfig.ideal(), camera=None, segments=legs, seed=3, knee_secondary=0.0
    )
    assert knee_off_axis_share(hinge) < 0.03
    rec = virtual_recording(motion, imu=ImuConfig.ideal(), camera=None, segments=legs, seed=3)
    assert knee_off_axis_share(rec) > 0.05
    assert knee_off_axis_share(load(shared_data / "xio_imu_mocap_lower_body")) > 0.3


def test_tuning_and_report_sets_are_disjoint():
    for key in TUNING:
        assert not set(TUNING[key]) & set(REPORT[key]), key


def test_realism_quick_runs_all_five_measures(shared_data):
    assert "realism" in EXPERIMENTS
    out = run_experiment("realism", shared_data, quick=True, quiet=True)
    rows = out["results"]["rows"]
    measures = {r["measure"][:5] for r in rows}
    assert measures == {"(i) B", "(ii) ", "(iii)", "(iv) ", "(v) I"}
    assert {r["set"] for r in rows} == {"tuning", "report"}
    for r in rows:
        assert np.isfinite(r["real"]) and r["real"] > 0 and r["virtual"] > 0, r
        assert r["within_tolerance"] == (abs(r["virtual"] / r["real"] - 1) <= TOLERANCE)
    (table,) = out["tables"]
    assert table.value_headers[:2] == ("Real", "Virtual")
    assert any("QUICK" in n for n in out["notes"])


def test_realism_needs_the_data(tmp_path):
    with pytest.raises(InputError, match="broad"):
        run_experiment("realism", tmp_path, quick=True, quiet=True)


def test_imu_only_measure_is_the_neura_experiments_first_row(shared_data):
    """Measure (v) on the Neura walk is the mean of ``kinefuse experiment neura-imu-only``'s
    'functional (IMU only), tape lengths' row (the same procedure, called twice)."""
    from kinefuse.apps.neura_imu_only import TAPE_LENGTHS_M, run_neura_imu_only
    from kinefuse.apps.realism import imu_only_chain_error_cm
    from kinefuse.io import load

    row = run_neura_imu_only(shared_data)["results"]["rows"][0]
    assert row["label"] == "functional (IMU only), tape lengths"
    expected = 100 * np.mean([row[j] for j in ("knee_l", "knee_r", "ankle_l", "ankle_r")])
    rec = load(shared_data / "neura_sparse_sample", format="neura")
    assert imu_only_chain_error_cm(rec, TAPE_LENGTHS_M) == pytest.approx(expected, rel=1e-12)
