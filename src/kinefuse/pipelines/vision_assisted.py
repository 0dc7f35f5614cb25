"""Vision-assisted IMU motion capture: the method registry and the public entry point.

:func:`vision_assisted` validates the arrays of all joints and runs one method of
:data:`METHODS` on them: paper B (Xu 2023; ELM/FIR + IMM + RTS per joint, SPEC §10.3:
:mod:`kinefuse.pipelines.paper_b`), its ELM/KF comparator, the baselines
(:mod:`kinefuse.pipelines.baselines`) and ``"kinefuse"``. :func:`register_method` is the
extension point for further methods; :func:`~kinefuse.pipelines.vision_assisted_from_recording`
(:mod:`kinefuse.pipelines.vision_recording`) builds the inputs from a recording.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.pipelines._outages import SOURCE_NONE, OutageEpisode
from kinefuse.pipelines.baselines import (
    GAPFILL_MAX_SAMPLES,
    OFFSET_HOLD_SAMPLES,
    camera_gapfill,
    camera_only,
    imu_only,
    offset_hold,
    offset_interp,
)
from kinefuse.pipelines.fusion_context import FusionContext, FusionResult, check_inputs, finish
from kinefuse.pipelines.kinefuse_fusion import kinefuse_fusion
from kinefuse.pipelines.paper_b import elm_fir, elm_kf
from kinefuse.pipelines.vision_params import VisionParams

__all__ = [
    "GAPFILL_MAX_SAMPLES",
    "METHODS",
    "OFFSET_HOLD_SAMPLES",
    "SOURCE_NONE",
    "FusionResult",
    "OutageEpisode",
    "VisionParams",
    "register_method",
    "vision_assisted",
]

#: Methods that read the camera only (no IMU sample needed).
_CAMERA_METHODS = ("camera-only", "camera-gapfill")


def _kinefuse(ctx: FusionContext) -> FusionResult:
    """``"kinefuse"``: :func:`kinefuse.pipelines.kinefuse_fusion.kinefuse_fusion` (this package's
    own method, not paper B's), offline or causal as ``ctx.causal``; ``ctx.features`` are its
    IMU features φ (default: chain features), or ``ctx.segment_rotations`` its segment-frame
    error model. ``params.fixed_lag`` is its ``lag`` when causal."""
    lag = int(ctx.params.fixed_lag) if ctx.causal else 0
    res = kinefuse_fusion(
        ctx.z_imu.transpose(1, 0, 2),
        ctx.z_cam.transpose(1, 0, 2),
        ctx.available.T,
        ctx.dt_s,
        causal=ctx.causal,
        lag=lag,
        features=None if ctx.features is None else ctx.features.transpose(1, 0, 2),
        segment_rotations=None
        if ctx.segment_rotations is None
        else np.swapaxes(ctx.segment_rotations, 0, 1),
    )
    return finish(
        ctx,
        res.position.transpose(1, 0, 2),
        res.cov.transpose(1, 0, 2, 3),
        res.source.T,
        causal=ctx.causal,
    )


#: Registry of fusion methods: name -> function ``(ctx) -> FusionResult``; ``ctx`` is a
#: :class:`~kinefuse.pipelines.fusion_context.FusionContext` (validated joint-major inputs
#: ``z_imu, z_cam (J, T, 3)``, ``available (J, T)``, ``dt_s``, ``params``, ``causal``,
#: ``joints``, ``method``, ``features`` and the two models ``model_imu``, ``model_cam``).
METHODS: dict[str, Callable[[FusionContext], FusionResult]] = {
    "elm-fir": elm_fir,
    "elm-kf": elm_kf,
    "imu-only": imu_only,
    "camera-only": camera_only,
    "kinefuse": _kinefuse,
    "offset-interp": offset_interp,
    "offset-hold": offset_hold,
    "camera-gapfill": camera_gapfill,
}


def register_method(name: str, function: Callable, *, replace: bool = False) -> None:
    """Add a fusion method to :data:`METHODS` (extension point, e.g. ``"kinefuse"``).

    Parameters
    ----------
    name : str
        Method name passed as ``vision_assisted(..., method=name)``.
    function : callable
        ``function(ctx) -> FusionResult``; see :data:`METHODS` for the fields of ``ctx``.
    replace : bool
        Allow replacing an existing method (default False: ValueError).
    """
    if not isinstance(name, str) or not name:
        raise InputError(f"expected name as a non-empty str, got {name!r}")
    if not callable(function):
        raise InputError(f"expected function as a callable, got {type(function).__name__}")
    if name in METHODS and not replace:
        raise InputError(f"method {name!r} already registered; pass replace=True to override")
    METHODS[name] = function


def vision_assisted(
    z_imu,
    z_cam,
    available,
    dt_s: float = 1 / 30,
    method: str = "elm-fir",
    *,
    joints: Sequence[str] | None = None,
    causal: bool = False,
    params: VisionParams | None = None,
    features=None,
    segment_rotations=None,
) -> FusionResult:
    r"""Vision-data-assisted IMU joint positions, paper B (Xu 2023) per joint, all joints at once.

    Parameters
    ----------
    z_imu : array_like of float, shape (T, J, 3)
        IMU-chain joint positions ``z^I`` (SPEC §2.2: ENU, chest-relative), m. NaN rows are
        missing samples (filters predict); every joint needs at least one finite row.
    z_cam : array_like of float, shape (T, J, 3)
        Camera joint positions ``z^V`` aligned to the same frame, m; values where
        ``available`` is False are ignored.
    available : array_like of bool, shape (T, J)
        Camera availability (Kinect ``Tracked`` and finite, SPEC §2.2); non-finite ``z_cam``
        rows count as unavailable.
    dt_s : float
        Sample interval, s (> 0; default 1/30, SPEC §12.2).
    method : str
        ``"elm-fir"`` (paper B), ``"elm-kf"`` (paper B's comparator: KFs with the same Q, R in
        place of FIR-1..3), ``"imu-only"`` (FIR-1 everywhere), ``"camera-only"`` (camera where
        available, linear interpolation across gaps, the last value held after the last camera
        sample, NaN before the first); the baselines ``"offset-interp"`` (offline),
        ``"offset-hold"`` (causal) and ``"camera-gapfill"`` (gaps <= 20 samples) and
        ``"kinefuse"`` (:data:`METHODS`); further methods via :func:`register_method`.
    joints : sequence of str, optional
        Joint names (default ``joint_0 ...``).
    causal : bool
        False (default): offline, the fused output is the RTS-smoothed IMM output over each
        maximal available segment. True: the IMM filtered output (``params.fixed_lag`` > 0:
        fixed-lag RTS, delayed by that many samples); no output reads later samples.
        ``"camera-only"`` is never causal.
    params : VisionParams, optional
        Settings (default ``VisionParams()``, SPEC §12.2).
    features : array_like of float, shape (T, J, F), optional
        Extra ELM-1 inputs appended to ``z_imu`` (e.g. segment orientations); default None
        (paper: position only). Rows with NaN are excluded from training and bridged output.
    segment_rotations : array_like of float, shape (T, J, S, 3, 3), optional
        ``R_frame_from_sensor`` of the segments that move each joint (all-zero padding), in the
        frame of ``z_imu``: ``"kinefuse"`` then models the chain error in the segments' frames
        (:func:`~kinefuse.pipelines.kinefuse_fusion.kinefuse_fusion`); the other methods do
        not read it.

    Returns
    -------
    FusionResult
        ``position (T, J, 3)``, ``cov (T, J, 3, 3)``, ``source (T, J)`` and diagnostics.

    Raises
    ------
    ValueError
        Shapes of ``z_imu``, ``z_cam``, ``available`` disagree or are not ``(T, J, 3)`` /
        ``(T, J)``; unknown method; ``dt_s <= 0``; a joint without any finite IMU sample.

    Notes
    -----
    ``"elm-fir"`` / ``"elm-kf"`` run :class:`kinefuse.pipelines.paper_b.PaperBCore` once over the
    series (its module docstring has the per-joint pipeline, SPEC §10.3, and the "Deviations
    from the paper"); offline, the fused samples are then the RTS over each maximal available
    segment. The streaming processor steps the same core frame by frame.
    """
    if params is None:
        params = VisionParams()
    elif not isinstance(params, VisionParams):
        raise InputError(f"expected params as a VisionParams, got {type(params).__name__}")
    if not isinstance(causal, (bool, np.bool_)):
        raise InputError(f"expected causal as a bool, got {causal!r}")
    if not isinstance(method, str) or method not in METHODS:
        raise InputError(f"unknown method {method!r}; expected one of {sorted(METHODS)}")
    zi, zc, av, dt, names, feats = check_inputs(
        z_imu, z_cam, available, dt_s, joints, features, need_imu=method not in _CAMERA_METHODS
    )
    rots = None
    if segment_rotations is not None:
        rots = np.asarray(segment_rotations)
        if rots.ndim != 5 or rots.shape[:2] != zi.shape[1::-1] or rots.shape[3:] != (3, 3):
            raise InputError(
                f"expected segment_rotations with shape (T, J, S, 3, 3) = "
                f"({zi.shape[1]}, {zi.shape[0]}, S, 3, 3), got {rots.shape}"
            )
        rots = np.swapaxes(rots, 0, 1)
    ctx = FusionContext(zi, zc, av, dt, params, bool(causal), names, method, feats, rots)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="ELM fitted on", category=UserWarning)
        return METHODS[method](ctx)
