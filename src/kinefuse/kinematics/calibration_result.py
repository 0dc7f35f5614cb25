"""The result of a sensor-to-segment calibration and the recording look-ups its methods share.

:class:`Calibration` is what :func:`kinefuse.kinematics.calibrate` (static, reference, vision),
:func:`kinefuse.kinematics.functional_calibration` and
:func:`kinefuse.kinematics.hinge.hinge_frames` return, and what
:func:`kinefuse.kinematics.chain_positions` consumes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError
from kinefuse.io.recording import ImuStream, JointStream, Recording
from kinefuse.kinematics.forward import rotation_z
from kinefuse.kinematics.skeleton import Skeleton, unit_axis
from kinefuse.kinematics.still import StillWindow

__all__ = ["Calibration", "joint_stream", "oriented_imu", "turn_heading", "turned_heading"]


@dataclass(frozen=True, eq=False)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    axes : dict of str -> ndarray, shape (3,)
        Unit segment axis (proximal -> distal) in each segment's IMU frame, ``a_i``.
    lengths_m : dict of str -> float
        Segment lengths measured in the calibration window (reference/vision methods), m; empty
        for the static method.
    R_world_from_camera : ndarray, shape (3, 3), or None
        Rotation taking vectors from the joint stream's frame (camera or reference) into the IMU
        world frame; None when the frames are taken as shared (no alignment estimated).
    method : str
        ``"static"``, ``"reference"`` or ``"vision"``.
    window_s : tuple of float
        ``(start, end)`` of the calibration window, s.
    residual_deg : dict of str -> float
        RMS angle in the window between the modelled segment direction ``R_i a_i`` and the
        observed one (reference/vision) or ``d0`` (static), deg.
    align : str
        Alignment used: ``"none"``, ``"heading"`` or ``"rotation"``.
    frames : dict of str -> ndarray, shape (3, 3)
        Static and functional: ``R_sensor_from_segment`` of each segment, columns = the
        segment's ISB axes (X anterior, Y superior, Z right) in the sensor frame; used for joint
        angles (functional: only segments next to an elbow or knee).
    world_heading_deg : dict of str -> float
        Static with ``heading="static"``: rotation about the vertical that this calibration
        applies to each sensor's world frame, deg (``R_world_from_sensor <- R_z(ψ)
        R_world_from_sensor``, in :func:`chain_positions` and :func:`segment_orientations`).
    still : StillWindow or None
        Static only: the window and how still it was.
    pose_residual_deg : dict of str -> float
        Static with ``mounting``: RMS angle between the declared sensor axis and the assumed
        pose direction in the window, deg.
    hinge_residual_rad_s : dict of str -> float
        Hinge joints whose segment frames come from the measured flexion axis
        (:func:`kinefuse.kinematics.hinge.hinge_frames`): RMS residual of the joint's
        angular-rate constraint, rad/s (0 for an ideal joint).
    facing : ndarray, shape (3,), or None
        Static: the subject's horizontal facing direction in the (heading-corrected) IMU world
        frame that the pose frames used.
    facing_from : str
        Static: where ``facing`` came from: ``"declared"``, ``"hinges"`` (estimated from the
        flexion axes fitted to the movement, :func:`kinefuse.kinematics.hinge.hinge_facing`)
        or ``"default"`` (north, nothing to estimate it from).
    pose_angles_deg : dict of str -> ndarray, shape (3,)
        Static: the joint angles (:func:`kinefuse.kinematics.joint_angles`) that the pose itself
        implies, per joint whose two segments it calibrated: zero, except the shoulders in the
        T-pose (adduction −90°, flexion and internal rotation 0 by convention: the arm
        horizontal to the side is the decomposition's singular position).
    limb_heading_deg : dict of str -> float
        Static with ``heading="static"`` and flexion axes from the movement: per hinge, the turn
        about the vertical applied to its limb's sensors (included in ``world_heading_deg``) so
        that its flexion axis is the body's medio-lateral axis in the pose, deg
        (:func:`kinefuse.kinematics.hinge.limb_headings`).
    foot_heading_deg : dict of str -> float
        Static with ``heading="static"`` and flexion axes from the movement: per ankle, the turn
        about the vertical applied to its foot sensor (included in ``world_heading_deg``),
        fitted to the ankle's movement relative to the shank, deg
        (:func:`kinefuse.kinematics.hinge.foot_headings`).
    pelvis_heading_deg : dict
        Static with ``heading="static"`` and flexion axes from the movement, where the hips
        moved: ``turn``, the turn about the vertical applied to the pelvis sensor (included in
        ``world_heading_deg``, its frame turned with it), deg, and the hips' estimates it came
        from (``rates``, ``accelerations``: per hip, deg)
        (:func:`kinefuse.kinematics.pelvis_heading.pelvis_heading`).
    """

    axes: Mapping[str, np.ndarray]
    lengths_m: Mapping[str, float] = field(default_factory=dict)
    R_world_from_camera: np.ndarray | None = None
    method: str = "static"
    window_s: tuple[float, float] = (0.0, 0.0)
    residual_deg: Mapping[str, float] = field(default_factory=dict)
    align: str = "none"
    frames: Mapping[str, np.ndarray] = field(default_factory=dict)
    world_heading_deg: Mapping[str, float] = field(default_factory=dict)
    still: StillWindow | None = None
    pose_residual_deg: Mapping[str, float] = field(default_factory=dict)
    hinge_residual_rad_s: Mapping[str, float] = field(default_factory=dict)
    facing: np.ndarray | None = None
    facing_from: str = ""
    pose_angles_deg: Mapping[str, np.ndarray] = field(default_factory=dict)
    limb_heading_deg: Mapping[str, float] = field(default_factory=dict)
    foot_heading_deg: Mapping[str, float] = field(default_factory=dict)
    pelvis_heading_deg: Mapping[str, object] = field(default_factory=dict)

    def heading_matrix(self, segment: str) -> np.ndarray:
        """``R_z(ψ)`` applied to ``segment``'s sensor world frame (identity if none), (3, 3)."""
        return rotation_z(np.radians(self.world_heading_deg.get(segment, 0.0)))

    def q_sensor_from_segment(self, segment: str, segment_axis="+e2") -> np.ndarray:
        """The shortest rotation taking ``segment_axis`` (segment frame) onto ``a_i`` (sensor frame).

        Only the axis is calibrated; the rotation about it is the minimal one (``wxyz``, (4,)).
        """
        if segment not in self.axes:
            raise InputError(
                f"unknown segment {segment!r}; calibrated segments are {sorted(self.axes)}"
            )
        e = unit_axis(segment_axis, "segment_axis")
        rot = Rotation.align_vectors(self.axes[segment][None], e[None])[0]
        return rot.as_quat(scalar_first=True)

    def apply(self, skeleton: Skeleton, *, lengths: bool = True) -> Skeleton:
        """``skeleton`` with the calibrated axes (and, if ``lengths``, the measured lengths)."""
        sk = skeleton.with_axes({s: a for s, a in self.axes.items() if s in skeleton.segments})
        if lengths and self.lengths_m:
            sk = sk.with_lengths(
                {s: v for s, v in self.lengths_m.items() if s in skeleton.segments}
            )
        return sk


def oriented_imu(recording: Recording, segment: str, purpose: str) -> ImuStream:
    """``recording.imu[segment]``, which must carry ``q_world_from_sensor`` (``purpose`` names the use)."""
    if segment not in recording.imu:
        raise InputError(
            f"missing IMU for segment {segment!r} ({purpose}); expected it among the recording's IMUs "
            f"{sorted(recording.imu)}"
        )
    s = recording.imu[segment]
    if s.q_world_from_sensor is None:
        raise InputError(
            f"IMU {segment!r} has raw data but no orientation; estimate it first, e.g. "
            "kinefuse.orientation.estimate(acc, gyr, mag, rate_hz=...)"
        )
    return s


def turned_heading(stream: ImuStream, psi_deg: float) -> ImuStream:
    """``stream`` with its orientations turned about the vertical of their world frame:
    ``q_world_from_sensor <- Rz(ψ) q_world_from_sensor``, ``ψ = psi_deg``; missing rows stay
    missing (NaN)."""
    q = turn_heading(np.asarray(stream.q_world_from_sensor, dtype=float), psi_deg)
    q[~np.all(np.isfinite(q), axis=1)] = np.nan
    return replace(stream, q_world_from_sensor=q)


def turn_heading(q: np.ndarray, psi_deg: float) -> np.ndarray:
    """``Rz(ψ) q`` for ``wxyz`` quaternions ``q (..., 4)``, ``ψ = psi_deg``: a new array.

    Each row is normalised first (as ``scipy.spatial.transform.Rotation.from_quat``), then
    multiplied on the left by ``[cos ψ/2, 0, 0, sin ψ/2]`` (the Hamilton product written out):
    the rotation of scipy's ``Rotation.from_matrix(R_z(ψ)) * Rotation.from_quat(q)``, with the
    sign that follows ``q`` (scipy's ``from_matrix`` picks its own, flipping the result for
    some ψ). A NaN row stays NaN; ``ψ = 0`` returns the normalised rows.
    """
    q = np.asarray(q, dtype=float)
    q = q / np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
    if psi_deg == 0.0:
        return q
    half = np.radians(psi_deg) / 2.0
    c, s = np.cos(half), np.sin(half)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w], axis=-1)


def joint_stream(recording: Recording, source: str) -> JointStream:
    """``recording.reference`` or ``recording.vision`` (``source``), which must be present."""
    if source not in ("reference", "vision"):
        raise InputError(f"expected source in ('reference', 'vision'), got {source!r}")
    st = getattr(recording, source)
    if st is None:
        raise InputError(
            f"the recording has no {source} joint stream (needed for {source!r} calibration or root)"
        )
    return st
