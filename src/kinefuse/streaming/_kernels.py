"""Compiled per-frame geometry of the online engine (orientations -> chain joint positions).

One call per frame replaces a dozen small NumPy operations (normalisation, quaternion ->
matrix, the chain's matrix-vector products), which on a live, mostly idle process cost more
than the arithmetic itself.
"""

from __future__ import annotations

import math

import numpy as np

from kinefuse._compile import njit
from kinefuse.conventions import SOURCE_CAMERA, SOURCE_FUSED, SOURCE_IMU
from kinefuse.conventions import SOURCE_PREDICTED as SOURCE_PREDICT
from kinefuse.filters._kernels_axis import kf_filter_axis


@njit
def slerp(q0, q1, u):  # pragma: no cover - compiled
    """Spherical linear interpolation of unit quaternions (wxyz), shortest path: (4,)."""
    d = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    sign = 1.0
    if d < 0.0:
        sign, d = -1.0, -d
    out = np.empty(4)
    if d > 0.9999995:  # nearly equal: normalised linear interpolation
        for i in range(4):
            out[i] = q0[i] + u * (sign * q1[i] - q0[i])
        n = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
        for i in range(4):
            out[i] /= n
        return out
    theta = math.acos(min(d, 1.0))
    s = math.sin(theta)
    a = math.sin((1.0 - u) * theta) / s
    b = sign * math.sin(u * theta) / s
    for i in range(4):
        out[i] = a * q0[i] + b * q1[i]
    return out


@njit
def chain_positions(
    Q, U, R_cam, use_cam, root, dst, src, seg, vec, out_node
):  # pragma: no cover - compiled
    """Joint positions of one frame from per-segment orientations.

    Parameters
    ----------
    Q : ndarray, shape (2, S, 4)
        Per segment the two ``q_world_from_sensor`` samples (unit, wxyz) around the frame
        time; the orientation is ``slerp(Q[0, s], Q[1, s], U[s])`` (a NaN row = stale
        segment).
    U : ndarray, shape (S,)
        Interpolation fractions in [0, 1] (0: ``Q[0, s]`` itself).
    R_cam : ndarray, shape (3, 3)
        ``R_world_from_camera``; used when ``use_cam`` (segments then map sensor -> camera
        frame: ``R_cam.T @ R``).
    use_cam : bool
    root : ndarray, shape (3,)
        Position of node 0 (the chain root), m.
    dst, src, seg : ndarray of int64, shape (K,)
        Chain steps in order: ``pos[dst] = pos[src] + R[seg] @ vec``.
    vec : ndarray, shape (K, 3)
        Segment vectors in the sensor frames, m.
    out_node : ndarray of int64, shape (J,)
        Node of each output joint (-1: not computable, NaN row).

    Returns
    -------
    ndarray, shape (J, 3)
        Joint positions, m (NaN where a step used a stale segment).
    """
    S = Q.shape[1]
    R = np.empty((S, 3, 3))
    for s in range(S):
        q = Q[0, s] if U[s] == 0.0 else slerp(Q[0, s], Q[1, s], U[s])
        w, x, y, z = q[0], q[1], q[2], q[3]
        n = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / n, x / n, y / n, z / n
        M = np.empty((3, 3))
        M[0, 0] = 1 - 2 * (y * y + z * z)
        M[0, 1] = 2 * (x * y - w * z)
        M[0, 2] = 2 * (x * z + w * y)
        M[1, 0] = 2 * (x * y + w * z)
        M[1, 1] = 1 - 2 * (x * x + z * z)
        M[1, 2] = 2 * (y * z - w * x)
        M[2, 0] = 2 * (x * z - w * y)
        M[2, 1] = 2 * (y * z + w * x)
        M[2, 2] = 1 - 2 * (x * x + y * y)
        if use_cam:
            for i in range(3):
                for k in range(3):
                    R[s, i, k] = (
                        R_cam[0, i] * M[0, k] + R_cam[1, i] * M[1, k] + R_cam[2, i] * M[2, k]
                    )
        else:
            R[s] = M
    n_nodes = 1
    for k in range(dst.shape[0]):
        if dst[k] + 1 > n_nodes:
            n_nodes = dst[k] + 1
    pos = np.full((n_nodes, 3), np.nan)
    pos[0] = root
    for k in range(dst.shape[0]):
        r = R[seg[k]]
        a = src[k]
        for i in range(3):
            pos[dst[k], i] = pos[a, i] + (
                r[i, 0] * vec[k, 0] + r[i, 1] * vec[k, 1] + r[i, 2] * vec[k, 2]
            )
    J = out_node.shape[0]
    out = np.full((J, 3), np.nan)
    for j in range(J):
        if out_node[j] >= 0:
            out[j] = pos[out_node[j]]
    return out


@njit
def fusion_step(z_imu, z_cam, available, w_imu, w_cam, r, P0b, x, P, init, Fb, Qb, Hb, mean, cov,
                source):  # pragma: no cover - compiled  # fmt: skip
    """One frame of the KF fusion processor: per joint a constant-velocity Kalman filter step
    on the information-weighted measurement of the sensors that saw the joint.

    Per joint ``j``: case 0 (IMU and camera) ``z = (w_c z_cam + w_i z_imu) / (w_c + w_i)``,
    case 1 (camera only) ``z_cam``, case 2 (IMU only, or nothing: predict) ``z_imu``; then one
    step of :func:`kinefuse.filters._kernels_axis.kf_filter_axis` (the per-axis Kalman filter
    behind :class:`~kinefuse.filters.KalmanFilter`) with the case's variance ``r[case]`` and
    initial covariance ``P0b[case]``. Nothing of the filter is re-implemented here.

    Parameters
    ----------
    z_imu, z_cam : ndarray, shape (J, n_z)
        IMU-chain and camera positions, m (NaN rows: no measurement).
    available : ndarray of bool, shape (J,)
        Camera availability.
    w_imu, w_cam : float
        Inverse measurement variances of the two sensors, 1/m².
    r : ndarray, shape (3, n_a)
        Per-axis measurement variances of the three cases, m².
    P0b : ndarray, shape (3, n_a, 2, 2)
        Per-axis initial covariances of the three cases.
    x, P, init : ndarray, shapes (J, n_x), (J, n_x, n_x), (J,)
        Filter state, updated in place.
    Fb, Qb, Hb : ndarray
        Per-axis model blocks (:func:`~kinefuse.filters._kernels_axis.axis_block_params`).
    mean, cov : ndarray, shapes (J, 1, n_x), (J, 1, n_x, n_x)
        Filtered mean and covariance (``cov`` zero-filled by the caller).
    source : ndarray of int8, shape (J,)
        Out: 1 fused, 2 camera, 0 IMU, -1 predict (codes of
        :mod:`kinefuse.conventions` and ``SOURCE_PREDICT``).
    """
    J, n_z = z_imu.shape
    z = np.empty((1, 1, n_z))
    pos = np.empty((1, 1, n_z))
    obs = np.empty((1, 1), dtype=np.bool_)
    nu = np.empty((1, 1, n_z))
    dist = np.empty((1, 1))
    for j in range(J):
        has_imu = True
        has_cam = available[j]
        for a in range(n_z):
            if not np.isfinite(z_imu[j, a]):
                has_imu = False
            if not np.isfinite(z_cam[j, a]):
                has_cam = False
        if has_cam and has_imu:
            c = 0
            source[j] = SOURCE_FUSED
            for a in range(n_z):
                z[0, 0, a] = (z_cam[j, a] * w_cam + z_imu[j, a] * w_imu) / (w_cam + w_imu)
        elif has_cam:
            c = 1
            source[j] = SOURCE_CAMERA
            for a in range(n_z):
                z[0, 0, a] = z_cam[j, a]
        else:
            c = 2
            source[j] = SOURCE_IMU if has_imu else SOURCE_PREDICT
            for a in range(n_z):
                z[0, 0, a] = z_imu[j, a]
        kf_filter_axis(z, x[j : j + 1], P[j : j + 1], init[j : j + 1], Fb, Qb, Hb, r[c], P0b[c],
                       mean[j : j + 1], cov[j : j + 1], pos, obs, nu, dist)  # fmt: skip


@njit
def joint_flags(status, dep_mask, computable, avail, camera, cam_missing, forced,
                fresh, held, stale, f_held, f_stale, f_cam_missing, f_no_cam, f_forced):  # pragma: no cover - compiled  # fmt: skip
    """Per-joint IMU status (the worst over the segments a joint depends on) and flag bits.

    Parameters
    ----------
    status : ndarray of int8, shape (S,)
        Per segment: ``fresh`` < ``held`` < ``stale``.
    dep_mask : ndarray of bool, shape (J, S)
        Segments each joint depends on.
    computable : ndarray of bool, shape (J,)
        Joints the chain places (others are ``stale``).
    avail : ndarray of bool, shape (J,)
        Camera saw the joint.
    camera, cam_missing, forced : bool
        A camera is configured / this frame has no camera frame / processed after max latency.
    fresh, held, stale : int
        Status codes; ``f_*``: flag bits.

    Returns
    -------
    jstat : ndarray of int8, shape (J,)
    flags : ndarray of uint8, shape (J,)
    """
    J = dep_mask.shape[0]
    S = status.shape[0]
    jstat = np.empty(J, np.int8)
    flags = np.zeros(J, np.uint8)
    for j in range(J):
        w = fresh
        for s in range(S):
            if dep_mask[j, s] and status[s] > w:
                w = status[s]
        if not computable[j]:
            w = stale
        jstat[j] = w
        f = 0
        if w == held:
            f |= f_held
        if w == stale:
            f |= f_stale
        if camera:
            if cam_missing:
                f |= f_cam_missing
            if not avail[j]:
                f |= f_no_cam
        if forced:
            f |= f_forced
        flags[j] = f
    return jstat, flags
