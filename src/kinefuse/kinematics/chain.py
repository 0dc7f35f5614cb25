"""Joint positions and segment orientations of a calibrated IMU chain (SPEC §2.1/§2.2).

A recording's IMU orientations, a skeleton and a :class:`~kinefuse.kinematics.Calibration`
give the chain's joint positions (forward kinematics from measured roots) and the ISB segment
orientations used for joint angles.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.io.recording import JointStream, Recording
from kinefuse.kinematics.calibration_result import Calibration, joint_stream, oriented_imu
from kinefuse.kinematics.forward import as_rotation_matrices, forward_kinematics
from kinefuse.kinematics.skeleton import Skeleton
from kinefuse.orientation.resample import slerp_resample

__all__ = ["chain_orientations", "chain_positions", "segment_orientations"]


def chain_positions(
    recording: Recording,
    skeleton: Skeleton,
    calibration: Calibration | None = None,
    *,
    root: str | Sequence[str] | Mapping[str, object] | None = None,
    source: str = "reference",
    t_s=None,
    use_calibrated_lengths: bool = True,
    orientations: Mapping[str, np.ndarray] | None = None,
) -> JointStream:
    """Joint positions of the IMU chain (SPEC §2.1/§2.2) for a recording.

    Parameters
    ----------
    recording : Recording
        IMU orientations per segment; the ``source`` joint stream when roots come from it.
    skeleton : Skeleton
        Topology, lengths and default axes.
    calibration : Calibration, optional
        Calibrated axes (override the skeleton's), measured lengths (if
        ``use_calibrated_lengths``) and the camera/reference alignment.
    root : str, sequence of str, mapping, optional
        Root joint positions. Names are taken from the ``source`` joint stream (the root segment
        carries no sensor: paper A measures the shoulder; for Neura the hip centres come from
        Vicon). A mapping gives arrays ``(T, 3)`` on the timeline ``t_s``. Default: the proximal
        joints of the parentless segments if the stream has them all, else ``skeleton.root``.
    source : {"reference", "vision"}
        Joint stream for named roots, and the output timeline and frame.
    t_s : array_like, shape (T,), optional
        Timeline for mapping roots (default: the source stream's, else the first segment IMU's).
    use_calibrated_lengths : bool
        Use the lengths measured during calibration where available.
    orientations : mapping of str -> ndarray, shape (T, 3, 3), optional
        :func:`chain_orientations` of the same recording and calibration on the output
        timeline, when the caller has them already (they are not resampled again).

    Returns
    -------
    JointStream
        On the root's timeline (IMU orientations SLERP-resampled to it where the times differ),
        in the root stream's frame (``R_world_from_camera`` applied when calibrated), joints = the
        roots and every joint the chain computes; ``available`` False where an input was missing.
    """
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    if calibration is not None:
        skeleton = calibration.apply(skeleton, lengths=use_calibrated_lengths)
    stream = getattr(recording, source, None) if source in ("reference", "vision") else None
    if source not in ("reference", "vision"):
        raise InputError(f"expected source in ('reference', 'vision'), got {source!r}")
    if isinstance(root, Mapping):
        t, roots, frame = _given_roots(recording, skeleton, root, stream, t_s)
    else:
        t, roots, frame = _stream_roots(recording, skeleton, root, source)
    needed = list(skeleton.segments)
    if skeleton.root_segment is not None and any(j not in roots for j in skeleton.offsets_m):
        needed.append(skeleton.root_segment)
    have = {} if orientations is None else orientations
    ori = {s: have[s] for s in needed if s in have}
    bad = [s for s, R in ori.items() if np.shape(R) != (t.size, 3, 3)]
    if bad:
        raise InputError(
            f"orientations of {bad}: expected shape ({t.size}, 3, 3) (the output timeline), got "
            f"{[np.shape(ori[s]) for s in bad]}"
        )
    if len(ori) < len(needed):
        ori.update(
            _chain_orientations(recording, calibration, [s for s in needed if s not in ori], t)
        )
    pos = forward_kinematics(skeleton, ori, roots)
    names = [j for j in skeleton.joints if j in pos] + [j for j in pos if j not in skeleton.joints]
    P = np.stack([pos[j] for j in names], axis=1)
    return JointStream(t_s=t, position_m=P, joints=tuple(names), frame=frame)


def _given_roots(recording, skeleton, root: Mapping, stream, t_s):
    """Root positions given as arrays: ``(timeline, roots, frame)``."""
    frame = "ENU"
    if t_s is not None:
        t = np.asarray(t_s, dtype=float)
    elif stream is not None:
        t = stream.t_s
    else:
        t = oriented_imu(recording, skeleton.segments[0], "timeline").t_s
    roots = {}
    for j, v in root.items():
        a = np.asarray(v, dtype=float)
        if a.shape != (t.size, 3):
            raise InputError(
                f"expected root {j!r} with shape (T, 3) = ({t.size}, 3), got {a.shape}"
            )
        roots[j] = a
    if stream is not None and t_s is None:
        frame = stream.frame
    return t, roots, frame


def _stream_roots(recording, skeleton, root, source: str):
    """Root positions named from the ``source`` joint stream: ``(timeline, roots, frame)``."""
    stream = joint_stream(recording, source)
    if root is None:
        starts = [skeleton.proximal[i] for i, p in enumerate(skeleton.parents) if p == -1]
        names = (
            list(dict.fromkeys(starts))
            if all(j in stream.joints for j in starts)
            else [skeleton.root]
        )
    else:
        names = [root] if isinstance(root, str) else list(root)
    lack = [j for j in names if j not in stream.joints]
    if lack:
        raise InputError(
            f"root joint(s) {lack} not in the {source} stream; it has {list(stream.joints)}"
        )
    return stream.t_s, {j: stream.position(j) for j in names}, stream.frame


def chain_orientations(
    recording: Recording, skeleton: Skeleton, calibration: Calibration | None, t_s
) -> dict[str, np.ndarray]:
    """The sensor orientations :func:`chain_positions` uses, in the frame of its output.

    Parameters
    ----------
    recording, skeleton, calibration
        As in :func:`chain_positions`: the skeleton's segments (and its root segment where that
        has an IMU) are returned, with the calibration's heading corrections and
        ``R_world_from_camera`` (the output frame of a chain rooted at the camera or the
        reference) applied. ``calibration`` may be None.
    t_s : array_like, shape (T,)
        The output timeline, s (orientations SLERP-resampled to it).

    Returns
    -------
    dict of str -> ndarray, shape (T, 3, 3)
        ``R_frame_from_sensor`` per segment; NaN where the IMU has no sample.
    """
    segs = list(skeleton.segments)
    if skeleton.root_segment is not None and skeleton.root_segment in recording.imu:
        segs.append(skeleton.root_segment)
    return _chain_orientations(recording, calibration, segs, np.asarray(t_s, dtype=float))


def _chain_orientations(recording, calibration, needed, t) -> dict[str, np.ndarray]:
    """``R_frame_from_sensor`` on ``t`` of the ``needed`` segments (headings, ``R_c`` applied)."""
    Rc = None if calibration is None else calibration.R_world_from_camera
    ori = {}
    for s in needed:
        st = oriented_imu(recording, s, "chain")
        R = as_rotation_matrices(
            slerp_resample(st.t_s, st.q_world_from_sensor, t), f"IMU {s!r} orientation"
        )
        if calibration is not None and s in calibration.world_heading_deg:
            R = np.einsum("ij,kjl->kil", calibration.heading_matrix(s), R)
        ori[s] = R if Rc is None else np.einsum("ji,kjl->kil", Rc, R)  # camera_from_sensor = Rcᵀ R
    return ori


def segment_orientations(
    recording: Recording,
    calibration: Calibration,
    t_s,
    segments: Sequence[str] | None = None,
) -> dict[str, np.ndarray]:
    """``R_world_from_segment`` (ISB segment frames) of calibrated segments on a timeline.

    Parameters
    ----------
    recording : Recording
        IMU orientations per segment.
    calibration : Calibration
        With ``frames`` (static calibration); its heading corrections are applied.
    t_s : array_like, shape (T,)
        Timeline, s (orientations SLERP-resampled to it).
    segments : sequence of str, optional
        Default: every segment of ``calibration.frames``.

    Returns
    -------
    dict of str -> ndarray, shape (T, 3, 3)
        ``R_z(ψ_i) R_world_from_sensor(t) R_sensor_from_segment``; NaN where the IMU has no
        sample.
    """
    if not calibration.frames:
        raise InputError(
            f"{calibration.method!r} calibration gives segment axes only, not segment frames; "
            "joint angles need a static (or functional) calibration"
        )
    t = np.asarray(t_s, dtype=float)
    out = {}
    for s in calibration.frames if segments is None else segments:
        if s not in calibration.frames:
            raise InputError(
                f"segment {s!r} has no calibrated frame; calibrated: {sorted(calibration.frames)}"
            )
        st = oriented_imu(recording, s, "segment orientation")
        R = as_rotation_matrices(
            slerp_resample(st.t_s, st.q_world_from_sensor, t), f"IMU {s!r} orientation"
        )
        out[s] = np.einsum(
            "ij,kjl,lm->kim", calibration.heading_matrix(s), R, calibration.frames[s]
        )
    return out
