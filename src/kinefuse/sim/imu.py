"""Virtual body-worn IMUs driven by a :class:`~kinefuse.io.motion.Motion` (real mocap).

Signal generation (noise-free part)
-----------------------------------
Time grid
    ``t_k = t_0 + k / rate_hz`` within the motion's span (default 100 Hz from 120 Hz mocap).
Motion smoothing
    Optical mocap carries marker jitter that second differences amplify (CMU 02_05 at 120 Hz:
    median |second difference| of the pelvis 7 m/s², 1.2 m/s² after a 10 Hz low-pass). By
    default (``motion_lowpass_hz = 15``) the segment's quaternion components (sign-continuous)
    and the sensor positions at the mocap samples are low-passed with a zero-phase 2nd-order
    Butterworth filter (``scipy.signal.filtfilt``, hence 4th order overall) before the steps
    below, and quaternions are renormalised. The IMU signals are then exact for this smoothed
    motion (returned as ``truth["q_world_from_segment"]``); ``None`` uses the raw mocap.
Orientation
    ``q_world_from_segment(t)`` is a C2 rotation spline (:class:`scipy.spatial.transform.RotationSpline`)
    through the mocap samples, evaluated at ``t_k``; the sensor is mounted with a constant
    ``q_segment_from_sensor`` (mounting misalignment), ``R_ws = R_world_from_segment · R_segment_from_sensor``.
Gyroscope
    ``gyr_k = log(R_ws,k-1ᵀ R_ws,k) / dt`` for k >= 1 (``gyr_0 = gyr_1``): the constant body rate
    that carries the sensor from sample k-1 to sample k. Integrating it with
    ``q_k = q_k-1 ⊗ exp(gyr_k · dt)`` (the convention of VQF's ``updateGyr``) reproduces the
    orientation exactly; relative to the instantaneous rate it lags by dt/2.
Accelerometer
    Specific force ``acc_k = R_ws,kᵀ (a(t_k) − g)``, ``g = [0, 0, −9.80665]`` m/s² (ENU). The
    sensor sits on the segment axis at ``position_along_segment · length`` from the proximal
    joint (default the midpoint; the pelvis sensor at the pelvis joint). ``a(t)`` is the central
    second difference, with step ``h`` = the mocap sample interval, of a cubic spline through the
    sensor positions at the mocap samples: ``a(t) = [p(t+h) − 2 p(t) + p(t−h)] / h²``. At mocap
    sample times this *is* the plain central difference of the mocap positions; at other times it
    is the same smoothing applied to the interpolant. (Near both ends the spline extrapolates.)

Error model (each sensor draws its own, per axis)
-------------------------------------------------
``y = (I + X) · diag(1 + s) · y_true + b_0 + b_gm(t) + b_rw(t) + n``, with cross-axis terms X
(off-diagonal, uniform ±cross_axis), scale errors s (uniform ±scale_error), turn-on bias b_0
(uniform ±turn_on_bias), bias instability b_gm (first-order Gauss-Markov, std and correlation
time below), bias random walk b_rw and white noise n of std ``density · sqrt(rate_hz / 2)``
(noise bandwidth = Nyquist). Datasheet "±" tolerances are used as uniform bounds.

Defaults: TDK InvenSense ICM-20948 datasheet DS-000189 rev. 1.3 (the IMU of paper B):
gyroscope rate noise spectral density 0.015 °/s/√Hz, initial ZRO tolerance ±5 °/s, sensitivity
scale-factor tolerance ±1.5 %, cross-axis sensitivity ±2 % (Table 1); accelerometer noise
spectral density 230 µg/√Hz, board-level zero-g initial tolerance ±50 mg, sensitivity initial
tolerance ±0.5 %, cross-axis sensitivity ±2 % (Table 2). The datasheet gives no bias instability
or random walk: the defaults (gyro 0.003 °/s ≈ 10 °/h and accel 0.05 mg Gauss-Markov with 100 s
correlation time; random walks 2e-4 °/s/√s and 2e-5 g/√s) are [J] typical consumer-MEMS
Allan-variance figures. Mounting misalignment: 2° std per axis [J].

On-board orientation (what an AHRS/DMP outputs)
-----------------------------------------------
``q_world_from_sensor = q_err(t) ⊗ q_world_from_sensor_true`` with a world-frame error: heading
``ψ(t) = ψ_0 + ψ̇ · (t − t_0) + N(0, heading_noise²)`` (ψ_0 uniform ±initial, ψ̇ normal with std
``ahrs_heading_drift_deg_per_min``) about ENU z, times a white tilt error about x and y.
Defaults [J]: drift 0.5 °/min (std), heading noise 0.2°, tilt noise 0.1°, no initial heading
offset (magnetometer-referenced start).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import butter, filtfilt
from scipy.spatial.transform import Rotation, RotationSpline

from kinefuse.conventions import GRAVITY_ENU_M_S2, GRAVITY_M_S2
from kinefuse.exceptions import InputError
from kinefuse.io.motion import SEGMENT_AXIS, Motion, _continuous_quat
from kinefuse.io.recording import ImuStream

__all__ = ["ImuConfig", "simulate_imu", "time_grid"]

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class ImuConfig:
    """Virtual IMU settings (datasheet units in the names; defaults: ICM-20948, see module doc).

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
        differentiation, Hz (module doc); ``None`` = raw mocap.
    mounting_error_deg : float
        Std per axis of the rotation vector of ``q_segment_from_sensor``, degrees.
    ahrs_heading_drift_deg_per_min, ahrs_heading_noise_deg, ahrs_tilt_noise_deg, ahrs_initial_heading_deg : float
        On-board orientation error (module doc), degrees.
    """

    rate_hz: float = 100.0
    position_along_segment: float = 0.5
    motion_lowpass_hz: float | None = 15.0
    gyr_noise_dps_sqrt_hz: float = 0.015
    acc_noise_ug_sqrt_hz: float = 230.0
    gyr_turn_on_bias_dps: float = 5.0
    acc_turn_on_bias_mg: float = 50.0
    gyr_bias_instability_dps: float = 0.003
    acc_bias_instability_mg: float = 0.05
    bias_correlation_time_s: float = 100.0
    gyr_bias_random_walk_dps_sqrt_s: float = 2e-4
    acc_bias_random_walk_mg_sqrt_s: float = 0.02
    gyr_scale_error: float = 0.015
    acc_scale_error: float = 0.005
    gyr_cross_axis: float = 0.02
    acc_cross_axis: float = 0.02
    mounting_error_deg: float = 2.0
    ahrs_heading_drift_deg_per_min: float = 0.5
    ahrs_heading_noise_deg: float = 0.2
    ahrs_tilt_noise_deg: float = 0.1
    ahrs_initial_heading_deg: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "motion_lowpass_hz" and v is None:
                continue
            if (
                not isinstance(v, (int, float))
                or isinstance(v, bool)
                or not math.isfinite(v)
                or v < 0
            ):
                raise InputError(f"ImuConfig.{f.name}: expected a finite number >= 0, got {v!r}")
        if self.rate_hz <= 0:
            raise InputError(f"ImuConfig.rate_hz: expected > 0, got {self.rate_hz!r}")
        if self.bias_correlation_time_s <= 0:
            raise InputError(
                f"ImuConfig.bias_correlation_time_s: expected > 0, got {self.bias_correlation_time_s!r}"
            )
        if self.motion_lowpass_hz is not None and self.motion_lowpass_hz <= 0:
            raise InputError(
                f"ImuConfig.motion_lowpass_hz: expected None or > 0, got {self.motion_lowpass_hz!r}"
            )
        if not 0.0 <= self.position_along_segment <= 1.0:
            raise InputError(
                f"ImuConfig.position_along_segment: expected in [0, 1], got {self.position_along_segment!r}"
            )

    @classmethod
    def ideal(cls, rate_hz: float = 100.0, **overrides) -> ImuConfig:
        """Noise-free, perfectly calibrated and perfectly mounted sensors, exact AHRS output.

        ``overrides`` set other fields, e.g. ``motion_lowpass_hz=None`` for the raw mocap.
        """
        keep = ("rate_hz", "position_along_segment", "bias_correlation_time_s", "motion_lowpass_hz")
        kwargs = {f.name: 0.0 for f in fields(cls) if f.name not in keep}
        kwargs.update(overrides)
        return cls(rate_hz=rate_hz, **kwargs)


def time_grid(t_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """``t_0 + k / rate_hz`` for all k with the time inside ``[t_s[0], t_s[-1]]``, shape (n,)."""
    n = int(math.floor((t_s[-1] - t_s[0]) * rate_hz + 1e-9)) + 1
    if n < 2:
        raise InputError(
            f"expected a motion spanning at least 2 samples at {rate_hz} Hz, got {t_s[-1] - t_s[0]:.4g} s"
        )
    return t_s[0] + np.arange(n) / rate_hz


def _gauss_markov(
    rng: np.random.Generator, n: int, dim: int, std: float, tau_s: float, dt: float
) -> np.ndarray:
    """Stationary first-order Gauss-Markov sequences, shape (n, dim)."""
    w = rng.standard_normal((n, dim))
    if std == 0.0:
        return np.zeros((n, dim))
    phi = math.exp(-dt / tau_s) if tau_s > 0 else 0.0
    out = np.empty((n, dim))
    out[0] = std * w[0]
    c = std * math.sqrt(1.0 - phi * phi)
    for k in range(1, n):
        out[k] = phi * out[k - 1] + c * w[k]
    return out


def _lowpass(x: np.ndarray, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth low-pass along axis 0."""
    wn = cutoff_hz / (0.5 * rate_hz)
    if not 0.0 < wn < 1.0:
        raise InputError(
            f"ImuConfig.motion_lowpass_hz: expected below the motion's Nyquist {0.5 * rate_hz:.4g} Hz, got {cutoff_hz!r}"
        )
    b, a = butter(2, wn)
    return filtfilt(b, a, x, axis=0, padlen=min(3 * max(len(a), len(b)), x.shape[0] - 1))


def _error_model(rng, y_true, *, scale, cross, bias0, bias_gm, tau_s, rw, noise, dt):
    """Apply the per-sensor error model to ``y_true`` (n, 3); returns (y, parameters)."""
    n = y_true.shape[0]
    s = rng.uniform(-1.0, 1.0, 3) * scale
    X = rng.uniform(-1.0, 1.0, (3, 3)) * cross
    np.fill_diagonal(X, 0.0)
    M = (np.eye(3) + X) @ np.diag(1.0 + s)
    b0 = rng.uniform(-1.0, 1.0, 3) * bias0
    b_gm = _gauss_markov(rng, n, 3, bias_gm, tau_s, dt)
    b_rw = np.cumsum(rng.standard_normal((n, 3)) * (rw * math.sqrt(dt)), axis=0)
    white = rng.standard_normal((n, 3)) * noise
    y = y_true @ M.T + b0 + b_gm + b_rw + white
    return y, {"sensitivity_matrix": M, "turn_on_bias": b0, "bias": b0 + b_gm + b_rw}


def simulate_imu(
    motion: Motion,
    segment: str,
    config: ImuConfig,
    rng: np.random.Generator,
    t_s: np.ndarray | None = None,
) -> tuple[ImuStream, dict]:
    """One virtual IMU on ``segment``.

    Parameters
    ----------
    motion : Motion
        The driving motion (ENU).
    segment : str
        Canonical segment carrying the sensor.
    config : ImuConfig
        Rate and error model.
    rng : numpy.random.Generator
        Source of all random draws of this sensor (draw order fixed).
    t_s : ndarray, shape (n,), optional
        Output times, s, spaced ``1 / config.rate_hz``; default :func:`time_grid`.

    Returns
    -------
    stream : ImuStream
        ``acc_m_s2`` (n, 3) specific force, ``gyr_rad_s`` (n, 3), ``q_world_from_sensor`` (n, 4)
        as an AHRS outputs it (with its error), in the sensor frame; ``name = segment``.
    truth : dict
        ``q_world_from_sensor``, ``q_world_from_segment`` (n, 4) true; ``q_segment_from_sensor``
        (4,); ``acc_m_s2``, ``gyr_rad_s`` (n, 3) noise-free; ``acc_error``/``gyr_error``
        (sensitivity matrix, turn-on bias, total bias (n, 3)); ``position_m`` (n, 3) true sensor
        position, ENU.
    """
    t = time_grid(motion.t_s, config.rate_hz) if t_s is None else np.asarray(t_s, dtype=float)
    dt = 1.0 / config.rate_hz
    i = motion.segment_index(segment)
    q_mocap = motion.q_world_from_segment[:, i]
    rot_seg_mocap = Rotation.from_quat(q_mocap, scalar_first=True)
    # sensor point on the segment axis, at the mocap samples
    prox, dist = motion.segment_joints[segment]
    p = motion.position(prox).copy()
    if dist is not None:
        lever = config.position_along_segment * motion.segment_length_m[segment]
        p = p + lever * rot_seg_mocap.apply(SEGMENT_AXIS)
    if config.motion_lowpass_hz is not None:
        q_s = _lowpass(q_mocap, config.motion_lowpass_hz, motion.rate_hz)
        rot_seg_mocap = Rotation.from_quat(
            q_s / np.linalg.norm(q_s, axis=1, keepdims=True), scalar_first=True
        )
        p = _lowpass(p, config.motion_lowpass_hz, motion.rate_hz)
    rot_seg = RotationSpline(motion.t_s, rot_seg_mocap)(t)

    mount = Rotation.from_rotvec(rng.standard_normal(3) * config.mounting_error_deg * _DEG)
    rot_ws = rot_seg * mount

    # gyroscope: rate carrying sample k-1 to sample k
    w = (rot_ws[:-1].inv() * rot_ws[1:]).as_rotvec() / dt
    gyr_true = np.vstack([w[:1], w])

    # accelerometer: second difference of a cubic spline through the sensor positions
    spline = CubicSpline(motion.t_s, p, axis=0)
    h = float(np.median(np.diff(motion.t_s)))
    a = (spline(t + h) - 2.0 * spline(t) + spline(t - h)) / (h * h)
    acc_true = rot_ws.inv().apply(a - GRAVITY_ENU_M_S2)

    g = GRAVITY_M_S2
    gyr, gyr_err = _error_model(
        rng,
        gyr_true,
        scale=config.gyr_scale_error,
        cross=config.gyr_cross_axis,
        bias0=config.gyr_turn_on_bias_dps * _DEG,
        bias_gm=config.gyr_bias_instability_dps * _DEG,
        tau_s=config.bias_correlation_time_s,
        rw=config.gyr_bias_random_walk_dps_sqrt_s * _DEG,
        noise=config.gyr_noise_dps_sqrt_hz * _DEG * math.sqrt(config.rate_hz / 2.0),
        dt=dt,
    )
    acc, acc_err = _error_model(
        rng,
        acc_true,
        scale=config.acc_scale_error,
        cross=config.acc_cross_axis,
        bias0=config.acc_turn_on_bias_mg * 1e-3 * g,
        bias_gm=config.acc_bias_instability_mg * 1e-3 * g,
        tau_s=config.bias_correlation_time_s,
        rw=config.acc_bias_random_walk_mg_sqrt_s * 1e-3 * g,
        noise=config.acc_noise_ug_sqrt_hz * 1e-6 * g * math.sqrt(config.rate_hz / 2.0),
        dt=dt,
    )

    # on-board orientation with a world-frame heading drift and tilt noise
    n = t.size
    psi0 = rng.uniform(-1.0, 1.0) * config.ahrs_initial_heading_deg * _DEG
    psi_rate = rng.standard_normal() * config.ahrs_heading_drift_deg_per_min * _DEG / 60.0
    psi = (
        psi0 + psi_rate * (t - t[0]) + rng.standard_normal(n) * config.ahrs_heading_noise_deg * _DEG
    )
    tilt = rng.standard_normal((n, 2)) * config.ahrs_tilt_noise_deg * _DEG
    err = Rotation.from_rotvec(np.column_stack([np.zeros((n, 2)), psi])) * Rotation.from_rotvec(
        np.column_stack([tilt, np.zeros(n)])
    )
    q_true = _continuous_quat(rot_ws.as_quat(scalar_first=True))
    q_ahrs = _continuous_quat((err * rot_ws).as_quat(scalar_first=True))

    stream = ImuStream(t_s=t, q_world_from_sensor=q_ahrs, acc_m_s2=acc, gyr_rad_s=gyr, name=segment)
    truth = {
        "q_world_from_sensor": q_true,
        "q_world_from_segment": _continuous_quat(rot_seg.as_quat(scalar_first=True)),
        "q_segment_from_sensor": mount.as_quat(scalar_first=True),
        "acc_m_s2": acc_true,
        "gyr_rad_s": gyr_true,
        "acc_error": acc_err,
        "gyr_error": gyr_err,
        "ahrs_heading_error_rad": psi,
        "position_m": spline(t),
    }
    return stream, truth
