"""Skeleton (parent-index tree), forward kinematics and sensor-to-segment calibration (SPEC §2)."""

from kinefuse.kinematics.calibration import (
    Calibration,
    calibrate,
    chain_positions,
    heading_rotation,
    kabsch_rotation,
)
from kinefuse.kinematics.forward import as_rotation_matrices, euler_to_matrix, forward_kinematics
from kinefuse.kinematics.functional import FunctionalCalibration, functional_calibration
from kinefuse.kinematics.skeleton import (
    ANTHROPOMETRIC_RATIOS,
    AXES,
    Skeleton,
    full_body,
    lengths_from_joints,
    lower_body,
    upper_limb,
)

__all__ = [
    "ANTHROPOMETRIC_RATIOS",
    "AXES",
    "Calibration",
    "FunctionalCalibration",
    "Skeleton",
    "as_rotation_matrices",
    "calibrate",
    "chain_positions",
    "euler_to_matrix",
    "forward_kinematics",
    "full_body",
    "functional_calibration",
    "heading_rotation",
    "kabsch_rotation",
    "lengths_from_joints",
    "lower_body",
    "upper_limb",
]
