"""Skeleton (parent-index tree), forward kinematics and sensor-to-segment calibration (SPEC §2)."""

from kinefuse.kinematics.alignment import heading_rotation, kabsch_rotation
from kinefuse.kinematics.angles import JOINT_ANGLE_COMPONENTS, angle_components, joint_angles
from kinefuse.kinematics.calibration import calibrate
from kinefuse.kinematics.calibration_result import Calibration
from kinefuse.kinematics.chain import chain_orientations, chain_positions, segment_orientations
from kinefuse.kinematics.forward import as_rotation_matrices, euler_to_matrix, forward_kinematics
from kinefuse.kinematics.functional import FunctionalCalibration, functional_calibration
from kinefuse.kinematics.skeleton import (
    ANTHROPOMETRIC_RATIOS,
    AXES,
    Skeleton,
    full_body,
    lengths_from_joints,
    lower_body,
    segment_lengths,
    upper_limb,
)
from kinefuse.kinematics.still import StillWindow, find_still_window

__all__ = [
    "ANTHROPOMETRIC_RATIOS",
    "AXES",
    "Calibration",
    "FunctionalCalibration",
    "JOINT_ANGLE_COMPONENTS",
    "Skeleton",
    "StillWindow",
    "angle_components",
    "as_rotation_matrices",
    "calibrate",
    "chain_orientations",
    "chain_positions",
    "euler_to_matrix",
    "find_still_window",
    "forward_kinematics",
    "full_body",
    "functional_calibration",
    "heading_rotation",
    "joint_angles",
    "kabsch_rotation",
    "lengths_from_joints",
    "lower_body",
    "segment_lengths",
    "segment_orientations",
    "upper_limb",
]
