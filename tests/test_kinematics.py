"""Skeleton presets, forward kinematics (SPEC §2.1/§2.2) and paper B's Euler helper, vs scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError
from kinefuse.io.recording import JointStream
from kinefuse.kinematics import (
    ANTHROPOMETRIC_RATIOS,
    Skeleton,
    euler_to_matrix,
    forward_kinematics,
    full_body,
    lengths_from_joints,
    lower_body,
    upper_limb,
)

IDENTITY = np.array([[1.0, 0.0, 0.0, 0.0]])


def quat(rotvec) -> np.ndarray:
    return Rotation.from_rotvec(np.atleast_2d(rotvec)).as_quat(scalar_first=True)


# ---------------------------------------------------------------- paper A chain
def test_identity_rotations_put_joints_along_e2():
    sk = upper_limb("r", lengths={"upper_arm_r": 0.3, "forearm_r": 0.25})
    p0 = np.array([[0.1, 0.2, 1.4]])
    pos = forward_kinematics(sk, {"upper_arm_r": IDENTITY, "forearm_r": IDENTITY}, p0)
    np.testing.assert_allclose(pos["shoulder_r"], p0)
    np.testing.assert_allclose(pos["elbow_r"], p0 + [0, 0.3, 0])
    np.testing.assert_allclose(pos["wrist_r"], p0 + [0, 0.55, 0])


def test_90_degree_rotations():
    sk = upper_limb("l", lengths={"upper_arm_l": 0.3, "forearm_l": 0.25})
    rz = quat([0, 0, np.pi / 2])  # e2 -> -e1
    rx = quat([np.pi / 2, 0, 0])  # e2 -> +e3
    pos = forward_kinematics(sk, {"upper_arm_l": rz, "forearm_l": rx}, np.zeros((1, 3)))
    np.testing.assert_allclose(pos["elbow_l"], [[-0.3, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(pos["wrist_l"], [[-0.3, 0, 0.25]], atol=1e-15)
    # arms hanging: segment axis -e3 with identity orientation -> straight down
    sk_down = sk.with_axes({"upper_arm_l": "-e3", "forearm_l": (0, 0, -2.0)})
    pos = forward_kinematics(
        sk_down, {"upper_arm_l": IDENTITY, "forearm_l": IDENTITY}, np.zeros((1, 3))
    )
    np.testing.assert_allclose(pos["wrist_l"], [[0, 0, -0.55]])


def test_random_rotations_match_scipy_apply(rng):
    T = 50
    r1 = Rotation.random(T, random_state=1)
    r2 = Rotation.random(T, random_state=2)
    a1, a2 = np.array([0.0, 0.6, 0.8]), np.array([-1.0, 0.0, 0.0])
    sk = upper_limb(
        lengths={"upper_arm_r": 0.31, "forearm_r": 0.27}, axes={"upper_arm_r": a1, "forearm_r": a2}
    )
    p0 = rng.standard_normal((T, 3))
    q = {
        "upper_arm_r": r1.as_quat(scalar_first=True),
        "forearm_r": r2.as_matrix(),
    }  # quats and matrices
    pos = forward_kinematics(sk, q, p0)
    elbow = p0 + 0.31 * r1.apply(a1)
    np.testing.assert_allclose(pos["elbow_r"], elbow, atol=1e-14)
    np.testing.assert_allclose(pos["wrist_r"], elbow + 0.27 * r2.apply(a2), atol=1e-14)


def test_batched_equals_loop():
    sk = upper_limb(height_m=1.75)
    B, T = 3, 20
    qa = Rotation.random(B * T, random_state=3).as_quat(scalar_first=True).reshape(B, T, 4)
    qf = Rotation.random(B * T, random_state=4).as_quat(scalar_first=True).reshape(B, T, 4)
    root = np.arange(B * T * 3, dtype=float).reshape(B, T, 3)
    batch = forward_kinematics(sk, {"upper_arm_r": qa, "forearm_r": qf}, root)
    for b in range(B):
        one = forward_kinematics(sk, {"upper_arm_r": qa[b], "forearm_r": qf[b]}, root[b])
        for j in one:
            np.testing.assert_array_equal(batch[j][b], one[j])


def test_nan_orientation_rows_give_nan_positions():
    sk = upper_limb(lengths={"upper_arm_r": 0.3, "forearm_r": 0.25})
    q = np.repeat(IDENTITY, 3, axis=0)
    q[1] = np.nan
    pos = forward_kinematics(sk, {"upper_arm_r": q, "forearm_r": q}, np.zeros((3, 3)))
    assert np.all(np.isnan(pos["wrist_r"][1])) and np.all(np.isfinite(pos["wrist_r"][[0, 2]]))


# ---------------------------------------------------------------- paper B
def test_euler_to_matrix_matches_scipy_and_paper_factors(rng):
    g, t, p = rng.uniform(-np.pi, np.pi, (3, 40))
    C = euler_to_matrix(g, t, p)
    np.testing.assert_allclose(
        C, Rotation.from_euler("ZXY", np.stack([-p, t, g], 1)).as_matrix(), atol=1e-15
    )
    # transpose of the printed factors R_y(γ) R_x(θ) R_z(φ) (paper B Eq. 1, C_n^b)
    for k in range(5):
        cg, sg, ct, st, cp, sp = (
            np.cos(g[k]),
            np.sin(g[k]),
            np.cos(t[k]),
            np.sin(t[k]),
            np.cos(p[k]),
            np.sin(p[k]),
        )
        Ry = np.array([[cg, 0, -sg], [0, 1, 0], [sg, 0, cg]])
        Rx = np.array([[1, 0, 0], [0, ct, st], [0, -st, ct]])
        Rz = np.array([[cp, -sp, 0], [sp, cp, 0], [0, 0, 1]])
        np.testing.assert_allclose(C[k], (Ry @ Rx @ Rz).T, atol=1e-15)
    # heading clockwise from north: at θ = 0 the body y axis points along [sin φ, cos φ, 0]
    phi = np.radians(30.0)
    np.testing.assert_allclose(
        euler_to_matrix(0.7, 0.0, phi)[:, 1], [np.sin(phi), np.cos(phi), 0], atol=1e-15
    )
    assert euler_to_matrix(0.1, 0.2, 0.3).shape == (3, 3)


def test_full_body_world_and_chest_frame():
    H = 1.8
    sk = full_body(height_m=H)
    assert sk.length("thigh_l") == pytest.approx(0.245 * H)
    assert sk.length("forearm_r") == pytest.approx(0.146 * H)
    T = 10
    ori = {
        s: Rotation.random(T, random_state=i).as_quat(scalar_first=True)
        for i, s in enumerate([*sk.segments, "chest"])
    }
    p0 = np.tile([1.0, 2.0, 1.5], (T, 1))
    pos = forward_kinematics(sk, ori, p0)
    R0 = Rotation.from_quat(ori["chest"], scalar_first=True)
    sw = ANTHROPOMETRIC_RATIOS["shoulder_width"] * H
    np.testing.assert_allclose(pos["shoulder_r"], p0 + R0.apply([sw / 2, 0, 0]), atol=1e-14)
    knee = pos["hip_l"] + sk.length("thigh_l") * Rotation.from_quat(
        ori["thigh_l"], scalar_first=True
    ).apply([0, 1, 0])
    np.testing.assert_allclose(pos["knee_l"], knee, atol=1e-14)
    chest = forward_kinematics(sk, ori, p0, frame="root_segment")
    for j in pos:
        np.testing.assert_allclose(chest[j], R0.inv().apply(pos[j] - p0), atol=1e-14)
    np.testing.assert_allclose(chest["shoulder_l"], np.tile([-sw / 2, 0, 0], (T, 1)), atol=1e-14)


def test_roots_given_as_dict_skip_offsets():
    sk = lower_body(lengths={"thigh_l": 0.4, "shank_l": 0.4, "thigh_r": 0.41, "shank_r": 0.39})
    ori = {s: IDENTITY for s in sk.segments}
    roots = {"hip_l": np.array([[-0.1, 0, 1.0]]), "hip_r": np.array([[0.1, 0, 1.0]])}
    pos = forward_kinematics(sk.with_axes(dict.fromkeys(sk.segments, "-e3")), ori, roots)
    np.testing.assert_allclose(pos["ankle_r"], [[0.1, 0, 1.0 - 0.8]])
    with pytest.raises(InputError, match=r"offset of joint 'hip_l' is unknown \(NaN\)"):
        forward_kinematics(sk, {**ori, "pelvis": IDENTITY}, np.zeros((1, 3)))


# ---------------------------------------------------------------- lengths
def test_length_preference_and_lengths_from_joints(rng):
    sk = lower_body(lengths={"thigh_l": 0.5}, height_m=1.7)
    assert sk.length("thigh_l") == 0.5 and sk.length("shank_l") == pytest.approx(0.246 * 1.7)
    T = 200
    hip = rng.standard_normal((T, 3))
    knee = hip + 0.42 * np.array([0, 0, -1.0]) + 0.002 * rng.standard_normal((T, 3))
    ankle = knee + [0, 0.39, 0]
    js = JointStream(
        t_s=np.arange(T) / 100,
        position_m=np.stack([hip, knee, ankle], 1),
        joints=("hip_l", "knee_l", "ankle_l"),
    )
    L = lengths_from_joints(
        js, [("thigh_l", "hip_l", "knee_l"), ("shank_l", "knee_l", "ankle_l")], window_s=1.0
    )
    assert L["thigh_l"] == pytest.approx(0.42, abs=0.003) and L["shank_l"] == pytest.approx(
        0.39, abs=0.003
    )
    sk2 = sk.with_lengths_from(js)  # right leg joints absent: kept
    assert sk2.length("thigh_r") == sk.length("thigh_r")
    right = js.position_m + [0.2, 0, 0]
    both = JointStream(
        t_s=js.t_s,
        position_m=np.concatenate([js.position_m, right], axis=1),
        joints=("hip_l", "knee_l", "ankle_l", "hip_r", "knee_r", "ankle_r"),
    )
    sk3 = Skeleton.from_joint_stream(both, "lower_body", start_s=0.5, window_s=1.0)
    assert sk3.length("shank_r") == pytest.approx(0.39) and sk3.length("thigh_r") == pytest.approx(
        0.42, abs=0.003
    )
    with pytest.raises(
        InputError, match=r"segment 'thigh_r': expected joints \['hip_r', 'knee_r'\]"
    ):
        Skeleton.from_joint_stream(js, "lower_body")


# ---------------------------------------------------------------- bad input
def test_rotation_matrix_check_matches_gram_and_determinant(rng):
    """Oracle: max |RᵀR − I| from batched matrix products and numpy's determinant, over more
    matrices than one chunk of the check; NaN rows are missing, not refused."""
    from kinefuse.kinematics.forward import _orthonormality, as_rotation_matrices

    R = Rotation.random(20000, random_state=3).as_matrix()
    R[123] += rng.normal(0, 2e-5, (3, 3))  # within the 1e-4 tolerance
    R[17_000, 0] *= 1 + 3e-5
    err, det_min = _orthonormality(R.reshape(-1, 9))
    want = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max()
    assert err == pytest.approx(want, rel=1e-9) and 1e-5 < err < 1e-4
    assert det_min == pytest.approx(np.linalg.det(R).min(), rel=1e-12)
    R[5] = np.nan
    assert as_rotation_matrices(R) is not None
    bad = R.copy()
    bad[9000, :, 1] *= 1.001  # off by 2e-3
    with pytest.raises(InputError, match=r"max \|RᵀR − I\| = 0.002"):
        as_rotation_matrices(bad)
    bad = R.copy()
    bad[19_999] *= -1  # a reflection: orthonormal, det −1
    with pytest.raises(InputError, match="det < 0"):
        as_rotation_matrices(bad)


def test_bad_input_messages():
    sk = upper_limb(lengths={"upper_arm_r": 0.3, "forearm_r": 0.25})
    ok = {"upper_arm_r": IDENTITY, "forearm_r": IDENTITY}
    with pytest.raises(
        InputError, match=r"unknown segment\(s\) \['forearm_x'\].*expected names from"
    ):
        forward_kinematics(sk, {**ok, "forearm_x": IDENTITY}, np.zeros((1, 3)))
    with pytest.raises(
        InputError, match=r"missing orientation for segment 'forearm_r'.*got \['upper_arm_r'\]"
    ):
        forward_kinematics(sk, {"upper_arm_r": IDENTITY}, np.zeros((1, 3)))
    with pytest.raises(
        InputError,
        match=r"\(\.\.\., T, 4\) quaternions wxyz or \(\.\.\., T, 3, 3\) matrices, got \(1, 3\)",
    ):
        forward_kinematics(sk, {**ok, "forearm_r": np.zeros((1, 3))}, np.zeros((1, 3)))
    with pytest.raises(InputError, match="unit quaternions wxyz, got norm 2"):
        forward_kinematics(sk, {**ok, "forearm_r": 2 * IDENTITY}, np.zeros((1, 3)))
    with pytest.raises(
        InputError,
        match=r"root position 'shoulder_r' as floats with shape \(\.\.\., T, 3\), got \(3,\)",
    ):
        forward_kinematics(sk, ok, np.zeros(3))
    with pytest.raises(InputError, match="does not match its start joint"):
        forward_kinematics(sk, ok, np.zeros((4, 3)))
    with pytest.raises(
        InputError, match=r"with_lengths: unknown segment\(s\) \['thigh_l'\]; expected names from"
    ):
        sk.with_lengths({"thigh_l": 0.4})
    with pytest.raises(InputError, match="unknown axis name 'e4'"):
        sk.with_axes({"forearm_r": "e4"})
    with pytest.raises(InputError, match="millimetres"):
        upper_limb(lengths={"upper_arm_r": 300.0, "forearm_r": 250.0})
    with pytest.raises(InputError, match="no length for 'upper_arm_l'"):
        upper_limb("l")
    with pytest.raises(InputError, match="expected side"):
        upper_limb("x", height_m=1.7)
    with pytest.raises(InputError, match="expected frame in"):
        forward_kinematics(sk, ok, np.zeros((1, 3)), frame="chest")
    with pytest.raises(
        InputError, match="starts at 'elbow_r' but its parent 'upper_arm_r' ends at 'knee_r'"
    ):
        Skeleton(
            segments=("upper_arm_r", "forearm_r"),
            parents=(-1, 0),
            proximal=("shoulder_r", "elbow_r"),
            distal=("knee_r", "wrist_r"),
            lengths_m=(0.3, 0.25),
            axes=np.tile([0, 1.0, 0], (2, 1)),
            root="shoulder_r",
        )
