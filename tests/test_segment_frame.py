"""The segment-frame chain-error model of ``"kinefuse"`` (``segment_rotations``)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError
from kinefuse.io import load
from kinefuse.kinematics import full_body
from kinefuse.pipelines import vision_assisted
from kinefuse.pipelines.features import joint_rotations, joint_segments, segment_frame_design
from kinefuse.pipelines.kinefuse_fusion import kinefuse_fusion
from kinefuse.pipelines.kinefuse_ridge import AxisRidgeCorrection
from kinefuse.pipelines.run import process_recording

DT = 1 / 30


def _rotations(T, n, seed):
    """n smooth, varied rotation sequences (T, 3, 3): rotation vectors of a few slow sines."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    out = []
    for _ in range(n):
        f = rng.uniform(0.2, 0.7, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        rv = 1.2 * np.sin(2 * np.pi * f * t[:, None] + ph) + rng.normal(0, 0.3, 3)
        out.append(Rotation.from_rotvec(rv).as_matrix())
    return out


def test_design_columns_follow_the_documented_model():
    # e_i = c_i + Σ_s R_s[i, :] δ_s: built here from the documented column layout (indicators,
    # then 3 columns per segment), compared with direct evaluation
    T = 200
    R0, R1 = _rotations(T, 2, seed=1)
    c, d0, d1 = np.random.default_rng(2).normal(0, 0.03, (3, 3))
    want = c + np.einsum("tij,tj->ti", R0, np.broadcast_to(d0, (T, 3)))
    want += np.einsum("tij,j->ti", R1, d1)
    X = segment_frame_design([[R0, R1]])
    assert X.shape == (T, 1, 3, 9)
    np.testing.assert_allclose(X[:, 0] @ np.concatenate([c, d0, d1]), want, rtol=0, atol=1e-12)


def test_design_pads_joints_with_fewer_segments_and_keeps_missing_rows_nan():
    R0, R1 = _rotations(50, 2, seed=3)
    R1 = R1.copy()
    R1[10] = np.nan
    X = segment_frame_design([[R0], [R0, R1]])
    assert X.shape == (50, 2, 3, 9)
    assert np.all(X[:, 0, :, 6:] == 0)  # one segment: 3 + 3 columns, then padding
    assert np.all(np.isnan(X[10, 1, :, 6:])) and np.all(np.isfinite(X[11, 1]))
    with pytest.raises(InputError, match="expected rotations with shape"):
        segment_frame_design([[R0, R1[:10]]])
    with pytest.raises(InputError, match="at least one segment"):
        segment_frame_design([[]])


def test_axis_ridge_without_penalty_is_least_squares():
    # oracle: numpy's least squares on the stacked rows (shared coefficients, one intercept)
    rng = np.random.default_rng(4)
    n, K = 300, 5
    X = rng.normal(size=(n, 3, K))
    theta = rng.normal(size=K)
    Y = X @ theta + 0.3 + rng.normal(0, 0.01, (n, 3))
    reg = AxisRidgeCorrection(alphas=(1e-12,), block=30).fit(X, Y)
    A = np.concatenate([X.reshape(-1, K), np.ones((3 * n, 1))], axis=1)
    sol = np.linalg.lstsq(A, Y.reshape(-1), rcond=None)[0]
    np.testing.assert_allclose(reg.coef_[:, 0], sol[:K], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(reg.intercept_[0], sol[K], rtol=1e-6)
    np.testing.assert_allclose(reg.predict(X), (A @ sol).reshape(n, 3), rtol=0, atol=1e-9)
    assert reg.block == 30


def _limb(T=900, seed=0, outage=(450, 540)):
    """A joint carried by two rotating segments; the chain is off by constant vectors in the
    segments' sensor frames (a mis-calibration); camera = truth + 5 mm noise, one outage."""
    R0, R1 = _rotations(T, 2, seed)
    truth = 0.3 * R0[:, :, 0] + 0.25 * R1[:, :, 0]  # (T, 3)
    delta0, delta1 = np.array([0.0, 0.03, -0.02]), np.array([0.02, 0.0, 0.025])
    chain = truth + R0 @ delta0 + R1 @ delta1
    rng = np.random.default_rng(seed + 1)
    cam = truth + rng.normal(0, 0.005, truth.shape)
    av = np.ones((T, 1), bool)
    av[outage[0] : outage[1]] = False
    rots = np.stack([R0, R1], axis=1)[:, None]  # (T, 1, 2, 3, 3)
    return chain[:, None], cam[:, None], av, truth[:, None], rots


def _rmse(a, b, m):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, -1)[m])))


@pytest.mark.parametrize("causal", [False, True])
def test_segment_rotations_recover_a_sensor_frame_calibration_error(causal):
    zi, zc, av, truth, rots = _limb()
    out = ~av
    interp = vision_assisted(zi, zc, av, DT, "offset-interp").position
    plain = kinefuse_fusion(zi, zc, av, DT, causal=causal).position
    seg = kinefuse_fusion(zi, zc, av, DT, causal=causal, segment_rotations=rots).position
    raw = _rmse(zi, truth, out)
    assert raw > 0.03  # the mis-calibration moves the joint by several cm, with the pose
    assert _rmse(seg, truth, out) < 0.01  # about the camera's noise level
    assert _rmse(seg, truth, out) < 0.3 * _rmse(interp, truth, out)
    assert _rmse(seg, truth, out) < 0.5 * _rmse(plain, truth, out)


def test_segment_rotations_through_vision_assisted_and_bad_shapes():
    zi, zc, av, truth, rots = _limb(T=300, outage=(150, 180))
    a = vision_assisted(zi, zc, av, DT, "kinefuse", segment_rotations=rots).position
    b = kinefuse_fusion(zi, zc, av, DT, segment_rotations=rots).position
    np.testing.assert_array_equal(a, b)
    # the other methods do not read it
    e1 = vision_assisted(zi, zc, av, DT, "elm-fir", segment_rotations=rots).position
    e2 = vision_assisted(zi, zc, av, DT, "elm-fir").position
    np.testing.assert_array_equal(e1, e2)
    with pytest.raises(InputError, match=r"segment_rotations with shape \(T, J, S, 3, 3\)"):
        vision_assisted(zi, zc, av, DT, "kinefuse", segment_rotations=rots[:, :, :, :2])
    with pytest.raises(InputError, match="segment_rotations as floats with shape"):
        kinefuse_fusion(zi, zc, av, DT, segment_rotations=rots[:-1])
    with pytest.raises(InputError, match="only padding"):
        kinefuse_fusion(zi, zc, av, DT, segment_rotations=np.zeros_like(rots))


def test_joint_rotations_orders_and_pads():
    T = 20
    names = ["chest", "upper_arm_l", "forearm_l", "thigh_l"]
    mats = dict(zip(names, _rotations(T, len(names), seed=6), strict=True))
    sk = full_body(height_m=1.75)
    wrist = [s for s in joint_segments(sk, "wrist_l") if s in mats]
    assert wrist == ["chest", "upper_arm_l", "forearm_l"]
    out = joint_rotations(mats, [wrist, ["thigh_l"]])
    assert out.shape == (T, 2, 3, 3, 3)
    for k, s in enumerate(wrist):
        np.testing.assert_array_equal(out[:, 0, k], mats[s])
    np.testing.assert_array_equal(out[:, 1, 0], mats["thigh_l"])
    assert np.all(out[:, 1, 1:] == 0)
    with pytest.raises(InputError, match=r"no orientation for segments \['shank_l'\]"):
        joint_rotations(mats, [["thigh_l", "shank_l"]])
    with pytest.raises(InputError, match="at least one segment"):
        joint_rotations(mats, [[]])


def test_session_output_rotations_are_the_chains_frames(shared_data):
    # the chain's shank vector, seen in the shank sensor's frame, is the calibrated constant
    # (axis x length): so the orientations are those the chain was built from, in its frame
    rec = load(shared_data / "neura_sparse_sample", format="neura")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = process_recording(rec, "imu-only", {"calibration": "functional"})
    # the pelvis IMU places the hips (root segment), then the chain to the ankle
    assert out.joint_segments["ankle_l"] == ("pelvis", "thigh_l", "shank_l")
    R = out.segment_rotations(["knee_l", "ankle_l"])
    assert R.shape == (out.t_s.size, 2, 3, 3, 3)
    shank = R[:, 1, 2]
    np.testing.assert_allclose(
        shank @ shank.transpose(0, 2, 1), np.broadcast_to(np.eye(3), shank.shape), atol=1e-9
    )
    ok = np.all(np.isfinite(out.chain[:, [0, 1]]), axis=(1, 2))
    j = {n: out.joints.index(n) for n in ("knee_l", "ankle_l")}
    v = np.einsum("tji,tj->ti", shank, out.chain[:, j["ankle_l"]] - out.chain[:, j["knee_l"]])[ok]
    assert np.linalg.norm(v.mean(0)) > 0.3
    np.testing.assert_allclose(v, np.broadcast_to(v.mean(0), v.shape), atol=1e-9)


def test_a_kinefuse_run_says_what_its_correction_models():
    from kinefuse.apps.demo import demo_recording

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = process_recording(demo_recording(), "kinefuse", {})
        base = process_recording(demo_recording(), "offset-interp", {})
    assert any("modelled in the frames of the sensors" in n for n in out.notes)
    assert not any("paper B pipeline" in n for n in out.notes + base.notes)  # not paper B's
    assert not any("frames of the sensors" in n for n in base.notes)
    # the paper-B rig builds its own chain: its orientations come with it, in its frame
    assert out.joint_segments["wrist_l"] == ("chest", "upper_arm_l", "forearm_l")
    fa = out.segment_rotations(["wrist_l"])[:, 0, 2]
    j = {n: out.joints.index(n) for n in ("elbow_l", "wrist_l")}
    v = np.einsum("tji,tj->ti", fa, out.chain[:, j["wrist_l"]] - out.chain[:, j["elbow_l"]])
    np.testing.assert_allclose(v, np.broadcast_to(v.mean(0), v.shape), atol=1e-9)


def test_a_session_with_a_camera_passes_the_chains_orientations(shared_data):
    # kinefuse run's per-joint path (not the paper-B rig): the Neura legs with a camera made
    # from Vicon, as in kinefuse experiment paper-b; the correction names the sensors it used
    from pathlib import Path

    from kinefuse.apps import paper_b

    rec, joints = paper_b.neura_inputs(Path(shared_data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = process_recording(rec, "kinefuse", {"calibration": "vision"})
    note = next(n for n in out.notes if "frames of the sensors" in n)
    assert "ankle_l: thigh_l, shank_l" in note
    assert out.segment_rotations(joints).shape == (out.t_s.size, 4, 2, 3, 3)
    seen = np.all(np.isfinite(out.camera), axis=-1)
    assert np.all(np.isfinite(out.position[seen]))


def test_segment_rotations_that_are_not_rotations_are_refused():
    """A (T, J, S, 3, 3) of ones (or 1e3) was taken as orientations and changed the output;
    all-NaN rotations failed with a zip() error (they are padding, and a joint with nothing
    else is refused). Zero padding and NaN rows stay allowed."""
    rng = np.random.default_rng(0)
    T = 200
    zi = rng.normal(size=(T, 1, 3))
    zc = zi + 0.01 * rng.normal(size=(T, 1, 3))
    av = np.ones((T, 1), bool)
    av[120:140] = False
    R = Rotation.random(T, random_state=1).as_matrix()[:, None, None]  # (T, 1, 1, 3, 3)
    R = np.concatenate([R, np.zeros_like(R)], axis=2)  # a padded second segment
    R[5] = np.nan  # a missing orientation
    kinefuse_fusion(zi, zc, av, 1 / 30, segment_rotations=R)
    with pytest.raises(InputError, match=r"joint 0, segment 0, sample 0 is not a rotation"):
        kinefuse_fusion(zi, zc, av, 1 / 30, segment_rotations=np.ones((T, 1, 1, 3, 3)))
    with pytest.raises(InputError, match="joint 0 has only padding"):
        kinefuse_fusion(zi, zc, av, 1 / 30, segment_rotations=np.full((T, 1, 1, 3, 3), np.nan))
