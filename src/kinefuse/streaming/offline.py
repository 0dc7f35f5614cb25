"""The online engine's computation on a recording: offline (batch) and causal.

:func:`offline_causal` runs the engine's own per-frame code: it fills the engine's
:class:`~.alignment.SegmentBuffer` s with the recorded samples, calls the engine's
:class:`~.alignment.FrameAssembler` once per frame (orientation at the frame time, camera
joints, IMU chain, status and flags) and hands the stacked frames to the processor's batch form
``run`` (equal to its ``step`` repeated, then ``flush``). That the engine's outputs equal it is
then a consequence of one implementation, checked by the tests.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.streaming.alignment import FrameAssembler, SegmentBuffer, camera_frame_due
from kinefuse.streaming.engine_types import EngineConfig
from kinefuse.streaming.heading import PoseHeading
from kinefuse.streaming.processors import Processor

__all__ = ["OfflineCausalResult", "offline_causal"]


@dataclass(frozen=True, eq=False)
class OfflineCausalResult:
    """Output of :func:`offline_causal` (T frames, J output joints).

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Frame times, s.
    position_m : ndarray, shape (T, J, 3)
    cov_m2 : ndarray, shape (T, J, 3, 3)
    source : ndarray of int8, shape (T, J)
        Processor source codes.
    imu_status : ndarray of int8, shape (T, J)
        Worst ``IMU_*`` status over the segments carrying each joint.
    flags : ndarray of uint8, shape (T, J)
        ``FLAG_*`` bits as in :attr:`~kinefuse.streaming.engine.EngineOutput.flags` (never
        ``FLAG_FORCED``: offline every sample has arrived).
    synthesized : ndarray of bool, shape (T,)
        Frames without a camera frame (camera holes, or no camera at all: False).
    z_imu, z_cam : ndarray, shape (T, J, 3)
        The processor's inputs: IMU-chain and camera joint positions, m (NaN = none).
    available : ndarray of bool, shape (T, J)
        Camera availability per joint.
    angles_deg : ndarray, shape (T, A, 3), or None
        Joint angles of ``config.angle_joints``, deg (None without segment frames).
    """

    t_s: np.ndarray
    position_m: np.ndarray
    cov_m2: np.ndarray
    source: np.ndarray
    imu_status: np.ndarray
    flags: np.ndarray
    synthesized: np.ndarray
    z_imu: np.ndarray
    z_cam: np.ndarray
    available: np.ndarray
    angles_deg: np.ndarray | None = None


def _camera_series(camera, cfg: EngineConfig):
    """Camera frames sorted by time: ``t (M,)``, ``position (M, Jc, 3)``, ``available (M, Jc)``
    (availability and finiteness combined, as :meth:`~.engine.Engine.push_camera` does)."""
    ct, cpos, cav = (np.asarray(a) for a in camera)
    order = np.argsort(ct, kind="stable")
    ct, cpos, cav = ct[order].astype(float), cpos[order].astype(float), cav[order].astype(bool)
    Jc = len(cfg.camera_joints)
    if cpos.shape != (ct.size, Jc, 3) or cav.shape != (ct.size, Jc):
        raise InputError(
            f"expected camera (t (M,), position (M, {Jc}, 3), available (M, {Jc})), got "
            f"{ct.shape}, {cpos.shape}, {cav.shape}"
        )
    return ct, cpos, cav & np.all(np.isfinite(cpos), axis=-1)


def _frame_times(ct: np.ndarray, period: float) -> np.ndarray:
    """The engine's frames for camera frames at ``ct``: each frame, and in a hole the expected
    frames ``t_prev + period`` before it (:func:`~.alignment.camera_frame_due`)."""
    ft: list[float] = []
    for k, tc in enumerate(ct):
        if k:
            t_exp = ft[-1] + period
            while not camera_frame_due(tc, t_exp, period):
                ft.append(t_exp)
                t_exp += period
        ft.append(float(tc))
    return np.asarray(ft)


def offline_causal(
    config: EngineConfig,
    processor: Processor,
    imu: Mapping[str, tuple],
    camera: tuple | None,
    frame_times: Sequence[float] | None = None,
) -> OfflineCausalResult:
    """The engine's computation done offline (causal, batch) on recorded samples.

    Parameters
    ----------
    config : EngineConfig
    processor : Processor
        A processor of the same configuration as the engine's; its ``run`` is used (its
        online state is not touched).
    imu : mapping of str -> (t (N,), q (N, 4))
        Accepted orientation samples per segment (any order; sorted here).
    camera : (t (M,), position (M, Jc, 3), available (M, Jc)) or None
        Accepted camera frames (ignored with ``config.camera`` False).
    frame_times : sequence of float, optional
        Frame times. Default: the camera frames plus the frames the engine synthesizes in
        camera holes (``t_prev + period`` while the next frame is more than 0.75 periods
        beyond); required without a camera.

    Returns
    -------
    OfflineCausalResult

    Notes
    -----
    Per frame the engine's own :class:`~.alignment.FrameAssembler` on buffers holding the whole
    recording (orientation at the frame time: the sample, else SLERP unless a gap, else hold
    of the last sample at most ``stale_after_s`` old, else stale; the chain root from the
    camera, carried forward). Equals the engine's outputs whenever the engine never forced a
    frame (every live IMU sample at or after a frame time had arrived when it was processed)
    and was given ``frame_times`` equal to its frames.
    """
    cfg = config
    if camera is not None and cfg.camera:
        ct, cpos, cav = _camera_series(camera, cfg)
    else:
        ct = np.zeros(0)
    if frame_times is None:
        if camera is None:
            raise InputError("offline_causal: frame_times is required without a camera")
        t = _frame_times(ct, cfg.frame_period_s)
    else:
        t = np.asarray(frame_times, dtype=float)
    if cfg.heading_pose_s is not None:  # 6-D: the engine's heading search, on the whole record
        heading = PoseHeading(cfg.segment_frames, cfg.heading_pose_s, cfg.segments,
                              cfg.heading_reference, cfg.heading_pose_yaw_deg)  # fmt: skip
        turned = heading.apply(imu)
        if turned is None:
            raise InputError(
                f"offline_causal: no still pose of {cfg.heading_pose_s:g} s in the IMU samples "
                "(6-D headings unknown; the engine outputs nothing)"
            )
        imu = turned
    buffers = []
    for s in cfg.segments:
        ts, qs = imu.get(s, (np.zeros(0), np.zeros((0, 4))))
        period = cfg.imu_period_s(s)
        buffers.append(SegmentBuffer(s, period, cfg.gap_factor * period).fill(ts, qs))
    frames = FrameAssembler(cfg)
    cam_index: dict[float, int] = {}
    for k, v in enumerate(ct.tolist()):
        cam_index.setdefault(v, k)  # a repeated time stamp: the first frame (the engine's)
    root = np.array(cfg.root_position_m)
    rows = []
    for tk in t.tolist():
        c = cam_index.get(tk)
        fr = frames.assemble(tk, None if c is None else cpos[c], None if c is None else cav[c],
                             buffers, root, False)  # fmt: skip
        root = fr.root
        rows.append(fr)
    synthesized = np.array([cfg.camera and tk not in cam_index for tk in t.tolist()], bool)
    J = len(cfg.joints)

    def stack(name, shape, dtype):
        return np.array([getattr(r, name) for r in rows], dtype).reshape(t.size, *shape)

    z_imu, z_cam = stack("z_imu", (J, 3), float), stack("z_cam", (J, 3), float)
    avail = stack("available", (J,), bool)
    position, cov, source = processor.run(t, z_imu, z_cam, avail)
    return OfflineCausalResult(
        t_s=t, position_m=position, cov_m2=cov, source=source,
        imu_status=stack("imu_status", (J,), np.int8), flags=stack("flags", (J,), np.uint8),
        synthesized=synthesized, z_imu=z_imu, z_cam=z_cam, available=avail,
        angles_deg=stack("angles_deg", (len(cfg.angle_joints), 3), float) if cfg.angle_joints else None,
    )  # fmt: skip
