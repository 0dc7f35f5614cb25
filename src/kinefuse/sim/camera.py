"""A virtual depth camera (Kinect-like skeleton tracker) driven by a :class:`~kinefuse.io.motion.Motion`.

Model, per camera frame ``t_k = t_0 + k / rate_hz``:

1. Truth: joint positions interpolated with a cubic spline through the mocap samples (exact at
   mocap sample times; at 30 Hz from 120 Hz mocap every camera frame is a mocap frame).
2. Bone-length variation: every edge of the canonical skeleton tree (spine_base -> spine_mid ->
   spine_shoulder -> neck -> head; spine_shoulder -> shoulder -> elbow -> wrist -> hand;
   spine_base -> hip -> knee -> ankle -> foot) is scaled by ``1 + ε(t)``, ε a stationary
   first-order Gauss-Markov process (std ``bone_length_std``, correlation time
   ``bone_length_corr_time_s``), and the skeleton is rebuilt from spine_base outwards.
3. Jitter: white Gaussian noise with per-axis std ``noise_std_m`` in the camera axes.
4. Outages: per joint, independent occlusions; plus whole-body dropouts. Each is an alternating
   renewal process: visible for an exponential time with rate ``*_rate_per_min`` (at least one
   frame), then missing for a duration drawn uniformly in ``*_duration_s`` (rounded to whole
   frames inside the bounds). ``available = False`` during occlusions and dropouts and the
   positions there are NaN. Expected missing fraction of one process:
   ``λ d̄ / (60 + λ d̄)`` with λ per minute and d̄ the mean duration in s.

Defaults fitted to the real UTD-MHAD Kinect v1 skeletons by ``benchmarks/fit_kinect_noise.py``:
jitter of still joints (lower body during the arm-only actions 1-21, 172,802 joint-frames):
high-pass residual about a Savitzky-Golay fit (9 frames, order 2) corrected to white-noise
equivalent, std **0.74, 0.73, 1.00 mm** along camera x (lateral), y (up), z (depth) (pooled
0.83 mm; second differences give 0.59, 0.56, 0.81 mm). Bone-length variation: median over
trials and the eight limb bones of the relative std of the bone length, **0.057** (0.072 for
moving arm bones, 0.022 for still leg bones), correlation time (autocorrelation < 1/e)
**0.17 s**. Occlusion and dropout rates have no real counterpart (UTD-MHAD has no outages):
defaults [J] 2 occlusions per joint per minute and 0.5 dropouts per minute, 0.3-3 s.

5. Tracking error: the skeleton fit of a depth camera misplaces joints by centimetres for
   tenths of a second (pose- and occlusion-dependent; Kinect v1 joint positions differ from
   optical mocap by several centimetres in the arms, Obdržálek et al., EMBC 2012): a per-joint,
   per-camera-axis first-order Gauss-Markov offset with std ``tracking_error_std_m`` and
   correlation time ``tracking_error_time_s``, added after the jitter (drawn after the outages,
   so the other draws do not depend on it). Jitter and bone lengths cannot reveal it (it is
   slow and moves joints, not bones, coherently). Defaults **2.5 cm** and **0.2 s**, chosen so
   that the IMU wrist chain meets the virtual Kinect as the real one meets the UTD-MHAD Kinect:
   same chain-camera RMSE and calibration residual, and the same decorrelation time of their
   difference (1/e of its autocorrelation: 0.13 s median on UTD-MHAD) (``kinefuse experiment
   realism``, tuning subjects 1-3 against CMU 02_05 and 02_07).

Camera frame: Kinect convention (x to the sensor's left, y up, z along the optical axis). The
camera looks horizontally along heading ``heading_deg`` (clockwise from north) from
``distance_m`` behind the mean pelvis position, at height ``height_m``.
``R_world_from_camera`` and ``camera_position_m`` are returned (and stored in the recording's
metadata); with ``frame="camera"`` the positions are ``R_world_from_cameraᵀ (p − c)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from kinefuse.exceptions import InputError
from kinefuse.io.motion import Motion
from kinefuse.io.recording import JointStream
from kinefuse.sim.noise import gauss_markov

__all__ = ["SKELETON_PARENT", "CameraConfig", "camera_pose", "reference_at", "simulate_camera"]

#: Canonical skeleton tree used for the bone-length variation (child -> parent).
SKELETON_PARENT: dict[str, str] = {
    "pelvis": "spine_base",
    "spine_mid": "spine_base",
    "spine_shoulder": "spine_mid",
    "neck": "spine_shoulder",
    "head": "neck",
    "shoulder_l": "spine_shoulder",
    "shoulder_r": "spine_shoulder",
    "elbow_l": "shoulder_l",
    "elbow_r": "shoulder_r",
    "wrist_l": "elbow_l",
    "wrist_r": "elbow_r",
    "hand_l": "wrist_l",
    "hand_r": "wrist_r",
    "hip_l": "spine_base",
    "hip_r": "spine_base",
    "knee_l": "hip_l",
    "knee_r": "hip_r",
    "ankle_l": "knee_l",
    "ankle_r": "knee_r",
    "foot_l": "ankle_l",
    "foot_r": "ankle_r",
}


@dataclass(frozen=True)
class CameraConfig:
    """Virtual depth-camera settings (defaults fitted to UTD-MHAD Kinect; see module doc).

    Attributes
    ----------
    rate_hz : float
        Frame rate, Hz.
    joints : tuple of str or None
        Joints reported; ``None`` = all joints of the motion.
    noise_std_m : float or tuple of 3 floats
        White jitter std, m, along camera x, y, z.
    bone_length_std : float
        Std of the relative bone-length variation (0.057 = 5.7 %).
    bone_length_corr_time_s : float
        Correlation time of the bone-length variation, s (0 = white).
    occlusion_rate_per_min, dropout_rate_per_min : float
        Onsets per minute of visible time: per-joint occlusions, whole-body dropouts.
    occlusion_duration_s, dropout_duration_s : (float, float)
        Uniform duration range, s.
    frame : {"ENU", "camera"}
        Frame of the reported positions.
    heading_deg, distance_m, height_m : float
        Camera placement (module doc).
    tracking_error_std_m, tracking_error_time_s : float
        Slow skeleton-fitting error per joint and camera axis: std, m, and correlation time, s
        (module doc, step 5).
    """

    rate_hz: float = 30.0
    joints: tuple[str, ...] | None = None
    noise_std_m: float | tuple[float, float, float] = (0.74e-3, 0.73e-3, 1.00e-3)
    bone_length_std: float = 0.057
    bone_length_corr_time_s: float = 0.17
    occlusion_rate_per_min: float = 2.0
    occlusion_duration_s: tuple[float, float] = (0.3, 3.0)
    dropout_rate_per_min: float = 0.5
    dropout_duration_s: tuple[float, float] = (0.3, 3.0)
    frame: str = "ENU"
    heading_deg: float = 0.0
    distance_m: float = 3.0
    height_m: float = 0.8
    tracking_error_std_m: float = 0.025
    tracking_error_time_s: float = 0.2

    def __post_init__(self):
        noise = np.broadcast_to(np.asarray(self.noise_std_m, dtype=float), (3,))
        if not np.all(np.isfinite(noise)) or np.any(noise < 0):
            raise InputError(
                f"CameraConfig.noise_std_m: expected finite values >= 0, got {self.noise_std_m!r}"
            )
        object.__setattr__(self, "noise_std_m", tuple(float(x) for x in noise))
        for name in (
            "rate_hz",
            "bone_length_std",
            "bone_length_corr_time_s",
            "occlusion_rate_per_min",
            "dropout_rate_per_min",
            "distance_m",
            "tracking_error_std_m",
            "tracking_error_time_s",
        ):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InputError(f"CameraConfig.{name}: expected a finite number >= 0, got {v!r}")
        if self.rate_hz <= 0:
            raise InputError(f"CameraConfig.rate_hz: expected > 0, got {self.rate_hz!r}")
        if self.tracking_error_time_s <= 0:
            raise InputError(
                f"CameraConfig.tracking_error_time_s: expected > 0, got {self.tracking_error_time_s!r}"
            )
        for name in ("occlusion_duration_s", "dropout_duration_s"):
            lo, hi = (float(x) for x in getattr(self, name))
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise InputError(
                    f"CameraConfig.{name}: expected 0 < min <= max, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, (lo, hi))
        if self.frame not in ("ENU", "camera"):
            raise InputError(f"CameraConfig.frame: expected 'ENU' or 'camera', got {self.frame!r}")
        if self.joints is not None:
            object.__setattr__(self, "joints", tuple(self.joints))

    @classmethod
    def ideal(cls, rate_hz: float = 30.0, **kwargs) -> CameraConfig:
        """Noise-free camera without outages (truth at the camera rate)."""
        base = dict(
            noise_std_m=0.0,
            bone_length_std=0.0,
            tracking_error_std_m=0.0,
            occlusion_rate_per_min=0.0,
            dropout_rate_per_min=0.0,
        )
        base.update(kwargs)
        return cls(rate_hz=rate_hz, **base)


def reference_at(motion: Motion, t_s: np.ndarray, joints=None) -> JointStream:
    """True joint positions at times ``t_s`` (cubic spline through the mocap samples).

    Parameters
    ----------
    motion : Motion
    t_s : ndarray, shape (n,)
        Times, s, inside the motion's span.
    joints : sequence of str, optional
        Default all joints of the motion.

    Returns
    -------
    JointStream
        ENU positions (n, J, 3), m, all available.
    """
    names = tuple(motion.joints if joints is None else joints)
    idx = [motion.joint_index(j) for j in names]
    t = np.asarray(t_s, dtype=float)
    outside = ~((t >= motion.t_s[0] - 1e-9) & (t <= motion.t_s[-1] + 1e-9))
    if np.any(outside):  # a spline extrapolates wildly (4e5 m 7 s past the end): an error
        k = int(np.flatnonzero(outside)[0])
        raise InputError(
            f"expected t_s inside the motion's span {motion.t_s[0]:.4g}-{motion.t_s[-1]:.4g} s, "
            f"got {t[k]!r} (sample {k})"
        )
    pos = CubicSpline(motion.t_s, motion.position_m[:, idx], axis=0)(t)
    return JointStream(t_s=t_s, position_m=pos, joints=names, frame="ENU")


def camera_pose(motion: Motion, config: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """``R_world_from_camera`` (3, 3) and camera position (3,), m, ENU (module doc)."""
    h = config.heading_deg * math.pi / 180.0
    d = np.array([math.sin(h), math.cos(h), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    R = np.column_stack([np.cross(up, d), up, d])
    centre = (
        motion.position("pelvis").mean(axis=0)
        if "pelvis" in motion.joints
        else motion.position_m.mean(axis=(0, 1))
    )
    c = np.array([centre[0], centre[1], config.height_m]) - config.distance_m * d
    return R, c


def _outages(
    rng: np.random.Generator, n: int, rate_hz: float, rate_per_min: float, duration_s
) -> np.ndarray:
    """Boolean (n,) mask of an alternating renewal process (module doc)."""
    mask = np.zeros(n, dtype=bool)
    if rate_per_min <= 0:
        return mask
    mean_gap = 60.0 / rate_per_min * rate_hz  # frames
    lo = math.ceil(duration_s[0] * rate_hz - 1e-9)
    hi = max(lo, math.floor(duration_s[1] * rate_hz + 1e-9))
    k = 0
    while True:
        k += max(1, math.ceil(rng.exponential(mean_gap)))
        if k >= n:
            return mask
        m = min(hi, max(lo, round(rng.uniform(*duration_s) * rate_hz)))
        mask[k : k + m] = True
        k += m


def bone_edges(names) -> list[tuple[str, str]]:
    """Bones ``(parent, child)`` among ``names`` along :data:`SKELETON_PARENT`.

    A joint whose canonical parent is absent hangs from its nearest present ancestor.
    """
    names = tuple(names)

    def parent_of(j):
        p = SKELETON_PARENT.get(j)
        while p is not None and p not in names:
            p = SKELETON_PARENT.get(p)
        return p

    return [(parent_of(j), j) for j in names if parent_of(j) is not None]


def simulate_camera(
    motion: Motion, config: CameraConfig, rng: np.random.Generator, t_s: np.ndarray
) -> tuple[JointStream, dict]:
    """The virtual camera's joint stream at times ``t_s`` (spaced ``1 / config.rate_hz``).

    Returns
    -------
    stream : JointStream
        Positions (n, J, 3), m, in ``config.frame``; NaN and ``available = False`` during
        occlusions and dropouts.
    truth : dict
        ``R_world_from_camera`` (3, 3), ``camera_position_m`` (3,), ``occluded`` (n, J) and
        ``dropout`` (n,) masks, ``bone_scale`` (n, E) with ``bone_edges`` (E pairs), and
        ``position_unmasked_m`` (n, J, 3): the noisy positions before masking, ENU.
    """
    names = tuple(motion.joints if config.joints is None else config.joints)
    for j in names:
        motion.joint_index(j)
    n = t_s.size
    dt = 1.0 / config.rate_hz
    true_all = reference_at(motion, t_s).position_m  # (n, J_all, 3)
    all_names = motion.joints

    perturbed, edges, eps = _bone_length_variation(rng, true_all, all_names, names, config, dt)

    R_wc, c = camera_pose(motion, config)
    noise_cam = rng.standard_normal((n, len(names), 3)) * np.asarray(config.noise_std_m)
    noisy_world = perturbed + noise_cam @ R_wc.T

    occluded, dropout = _outage_masks(rng, n, names, config)
    available = ~(occluded | dropout[:, None])
    J = len(names)
    track = np.zeros((n, J, 3))
    if config.tracking_error_std_m > 0:  # the last draw: skipping it changes nothing else
        track = gauss_markov(
            rng, n, 3 * J, config.tracking_error_std_m, config.tracking_error_time_s, dt
        ).reshape(n, J, 3)
    noisy_world = noisy_world + track @ R_wc.T

    pos = (noisy_world - c) @ R_wc if config.frame == "camera" else noisy_world.copy()
    pos[~available] = np.nan
    stream = JointStream(
        t_s=t_s, position_m=pos, available=available, joints=names, frame=config.frame
    )
    truth = {
        "R_world_from_camera": R_wc,
        "camera_position_m": c,
        "occluded": occluded,
        "dropout": dropout,
        "bone_edges": tuple(edges),
        "bone_scale": 1.0 + eps,
        "position_unmasked_m": noisy_world,
        "tracking_error_m": track @ R_wc.T,
    }
    return stream, truth


def _bone_length_variation(rng, true_all, all_names, names, config: CameraConfig, dt: float):
    """Joints ``names`` with every bone of the canonical tree scaled by ``1 + ε(t)`` (ENU).

    Returns the perturbed positions (n, J, 3), the bones ``(parent, child)`` and ``ε`` (n, E).
    """
    n = true_all.shape[0]
    edges = bone_edges(all_names)
    eps = gauss_markov(
        rng, n, len(edges), config.bone_length_std, config.bone_length_corr_time_s, dt
    )
    scale = {child: 1.0 + eps[:, e] for e, (_, child) in enumerate(edges)}
    parent = dict((c, p) for p, c in edges)
    out = {}

    def place(j):
        if j in out:
            return out[j]
        i = all_names.index(j)
        if j not in parent:
            out[j] = true_all[:, i]
        else:
            p = parent[j]
            ip = all_names.index(p)
            out[j] = place(p) + scale[j][:, None] * (true_all[:, i] - true_all[:, ip])
        return out[j]

    return np.stack([place(j) for j in names], axis=1), edges, eps


def _outage_masks(rng, n: int, names, config: CameraConfig):
    """Per-joint occlusion (n, J) and whole-body dropout (n,) masks (draw order fixed)."""
    occluded = np.stack(
        [
            _outages(
                rng, n, config.rate_hz, config.occlusion_rate_per_min, config.occlusion_duration_s
            )
            for _ in names
        ],
        axis=1,
    )
    dropout = _outages(
        rng, n, config.rate_hz, config.dropout_rate_per_min, config.dropout_duration_s
    )
    return occluded, dropout
