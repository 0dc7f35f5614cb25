"""Forward kinematics of a segment chain: SPEC §2.1 (paper A Eqs. 1-2) and §2.2 (paper B Eqs. 1-17), corrected.

Every joint is its parent joint plus ``length · R_world_from_segment(k) @ axis``; all positions
are in the world frame of the orientations (ENU for kinefuse orientations), batched over time.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse._validation import finite_rows
from kinefuse.exceptions import InputError
from kinefuse.kinematics.skeleton import Skeleton

__all__ = ["as_rotation_matrices", "euler_to_matrix", "forward_kinematics", "rotation_z"]


def euler_to_matrix(gamma, theta, phi) -> np.ndarray:
    """Paper B Eq. (1), transposed: body -> ENU rotation ``C_b^n`` from roll, pitch, heading.

    Parameters
    ----------
    gamma : array_like, shape (...)
        Roll γ about the body y (forward) axis, rad.
    theta : array_like, shape (...)
        Pitch θ about the body x (right) axis, rad.
    phi : array_like, shape (...)
        Heading φ, positive **clockwise from North**, rad.

    Returns
    -------
    C_b_n : ndarray, shape (..., 3, 3)
        ``R_world_from_sensor`` (ENU world, right-front-up body), i.e.
        ``(R_y(γ) R_x(θ) R_z(φ))ᵀ`` = ``Rotation.from_euler('ZXY', [-φ, θ, γ]).as_matrix()``.

    Notes
    -----
    Deviations from the paper (SPEC §2.2-5): Eq. (1) is labelled ``C_n^b`` while the text calls
    it the b -> n rotation; only reading the printed product as n -> b makes Eq. (2) consistent,
    so the b -> n matrix returned here is its transpose. Converting back to Euler angles is
    singular at θ = ±90° (SPEC §13): never round-trip through Euler angles.
    """
    g, t, p = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (gamma, theta, phi)))
    shape = g.shape
    angles = np.stack([-p.ravel(), t.ravel(), g.ravel()], axis=-1)
    return Rotation.from_euler("ZXY", angles).as_matrix().reshape(*shape, 3, 3)


def rotation_z(psi: float) -> np.ndarray:
    """``R_z(ψ)``: rotation by ``psi`` (rad, counter-clockwise seen from above) about z, (3, 3)."""
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def as_rotation_matrices(value, name: str = "orientation") -> np.ndarray:
    """``(..., 4)`` ``wxyz`` quaternions or ``(..., 3, 3)`` rotation matrices -> ``(..., 3, 3)`` matrices.

    NaN quaternion rows (missing samples) give NaN matrices. Quaternions are normalised; norms
    off by more than 1e-2 (a wrong layout or units) and non-orthonormal matrices are refused.
    """
    a = np.asarray(value)
    if not np.issubdtype(a.dtype, np.floating):
        raise InputError(
            f"expected {name} as floats (quaternions or matrices), got dtype {a.dtype}"
        )
    a = a.astype(float, copy=False)
    if a.ndim >= 1 and a.shape[-1] == 4:
        flat = a.reshape(-1, 4)
        ok = finite_rows(flat)
        every = bool(ok.all())
        q = flat if every else flat[ok]
        n = np.sqrt(np.einsum("ij,ij->i", q, q))
        if np.any(np.abs(n - 1.0) > 1e-2):
            bad = np.flatnonzero(ok)[int(np.argmax(np.abs(n - 1.0)))]
            raise InputError(
                f"expected {name} as unit quaternions wxyz, got norm {np.linalg.norm(flat[bad]):.4g} at row {bad}"
            )
        if every and q.size:  # no missing row: no masked copy
            out = Rotation.from_quat(q, scalar_first=True).as_matrix()
        else:
            out = np.full((flat.shape[0], 3, 3), np.nan)
            if q.size:
                out[ok] = Rotation.from_quat(q, scalar_first=True).as_matrix()
        return out.reshape(*a.shape[:-1], 3, 3)
    if a.ndim >= 2 and a.shape[-2:] == (3, 3):
        flat = a.reshape(-1, 9)
        ok = finite_rows(flat)
        err, det_min = _orthonormality(flat if ok.all() else flat[ok])
        if err > 1e-4 or det_min < 0:
            raise InputError(
                f"expected {name} as proper rotation matrices, got max |RᵀR − I| = {err:.3g} or det < 0"
            )
        return a
    raise InputError(
        f"expected {name} with shape (..., T, 4) quaternions wxyz or (..., T, 3, 3) matrices, got {a.shape}"
    )


def forward_kinematics(
    skeleton: Skeleton,
    orientations: Mapping[str, object],
    root_position,
    *,
    frame: str = "world",
) -> dict[str, np.ndarray]:
    """Joint positions from segment orientations (batched over time).

    Parameters
    ----------
    skeleton : Skeleton
        Topology, lengths (m), segment axes (in the frame of the orientations given) and offsets.
    orientations : mapping of str -> array_like
        Per segment ``q_world_from_segment`` as ``(..., T, 4)`` ``wxyz`` quaternions or
        ``(..., T, 3, 3)`` matrices. Pass IMU orientations ``q_world_from_sensor`` together with a
        skeleton whose axes are the calibrated axes in the sensor frames (SPEC §2.1). Needs every
        skeleton segment, plus ``skeleton.root_segment`` when offset joints must be computed or
        ``frame="root_segment"``. NaN rows give NaN positions.
    root_position : array_like, shape (..., T, 3), or mapping of str -> array_like
        Position of ``skeleton.root`` (m, world frame), or positions of several root joints
        (e.g. ``{"hip_l": ..., "hip_r": ...}`` from a reference); a given joint is used as is
        instead of being computed from an offset.
    frame : {"world", "root_segment"}
        ``"world"``: positions in the world frame of the orientations (ENU). ``"root_segment"``:
        paper B's literal output, ``R0ᵀ (p − p_root)`` in the root segment's (chest IMU) frame.

    Returns
    -------
    dict of str -> ndarray, shape (..., T, 3)
        Every joint of the skeleton (root, offset joints, distal joints), m.

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        Unknown or missing segments, inconsistent shapes, unknown frame, unknown offsets needed.

    Notes
    -----
    SPEC §2.1 corrected paper A Eqs. (1)-(2)::

        p1_k = p0 + l1 R1_k a1 ;   p2_k = p1_k + l2 R2_k a2

    SPEC §2.2 corrected paper B Eqs. (3)-(17)::

        shoulder_S = p0 + R0 s_S ;  hip_S = p0 + R0 h_S
        elbow_S = shoulder_S + lE R1S a ;  wrist_S = elbow_S + lW R3S a
        knee_S  = hip_S + lk R4S a      ;  ankle_S = knee_S + la R5S a

    Deviations from the paper: paper A's ``T^i_{0,k}`` ("attitude transfer matrix") is read as
    the unit segment direction ``R_i a_i`` in ENU and its relative rotation ``T^2_{1,k}`` as the
    absolute ``R_2`` (SPEC §2.1-1/2); paper B's positions are computed in ENU with absolute
    orientations instead of chest-relative rotations (SPEC §2.2-2; ``frame="root_segment"``
    gives the paper's chest-frame output), with a configurable axis instead of "first column"
    (SPEC §2.2-1) and hip offsets from the chest origin (SPEC §2.2-4).
    """
    known = _check_inputs(skeleton, orientations, frame)
    pos = _root_positions(skeleton, root_position)
    roots = sorted(pos)
    matrix = _SegmentMatrices(orientations, known)
    needs_root_seg = frame == "root_segment" or any(j not in pos for j in skeleton.offsets_m)
    R0 = None
    if needs_root_seg and skeleton.root_segment is not None:
        R0 = matrix(skeleton.root_segment, "root segment: rotates the offsets / output frame")
    _add_offset_joints(skeleton, pos, R0)
    _add_chain_joints(skeleton, pos, matrix, roots)
    if frame == "root_segment":
        pos = _in_root_segment_frame(skeleton, pos, R0, roots)
    return pos


def _check_inputs(skeleton: Skeleton, orientations, frame: str) -> set[str]:
    """Validate the arguments of :func:`forward_kinematics`; the segment names it accepts."""
    if not isinstance(skeleton, Skeleton):
        raise InputError(f"expected skeleton as a Skeleton, got {type(skeleton).__name__}")
    if frame not in ("world", "root_segment"):
        raise InputError(f"expected frame in ('world', 'root_segment'), got {frame!r}")
    if not isinstance(orientations, Mapping):
        raise InputError(
            f"expected orientations as a mapping segment -> (..., T, 4), got {type(orientations).__name__}"
        )
    known = set(skeleton.segments) | ({skeleton.root_segment} if skeleton.root_segment else set())
    unknown = sorted(set(orientations) - known)
    if unknown:
        raise InputError(
            f"unknown segment(s) {unknown} in orientations; expected names from {sorted(known)}"
        )
    return known


def _root_positions(skeleton: Skeleton, root_position) -> dict[str, np.ndarray]:
    """The given root joint positions, validated, as float arrays ``(..., T, 3)``."""
    if isinstance(root_position, Mapping):
        roots = dict(root_position)
    else:
        roots = {skeleton.root: root_position}
    allowed = set(skeleton.joints)
    unknown = sorted(set(roots) - allowed)
    if unknown:
        raise InputError(f"unknown root joint(s) {unknown}; expected names from {sorted(allowed)}")
    pos: dict[str, np.ndarray] = {}
    for j, v in roots.items():
        a = np.asarray(v)
        if not np.issubdtype(a.dtype, np.floating) or a.ndim < 2 or a.shape[-1] != 3:
            raise InputError(
                f"expected root position {j!r} as floats with shape (..., T, 3), got {a.shape} {a.dtype}"
            )
        pos[j] = a.astype(float)
    return pos


class _SegmentMatrices:
    """Rotation matrices of the segments, converted once on first use."""

    def __init__(self, orientations: Mapping[str, object], known: set[str]):
        self.orientations, self.known, self.mats = orientations, known, {}

    def __call__(self, seg: str, why: str) -> np.ndarray:
        if seg not in self.mats:
            if seg not in self.orientations:
                raise InputError(
                    f"missing orientation for segment {seg!r} ({why}); expected keys {sorted(self.known)}, "
                    f"got {sorted(self.orientations)}"
                )
            self.mats[seg] = as_rotation_matrices(self.orientations[seg], f"orientations[{seg!r}]")
        return self.mats[seg]


def _orthonormality(flat: np.ndarray, chunk: int = 8192) -> tuple[float, float]:
    """``(max |RᵀR − I|, min det R)`` over the row-major matrices ``flat (n, 9)`` (``(0, inf)``
    for none); in chunks of component rows, several times faster than batched 3×3 products."""
    err, det_min = 0.0, np.inf
    for i in range(0, flat.shape[0], chunk):
        c = flat[i : i + chunk].T.copy()
        a, b, d = c[0::3], c[1::3], c[2::3]  # the three columns, (3, n) each
        gram = [(a, a, 1.0), (b, b, 1.0), (d, d, 1.0), (a, b, 0.0), (a, d, 0.0), (b, d, 0.0)]
        for u, v, target in gram:
            err = max(err, float(np.abs(np.einsum("in,in->n", u, v) - target).max()))
        det = (a[0] * (b[1] * d[2] - b[2] * d[1]) + a[1] * (b[2] * d[0] - b[0] * d[2])
               + a[2] * (b[0] * d[1] - b[1] * d[0]))  # fmt: skip
        det_min = min(det_min, float(det.min()))
    return err, det_min


def _add_offset_joints(skeleton: Skeleton, pos: dict, R0) -> None:
    """Joints at a fixed offset from the root in the root segment's frame, added to ``pos``."""
    for j, off in skeleton.offsets_m.items():
        if j in pos:
            continue
        if np.any(np.isnan(off)):
            raise InputError(
                f"offset of joint {j!r} is unknown (NaN): supply {j!r} in root_position or give the skeleton offsets"
            )
        if skeleton.root not in pos:
            raise InputError(
                f"joint {j!r} needs the root {skeleton.root!r} position; got roots {sorted(pos)}"
            )
        if R0.shape[:-2] != pos[skeleton.root].shape[:-1]:
            raise InputError(
                f"root segment {skeleton.root_segment!r}: orientation shape (..., T) = {R0.shape[:-2]} does not "
                f"match the root positions {pos[skeleton.root].shape[:-1]}"
            )
        pos[j] = pos[skeleton.root] + np.einsum("...ij,j->...i", R0, off)


def _add_chain_joints(skeleton: Skeleton, pos: dict, matrix, roots: list[str]) -> None:
    """Every segment's distal joint, ``p_distal = p_proximal + l R a``, added to ``pos``."""
    for i, seg in enumerate(skeleton.segments):
        prox = skeleton.proximal[i]
        if prox not in pos:
            raise InputError(
                f"segment {seg!r} starts at {prox!r}, which is neither given in root_position "
                f"({sorted(roots)}) nor computable"
            )
        R = matrix(seg, "skeleton segment")
        if R.shape[:-2] != pos[prox].shape[:-1]:
            raise InputError(
                f"segment {seg!r}: orientation shape (..., T) = {R.shape[:-2]} does not match its start joint "
                f"{prox!r} positions {pos[prox].shape[:-1]} (expected the same (..., T))"
            )
        pos[skeleton.distal[i]] = pos[prox] + skeleton.lengths_m[i] * np.einsum(
            "...ij,j->...i", R, skeleton.axes[i]
        )


def _in_root_segment_frame(skeleton: Skeleton, pos: dict, R0, roots: list[str]) -> dict:
    """Paper B's output frame: ``R0ᵀ (p − p_root)`` for every joint."""
    if skeleton.root_segment is None:
        raise InputError("frame='root_segment' needs a skeleton with a root_segment, got None")
    if skeleton.root not in pos:
        raise InputError(
            f"frame='root_segment' needs the root {skeleton.root!r} position; got {roots}"
        )
    p0 = pos[skeleton.root]
    return {j: np.einsum("...ji,...j->...i", R0, p - p0) for j, p in pos.items()}
