"""Settings of a virtual IMU: :class:`ImuConfig`, its error model and the defaults' sources.

The signal generation, magnetometer and orientation source are described in :mod:`kinefuse.sim.imu`.

Error model (each sensor draws its own, per axis)
-------------------------------------------------
``y = (I + X) · diag(1 + s) · y_true + b_0 + b_gm(t) + b_rw(t) + n``, with cross-axis terms X
(off-diagonal, uniform ±cross_axis), scale errors s (uniform ±scale_error), turn-on bias b_0
(uniform ±turn_on_bias), bias instability b_gm (first-order Gauss-Markov, std and correlation
time below), bias random walk b_rw and white noise n of std ``density · sqrt(rate_hz / 2)``
(noise bandwidth = Nyquist). Datasheet "±" tolerances are used as uniform bounds.

Defaults: TDK InvenSense ICM-20948 datasheet DS-000189 rev. 1.3 (the IMU of paper B) for the
noise: gyroscope rate noise spectral density 0.015 °/s/√Hz (Table 1), accelerometer noise spectral
density 230 µg/√Hz (Table 2). The datasheet's *uncalibrated* tolerances (gyro ZRO ±5 °/s, scale
±1.5 %, cross-axis ±2 %; accelerometer zero-g ±50 mg, scale ±0.5 %, cross-axis ±2 %) are what a
sensor has before anyone calibrates it; a user of body-worn IMUs calibrates them (factory or
six-position calibration, start-up gyro offset), so the defaults are the *residuals* after that:
gyro turn-on bias ±5 °/s removed at start-up (below), gyro scale and cross-axis ±0.5 %,
accelerometer bias ±10 mg, scale and cross-axis ±0.2 %; magnetometer hard iron ±0.3 µT and soft
iron ±1 % after a field calibration, field inhomogeneity 1 µT. These magnitudes were chosen so that
VQF on virtual BROAD trials errs like VQF on the real ones (``kinefuse experiment realism``,
BROAD tuning trials 01, 06, 10, 24 undisturbed/tapping; 28, 32 for the disturbance size; the
other trials are only reported). The datasheet gives no bias instability or random walk: the
defaults (gyro 0.003 °/s ≈ 10 °/h and accel 0.05 mg Gauss-Markov with 100 s correlation time;
random walks 2e-4 °/s/√s and 2e-5 g/√s) are [J] typical consumer-MEMS Allan-variance figures.
Mounting misalignment: 2° std per axis [J] (the segment axis is calibrated, see
:func:`kinefuse.kinematics.calibrate`; the rest stays an error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from kinefuse.exceptions import InputError

__all__ = ["ORIENTATIONS", "ImuConfig"]

_DEG = math.pi / 180.0

#: Orientation sources of a virtual IMU (:mod:`kinefuse.sim.imu`, "Orientation").
ORIENTATIONS = ("vqf", "vqf-6d", "idealised-ahrs")


@dataclass(frozen=True)
class ImuConfig:
    """Virtual IMU settings (datasheet units in the names; defaults: ICM-20948, module doc).

    Attributes
    ----------
    rate_hz : float
        Output rate, Hz.
    position_along_segment : float
        Sensor position on the segment axis as a fraction of the bone length from the proximal
        joint (0.5 = midpoint), in [0, 1].
    gyr_noise_dps_sqrt_hz, acc_noise_ug_sqrt_hz : float
        White-noise spectral densities, °/s/√Hz and µg/√Hz.
    gyr_turn_on_bias_dps, acc_turn_on_bias_mg : float
        Half-range of the uniform turn-on bias per axis, °/s and mg.
    gyr_bias_instability_dps, acc_bias_instability_mg : float
        Std of the Gauss-Markov bias, °/s and mg.
    bias_correlation_time_s : float
        Correlation time of the Gauss-Markov biases, s.
    gyr_bias_random_walk_dps_sqrt_s, acc_bias_random_walk_mg_sqrt_s : float
        Bias random-walk intensities, °/s/√s and mg/√s.
    gyr_scale_error, acc_scale_error : float
        Half-range of the uniform scale-factor error (0.015 = ±1.5 %).
    gyr_cross_axis, acc_cross_axis : float
        Half-range of the uniform cross-axis coupling (0.02 = ±2 %).
    motion_lowpass_hz : float or None
        Cut-off of the zero-phase low-pass applied to the mocap segment motion before
        differentiation, Hz (:mod:`kinefuse.sim.imu`); ``None`` = raw mocap.
    mounting_error_deg : float
        Std per axis of the rotation vector of ``q_segment_from_sensor``, degrees.
    soft_tissue_scale : float
        Factor on :data:`STA_AMPLITUDE` (0 = sensor rigidly on the bone).
    mag_field_ut, mag_inclination_deg : float
        Undisturbed field strength, µT, and its inclination below the horizon (towards +y).
    mag_noise_ut : float
        White noise std per axis, µT.
    mag_hard_iron_ut : float
        Half-range of the uniform residual hard-iron offset per axis (after a user's
        calibration), µT.
    mag_soft_iron : float
        Half-range of the uniform residual soft-iron scale and cross-axis terms.
    mag_inhomogeneity_ut, mag_inhomogeneity_time_s : float
        Std (µT, per world axis) and correlation time (s) of the slow indoor field changes.
    mag_disturbance_per_min, mag_disturbance_ut, mag_disturbance_duration_s : float
        Disturbance episodes: rate (per minute), largest magnitude (µT), mean duration (s).
    mag_mount_magnet_ut, mag_mount_magnet_from, mag_mount_magnet_to : float
        A magnet fixed to the sensor's mount for part of the recording (default none): a
        constant field in the *sensor* frame (it moves with the sensor: a hard-iron offset
        the user's calibration did not see) of this magnitude, µT, random direction, present
        from the fraction ``from`` to the fraction ``to`` of the recording (1 s ramps).
    mag_mount_magnet_dir : tuple of 3 float or None
        That field's direction in the sensor frame (normalised here); None: random.
    orientation : {"vqf", "vqf-6d", "idealised-ahrs"}
        Where ``q_world_from_sensor`` comes from (:mod:`kinefuse.sim.imu`).
    warmup_s : float
        VQF only: the sensor is switched on this long before the recording and lies still in the
        first pose (:mod:`kinefuse.sim.imu`); 0 = VQF starts at the first recorded sample.
    gyr_startup_calibration : bool
        With a warm-up: the gyroscope offset is estimated as the mean over the warm-up rest and
        removed from every output sample, as sensor drivers and on-board fusion do at start-up
        (the residual is the noise of that mean plus the later bias drift).
    ahrs_heading_drift_deg_per_min, ahrs_heading_noise_deg, ahrs_tilt_noise_deg, ahrs_initial_heading_deg : float
        Error of the ``"idealised-ahrs"`` orientation (:mod:`kinefuse.sim.imu`), degrees.
    """

    rate_hz: float = 100.0
    position_along_segment: float = 0.5
    motion_lowpass_hz: float | None = 15.0
    gyr_noise_dps_sqrt_hz: float = 0.015
    acc_noise_ug_sqrt_hz: float = 230.0
    gyr_turn_on_bias_dps: float = 5.0
    acc_turn_on_bias_mg: float = 10.0
    gyr_bias_instability_dps: float = 0.003
    acc_bias_instability_mg: float = 0.05
    bias_correlation_time_s: float = 100.0
    gyr_bias_random_walk_dps_sqrt_s: float = 2e-4
    acc_bias_random_walk_mg_sqrt_s: float = 0.02
    gyr_scale_error: float = 0.005
    acc_scale_error: float = 0.002
    gyr_cross_axis: float = 0.005
    acc_cross_axis: float = 0.002
    mounting_error_deg: float = 2.0
    soft_tissue_scale: float = 1.0
    mag_field_ut: float = 44.0
    mag_inclination_deg: float = 68.0
    mag_noise_ut: float = 0.3
    mag_hard_iron_ut: float = 0.3
    mag_soft_iron: float = 0.01
    mag_inhomogeneity_ut: float = 1.0
    mag_inhomogeneity_time_s: float = 5.0
    mag_disturbance_per_min: float = 1.0
    mag_disturbance_ut: float = 20.0
    mag_disturbance_duration_s: float = 5.0
    mag_mount_magnet_ut: float = 0.0
    mag_mount_magnet_from: float = 0.0
    mag_mount_magnet_to: float = 1.0
    mag_mount_magnet_dir: tuple | None = None
    orientation: str = "vqf"
    warmup_s: float = 10.0
    gyr_startup_calibration: bool = True
    ahrs_heading_drift_deg_per_min: float = 0.5
    ahrs_heading_noise_deg: float = 0.2
    ahrs_tilt_noise_deg: float = 0.1
    ahrs_initial_heading_deg: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "orientation":
                if v not in ORIENTATIONS:
                    raise InputError(
                        f"ImuConfig.orientation: expected one of {ORIENTATIONS}, got {v!r}"
                    )
                continue
            if f.name == "motion_lowpass_hz" and v is None:
                continue
            if f.name == "mag_mount_magnet_dir":
                if v is not None and not _is_direction(v):
                    raise InputError(
                        f"ImuConfig.{f.name}: expected None or 3 finite numbers, not all 0, "
                        f"got {v!r}"
                    )
                continue
            if f.name == "gyr_startup_calibration":
                if not isinstance(v, bool):
                    raise InputError(f"ImuConfig.{f.name}: expected a bool, got {v!r}")
                continue
            if (
                not isinstance(v, (int, float))
                or isinstance(v, bool)
                or not math.isfinite(v)
                or v < 0
            ):
                raise InputError(f"ImuConfig.{f.name}: expected a finite number >= 0, got {v!r}")
        for name in ("rate_hz", "bias_correlation_time_s", "mag_inhomogeneity_time_s"):
            if getattr(self, name) <= 0:
                raise InputError(f"ImuConfig.{name}: expected > 0, got {getattr(self, name)!r}")
        if self.motion_lowpass_hz is not None and self.motion_lowpass_hz <= 0:
            raise InputError(
                f"ImuConfig.motion_lowpass_hz: expected None or > 0, got {self.motion_lowpass_hz!r}"
            )
        if not 0.0 <= self.position_along_segment <= 1.0:
            raise InputError(
                f"ImuConfig.position_along_segment: expected in [0, 1], got {self.position_along_segment!r}"
            )
        if not self.mag_mount_magnet_from <= self.mag_mount_magnet_to <= 1.0:
            raise InputError(
                "ImuConfig.mag_mount_magnet_from/_to: expected 0 <= from <= to <= 1, got "
                f"{self.mag_mount_magnet_from!r}, {self.mag_mount_magnet_to!r}"
            )
        if self.mag_inclination_deg > 90.0:
            raise InputError(
                f"ImuConfig.mag_inclination_deg: expected in [0, 90], got {self.mag_inclination_deg!r}"
            )

    @classmethod
    def ideal(cls, rate_hz: float = 100.0, **overrides) -> ImuConfig:
        """Noise-free, perfectly calibrated, rigidly and perfectly mounted sensors in an
        undisturbed field, with the exact orientation (``"idealised-ahrs"`` without error).

        ``overrides`` set other fields, e.g. ``motion_lowpass_hz=None`` for the raw mocap, or
        ``orientation="vqf"`` for VQF on the noise-free signals.
        """
        keep = (
            "rate_hz",
            "position_along_segment",
            "bias_correlation_time_s",
            "motion_lowpass_hz",
            "mag_field_ut",
            "mag_inclination_deg",
            "mag_inhomogeneity_time_s",
            "mag_mount_magnet_dir",
            "orientation",
        )
        kwargs = {f.name: 0.0 for f in fields(cls) if f.name not in keep}
        kwargs["gyr_startup_calibration"] = False
        kwargs["orientation"] = "idealised-ahrs"
        kwargs.update(overrides)
        return cls(rate_hz=rate_hz, **kwargs)

    @property
    def mag_earth_ut(self) -> np.ndarray:
        """Undisturbed field in ENU, µT, shape (3,): ``F · [0, cos I, −sin I]``."""
        inc = self.mag_inclination_deg * _DEG
        return self.mag_field_ut * np.array([0.0, math.cos(inc), -math.sin(inc)])


def _is_direction(v) -> bool:
    """Whether ``v`` is 3 finite real numbers, not all zero."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return False
    return a.shape == (3,) and bool(np.isfinite(a).all()) and bool(np.any(a != 0.0))
