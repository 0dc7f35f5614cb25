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
    ``q_segment_from_sensor`` (mounting misalignment) and moves on the soft tissue (below):
    ``R_ws = R_world_from_segment · exp(δθ) · R_segment_from_sensor``.
Gyroscope
    ``gyr_k = log(R_ws,k-1ᵀ R_ws,k) / dt`` for k >= 1 (``gyr_0 = gyr_1``): the constant body rate
    that carries the sensor from sample k-1 to sample k. Integrating it with
    ``q_k = q_k-1 ⊗ exp(gyr_k · dt)`` (the convention of VQF's ``updateGyr``) reproduces the
    orientation exactly; relative to the instantaneous rate it lags by dt/2.
Accelerometer
    Specific force ``acc_k = R_ws,kᵀ (a(t_k) − g)``, ``g = [0, 0, −9.80665]`` m/s² (ENU). The
    sensor sits on the segment axis at ``position_along_segment · length`` from the proximal
    joint (default the midpoint; the pelvis sensor at the pelvis joint), displaced by the soft
    tissue ``R_world_from_segment δp`` (below). ``a(t)`` is the central
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

Soft-tissue artefact (STA)
--------------------------
A body-worn sensor does not follow the bone: skin, fat and muscle let it slide and rotate
relative to the bone, and the motion follows the movement (its frequency content is that of the
movement, so filtering cannot remove it; Leardini et al. 2005, Cappozzo et al. 1996). kinefuse
uses the linear STA model of Dumas, Camomilla, Bonci, Cheze and Cappozzo (J. Biomech. 47, 2014):
the rigid cluster motion relative to the bone is a linear function of the angles of the joints
the segment spans. Here the driving signal ``s(t)`` stacks the rotation vectors (rad) of the
joints at both ends of the segment (the relative rotation to every neighbouring segment of the
motion, minus its trial mean), and

``δθ(t) = A_rot · M_rot s(t)``, ``δp(t) = A_tr · M_tr s(t)`` (segment frame),

with ``M`` random matrices of spectral norm <= 1 (singular values uniform in [0.5, 1], random
directions), so ``|δθ| <= A_rot |s|`` and ``|δp| <= A_tr |s|``: ``A`` is the artefact per radian
of joint motion. The sensor pose is ``R_world_from_sensor = R_world_from_segment · exp(δθ) ·
R_segment_from_sensor`` and its position is the bone point plus ``R_world_from_segment δp``;
gyroscope and accelerometer are exact for that moving pose. Amplitudes :data:`STA_AMPLITUDE`
(per radian of joint excursion, ≈ the peak over a gait cycle whose knee flexes by about 60°),
times ``ImuConfig.soft_tissue_scale``:

* thigh 18 mm, 10° and shank 17 mm, 7°: the rigid marker-cluster STA measured against
  fluoroscopy during gait (Ancillao et al., Hum. Mov. Sci. 2021, CAMS-Knee), within the thigh
  10-30 mm and shank 5-20 mm ranges of Cappozzo et al. (Clin. Biomech. 11, 1996), Leardini et al.
  (Gait Posture 21, 2005, review) and Peters et al. (Gait Posture 31, 2010, review: thigh STA is
  the largest of the lower limb);
* upper arm 20 mm, 8° and forearm 10 mm, 5° [J]: humeral axial rotation is underestimated by
  skin sensors by up to a third of its range (Cutti et al., Gait Posture 21, 2005) and the
  upper-arm cluster moves by centimetres (Blache et al., J. Biomech. 62, 2017); the forearm STA
  is mostly about its long axis (pronation-supination).
* chest, pelvis, feet: none.

Magnetometer
------------
World field ``m_w(t) = m_earth + m_inh(t) + m_dist(t)`` in µT, sensor reading ``R_wsᵀ m_w``
passed through the error model (hard-iron residual = turn-on bias, soft-iron residual = scale
and cross-axis terms, white noise). ``m_earth``: strength 44 µT, inclination 68° below the
horizon towards +y (north), the undisturbed field of the BROAD laboratory (median of the
world-frame field over the first 20 s of the undisturbed trials: about [0, 13-17, -40] µT).
``m_inh``: a world-frame first-order Gauss-Markov field (std ``mag_inhomogeneity_ut``,
correlation time ``mag_inhomogeneity_time_s``) for the slow changes of an indoor field as a
person moves through it (the undisturbed BROAD trials deviate from their start field by 1.3-3.5
µT median, 2.5-7.6 µT at the 95th percentile). ``m_dist``: disturbance episodes (near steel
furniture, floors, devices) starting as a Poisson process of rate ``mag_disturbance_per_min``,
each lasting ``mag_disturbance_duration_s`` · U(0.5, 1.5) with 1 s raised-cosine ramps and a
constant world-frame vector of random direction and magnitude ``mag_disturbance_ut`` · U(0.25, 1)
(the BROAD magnet trials reach 20-87 µT at most, 8-60 µT at the 95th percentile). Defaults 1
episode per minute, up to 20 µT, 5 s mean: size and duration chosen on the BROAD magnet tuning
trials 28 and 32 (where the protocol repeats them about 3 times a minute).

Orientation (what the virtual IMU outputs)
------------------------------------------
``orientation = "vqf"`` (default): VQF 9D run on the simulated raw gyro, accelerometer and
magnetometer (:func:`kinefuse.orientation.estimate`, causal, default parameters; Laidig & Seel
2023) - the project's own orientation estimation, never a perturbed truth. Body-worn sensors are
switched on before a recording starts: VQF first sees ``warmup_s`` (default 10 s) of the sensor
at rest in the first pose (the same error model, continuing into the trial), so that a short
trial is not dominated by the filter's start-up convergence; the warm-up is not output. During
it the gyroscope offset is estimated (mean at rest) and removed, as drivers and on-board fusion
do at start-up (``gyr_startup_calibration``); without that a ±5 °/s turn-on bias exceeds VQF's
rest threshold (2 °/s) and bias clip (2 °/s) and the orientation drifts by tens of degrees. ``"vqf-6d"``: VQF
without magnetometer (heading arbitrary; the stream's frame is then ``"VQF-6D"``, not ENU).
``"idealised-ahrs"`` (kept for :data:`kinefuse.pipelines.experiments.DEGRADED_AHRS` and exact
tests, *not realistic*): the true sensor orientation times a world-frame error: heading
``ψ(t) = ψ_0 + ψ̇ · (t − t_0) + N(0, heading_noise²)`` (ψ_0 uniform ±initial, ψ̇ normal with std
``ahrs_heading_drift_deg_per_min``) about ENU z, times a white tilt error about x and y
(defaults [J]: drift 0.5 °/min, heading noise 0.2°, tilt noise 0.1°).
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

__all__ = [
    "ORIENTATIONS",
    "STA_AMPLITUDE",
    "ImuConfig",
    "simulate_imu",
    "simulate_imu_from_pose",
    "time_grid",
]

_DEG = math.pi / 180.0


#: Orientation sources of a virtual IMU (module doc, "Orientation").
ORIENTATIONS = ("vqf", "vqf-6d", "idealised-ahrs")

#: Soft-tissue artefact per radian of joint motion: segment kind -> (translation mm, rotation
#: deg); module doc "Soft-tissue artefact" for the sources.
STA_AMPLITUDE = {
    "thigh": (18.0, 10.0),
    "shank": (17.0, 7.0),
    "upper_arm": (20.0, 8.0),
    "forearm": (10.0, 5.0),
}


def _sta_kind(segment: str) -> str | None:
    kind = segment.rsplit("_", 1)[0] if segment.endswith(("_l", "_r")) else segment
    return kind if kind in STA_AMPLITUDE else None


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
    orientation : {"vqf", "vqf-6d", "idealised-ahrs"}
        Where ``q_world_from_sensor`` comes from (module doc).
    warmup_s : float
        VQF only: the sensor is switched on this long before the recording and lies still in the
        first pose (module doc); 0 = VQF starts at the first recorded sample.
    gyr_startup_calibration : bool
        With a warm-up: the gyroscope offset is estimated as the mean over the warm-up rest and
        removed from every output sample, as sensor drivers and on-board fusion do at start-up
        (the residual is the noise of that mean plus the later bias drift).
    ahrs_heading_drift_deg_per_min, ahrs_heading_noise_deg, ahrs_tilt_noise_deg, ahrs_initial_heading_deg : float
        Error of the ``"idealised-ahrs"`` orientation (module doc), degrees.
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


def _norm_bounded_matrix(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Random ``rows x cols`` matrix with singular values uniform in [0.5, 1] (spectral norm <= 1)."""
    u, _, vt = np.linalg.svd(rng.standard_normal((rows, cols)), full_matrices=False)
    return (u * rng.uniform(0.5, 1.0, min(rows, cols))) @ vt


def _neighbours(motion: Motion, segment: str) -> list[str]:
    """Segments of ``motion`` sharing a joint with ``segment`` (its proximal or distal joint)."""
    prox, dist = motion.segment_joints[segment]
    out = []
    for s in motion.segments:
        if s == segment:
            continue
        p2, d2 = motion.segment_joints[s]
        if (d2 is not None and d2 == prox) or (dist is not None and p2 == dist):
            out.append(s)
    return out


def _joint_drive(rot_seg: Rotation, rot_nbs: list[Rotation]) -> np.ndarray:
    """Stacked rotation vectors (rad) of the joints to the neighbours, minus the trial mean, (T, 3m)."""
    cols = []
    for rn in rot_nbs:
        rel = rn.inv() * rot_seg
        cols.append((rel.mean().inv() * rel).as_rotvec())
    return np.concatenate(cols, axis=1) if cols else np.zeros((len(rot_seg), 0))


def _disturbance_episodes(
    rng: np.random.Generator, t: np.ndarray, config: ImuConfig
) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """World-frame disturbance field (n, 3), µT, and the episodes ``(start_s, end_s)``."""
    n = t.size
    span_min = (t[-1] - t[0]) / 60.0
    k = int(rng.poisson(config.mag_disturbance_per_min * span_min))
    starts = np.sort(rng.uniform(t[0], t[-1], k))
    durations = config.mag_disturbance_duration_s * rng.uniform(0.5, 1.5, k)
    dirs = rng.standard_normal((k, 3))
    mags = config.mag_disturbance_ut * rng.uniform(0.25, 1.0, k)
    field = np.zeros((n, 3))
    episodes = []
    ramp = 1.0
    for t0, d, u, m in zip(starts, durations, dirs, mags, strict=True):
        t1 = t0 + d
        w = np.clip(np.minimum(t - t0, t1 - t) / ramp, 0.0, 1.0)
        w = 0.5 - 0.5 * np.cos(np.pi * w)
        field += w[:, None] * (m * u / np.linalg.norm(u))
        episodes.append((float(t0), float(t1)))
    return field, episodes


def simulate_imu(
    motion: Motion,
    segment: str,
    config: ImuConfig,
    rng: np.random.Generator,
    t_s: np.ndarray | None = None,
) -> tuple[ImuStream, dict]:
    """One virtual IMU on ``segment``: raw gyro, accelerometer, magnetometer and its orientation.

    Parameters
    ----------
    motion : Motion
        The driving motion (ENU).
    segment : str
        Canonical segment carrying the sensor.
    config : ImuConfig
        Rate, error model, soft-tissue artefact, magnetic field and orientation source.
    rng : numpy.random.Generator
        Source of all random draws of this sensor (draw order fixed: mounting, STA matrices,
        then :func:`simulate_imu_from_pose`).
    t_s : ndarray, shape (n,), optional
        Output times, s, spaced ``1 / config.rate_hz``; default :func:`time_grid`.

    Returns
    -------
    stream : ImuStream
        ``acc_m_s2`` (n, 3) specific force, ``gyr_rad_s`` (n, 3), ``mag`` (n, 3) µT,
        ``q_world_from_sensor`` (n, 4) from ``config.orientation`` (VQF by default), in the
        sensor frame; ``name = segment``.
    truth : dict
        As :func:`simulate_imu_from_pose`, plus ``q_world_from_segment`` (n, 4) of the bone,
        ``q_segment_from_sensor`` (4,) mounting, ``sta_rotvec_rad`` and ``sta_translation_m``
        (n, 3) soft-tissue artefact (segment frame), ``sta_drive_rad`` (n, 3m) the joint rotation
        vectors driving it and ``sta_amplitude`` ``(A_tr m, A_rot rad)`` per radian.

    Notes
    -----
    Module docstring: motion smoothing, mounting, soft-tissue artefact (Dumas et al. 2014 linear
    model with literature amplitudes), then :func:`simulate_imu_from_pose`.
    """
    i = motion.segment_index(segment)

    def _smoothed_rot(k: int) -> Rotation:
        q = motion.q_world_from_segment[:, k]
        if config.motion_lowpass_hz is not None:
            q = _lowpass(q, config.motion_lowpass_hz, motion.rate_hz)
            q = q / np.linalg.norm(q, axis=1, keepdims=True)
        return Rotation.from_quat(q, scalar_first=True)

    rot_seg_raw = Rotation.from_quat(motion.q_world_from_segment[:, i], scalar_first=True)
    prox, dist = motion.segment_joints[segment]
    p = motion.position(prox).copy()
    if dist is not None:
        lever = config.position_along_segment * motion.segment_length_m[segment]
        p = p + lever * rot_seg_raw.apply(SEGMENT_AXIS)
    if config.motion_lowpass_hz is not None:
        p = _lowpass(p, config.motion_lowpass_hz, motion.rate_hz)
    rot_seg = _smoothed_rot(i)

    mount = Rotation.from_rotvec(rng.standard_normal(3) * config.mounting_error_deg * _DEG)

    kind = _sta_kind(segment)
    nbs = _neighbours(motion, segment) if kind is not None else []
    drive = _joint_drive(rot_seg, [_smoothed_rot(motion.segment_index(s)) for s in nbs])
    a_tr, a_rot = (0.0, 0.0)
    if kind is not None:
        a_tr = STA_AMPLITUDE[kind][0] * 1e-3 * config.soft_tissue_scale
        a_rot = STA_AMPLITUDE[kind][1] * _DEG * config.soft_tissue_scale
    m_tr = _norm_bounded_matrix(rng, 3, drive.shape[1]) if drive.shape[1] else np.zeros((3, 0))
    m_rot = _norm_bounded_matrix(rng, 3, drive.shape[1]) if drive.shape[1] else np.zeros((3, 0))
    sta_rot = a_rot * drive @ m_rot.T
    sta_tr = a_tr * drive @ m_tr.T
    rot_sensor = rot_seg * Rotation.from_rotvec(sta_rot) * mount
    p_sensor = p + rot_seg.apply(sta_tr)

    t = time_grid(motion.t_s, config.rate_hz) if t_s is None else np.asarray(t_s, dtype=float)
    stream, truth = simulate_imu_from_pose(
        motion.t_s, rot_sensor.as_quat(scalar_first=True), p_sensor, config, rng, t, name=segment
    )
    rot_seg_t = RotationSpline(motion.t_s, rot_seg)(t)
    truth.update(
        q_world_from_segment=_continuous_quat(rot_seg_t.as_quat(scalar_first=True)),
        q_segment_from_sensor=mount.as_quat(scalar_first=True),
        sta_rotvec_rad=CubicSpline(motion.t_s, sta_rot, axis=0)(t),
        sta_translation_m=CubicSpline(motion.t_s, sta_tr, axis=0)(t),
        sta_drive_rad=CubicSpline(motion.t_s, drive, axis=0)(t) if drive.shape[1] else drive[:0],
        sta_amplitude=(a_tr, a_rot),
    )
    return stream, truth


def simulate_imu_from_pose(
    t_src: np.ndarray,
    q_world_from_sensor: np.ndarray,
    position_m: np.ndarray,
    config: ImuConfig,
    rng: np.random.Generator,
    t_s: np.ndarray | None = None,
    *,
    name: str = "imu",
) -> tuple[ImuStream, dict]:
    """Raw IMU signals and their orientation for a sensor moving along a given pose trajectory.

    Parameters
    ----------
    t_src : ndarray, shape (T,)
        Times of the trajectory samples, s, strictly increasing.
    q_world_from_sensor : ndarray, shape (T, 4)
        True sensor orientation, ``wxyz``, sensor -> ENU (already smoothed and mounted).
    position_m : ndarray, shape (T, 3)
        True sensor position, m, ENU.
    config : ImuConfig
        Error model, magnetic field and orientation source (``mounting_error_deg``,
        ``soft_tissue_scale`` and ``motion_lowpass_hz`` are not applied here).
    rng : numpy.random.Generator
        Draw order: gyroscope errors, accelerometer errors, field inhomogeneity, disturbance
        episodes, magnetometer errors, idealised-AHRS errors.
    t_s : ndarray, shape (n,), optional
        Output times, s, spaced ``1 / config.rate_hz``; default :func:`time_grid` of ``t_src``.
    name : str
        Stream name.

    Returns
    -------
    stream : ImuStream
        ``acc_m_s2``, ``gyr_rad_s`` (n, 3), ``mag`` (n, 3) µT, ``q_world_from_sensor`` (n, 4).
    truth : dict
        ``q_world_from_sensor`` (n, 4) true; ``acc_m_s2``, ``gyr_rad_s``, ``mag_ut`` (n, 3)
        noise-free; ``acc_error``/``gyr_error``/``mag_error`` (sensitivity matrix, turn-on bias,
        total bias (n, 3)); ``mag_world_ut`` (n, 3) the world field, ``mag_episodes`` list of
        ``(start_s, end_s)``; ``position_m`` (n, 3); ``ahrs_heading_error_rad`` (idealised only).

    Notes
    -----
    Gyroscope ``log(R_k-1ᵀ R_k)/dt``, accelerometer ``R_kᵀ (a(t_k) − g)`` with ``a`` the central
    second difference of a cubic spline through the positions, magnetometer ``R_kᵀ m_w(t_k)``
    (module docstring); orientation from VQF on the noisy signals unless ``config.orientation``
    is ``"idealised-ahrs"``.
    """
    t_src = np.asarray(t_src, dtype=float)
    t = time_grid(t_src, config.rate_hz) if t_s is None else np.asarray(t_s, dtype=float)
    dt = 1.0 / config.rate_hz
    rot_ws = RotationSpline(t_src, Rotation.from_quat(q_world_from_sensor, scalar_first=True))(t)

    # gyroscope: rate carrying sample k-1 to sample k
    w = (rot_ws[:-1].inv() * rot_ws[1:]).as_rotvec() / dt
    gyr_true = np.vstack([w[:1], w])

    # accelerometer: second difference of a cubic spline through the sensor positions
    spline = CubicSpline(t_src, position_m, axis=0)
    h = float(np.median(np.diff(t_src)))
    a = (spline(t + h) - 2.0 * spline(t) + spline(t - h)) / (h * h)
    acc_true = rot_ws.inv().apply(a - GRAVITY_ENU_M_S2)

    # warm-up: the sensor at rest in the first pose before the recording (VQF only)
    n_warm = 0
    if config.orientation != "idealised-ahrs" and config.warmup_s > 0:
        n_warm = int(round(config.warmup_s * config.rate_hz))
        gyr_true = np.vstack([np.zeros((n_warm, 3)), gyr_true])
        acc_true = np.vstack(
            [np.tile(rot_ws[0].inv().apply(-GRAVITY_ENU_M_S2), (n_warm, 1)), acc_true]
        )
        q_all = np.vstack([np.tile(rot_ws[0].as_quat(), (n_warm, 1)), rot_ws.as_quat()])
        rot_ws = Rotation.from_quat(q_all)
        t = np.concatenate([t[0] - dt * np.arange(n_warm, 0, -1), t])

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

    if n_warm and config.gyr_startup_calibration:
        offset = gyr[:n_warm].mean(axis=0)
        gyr = gyr - offset
        gyr_err["bias"] = gyr_err["bias"] - offset
        gyr_err["startup_offset"] = offset

    # magnetometer: earth field + slow indoor inhomogeneity + disturbance episodes
    n = t.size
    m_inh = _gauss_markov(
        rng, n, 3, config.mag_inhomogeneity_ut, config.mag_inhomogeneity_time_s, dt
    )
    m_dist, episodes = _disturbance_episodes(rng, t, config)
    m_world = config.mag_earth_ut + m_inh + m_dist
    mag_true = rot_ws.inv().apply(m_world)
    mag, mag_err = _error_model(
        rng,
        mag_true,
        scale=config.mag_soft_iron,
        cross=config.mag_soft_iron,
        bias0=config.mag_hard_iron_ut,
        bias_gm=0.0,
        tau_s=config.bias_correlation_time_s,
        rw=0.0,
        noise=config.mag_noise_ut,
        dt=dt,
    )

    q_true = _continuous_quat(rot_ws.as_quat(scalar_first=True))
    frame = "ENU"
    psi = None
    if config.orientation == "idealised-ahrs":
        psi0 = rng.uniform(-1.0, 1.0) * config.ahrs_initial_heading_deg * _DEG
        psi_rate = rng.standard_normal() * config.ahrs_heading_drift_deg_per_min * _DEG / 60.0
        psi = (
            psi0
            + psi_rate * (t - t[0])
            + rng.standard_normal(n) * config.ahrs_heading_noise_deg * _DEG
        )
        tilt = rng.standard_normal((n, 2)) * config.ahrs_tilt_noise_deg * _DEG
        err = Rotation.from_rotvec(np.column_stack([np.zeros((n, 2)), psi])) * Rotation.from_rotvec(
            np.column_stack([tilt, np.zeros(n)])
        )
        q_out = _continuous_quat((err * rot_ws).as_quat(scalar_first=True))
    else:
        from kinefuse.orientation import estimate

        use_mag = config.orientation == "vqf"
        q_out = estimate(acc, gyr, mag if use_mag else None, rate_hz=config.rate_hz)
        if not use_mag:
            frame = "VQF-6D"

    if n_warm:
        keep = slice(n_warm, None)
        t, rot_ws, q_out, q_true = t[keep], rot_ws[keep], q_out[keep], q_true[keep]
        acc, gyr, mag = acc[keep], gyr[keep], mag[keep]
        acc_true, gyr_true, mag_true, m_world = (
            acc_true[keep],
            gyr_true[keep],
            mag_true[keep],
            m_world[keep],
        )
        for err in (acc_err, gyr_err, mag_err):
            err["bias"] = err["bias"][keep]
        if psi is not None:
            psi = psi[keep]
    stream = ImuStream(
        t_s=t,
        q_world_from_sensor=q_out,
        acc_m_s2=acc,
        gyr_rad_s=gyr,
        mag=mag,
        name=name,
        frame=frame,
    )
    truth = {
        "q_world_from_sensor": q_true,
        "acc_m_s2": acc_true,
        "gyr_rad_s": gyr_true,
        "mag_ut": mag_true,
        "acc_error": acc_err,
        "gyr_error": gyr_err,
        "mag_error": mag_err,
        "mag_world_ut": m_world,
        "mag_episodes": episodes,
        "ahrs_heading_error_rad": psi,
        "position_m": spline(t),
    }
    return stream, truth
