"""Tests of paper A's pipeline (kinefuse.pipelines.upper_limb; SPEC §11)."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.conventions import MODE_FIR, MODE_KF, MODE_PREDICT
from kinefuse.filters import KalmanFilter
from kinefuse.filters.em_kalman import EMKalmanFilter
from kinefuse.filters.integrated import IntegratedFilter
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.io.recording import JointStream
from kinefuse.models import constant_velocity
from kinefuse.pipelines import UpperLimbResult, upper_limb

DT = 1 / 30


@pytest.fixture(scope="module")
def arm():
    rng = np.random.default_rng(5)
    T = 300
    t = np.arange(T) * DT
    elbow = np.stack([0.3 * np.sin(t), 0.1 * np.cos(2 * t), 1.1 + 0.05 * t], axis=-1)
    wrist = elbow + np.stack([0.25 * np.cos(1.5 * t), 0.25 * np.sin(1.5 * t), 0 * t], axis=-1)
    z_e = elbow + rng.normal(0, 0.02, elbow.shape)
    z_w = wrist + rng.normal(0, 0.02, wrist.shape)
    z_w[100:110] = np.nan
    return z_e, z_w


def _direct(flt, z_e, z_w):
    _, res = flt.filter(np.stack([z_e, z_w]))
    return res


def test_kf_equals_kalman_filter(arm):
    z_e, z_w = arm
    r = upper_limb(z_e, z_w, DT, "kf", q=0.5, r=0.02)
    ref = _direct(KalmanFilter(constant_velocity(DT, 0.5, 0.02)), z_e, z_w)
    assert isinstance(r, UpperLimbResult) and r.joints == ("elbow", "wrist")
    np.testing.assert_array_equal(r.position, ref.position.transpose(1, 0, 2))
    np.testing.assert_array_equal(r.cov, ref.cov[..., 0::2, 0::2].transpose(1, 0, 2, 3))
    np.testing.assert_array_equal(r.distance, ref.distance.T)
    np.testing.assert_array_equal(r.mode[100:110, 1], MODE_PREDICT)
    assert np.all(r.mode[:100] == MODE_KF)


@pytest.mark.parametrize(
    ("method", "make"),
    [
        ("em-kf-fir", lambda m: IntegratedFilter(m, 20, 2.0, 2.0, 3)),
        ("fir", lambda m: UFIRFilter(m, horizon=20)),
        ("em-kf", lambda m: EMKalmanFilter(m, n_iter=3)),
    ],
)
def test_methods_equal_their_filters(arm, method, make):
    z_e, z_w = arm
    r = upper_limb(z_e, z_w, DT, method)
    ref = _direct(make(constant_velocity(DT, 0.1, 0.01)), z_e, z_w)
    np.testing.assert_array_equal(r.position, ref.position.transpose(1, 0, 2))
    if method == "em-kf-fir":
        np.testing.assert_array_equal(r.mode, ref.mode.T)
        np.testing.assert_array_equal(r.distance2, ref.distance2.T)
    if method == "fir":
        assert np.all(r.mode[:18] == MODE_KF) and np.all(r.mode[30:100] == MODE_FIR)
        nu = ref.innovation.transpose(1, 0, 2)
        np.testing.assert_allclose(r.distance, np.sum(nu**2, -1) / 0.01)


def test_per_joint_noise_equals_separate_runs(arm):
    z_e, z_w = arm
    both = upper_limb(z_e, z_w, DT, "em-kf-fir", q=(1.0, 0.1), r=(0.01, 0.1))
    e = upper_limb(z_e, None, DT, "em-kf-fir", q=1.0, r=0.01)
    w = upper_limb(z_w, None, DT, "em-kf-fir", q=0.1, r=0.1, joints=("wrist",))
    np.testing.assert_array_equal(both.position[:, 0], e.position[:, 0])
    np.testing.assert_array_equal(both.position[:, 1], w.position[:, 0])


def test_chain_joint_stream_input(arm):
    z_e, z_w = arm
    t = 2.0 + np.arange(z_e.shape[0]) * DT
    sh = np.zeros_like(z_e)
    st = JointStream(
        t_s=t, position_m=np.stack([sh, z_e, z_w], 1), joints=("shoulder_r", "elbow_r", "wrist_r")
    )
    r = upper_limb(st, method="kf")
    a = upper_limb(z_e, z_w, DT, "kf")
    assert r.joints == ("elbow_r", "wrist_r") and r.t_s is st.t_s
    np.testing.assert_allclose(r.position, a.position, atol=1e-9)


def test_bad_input(arm):
    z_e, z_w = arm
    with pytest.raises(
        ValueError, match=r"expected z_wrist with the shape of z_elbow \(300, 3\), got \(299, 3\)"
    ):
        upper_limb(z_e, z_w[1:], DT)
    with pytest.raises(ValueError, match=r"expected z_elbow with shape \(T, 3\), got \(300, 2\)"):
        upper_limb(z_e[:, :2], z_w, DT)
    with pytest.raises(ValueError, match=r"unknown method 'ukf'; expected one of"):
        upper_limb(z_e, z_w, DT, "ukf")
    for dt in (0.0, -0.1):
        with pytest.raises(ValueError, match=r"expected dt_s finite and > 0, got"):
            upper_limb(z_e, z_w, dt)
    with pytest.raises(
        ValueError, match=r"expected q as a scalar or one value per joint \(2\), got 3"
    ):
        upper_limb(z_e, z_w, DT, q=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match=r"expected r finite and > 0"):
        upper_limb(z_e, z_w, DT, r=0.0)


def test_from_recording_on_virtual_cmu():
    import kinefuse.sim as sim
    from kinefuse.data import demo_motion
    from kinefuse.pipelines import upper_limb_from_recording

    rec = sim.virtual_recording(demo_motion(0.0, 6.0), seed=2)
    r = upper_limb_from_recording(rec, "r", source="reference", method="kf", q=1.0, r=0.01)
    ref = np.stack([rec.reference.position(j) for j in r.joints], axis=1)
    assert r.position.shape == ref.shape and r.joints == ("elbow_r", "wrist_r")
    np.testing.assert_array_equal(r.t_s, rec.reference.t_s)
    err = np.sqrt(np.mean(np.sum((r.position - ref) ** 2, axis=-1), axis=0))
    assert np.all(err < 0.05), err


def test_a_chain_stream_off_its_grid_or_a_wrong_dt_is_refused():
    """upper_limb filtered a JointStream with a 5-s hole, or a dt_s of 0.01 on a 30-Hz
    stream, as if its samples were dt apart: silently wrong positions."""
    from kinefuse.exceptions import InputError
    from kinefuse.io.recording import JointStream
    from kinefuse.pipelines import upper_limb

    t = np.arange(90) / 30.0
    p = np.zeros((90, 2, 3))
    st = JointStream(t_s=t, position_m=p, joints=("elbow_r", "wrist_r"))
    with pytest.raises(InputError, match="dt_s = 0.01 s differs from the chain stream's"):
        upper_limb(st, dt_s=0.01)
    holed = JointStream(t_s=np.r_[t[:45], t[45:] + 5.0], position_m=p, joints=st.joints)
    with pytest.raises(InputError, match="expected the chain stream on a regular timeline"):
        upper_limb(holed)
    upper_limb(st)  # regular: runs
