"""IMU features for learned chain-error corrections (input φ of :func:`kinefuse_fusion`).

The IMU chain position of a joint (SPEC §2.1/§2.2) is off by an error that depends on the state
of the limb: soft-tissue motion of the sensor across the movement, a mis-calibrated segment axis
or length, shoulder and hip offsets that are not rigid in the chest frame. That error is a
function of what the IMUs see, so a regression on IMU-derived features can predict it while the
camera is out. :func:`imu_features` builds those features from segment orientations;
:func:`chain_features` is the fallback built from the chain positions alone.
:func:`segment_frame_design` is the design of the segment-frame error model that
:func:`~kinefuse.pipelines.kinefuse_fusion.kinefuse_fusion` uses when it is given the segment
orientations.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError
from kinefuse.io.recording import ImuStream, Recording
from kinefuse.kinematics.forward import as_rotation_matrices
from kinefuse.kinematics.skeleton import Skeleton
from kinefuse.orientation import estimate
from kinefuse.orientation.resample import slerp_resample

__all__ = [
    "chain_features",
    "imu_features",
    "joint_rotations",
    "joint_segments",
    "moving_segments",
    "segment_frame_design",
]


def joint_segments(skeleton: Skeleton, joint: str) -> tuple[str, ...]:
    """Segments whose orientation moves ``joint`` or the limb at it, proximal first.

    Parameters
    ----------
    skeleton : Skeleton
        Topology (SPEC §2.2 ``full_body``, §2.1 ``upper_limb``...).
    joint : str
        A joint of the skeleton other than the root.

    Returns
    -------
    tuple of str
        ``root_segment`` (if the skeleton has offsets), the chain of segments from the root to
        ``joint`` (e.g. upper arm, forearm for the wrist) and the segment that starts at
        ``joint`` (e.g. the forearm for the elbow), without repeats.
    """
    if not isinstance(skeleton, Skeleton):
        raise InputError(f"expected skeleton as a Skeleton, got {type(skeleton).__name__}")
    if joint not in skeleton.distal:
        raise InputError(
            f"joint {joint!r} is not the distal joint of any segment; expected one of "
            f"{list(skeleton.distal)}"
        )
    i = skeleton.distal.index(joint)
    chain = []
    while i != -1:
        chain.append(skeleton.segments[i])
        i = skeleton.parents[i]
    chain = chain[::-1]
    children = [s for s, p in zip(skeleton.segments, skeleton.proximal, strict=True) if p == joint]
    out = ([skeleton.root_segment] if skeleton.offsets_m else []) + chain + children
    return tuple(dict.fromkeys(out))


def moving_segments(
    skeleton: Skeleton, joints: Sequence[str], available
) -> dict[str, tuple[str, ...]]:
    """Per joint its :func:`joint_segments` that are in ``available`` (e.g. the segments with
    an orientation), in that order."""
    return {j: tuple(s for s in joint_segments(skeleton, j) if s in available) for j in joints}


def joint_rotations(
    rotations: Mapping[str, np.ndarray], segments: Sequence[Sequence[str]]
) -> np.ndarray:
    """Per joint the orientations of the segments that move it, as one padded array.

    Parameters
    ----------
    rotations : mapping of str -> ndarray, shape (T, 3, 3)
        Segment orientations (``R_frame_from_sensor``) on one timeline.
    segments : sequence of sequence of str
        Per joint (J), the segments that move it (e.g. its :func:`joint_segments` that have an
        orientation), each a key of ``rotations``.

    Returns
    -------
    ndarray, shape (T, J, S, 3, 3)
        Per joint the rotations of its segments in that order, all-zero padded to the largest
        count S (the ``segment_rotations`` input of
        :func:`~kinefuse.pipelines.kinefuse_fusion.kinefuse_fusion`).
    """
    segs = [list(names) for names in segments]
    empty = [j for j, names in enumerate(segs) if not names]
    if empty or not segs:
        raise InputError(f"joints {empty}: expected at least one segment each, got none")
    missing = sorted({s for names in segs for s in names} - set(rotations))
    if missing:
        raise InputError(f"no orientation for segments {missing}; got {sorted(rotations)}")
    T = np.asarray(rotations[segs[0][0]]).shape[0]
    out = np.zeros((T, len(segs), max(len(names) for names in segs), 3, 3))
    for j, names in enumerate(segs):
        for k, s in enumerate(names):
            out[:, j, k] = rotations[s]
    return out


def _orientation_at(stream: ImuStream, t_s: np.ndarray, segment: str) -> np.ndarray:
    q = stream.q_world_from_sensor
    if q is None:
        q = estimate(stream.acc_m_s2, stream.gyr_rad_s, rate_hz=stream.rate_hz)
    if q.shape[0] < 2:
        raise InputError(
            f"IMU {segment!r}: expected at least 2 orientation samples, got {q.shape[0]}"
        )
    return as_rotation_matrices(slerp_resample(stream.t_s, q, t_s), f"IMU {segment!r} orientation")


def _world_rate(R: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """World-frame angular rate (T, 3), rad/s: ``log(R_t R_{t−1}ᵀ) / Δt`` (causal; 0 at t = 0)."""
    T = R.shape[0]
    w = np.zeros((T, 3))
    if T < 2:
        return w
    ok = np.all(np.isfinite(R), axis=(1, 2))
    pair = ok[1:] & ok[:-1]
    w[1:][~pair] = np.nan
    w[0] = np.nan if not ok[0] else 0.0
    if np.any(pair):
        rel = np.einsum("tij,tkj->tik", R[1:][pair], R[:-1][pair])
        w[1:][pair] = Rotation.from_matrix(rel).as_rotvec() / np.diff(t_s)[pair][:, None]
    return w


def _check_feature_args(recording_or_orientations, joints, t_s, R_world_from_camera):
    """Validated ``(streams, joints, t, R_world_from_camera or None)`` of :func:`imu_features`."""
    if isinstance(recording_or_orientations, Recording):
        streams = recording_or_orientations.imu
    elif isinstance(recording_or_orientations, Mapping):
        streams = dict(recording_or_orientations)
    else:
        raise InputError(
            "expected a Recording or a mapping segment -> ImuStream, got "
            f"{type(recording_or_orientations).__name__}"
        )
    for k, v in streams.items():
        if not isinstance(v, ImuStream):
            raise InputError(f"orientations[{k!r}]: expected an ImuStream, got {type(v).__name__}")
    if isinstance(joints, str):
        raise InputError(f"expected joints as a sequence of names, got the string {joints!r}")
    joints = list(joints)
    if not joints:
        raise InputError("expected at least one joint, got none")
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size < 1 or not np.all(np.isfinite(t)):
        raise InputError(f"expected t_s as a finite 1-D array, got shape {t.shape}")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise InputError("expected t_s strictly increasing")
    Rc = None
    if R_world_from_camera is not None:
        Rc = np.asarray(R_world_from_camera, dtype=float)
        if Rc.shape != (3, 3) or not np.all(np.isfinite(Rc)):
            raise InputError(f"expected R_world_from_camera with shape (3, 3), got {Rc.shape}")
    return streams, joints, t, Rc


def _joint_columns(skeleton, j, streams, seg, relative: bool, T: int) -> np.ndarray:
    """The feature columns ``(T, F_j)`` of joint ``j`` (``seg(s) -> (R (T, 3, 3), rate or None)``)."""
    segs = [s for s in joint_segments(skeleton, j) if s in streams]
    if not segs:
        raise InputError(
            f"joint {j!r}: none of its segments {list(joint_segments(skeleton, j))} has an IMU; "
            f"got IMUs for {sorted(streams)}"
        )
    cols = []
    for s in segs:
        R, w = seg(s)
        cols.append(R.reshape(T, 9))
        if w is not None:
            cols.append(w)
    if relative:
        for a, b in zip(segs[:-1], segs[1:], strict=True):
            cols.append(np.einsum("tji,tjk->tik", seg(a)[0], seg(b)[0]).reshape(T, 9))
    return np.concatenate(cols, axis=1)


def imu_features(
    recording_or_orientations: Recording | Mapping[str, ImuStream],
    skeleton: Skeleton,
    joints: Sequence[str],
    t_s,
    *,
    R_world_from_camera=None,
    rates: bool = True,
    relative: bool = True,
) -> np.ndarray:
    """Features φ of each joint from the orientations of the segments that move it.

    Parameters
    ----------
    recording_or_orientations : Recording or mapping of str -> ImuStream
        IMU streams keyed by segment, with ``q_world_from_sensor`` (or raw ``acc_m_s2`` and
        ``gyr_rad_s``: the orientation is then estimated with :func:`kinefuse.orientation.estimate`,
        6D VQF).
    skeleton : Skeleton
        Topology; selects the segments of each joint (:func:`joint_segments`); segments
        without an IMU stream are skipped (a joint needs at least one).
    joints : sequence of str
        The J joints, in the order of the fusion's joint axis.
    t_s : array_like, shape (T,)
        Output timeline (the camera timestamps), s. Orientations are SLERP-resampled to it
        (SPEC §12.2 "resampling").
    R_world_from_camera : array_like, shape (3, 3), optional
        When given, orientations are expressed in the camera frame (``Rcᵀ R``) so the features
        live in the frame of the positions. Only a fixed linear map of the features; it does not
        change a linear regression on them.
    rates : bool
        Include the angular rate of each segment (world frame, rad/s; backward differences,
        so the features at t use orientations up to t only).
    relative : bool
        Include the relative rotation ``R_aᵀ R_b`` of consecutive segments (the joint angle,
        independent of heading drift common to both).

    Returns
    -------
    ndarray, shape (T, J, F)
        Per joint: for each of its segments the 9 elements of ``R_world_from_sensor``
        (row-major) and, with ``rates``, its 3 world angular-rate components; with
        ``relative``, 9 elements of each consecutive relative rotation. Joints with fewer
        segments are zero-padded to the largest F (a constant column, harmless for a
        regression with intercept). NaN where an orientation is missing.

    Notes
    -----
    Each element of a rotation matrix is a smooth function of the limb's state, and products of
    elements of two segments (in ``R_aᵀ R_b``) carry the joint angle, so a linear regression on φ
    represents errors that vary with segment direction, joint angle and speed (the ``rates``)
    along the movement, such as soft-tissue motion over a gait cycle.
    """
    streams, joints, t, Rc = _check_feature_args(recording_or_orientations, joints, t_s,
                                                 R_world_from_camera)  # fmt: skip
    cache: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}

    def seg(s: str):
        if s not in cache:
            if s not in streams:
                raise InputError(f"no IMU for segment {s!r}; got IMUs for {sorted(streams)}")
            R = _orientation_at(streams[s], t, s)
            if Rc is not None:
                R = np.einsum("ji,tjk->tik", Rc, R)
            cache[s] = (R, _world_rate(R, t) if rates else None)
        return cache[s]

    per_joint = [_joint_columns(skeleton, j, streams, seg, relative, t.size) for j in joints]
    F = max(p.shape[1] for p in per_joint)
    out = np.zeros((t.size, len(joints), F))
    for k, p in enumerate(per_joint):
        out[:, k, : p.shape[1]] = p
    return out


def chain_features(z_imu, dt_s: float, parents: Sequence[int] | None = None) -> np.ndarray:
    """Fallback features from the IMU chain positions alone (no orientations available).

    Parameters
    ----------
    z_imu : array_like, shape (T, J, 3)
        IMU-chain joint positions, m.
    dt_s : float
        Sampling interval, s.
    parents : sequence of int, optional
        For each joint the index (into J) of its parent joint in the chain, or -1. The segment
        vector is ``z_imu[j] − z_imu[parent]``; without a parent (or ``parents=None``) it is the
        position itself (chain root at the origin, e.g. chest-relative positions, SPEC §2.2).

    Returns
    -------
    ndarray, shape (T, J, 10)
        Unit segment direction (3), segment length (1), the position (3) and its backward
        finite-difference velocity (3, m/s; 0 at t = 0): causal, uses samples up to t only.
    """
    z = np.asarray(z_imu, dtype=float)
    if z.ndim != 3 or z.shape[-1] != 3:
        raise InputError(f"expected z_imu with shape (T, J, 3), got {z.shape}")
    T, J, _ = z.shape
    if parents is None:
        parents = [-1] * J
    parents = list(parents)
    if len(parents) != J or any(not -1 <= int(p) < J for p in parents):
        raise InputError(f"expected parents as J = {J} indices in [-1, {J - 1}], got {parents}")
    seg = np.stack([z[:, j] - (z[:, p] if p >= 0 else 0.0) for j, p in enumerate(parents)], axis=1)
    n = np.linalg.norm(seg, axis=-1, keepdims=True)
    u = seg / np.where(n > 1e-9, n, 1.0)
    vel = np.zeros_like(z)
    vel[1:] = (z[1:] - z[:-1]) / float(dt_s)
    return np.concatenate([u, n, z, vel], axis=-1)


def segment_frame_design(rotations) -> np.ndarray:
    """Design of the segment-frame chain-error model: one row of regressors per world axis.

    A sensor-to-segment misalignment, a segment-length error or an offset error is a constant
    vector ``δ_s`` in the frame of its segment's sensor, so it moves the chain's joint by
    ``R_s(t) δ_s`` in the world. The chain error along world axis ``i`` is modelled as ::

        e_i(t) = c_i + Σ_s R_s(t)[i, :] δ_s

    linear in the unknowns ``(c, δ_s)`` with the same ``δ_s`` for all three axes (a rotation
    mixes the axes: a regression per world axis on the elements of ``R_s`` needs 27
    coefficients per segment for what this model says with 3).

    Parameters
    ----------
    rotations : sequence of sequence of ndarray
        Per joint (J), the ``R_frame_from_sensor (T, 3, 3)`` of the segments whose pose moves
        the joint (e.g. :func:`joint_rotations`), in the frame of the positions the error is
        measured in. NaN where an orientation is missing.

    Returns
    -------
    ndarray, shape (T, J, 3, K)
        Per joint and world axis ``i``: the indicator of ``i`` (3 columns, the constant world
        offset ``c``), then ``R_s[i, :]`` of each segment (3 columns each). Joints with fewer
        segments are zero-padded (constant columns, which a regression with an intercept
        ignores). NaN rows where an orientation is missing.
    """
    per_joint = []
    T = None
    for j, segs in enumerate(rotations):
        Rs = [np.asarray(R, dtype=float) for R in segs]
        if not Rs:
            raise InputError(f"joint {j}: expected at least one segment rotation, got none")
        for R in Rs:
            if R.ndim != 3 or R.shape[1:] != (3, 3) or (T is not None and R.shape[0] != T):
                want = "(T, 3, 3)" if T is None else f"({T}, 3, 3)"
                raise InputError(f"joint {j}: expected rotations with shape {want}, got {R.shape}")
            T = R.shape[0]
        per_joint.append(np.concatenate([np.broadcast_to(np.eye(3), (T, 3, 3)), *Rs], axis=2))
    if not per_joint:
        raise InputError("expected rotations for at least one joint, got none")
    K = max(p.shape[-1] for p in per_joint)
    out = np.zeros((T, len(per_joint), 3, K))
    for j, p in enumerate(per_joint):
        out[:, j, :, : p.shape[-1]] = p
    return out
