"""Hips of a pelvis-rooted chain: from a functional calibration's hip centres when it fitted
them, else Winter's hip width along the pelvis right axis (pipelines.run.chain)."""

from types import SimpleNamespace

import numpy as np
import pytest

from kinefuse.pipelines.run.chain import HIP_WIDTH_RANGE_M, hip_offsets_in_pelvis_sensor


def _cal(r_l, r_r, proximal="pelvis", frames=None):
    fit = lambda r: SimpleNamespace(proximal=proximal, r_proximal_m=np.asarray(r, float))  # noqa: E731
    return SimpleNamespace(joints={"hip_l": fit(r_l), "hip_r": fit(r_r)}, frames=frames or {})


def test_functional_hip_centres_relative_to_their_midpoint():
    r_l, r_r = np.array([0.02, -0.11, -0.09]), np.array([0.04, 0.08, -0.10])
    off, how = hip_offsets_in_pelvis_sensor(_cal(r_l, r_r), 1.75)
    mid = (r_l + r_r) / 2
    np.testing.assert_allclose(off["hip_l"], r_l - mid, atol=1e-15)
    np.testing.assert_allclose(off["hip_r"], r_r - mid, atol=1e-15)
    assert "functional calibration" in how and f"{np.linalg.norm(r_r - r_l):.3f} m" in how


@pytest.mark.parametrize("width", [0.05, 0.6])
def test_implausible_functional_width_falls_back_to_winter(width):
    lo, hi = HIP_WIDTH_RANGE_M
    assert not lo <= width <= hi
    off, how = hip_offsets_in_pelvis_sensor(_cal([0, -width / 2, 0], [0, width / 2, 0]), 1.75)
    w = 0.0928 * 1.75  # OpenSim gait2392 spacing; right-front-up sensor: the right axis is sensor x
    np.testing.assert_allclose(off["hip_r"], [w / 2, 0, 0], atol=1e-15)
    np.testing.assert_allclose(off["hip_l"], [-w / 2, 0, 0], atol=1e-15)
    assert "outside" in how and "right-front-up" in how


def test_without_pelvis_fits_the_calibrated_pelvis_frame_is_used():
    F = np.eye(3)[:, [2, 0, 1]]  # a calibrated pelvis frame whose right axis (Z) is sensor y
    cal = SimpleNamespace(joints={}, frames={"pelvis": F})
    off, how = hip_offsets_in_pelvis_sensor(cal, 1.8)
    w = 0.0928 * 1.8
    np.testing.assert_allclose(off["hip_r"], w / 2 * F[:, 2], atol=1e-15)
    assert "calibrated pelvis frame" in how
    # hips fitted against another sensor (not the pelvis IMU) are not pelvis offsets
    off2, _ = hip_offsets_in_pelvis_sensor(_cal([0, -0.1, 0], [0, 0.1, 0], proximal="chest"), 1.8)
    np.testing.assert_allclose(off2["hip_r"], [0.0928 * 1.8 / 2, 0, 0], atol=1e-15)
