"""What processing a recording gives: :class:`SessionOutput` and its evaluation."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from kinefuse.conventions import AXES_ENU
from kinefuse.evaluation import evaluate
from kinefuse.pipelines.features import joint_rotations

__all__ = ["SessionOutput"]


@dataclass(eq=False)
class SessionOutput:
    """Result of :func:`process_recording`.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Output timeline, s.
    joints : tuple of str
        Output joints (distal joints of the mapped segments).
    position : ndarray, shape (T, J, 3)
        Estimated joint positions, m, in ``frame``.
    std_m : ndarray, shape (T, J, 3)
        Per-axis standard deviation, m (NaN where the method gives none).
    source : ndarray of int, shape (T, J)
        :data:`kinefuse.conventions.SOURCE_NAMES` code per sample (-1: no estimate).
    mode : ndarray of int, shape (T, J)
        :data:`kinefuse.conventions.MODE_NAMES` filter branch per sample (-1: no filter).
    frame : str
        Frame of the positions (the root stream's, or ``"ENU chest-relative"``).
    method : str
        Method name; ``label`` is its table label.
    label : str
    chain : ndarray, shape (T, J, 3)
        The unfiltered IMU chain, m (same frame).
    camera : ndarray, shape (T, J, 3) or None
        Camera positions of the output joints in the same frame (NaN where unavailable).
    reference : ndarray, shape (T, J, 3) or None
        Reference positions at ``t_s`` in the same frame (NaN where unavailable).
    reference_frames : ndarray of bool, shape (T,), or None
        The samples scored: each the nearest to a frame of the reference
        (:func:`~kinefuse.pipelines.run.timeline.nearest_samples`). A reference sparser than
        the output (UTD-MHAD's Kinect, 15 Hz, under a 30-Hz camera method) is not scored where
        ``reference`` interpolates between its frames, so every method of a recording is
        scored at the same instants, where the reference measured. None: every sample.
    run_time_s : float
        Wall-clock time of the method (chain excluded), s; NaN for ``imu-only`` without a
        filter (nothing runs beyond the chain, so the report has no run-time table).
    edges : tuple of (str, str)
        Bones between output joints (report skeleton).
    notes : list of str
        What was done (calibration, lengths, alignments) and warnings.
    root : str
        Where the chain's root joints are (e.g. "pelvis (mid-hip) at [0, 0, 0] m ...").
    provenance : dict
        Which data calibrated what: calibration, heading, segment lengths and their sources,
        root, alignment, labels (also written to ``metrics.json``).
    angles : dict of str -> ndarray, shape (T, 3)
        Joint angles, deg, ``[flexion, adduction, internal_rotation]`` (ISB), where the
        calibration gives segment frames.
    sensor_orientations : dict of str -> ndarray, shape (T, 4)
        Calibrated sensor orientations per segment, ``q_world_from_sensor`` (wxyz) on ``t_s``
        with the calibration's heading corrections applied (one world frame for all sensors),
        for OpenSense IK.
    tag : str
        Label suffix of scores that used the reference beyond evaluation (e.g.
        ``" [calibrated on reference]"``); empty otherwise.
    baselines : dict of str -> ndarray, shape (T, J, 3)
        With a camera method and a reference (they are for the evaluation): the simple
        baselines on the same chain and camera, by table label (``offset interp``, ``offset
        hold``, ``camera gap-fill``; :func:`kinefuse.pipelines.vision_assisted`), m, same frame.
    available : ndarray of bool, shape (T, J) or None
        The sample is backed by the inputs the method needs (see :func:`kinefuse.pipelines.run.timeline.apply_coverage`);
        False where a stream did not cover it, even if the filter predicted a position.
    coverage : dict of str -> ndarray of bool
        Per input stream whether it covered each output sample: ``"imu <segment>"`` (T,),
        ``"imu"``, ``"root"``, ``"camera"``, ``"reference"`` (T, J) per output joint.
    warnings : list of str
        Short coverage and other problems the user must see (also in ``notes``).
    chain_description : dict or None
        The calibrated chain for live capture (:mod:`kinefuse.pipelines.run.chain_file`), or
        None when it cannot run live (the reason is in ``notes``).
    chain_orientations : dict of str -> ndarray, shape (T, 3, 3)
        The sensor orientations the chain was built from, ``R_frame_from_sensor`` in the frame
        of ``chain`` (:func:`kinefuse.kinematics.chain_orientations`).
    joint_segments : dict of str -> tuple of str
        Per output joint, the segments of ``chain_orientations`` that move it
        (:func:`kinefuse.pipelines.features.joint_segments`).
    """

    t_s: np.ndarray
    joints: tuple[str, ...]
    position: np.ndarray
    std_m: np.ndarray
    source: np.ndarray
    mode: np.ndarray
    frame: str
    method: str
    label: str
    chain: np.ndarray
    camera: np.ndarray | None = None
    reference: np.ndarray | None = None
    reference_frames: np.ndarray | None = None
    run_time_s: float = float("nan")
    edges: tuple[tuple[str, str], ...] = ()
    notes: list[str] = field(default_factory=list)
    root: str = ""
    provenance: dict = field(default_factory=dict)
    angles: dict = field(default_factory=dict)
    sensor_orientations: dict = field(default_factory=dict)
    tag: str = ""
    baselines: dict[str, np.ndarray] = field(default_factory=dict)
    available: np.ndarray | None = None
    coverage: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    chain_description: dict | None = None
    chain_orientations: dict = field(default_factory=dict)
    joint_segments: dict = field(default_factory=dict)

    def segment_rotations(self, joints: Sequence[str] | None = None) -> np.ndarray:
        """``(T, J, S, 3, 3)``: per joint (default: all output joints) the orientations of
        the segments that move it, all-zero padded; what ``"kinefuse"`` models the chain
        error with (:func:`kinefuse.pipelines.features.joint_rotations`)."""
        names = self.joints if joints is None else joints
        return joint_rotations(self.chain_orientations, [self.joint_segments[j] for j in names])

    def trajectories(self) -> dict[str, np.ndarray]:
        """Evaluated trajectories by their table label (tags such as "[calibrated on reference]")."""
        position = self.position
        if self.available is not None:  # predictions no input backs are not scored (issue 12)
            position = np.where(self.available[..., None], position, np.nan)
        est = {self.label + self.tag: position}
        if self.method != "camera-only" and not np.array_equal(
            self.position, self.chain, equal_nan=True
        ):
            est["IMU chain" + self.tag] = self.chain
        if (
            self.camera is not None
            and self.method != "camera-only"
            and self.reference is not None
            and not np.array_equal(self.camera, self.reference, equal_nan=True)
        ):
            est["camera" + (" [aligned to reference]" if "aligned" in self.tag else "")] = (
                self.camera
            )
        est.update({k + self.tag: v for k, v in self.baselines.items() if k != self.label})
        return est

    def evaluation(self):
        """Metrics of the method, the unfiltered IMU chain and the camera vs the reference.

        Returns
        -------
        EvaluationResult or None
            None without a reference.
        """
        if self.reference is None:
            return None
        est = self.trajectories()
        outage = None
        if self.camera is not None:
            outage = ~np.all(np.isfinite(self.camera), axis=-1)
        ref = self.reference
        if self.reference_frames is not None:  # not where it is interpolated between its frames
            ref = np.where(self.reference_frames[:, None, None], ref, np.nan)
        return evaluate(
            est,
            ref,
            outage,
            {self.label + self.tag: self.run_time_s} if math.isfinite(self.run_time_s) else None,
            joints=self.joints,
            # the axes' names: east/north/up only in an ENU frame (e.g. not Vicon's x, y, z)
            axes=AXES_ENU if self.frame.startswith("ENU") else ("X", "Y", "Z"),
        )
