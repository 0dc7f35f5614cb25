"""Virtual sensors from real motion: body-worn IMUs and a depth camera with realistic errors.

:func:`virtual_recording` turns a :class:`~kinefuse.io.motion.Motion` (e.g. a CMU mocap trial,
:func:`kinefuse.io.cmu.load_motion_asf_amc`) into a :class:`~kinefuse.io.recording.Recording`
with IMU streams, a camera skeleton stream and the truth, so that pipelines can be evaluated
against exact ground truth. Error models and defaults: :mod:`kinefuse.sim.imu` (ICM-20948 raw
gyro/accelerometer/magnetometer, soft-tissue artefact, mounting error, indoor magnetic
disturbances; orientation from VQF run on the raw signals), :mod:`kinefuse.sim.knee` (knee
internal/external rotation and ab/adduction added to hinge knees) and :mod:`kinefuse.sim.camera`
(fitted to UTD-MHAD Kinect). ``kinefuse experiment realism`` prints how close the virtual sensors
come to real ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict

import numpy as np

from kinefuse._validation import as_float
from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import InputError
from kinefuse.io.motion import Motion
from kinefuse.io.recording import ImuStream, Recording
from kinefuse.sim.camera import CameraConfig, camera_pose, reference_at, simulate_camera
from kinefuse.sim.imu import simulate_imu, simulate_imu_from_pose, time_grid
from kinefuse.sim.imu_config import ORIENTATIONS, ImuConfig
from kinefuse.sim.knee import KNEE_SECONDARY_GAIN, with_knee_secondary
from kinefuse.sim.soft_tissue import STA_AMPLITUDE

__all__ = [
    "KNEE_SECONDARY_GAIN",
    "ORIENTATIONS",
    "PAPER_B_SEGMENTS",
    "STA_AMPLITUDE",
    "CameraConfig",
    "ImuConfig",
    "camera_pose",
    "reference_at",
    "simulate_camera",
    "simulate_imu",
    "simulate_imu_from_pose",
    "time_grid",
    "virtual_recording",
]

#: The nine IMU segments of paper B (Xu 2023): chest, upper arms, forearms, thighs, shanks.
PAPER_B_SEGMENTS = tuple(s for s in SEGMENTS if s != "pelvis" and s[:-2] not in ("foot", "hand"))

_DEFAULT_IMU = ImuConfig()
_DEFAULT_CAMERA = CameraConfig()


def virtual_recording(
    motion: Motion,
    imu: ImuConfig | None = _DEFAULT_IMU,
    camera: CameraConfig | None = _DEFAULT_CAMERA,
    segments: Sequence[str] = PAPER_B_SEGMENTS,
    seed: int = 0,
    reference_rate_hz: float | None = None,
    knee_secondary: float = 1.0,
) -> Recording:
    """Simulate body-worn IMUs and a depth camera from a real motion.

    Parameters
    ----------
    motion : Motion
        Driving motion (ENU truth), e.g. from :func:`kinefuse.io.cmu.load_motion_asf_amc`.
    imu : ImuConfig or None
        IMU rate and error model (default ICM-20948 at 100 Hz); ``ImuConfig.ideal()`` for
        noise-free sensors; ``None`` for no IMUs.
    camera : CameraConfig or None
        Camera rate, noise and outages (default Kinect-like at 30 Hz); ``None`` for no camera.
    segments : sequence of str
        Canonical segments carrying an IMU (default the nine of paper B).
    seed : int
        Seed of all random draws. Each IMU draws from ``default_rng([seed, 1, k])`` with ``k``
        its index in :data:`kinefuse.conventions.SEGMENTS`, the camera from
        ``default_rng([seed, 2])``: the same seed gives identical output, and adding or removing
        a sensor does not change the others.
    reference_rate_hz : float, optional
        Rate of ``recording.reference``; default the camera rate (30 Hz without a camera).
    knee_secondary : float
        Factor on the internal/external rotation and ab/adduction added to hinge knees
        (:mod:`kinefuse.sim.knee`: 1 = the measured ranges in walking; 0 = the mocap's own knees).
        The truth (reference joints and orientations) is the motion with them, drawn from
        ``default_rng([seed, 4])``.

    Returns
    -------
    Recording
        ``imu``: one :class:`ImuStream` per segment (acc m/s², gyr rad/s, mag µT, sensor
        frame; ``q_world_from_sensor`` from VQF on those signals, or as ``imu.orientation``
        says) at ``imu.rate_hz``.
        ``vision``: the camera :class:`JointStream` (frame ``camera.frame``) or None.
        ``reference``: true joint positions at the **camera timestamps** (ENU; the pipelines
        evaluate at the camera rate).
        ``reference_orientation``: true ``q_world_from_segment`` per IMU segment at the IMU rate.
        ``metadata``: ``reference_imu_rate`` (truth JointStream at the IMU timestamps),
        ``imu_truth`` (per segment: true sensor orientation, mounting ``q_segment_from_sensor``,
        soft-tissue artefact, noise-free acc/gyr/mag, biases, sensitivity matrices, magnetic
        disturbance episodes), ``camera_truth`` (masks, bone
        scales), ``R_world_from_camera``, ``camera_position_m``, ``segment_length_m``,
        ``segment_joints``, the configurations, ``seed``, the motion's source and
        ``knee_secondary`` (its factor and, per knee changed, the added rotation vector, rad, at
        the motion's samples).
    """
    segments = _checked_segments(motion, imu, camera, segments)
    seed = int(seed)
    scale = as_float(
        knee_secondary, f"expected knee_secondary as a number >= 0, got {knee_secondary!r}"
    )
    if not (math.isfinite(scale) and scale >= 0.0):
        raise InputError(f"expected knee_secondary finite and >= 0, got {knee_secondary!r}")
    motion, knee_truth = with_knee_secondary(motion, np.random.default_rng([seed, 4]), scale)
    cam_rate = camera.rate_hz if camera is not None else 30.0
    ref_rate = cam_rate if reference_rate_hz is None else float(reference_rate_hz)
    t_ref = time_grid(motion.t_s, ref_rate)
    meta = {
        "source": motion.metadata.get("source", ""),
        "format": "virtual",
        "motion_metadata": dict(motion.metadata),
        "seed": seed,
        "imu_config": None if imu is None else asdict(imu),
        "camera_config": None if camera is None else asdict(camera),
        "reference_rate_hz": ref_rate,
        "segment_length_m": dict(motion.segment_length_m),
        "segment_joints": dict(motion.segment_joints),
        "segment_axis": "e2 (proximal -> distal) in the segment frame",
        "knee_secondary": {"scale": scale, "rotvec_rad": knee_truth},
    }
    imus: dict[str, ImuStream] = {}
    ref_orient: dict[str, ImuStream] = {}
    if imu is not None and segments:
        imus, ref_orient = _virtual_imus(motion, imu, segments, seed, meta)
    vision = None if camera is None else _virtual_camera(motion, camera, seed, meta)
    reference = reference_at(motion, t_ref, joints=vision.joints if vision is not None else None)
    return Recording(
        imu=imus,
        vision=vision,
        reference=reference,
        reference_orientation=ref_orient,
        metadata=meta,
    )


def _checked_segments(motion, imu, camera, segments) -> tuple[str, ...]:
    """Validate the arguments of :func:`virtual_recording`; the IMU segments (none without IMU)."""
    if not isinstance(motion, Motion):
        raise InputError(
            f"expected motion as a kinefuse.io.motion.Motion, got {type(motion).__name__}"
        )
    if imu is not None and not isinstance(imu, ImuConfig):
        raise InputError(f"expected imu as ImuConfig or None, got {type(imu).__name__}")
    if camera is not None and not isinstance(camera, CameraConfig):
        raise InputError(f"expected camera as CameraConfig or None, got {type(camera).__name__}")
    if isinstance(segments, str):
        raise InputError(f"expected segments as a sequence of names, got the string {segments!r}")
    segments = tuple(segments) if imu is not None else ()
    for s in segments:
        motion.segment_index(s)
    return segments


def _virtual_camera(motion, camera: CameraConfig, seed: int, meta: dict):
    """The virtual camera's joint stream; its truth added to ``meta``."""
    t_cam = time_grid(motion.t_s, camera.rate_hz)
    vision, cam_truth = simulate_camera(motion, camera, np.random.default_rng([seed, 2]), t_cam)
    meta["camera_truth"] = cam_truth
    meta["R_world_from_camera"] = cam_truth["R_world_from_camera"]
    meta["camera_position_m"] = cam_truth["camera_position_m"]
    return vision


def _virtual_imus(motion, imu: ImuConfig, segments, seed: int, meta: dict):
    """One virtual IMU per segment and the true segment orientations; truth added to ``meta``."""
    imus: dict[str, ImuStream] = {}
    ref_orient: dict[str, ImuStream] = {}
    t_imu = time_grid(motion.t_s, imu.rate_hz)
    truth_all = {}
    for s in segments:
        rng = np.random.default_rng([seed, 1, SEGMENTS.index(s)])
        stream, truth = simulate_imu(motion, s, imu, rng, t_imu)
        imus[s] = stream
        truth_all[s] = truth
        ref_orient[s] = ImuStream(
            t_s=t_imu, q_world_from_sensor=truth["q_world_from_segment"], name=s
        )
    meta["imu_truth"] = truth_all
    meta["reference_imu_rate"] = reference_at(motion, t_imu)
    return imus, ref_orient
