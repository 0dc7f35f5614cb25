"""Raw IMU data -> orientation ``q_world_from_sensor`` (adapters over ``vqf``), gyro integration.

No attitude filter is written here: :func:`estimate` and :class:`OrientationEstimator` are thin,
validated adapters over the ``vqf`` package (Laidig & Seel 2023). VQF's earth frame is ENU
(x east, y north, z up; the 6D heading is arbitrary, the 9D heading follows the magnetic field)
and its quaternions are scalar-first ``wxyz`` sensor-to-earth, i.e. exactly kinefuse's
``q_world_from_sensor`` (:mod:`kinefuse.conventions`).
"""

from kinefuse.orientation.integration import integrate_gyro, rate_from_orientation
from kinefuse.orientation.resample import MAX_GAP_S, default_max_gap_s, slerp_resample
from kinefuse.orientation.vqf_adapter import METHODS, OrientationEstimator, estimate

__all__ = [
    "MAX_GAP_S",
    "METHODS",
    "OrientationEstimator",
    "default_max_gap_s",
    "estimate",
    "integrate_gyro",
    "rate_from_orientation",
    "slerp_resample",
]
