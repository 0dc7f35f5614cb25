"""What every vision-assisted fusion method shares: validated inputs and the typed result.

:func:`check_inputs` validates the public arrays of :func:`~kinefuse.pipelines.vision_assisted`
and turns them joint-major; a :class:`FusionContext` carries them to a method of
:data:`~kinefuse.pipelines.METHODS`; :func:`finish` turns a method's joint-major output into the
time-major :class:`FusionResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.models import LinearGaussianModel
from kinefuse.pipelines._outages import SOURCE_NONE, outage_intervals
from kinefuse.pipelines.vision_params import VisionParams, check_float

__all__ = [
    "FusionContext",
    "FusionResult",
    "check_inputs",
    "empty_output",
    "finish",
    "joint_major",
    "pos_cov",
]


@dataclass(frozen=True, eq=False)
class FusionResult:
    """Output of :func:`vision_assisted` (all arrays time-major, like the inputs).

    Attributes
    ----------
    position : ndarray, shape (T, J, 3)
        Joint positions, m (frame of the inputs: ENU chest-relative for paper B).
    cov : ndarray, shape (T, J, 3, 3)
        Position covariance, m² (NaN where ``position`` is NaN).
    source : ndarray of int8, shape (T, J)
        :data:`kinefuse.conventions.SOURCE_NAMES` code per sample: ``SOURCE_FUSED`` (camera
        available, IMM(+RTS) output), ``SOURCE_BRIDGED`` (outage bridged by ELM/FIR, or
        camera-only interpolation), ``SOURCE_IMU`` (IMU only), ``SOURCE_CAMERA`` (raw camera);
        :data:`SOURCE_NONE` (-1) where there is no estimate.
    joints : tuple of str
        Joint names.
    method : str
        Method name (:data:`METHODS`).
    causal : bool
        True when every output at t depends only on inputs up to t (``fixed_lag`` > 0: up to
        ``t + fixed_lag``).
    mu : ndarray, shape (T, J, 2) or None
        IMM model probabilities (IMU, camera) where the camera was available; NaN elsewhere;
        None for methods without an IMM.
    outages : tuple of tuple of (int, int)
        Per joint, the maximal unavailable runs ``(start, stop)`` (stop exclusive).
    episodes : tuple of tuple of OutageEpisode
        Per joint, the prediction-stage episodes (recovery rule applied) and how each was
        bridged; empty for methods without an outage bridge.
    imu_fallback : ndarray of bool, shape (T, J)
        True where an episode had too little training data and FIR-1 (IMU only) was output.
    elm2_skipped : ndarray of bool, shape (T, J)
        True inside bridged episodes whose ELM-2 was skipped (FIR-3 output alone).
    dt_s : float
        Sample interval, s.
    params : VisionParams
    """

    position: np.ndarray
    cov: np.ndarray
    source: np.ndarray
    joints: tuple[str, ...]
    method: str
    causal: bool = False
    mu: np.ndarray | None = None
    outages: tuple = ()
    episodes: tuple = ()
    imu_fallback: np.ndarray | None = None
    elm2_skipped: np.ndarray | None = None
    dt_s: float = float("nan")
    params: VisionParams | None = None


# ------------------------------------------------------------------------------------ context
@dataclass(frozen=True, eq=False)
class FusionContext:
    """Validated inputs of one fusion run, joint-major (what a method of ``METHODS`` receives).

    ``z_imu, z_cam (J, T, 3)`` (z_cam NaN where unavailable), ``available (J, T)``, ``dt_s``,
    ``params``, ``causal``, ``joints``, ``method``, ``features (J, T, F)`` or None,
    ``segment_rotations (J, T, S, 3, 3)`` or None (read by ``"kinefuse"`` only) and the two
    constant-velocity models ``model_imu``, ``model_cam`` (``params.models(dt_s)``).
    """

    z_imu: np.ndarray
    z_cam: np.ndarray
    available: np.ndarray
    dt_s: float
    params: VisionParams
    causal: bool
    joints: tuple[str, ...]
    method: str
    features: np.ndarray | None
    segment_rotations: np.ndarray | None = None
    model_imu: LinearGaussianModel = field(init=False)
    model_cam: LinearGaussianModel = field(init=False)

    def __post_init__(self):
        mi, mc = self.params.models(self.dt_s)
        object.__setattr__(self, "model_imu", mi)
        object.__setattr__(self, "model_cam", mc)

    @property
    def shape(self) -> tuple[int, int]:
        return self.z_imu.shape[0], self.z_imu.shape[1]


def pos_cov(cov: np.ndarray) -> np.ndarray:
    """Position block ``H P Hᵀ`` of interleaved ``[x, vx, y, vy, z, vz]`` covariances."""
    return cov[..., 0::2, 0::2]


def joint_major(J: int, T: int, tail: tuple = (), dtype=np.float64, fill=None) -> np.ndarray:
    """A joint-major ``(J, T, *tail)`` view of a new time-major ``(T, J, *tail)`` array.

    :func:`finish` returns time-major arrays: a method that writes its output into these views
    is returned without a transposing copy (of the covariances, the largest output). ``fill``:
    the initial value (None: uninitialised).
    """
    a = np.empty((T, J, *tail), dtype) if fill is None else np.full((T, J, *tail), fill, dtype)
    return np.swapaxes(a, 0, 1)


def empty_output(ctx: FusionContext):
    """All-missing joint-major ``(position, cov, source)`` arrays for ``ctx``
    (:func:`joint_major` views)."""
    J, T = ctx.shape
    return (
        joint_major(J, T, (3,), fill=np.nan),
        joint_major(J, T, (3, 3), fill=np.nan),
        joint_major(J, T, dtype=np.int8, fill=SOURCE_NONE),
    )


def finish(
    ctx: FusionContext, pos, cov, src, *, causal: bool, mu=None, episodes=None, **flags
) -> FusionResult:
    """Assemble a time-major :class:`FusionResult` from joint-major arrays (copied unless they
    are :func:`joint_major` views)."""
    J, T = ctx.shape
    flags = {
        k: flags.get(k, np.zeros((J, T), dtype=bool)) for k in ("imu_fallback", "elm2_skipped")
    }
    episodes = tuple(() for _ in range(J)) if episodes is None else episodes
    return FusionResult(
        position=np.ascontiguousarray(pos.transpose(1, 0, 2)),
        cov=np.ascontiguousarray(cov.transpose(1, 0, 2, 3)),
        source=np.ascontiguousarray(src.T),
        joints=ctx.joints,
        method=ctx.method,
        causal=causal,
        mu=None if mu is None else np.ascontiguousarray(mu.transpose(1, 0, 2)),
        outages=tuple(outage_intervals(ctx.available[j]) for j in range(J)),
        episodes=episodes,
        imu_fallback=np.ascontiguousarray(flags["imu_fallback"].T),
        elm2_skipped=np.ascontiguousarray(flags["elm2_skipped"].T),
        dt_s=ctx.dt_s,
        params=ctx.params,
    )


def check_inputs(z_imu, z_cam, available, dt_s, joints, features, *, need_imu: bool = True):
    """Validated joint-major ``(z_imu, z_cam, available, dt_s, joints, features)``.

    ``z_cam`` is NaN where unavailable; ``available`` is False where ``z_cam`` is not finite;
    ``need_imu``: every joint needs a finite IMU sample. Messages name expected and actual.
    """
    dt = check_float(dt_s, "dt_s", lo=0.0, strict=True)
    arrs = []
    for name, v in (("z_imu", z_imu), ("z_cam", z_cam)):
        a = np.asarray(v)
        if not np.issubdtype(a.dtype, np.floating):
            raise InputError(f"expected {name} as a float array (T, J, 3), got dtype {a.dtype}")
        if a.ndim != 3 or a.shape[-1] != 3:
            raise InputError(f"expected {name} with shape (T, J, 3), got {a.shape}")
        if np.any(np.isinf(a)):
            raise InputError(f"expected {name} finite or NaN (missing), got ±inf")
        arrs.append(np.asarray(a, dtype=np.float64))
    zi, zc = arrs
    if zc.shape != zi.shape:
        raise InputError(
            f"expected z_cam with the shape of z_imu {zi.shape} (T, J, 3), got {zc.shape}"
        )
    T, J, _ = zi.shape
    if T < 1 or J < 1:
        raise InputError(
            f"expected at least one sample and one joint, got z_imu with shape {zi.shape}"
        )
    av = np.asarray(available)
    if av.dtype != bool:
        raise InputError(
            f"expected available as a bool array (T, J) = {(T, J)}, got dtype {av.dtype}"
        )
    if av.shape != (T, J):
        raise InputError(f"expected available with shape (T, J) = {(T, J)}, got {av.shape}")
    if need_imu:
        bad = ~np.any(np.all(np.isfinite(zi), axis=-1), axis=0)
        if np.any(bad):
            raise InputError(
                f"expected z_imu with at least one finite sample per joint, got none for joint(s) "
                f"{np.flatnonzero(bad).tolist()}"
            )
    av = av & np.all(np.isfinite(zc), axis=-1)
    if joints is None:
        names = tuple(f"joint_{j}" for j in range(J))
    else:
        if isinstance(joints, str):
            raise InputError(
                f"expected joints as a sequence of {J} names, got the string {joints!r}"
            )
        names = tuple(str(n) for n in joints)
        if len(names) != J:
            raise InputError(f"expected {J} joint names (z_imu.shape[1]), got {len(names)}")
    feats = None
    if features is not None:
        f = np.asarray(features)
        if not np.issubdtype(f.dtype, np.floating) or f.ndim != 3 or f.shape[:2] != (T, J):
            raise InputError(
                f"expected features as floats with shape (T, J, F) = ({T}, {J}, F), got {f.shape}"
            )
        feats = np.ascontiguousarray(f.transpose(1, 0, 2), dtype=np.float64)
    zc_masked = np.where(av[..., None], zc, np.nan)
    return (
        np.ascontiguousarray(zi.transpose(1, 0, 2)),
        np.ascontiguousarray(zc_masked.transpose(1, 0, 2)),
        np.ascontiguousarray(av.T),
        dt,
        names,
        feats,
    )
