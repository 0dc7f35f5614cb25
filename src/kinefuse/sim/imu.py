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

Error model and defaults
------------------------
See :mod:`kinefuse.sim.imu_config` (ICM-20948 residuals after a user's calibration).

Soft-tissue artefact (STA)
--------------------------
See :mod:`kinefuse.sim.soft_tissue` (Dumas et al. 2014 linear model, literature amplitudes).

Forearm pronation
-----------------
Mocap skeletons put pronation/supination at the wrist (CMU: the short wrist bone's ``ry``; the
canonical ``hand`` segment), not on the forearm bone, but the radius turns about the ulna along
the whole forearm: a sensor strapped to the forearm turns with it, by more the nearer it sits to
the wrist. A forearm sensor at ``position_along_segment`` ``f`` is turned about the forearm's
long axis by ``f · φ(t)``, with ``φ`` the twist of the hand relative to the forearm about that
axis (swing-twist decomposition; minus its trial mean, so that the mean sensor-to-bone rotation
is the mounting), before the soft tissue: ``R_ws = R_world_from_segment · exp(f φ e2) · exp(δθ) ·
R_segment_from_sensor``. Linear in ``f`` (none at the elbow, where the ulna does not turn, all at
the wrist): a modelling choice, not a measured profile. Without a hand segment in the motion
``φ = 0``.

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
trials 28 and 32 (an earlier model of both; see :mod:`kinefuse.apps.realism`). A magnet fixed to
the sensor's mount (``mag_mount_magnet_ut``, default none) adds a constant *sensor*-frame field
(random or given direction) over a span of the recording, with the same ramps: BROAD's
attached-magnet trials (trial 32, 1 cm: 57.7 µT, sd 1.6 µT per axis, constant in the sensor
frame from 23 % to 58 % of the trial).

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
``"idealised-ahrs"`` (kept for :data:`kinefuse.apps.paper_a.DEGRADED_AHRS` and exact
tests, *not realistic*): the true sensor orientation times a world-frame error: heading
``ψ(t) = ψ_0 + ψ̇ · (t − t_0) + N(0, heading_noise²)`` (ψ_0 uniform ±initial, ψ̇ normal with std
``ahrs_heading_drift_deg_per_min``) about ENU z, times a white tilt error about x and y
(defaults [J]: drift 0.5 °/min, heading noise 0.2°, tilt noise 0.1°).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import butter, filtfilt
from scipy.spatial.transform import Rotation, RotationSpline

from kinefuse.conventions import GRAVITY_ENU_M_S2, GRAVITY_M_S2
from kinefuse.exceptions import InputError
from kinefuse.io.motion import SEGMENT_AXIS, Motion, _continuous_quat
from kinefuse.io.recording import ImuStream
from kinefuse.orientation import estimate
from kinefuse.sim.imu_config import ORIENTATIONS, ImuConfig
from kinefuse.sim.noise import (
    disturbance_episodes,
    gauss_markov,
    norm_bounded_matrix,
    sensor_errors,
    window_weight,
)
from kinefuse.sim.soft_tissue import STA_AMPLITUDE, joint_drive, neighbours, sta_kind

__all__ = [
    "ORIENTATIONS",
    "STA_AMPLITUDE",
    "ImuConfig",
    "simulate_imu",
    "simulate_imu_from_pose",
    "time_grid",
]

_DEG = math.pi / 180.0


def time_grid(t_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """``t_0 + k / rate_hz`` for all k with the time inside ``[t_s[0], t_s[-1]]``, shape (n,)."""
    n = int(math.floor((t_s[-1] - t_s[0]) * rate_hz + 1e-9)) + 1
    if n < 2:
        raise InputError(
            f"expected a motion spanning at least 2 samples at {rate_hz} Hz, got {t_s[-1] - t_s[0]:.4g} s"
        )
    return t_s[0] + np.arange(n) / rate_hz


def _lowpass(x: np.ndarray, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth low-pass along axis 0."""
    wn = cutoff_hz / (0.5 * rate_hz)
    if not 0.0 < wn < 1.0:
        raise InputError(
            f"ImuConfig.motion_lowpass_hz: expected below the motion's Nyquist {0.5 * rate_hz:.4g} Hz, got {cutoff_hz!r}"
        )
    b, a = butter(2, wn)
    return filtfilt(b, a, x, axis=0, padlen=min(3 * max(len(a), len(b)), x.shape[0] - 1))


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
        vectors driving it, ``sta_amplitude`` ``(A_tr m, A_rot rad)`` per radian and
        ``twist_rad`` (n,) the forearm pronation turning the sensor (zeros elsewhere).

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

    p = _sensor_path(motion, segment, i, config)
    rot_seg = _smoothed_rot(i)
    twist = config.position_along_segment * _forearm_twist(motion, segment, rot_seg, _smoothed_rot)
    rot_skin = rot_seg * Rotation.from_rotvec(twist[:, None] * SEGMENT_AXIS)
    mount = Rotation.from_rotvec(rng.standard_normal(3) * config.mounting_error_deg * _DEG)
    kind = sta_kind(segment)
    nbs = neighbours(motion, segment) if kind is not None else []
    drive = joint_drive(rot_seg, [_smoothed_rot(motion.segment_index(s)) for s in nbs])
    a_tr, a_rot = (0.0, 0.0)
    if kind is not None:
        a_tr = STA_AMPLITUDE[kind][0] * 1e-3 * config.soft_tissue_scale
        a_rot = STA_AMPLITUDE[kind][1] * _DEG * config.soft_tissue_scale
    m_tr = norm_bounded_matrix(rng, 3, drive.shape[1]) if drive.shape[1] else np.zeros((3, 0))
    m_rot = norm_bounded_matrix(rng, 3, drive.shape[1]) if drive.shape[1] else np.zeros((3, 0))
    sta_rot = a_rot * drive @ m_rot.T
    sta_tr = a_tr * drive @ m_tr.T
    rot_sensor = rot_skin * Rotation.from_rotvec(sta_rot) * mount
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
        twist_rad=np.interp(t, motion.t_s, twist),
    )
    return stream, truth


def _forearm_twist(motion: Motion, segment: str, rot_seg: Rotation, smoothed_rot) -> np.ndarray:
    """Twist ``φ`` (rad, (T,), minus its mean) of the hand about a forearm's long axis; zeros
    for other segments and when the motion has no hand segment (module doc, forearm pronation)."""
    hand = "hand" + segment[len("forearm") :] if segment.startswith("forearm") else None
    if hand is None or hand not in motion.segments:
        return np.zeros(len(motion))
    rel = (rot_seg.inv() * smoothed_rot(motion.segment_index(hand))).as_quat(scalar_first=True)
    phi = np.unwrap(2.0 * np.arctan2(rel[:, 2], rel[:, 0]))  # twist about e2 (swing-twist)
    return phi - phi.mean()


def _sensor_path(motion: Motion, segment: str, i: int, config: ImuConfig) -> np.ndarray:
    """Bone point carrying the sensor (``position_along_segment``), low-passed, (T, 3) m."""
    rot_seg_raw = Rotation.from_quat(motion.q_world_from_segment[:, i], scalar_first=True)
    prox, dist = motion.segment_joints[segment]
    p = motion.position(prox).copy()
    if dist is not None:
        lever = config.position_along_segment * motion.segment_length_m[segment]
        p = p + lever * rot_seg_raw.apply(SEGMENT_AXIS)
    if config.motion_lowpass_hz is not None:
        p = _lowpass(p, config.motion_lowpass_hz, motion.rate_hz)
    return p


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
        episodes, mount magnet direction (only with a mount magnet), magnetometer errors,
        idealised-AHRS errors.
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
    spline = CubicSpline(t_src, position_m, axis=0)
    gyr_true, acc_true = _true_inertial(rot_ws, spline, t, t_src, dt)
    # warm-up: the sensor at rest in the first pose before the recording (VQF only)
    n_warm = 0
    if config.orientation != "idealised-ahrs" and config.warmup_s > 0:
        n_warm = int(round(config.warmup_s * config.rate_hz))
        gyr_true, acc_true, rot_ws, t = _prepend_rest(n_warm, gyr_true, acc_true, rot_ws, t, dt)
    out, truth = _readings(rng, t, rot_ws, gyr_true, acc_true, config, dt, n_warm)
    if n_warm:
        t = t[n_warm:]
        _drop_warmup(out, truth, n_warm)
    truth["position_m"] = spline(t)
    return ImuStream(t_s=t, name=name, **out), truth


def _readings(rng, t, rot_ws, gyr_true, acc_true, config: ImuConfig, dt: float, n_warm: int):
    """The sensor's outputs (ImuStream fields) and the truth, warm-up included (draw order fixed)."""
    gyr, gyr_err, acc, acc_err = _inertial_readings(rng, gyr_true, acc_true, config, dt)
    if n_warm and config.gyr_startup_calibration:
        offset = gyr[:n_warm].mean(axis=0)
        gyr = gyr - offset
        gyr_err["bias"] = gyr_err["bias"] - offset
        gyr_err["startup_offset"] = offset
    mag, mag_err, mag_true, m_world, episodes = _magnetometer(rng, t, rot_ws, config, dt, n_warm)
    q_true = _continuous_quat(rot_ws.as_quat(scalar_first=True))
    q_out, frame, psi = _output_orientation(rng, t, rot_ws, acc, gyr, mag, config)
    out = {"q_world_from_sensor": q_out, "acc_m_s2": acc, "gyr_rad_s": gyr, "mag": mag}
    out["frame"] = frame
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
    }
    return out, truth


def _drop_warmup(out: dict, truth: dict, n_warm: int) -> None:
    """Remove the ``n_warm`` warm-up samples from the outputs and the truth (in place)."""
    keep = slice(n_warm, None)
    for key in ("q_world_from_sensor", "acc_m_s2", "gyr_rad_s", "mag"):
        out[key] = out[key][keep]
    for key in ("q_world_from_sensor", "acc_m_s2", "gyr_rad_s", "mag_ut", "mag_world_ut"):
        truth[key] = truth[key][keep]
    for key in ("acc_error", "gyr_error", "mag_error"):
        truth[key]["bias"] = truth[key]["bias"][keep]
    if truth["ahrs_heading_error_rad"] is not None:
        truth["ahrs_heading_error_rad"] = truth["ahrs_heading_error_rad"][keep]


def _true_inertial(rot_ws: Rotation, spline: CubicSpline, t, t_src, dt: float):
    """Noise-free gyroscope (n, 3) rad/s and specific force (n, 3) m/s² (module doc)."""
    # gyroscope: rate carrying sample k-1 to sample k
    w = (rot_ws[:-1].inv() * rot_ws[1:]).as_rotvec() / dt
    gyr_true = np.vstack([w[:1], w])
    # accelerometer: second difference of a cubic spline through the sensor positions
    h = float(np.median(np.diff(t_src)))
    a = (spline(t + h) - 2.0 * spline(t) + spline(t - h)) / (h * h)
    acc_true = rot_ws.inv().apply(a - GRAVITY_ENU_M_S2)
    return gyr_true, acc_true


def _prepend_rest(n_warm: int, gyr_true, acc_true, rot_ws: Rotation, t, dt: float):
    """``n_warm`` samples of the sensor at rest in its first pose before the recording."""
    gyr_true = np.vstack([np.zeros((n_warm, 3)), gyr_true])
    acc_true = np.vstack([np.tile(rot_ws[0].inv().apply(-GRAVITY_ENU_M_S2), (n_warm, 1)), acc_true])
    q_all = np.vstack([np.tile(rot_ws[0].as_quat(), (n_warm, 1)), rot_ws.as_quat()])
    rot_ws = Rotation.from_quat(q_all)
    t = np.concatenate([t[0] - dt * np.arange(n_warm, 0, -1), t])
    return gyr_true, acc_true, rot_ws, t


def _inertial_readings(rng, gyr_true, acc_true, config: ImuConfig, dt: float):
    """Gyroscope then accelerometer through their error models (draw order fixed)."""
    g = GRAVITY_M_S2
    gyr, gyr_err = sensor_errors(
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
    acc, acc_err = sensor_errors(
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
    return gyr, gyr_err, acc, acc_err


def _magnetometer(rng, t, rot_ws: Rotation, config: ImuConfig, dt: float, n_warm: int = 0):
    """Earth field + slow indoor inhomogeneity + disturbance episodes, read by the sensor,
    + a magnet on the mount (sensor frame; its span counts from the first recorded sample,
    after ``n_warm`` warm-up samples).

    Returns the reading, its error parameters, the noise-free reading, the world field and the
    episodes.
    """
    n = t.size
    m_inh = gauss_markov(
        rng, n, 3, config.mag_inhomogeneity_ut, config.mag_inhomogeneity_time_s, dt
    )
    m_dist, episodes = disturbance_episodes(rng, t, config)
    m_world = config.mag_earth_ut + m_inh + m_dist
    mag_true = rot_ws.inv().apply(m_world)
    if config.mag_mount_magnet_ut > 0.0:  # drawn only then: other configurations unchanged
        u = rng.standard_normal(3)
        if config.mag_mount_magnet_dir is not None:  # (drawn anyway: one draw order)
            u = np.asarray(config.mag_mount_magnet_dir, dtype=float)
        t_a, span = t[n_warm], t[-1] - t[n_warm]
        w = window_weight(
            t, t_a + config.mag_mount_magnet_from * span, t_a + config.mag_mount_magnet_to * span
        )
        mag_true = mag_true + w[:, None] * (config.mag_mount_magnet_ut * u / np.linalg.norm(u))
    mag, mag_err = sensor_errors(
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
    return mag, mag_err, mag_true, m_world, episodes


def _output_orientation(rng, t, rot_ws: Rotation, acc, gyr, mag, config: ImuConfig):
    """``q_world_from_sensor`` the virtual IMU outputs, its frame and the AHRS heading error."""
    if config.orientation != "idealised-ahrs":
        use_mag = config.orientation == "vqf"
        q_out = estimate(acc, gyr, mag if use_mag else None, rate_hz=config.rate_hz)
        return q_out, "ENU" if use_mag else "VQF-6D", None
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
    return _continuous_quat((err * rot_ws).as_quat(scalar_first=True)), "ENU", psi
