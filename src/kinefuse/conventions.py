"""Single source of truth for kinefuse's conventions.

Arrays
    Signals are ``(..., T, d)``: time is axis -2, leading axes are batch axes (trials, joints).
    A streaming ``step`` takes one time slice ``(..., d)``. Covariances are ``(..., T, n, n)``.
Quaternions
    ``(..., 4)`` scalar-first ``wxyz``. At the SciPy boundary pass ``scalar_first=True``.
Frames
    Names read right to left: ``q_world_from_segment = q_world_from_sensor * q_sensor_from_segment``.
    The world frame is ENU (x east, y north, z up) unless a reader documents a conversion.
Units
    SI throughout (m, s, rad, m/s^2); units appear in names where ambiguous (``dt_s``, ``rate_hz``).
Missing data
    NaN in a measurement row means "not observed": filters predict only.
State layout
    Constant-velocity states are interleaved per axis: ``[x, vx, y, vy, z, vz]`` (paper A Eq. 3).
"""

from __future__ import annotations

import numpy as np

#: Standard gravity, m/s^2.
GRAVITY_M_S2 = 9.80665
#: Gravity vector in the ENU world frame (pointing down), m/s^2.
GRAVITY_ENU_M_S2 = np.array([0.0, 0.0, -GRAVITY_M_S2])

#: Canonical segment names.
SEGMENTS = (
    "chest",
    "pelvis",
    "upper_arm_l",
    "upper_arm_r",
    "forearm_l",
    "forearm_r",
    "thigh_l",
    "thigh_r",
    "shank_l",
    "shank_r",
    "foot_l",
    "foot_r",
    "hand_l",
    "hand_r",
)

#: Canonical joint names.
JOINTS = (
    "head",
    "neck",
    "spine_shoulder",
    "spine_mid",
    "spine_base",
    "shoulder_l",
    "shoulder_r",
    "elbow_l",
    "elbow_r",
    "wrist_l",
    "wrist_r",
    "hand_l",
    "hand_r",
    "hip_l",
    "hip_r",
    "knee_l",
    "knee_r",
    "ankle_l",
    "ankle_r",
    "foot_l",
    "foot_r",
    "pelvis",
)

#: The eight joints of paper B (Xu 2023).
PAPER_B_JOINTS = (
    "elbow_l",
    "elbow_r",
    "wrist_l",
    "wrist_r",
    "knee_l",
    "knee_r",
    "ankle_l",
    "ankle_r",
)

#: Axis names of ENU positions.
AXES_ENU = ("east", "north", "up")

#: Integer codes of the integrated filter's branch (paper A), stored in ``result.mode``.
MODE_KF, MODE_EM, MODE_FIR, MODE_PREDICT = 0, 1, 2, 3
MODE_NAMES = {MODE_KF: "KF", MODE_EM: "EM-KF", MODE_FIR: "FIR", MODE_PREDICT: "predict"}

#: Integer codes of the per-sample source of a fused joint position (paper B pipelines).
#: ``SOURCE_PREDICTED``: an output sample no input backs (a stream ended early, a gap):
#: the filter's prediction, never marked available (``kinefuse run``, issue 12).
SOURCE_FUSED, SOURCE_BRIDGED, SOURCE_IMU, SOURCE_CAMERA, SOURCE_PREDICTED = 0, 1, 2, 3, 4
SOURCE_NAMES = {
    SOURCE_FUSED: "camera-fused",
    SOURCE_BRIDGED: "bridged",
    SOURCE_IMU: "imu-only",
    SOURCE_CAMERA: "camera-only",
    SOURCE_PREDICTED: "predicted",
}
#: What each source code is: measured by one stream, fused, bridged or predicted.
SOURCE_KINDS = {
    SOURCE_FUSED: "fused",
    SOURCE_BRIDGED: "bridged",
    SOURCE_IMU: "measured",
    SOURCE_CAMERA: "measured",
    SOURCE_PREDICTED: "predicted",
}
