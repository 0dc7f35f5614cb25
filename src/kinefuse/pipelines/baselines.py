"""Baselines of the vision-assisted comparison: what a skeptic would try before paper B.

``"imu-only"`` (FIR-1 everywhere), ``"camera-only"`` (camera, gaps interpolated),
``"offset-interp"`` (chain + interpolated camera-chain offset, offline), ``"offset-hold"``
(chain + the last seen offset, causal) and ``"camera-gapfill"`` (camera, short gaps
interpolated). Each is a method of :data:`kinefuse.pipelines.METHODS`: ``(ctx) -> FusionResult``.
"""

from __future__ import annotations

import numpy as np

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_CAMERA, SOURCE_IMU
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.pipelines._outages import SOURCE_NONE, available_runs, interpolate_gaps
from kinefuse.pipelines.fusion_context import (
    FusionContext,
    FusionResult,
    empty_output,
    finish,
    pos_cov,
)

__all__ = [
    "GAPFILL_MAX_SAMPLES",
    "OFFSET_HOLD_SAMPLES",
    "camera_gapfill",
    "camera_only",
    "imu_only",
    "offset_hold",
    "offset_interp",
]

#: Longest camera gap (samples) ``"camera-gapfill"`` bridges by linear interpolation: 20 frames
#: (0.67 s at 30 Hz). Pose2Sim's ``interp_gap_smaller_than`` does the same (its default is 10).
GAPFILL_MAX_SAMPLES = 20
#: Number of last camera-seen samples whose mean chain offset ``"offset-hold"`` holds.
OFFSET_HOLD_SAMPLES = 5


def imu_only(ctx: FusionContext) -> FusionResult:
    """``"imu-only"``: FIR-1 (UFIR over the IMU-chain positions) everywhere, source IMU."""
    flt = UFIRFilter(ctx.model_imu, horizon=ctx.params.horizon, init="batch")
    _, res = flt.filter(ctx.z_imu)
    pos = res.mean[..., 0::2]
    src = np.where(np.all(np.isfinite(pos), axis=-1), SOURCE_IMU, SOURCE_NONE).astype(np.int8)
    return finish(ctx, pos, pos_cov(res.cov), src, causal=True)


def _assemble(ctx: FusionContext, pos_jt, src_jt, rows_i, rows_v):
    """A baseline's ``(position, cov, source)`` outputs (:func:`empty_output`'s joint-major
    views of time-major arrays) from its positions ``(J, T, 3)`` and sources ``(J, T)``, with
    the nominal covariance ``R_I`` at ``rows_i`` (None: nowhere) and ``R_V`` at ``rows_v`` (which
    wins), NaN elsewhere. Each output is written once for all joints: a joint's rows of a
    time-major array are strided, and masked writes joint by joint went through the whole array
    once per joint."""
    pos, cov, src = empty_output(ctx)
    pos[...] = pos_jt
    src[...] = src_jt
    if rows_i is not None:
        np.copyto(cov, np.asarray(ctx.params.r_imu), where=rows_i[..., None, None])
    np.copyto(cov, np.asarray(ctx.params.r_cam), where=rows_v[..., None, None])
    return pos, cov, src


def _camera_interp(ctx: FusionContext, max_gap: int | None) -> FusionResult:
    """Camera where available, gaps linearly interpolated (at most ``max_gap`` samples between
    two camera samples; None: every gap, and the last value held after the last sample)."""
    J, T = ctx.shape
    p = np.full((J, T, 3), np.nan)
    src = np.where(ctx.available, SOURCE_CAMERA, SOURCE_NONE).astype(np.int8)
    keep = ctx.available.copy()
    for j in range(J):
        av = ctx.available[j]
        pj, filled = interpolate_gaps(ctx.z_cam[j], av)
        if max_gap is not None:
            g_s, g_e = available_runs(~av)
            for a, e in zip(g_s, g_e, strict=True):
                if a == 0 or e == T or e - a > max_gap:
                    filled[a:e] = False
        keep[j] |= filled
        p[j, keep[j]] = pj[keep[j]]
        src[j, filled] = SOURCE_BRIDGED
    pos, cov, src = _assemble(ctx, p, src, None, keep)
    # interpolation reads the next camera sample: not causal
    return finish(ctx, pos, cov, src, causal=False)


def camera_only(ctx: FusionContext) -> FusionResult:
    """``"camera-only"``: camera positions; linear interpolation across gaps, the last value
    held after the last camera sample, NaN before the first (not causal)."""
    return _camera_interp(ctx, None)


def _imu_rows(ctx: FusionContext) -> np.ndarray:
    """``(J, T)``: the chain measured the joint."""
    return np.all(np.isfinite(ctx.z_imu), axis=-1)


def offset_interp(ctx: FusionContext) -> FusionResult:
    """Baseline ``"offset-interp"`` (offline): IMU chain + interpolated camera-chain offset.

    Per joint, the offset ``d_t = z^V_t − z^I_t`` at the camera-seen samples is interpolated
    linearly across each outage (held constant before the first and after the last seen
    sample) and added to the chain: ``out_t = z^I_t + d̂_t``. Where the camera sees the joint
    the output is the camera itself (source CAMERA); elsewhere source BRIDGED (IMU where the
    camera never sees the joint: ``d̂ = 0``). Reads the camera after each outage: never causal.
    The simplest fusion a skeptic would try: it assumes the chain error is constant or drifts
    linearly through an outage. Covariance: ``R_V`` in view, ``R_I`` in outages (nominal).
    """
    J, T = ctx.shape
    t = np.arange(T)
    ok_i = _imu_rows(ctx)
    seen = ctx.available & ok_i
    off = np.zeros((J, T, 3))
    bridged = seen.any(axis=1)
    for j in np.flatnonzero(bridged):
        idx = np.flatnonzero(seen[j])
        d = ctx.z_cam[j, idx] - ctx.z_imu[j, idx]
        for k in range(3):
            off[j, :, k] = np.interp(t, idx, d[:, k])
    p = np.where(seen[..., None], ctx.z_cam, ctx.z_imu + off)
    chain_src = np.where(bridged, SOURCE_BRIDGED, SOURCE_IMU)[:, None]
    src = np.where(seen, SOURCE_CAMERA, np.where(ok_i, chain_src, SOURCE_NONE)).astype(np.int8)
    pos, cov, src = _assemble(ctx, p, src, ok_i, seen)
    return finish(ctx, pos, cov, src, causal=False)


def offset_hold(ctx: FusionContext) -> FusionResult:
    """Baseline ``"offset-hold"`` (causal): IMU chain + the last seen camera-chain offset.

    Where the camera sees the joint the output is the camera (source CAMERA). In an outage it
    is the chain plus the mean offset ``z^V − z^I`` of the last :data:`OFFSET_HOLD_SAMPLES` (5)
    camera-seen samples before it (source BRIDGED); before the first camera sample the chain
    alone (source IMU). Every output at t reads inputs up to t only. The simplest causal
    bridge a skeptic would try (it holds the chain error constant through the outage).
    """
    T = ctx.shape[1]
    n = OFFSET_HOLD_SAMPLES
    ok_i = _imu_rows(ctx)
    seen = ctx.available & ok_i
    p = ctx.z_imu.copy()
    src = np.where(ok_i, SOURCE_IMU, SOURCE_NONE).astype(np.int8)
    for j in np.flatnonzero(seen.any(axis=1)):
        idx = np.flatnonzero(seen[j])
        d = ctx.z_cam[j, idx] - ctx.z_imu[j, idx]
        c = np.concatenate([np.zeros((1, 3)), np.cumsum(d, axis=0)])
        m = np.arange(1, idx.size + 1)  # seen samples so far, at each seen sample
        lo = np.maximum(m - n, 0)
        mean = (c[m] - c[lo]) / (m - lo)[:, None]  # mean of the last <= n offsets
        last = np.searchsorted(idx, np.arange(T), side="right") - 1  # last seen <= t
        gap = ok_i[j] & ~seen[j] & (last >= 0)
        p[j, gap] = ctx.z_imu[j, gap] + mean[last[gap]]
        src[j, gap] = SOURCE_BRIDGED
    p[seen] = ctx.z_cam[seen]
    src[seen] = SOURCE_CAMERA
    pos, cov, src = _assemble(ctx, p, src, ok_i, seen)
    return finish(ctx, pos, cov, src, causal=True)


def camera_gapfill(ctx: FusionContext) -> FusionResult:
    """Baseline ``"camera-gapfill"`` (offline): camera only, short gaps interpolated.

    The camera positions where available (source CAMERA); gaps of at most
    :data:`GAPFILL_MAX_SAMPLES` (20) samples between two camera samples are filled by linear
    interpolation (source BRIDGED), as Pose2Sim's ``interp_gap_smaller_than`` does; longer gaps
    and the samples before the first / after the last camera sample have no estimate (NaN,
    :data:`SOURCE_NONE`), so its outage figures cover the short gaps only. The gap filling
    users already have with a camera-only pipeline; reads the next camera sample: not causal.
    """
    return _camera_interp(ctx, GAPFILL_MAX_SAMPLES)
