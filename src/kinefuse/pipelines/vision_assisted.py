"""Vision-assisted IMU motion capture, paper B (Xu 2023): ELM/FIR + IMM + RTS, per joint (SPEC §10.3).

:func:`vision_assisted` runs the complete per-joint pipeline on arrays for all joints at once;
:func:`vision_assisted_from_recording` builds its inputs from a
:class:`~kinefuse.io.recording.Recording` (IMU chain + aligned camera skeleton).

Methods are looked up in :data:`METHODS` (name -> function); :func:`register_method` is the
extension point for further methods (e.g. ``"kinefuse"``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from kinefuse.conventions import (
    SOURCE_BRIDGED,
    SOURCE_CAMERA,
    SOURCE_FUSED,
    SOURCE_IMU,
)
from kinefuse.exceptions import InputError
from kinefuse.filters import (
    IMM,
    KalmanFilter,
    fixed_lag_smooth,
    lag_posteriors,
    rts_smooth_segments,
)
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.learning import ELMRegressor
from kinefuse.models import LinearGaussianModel, constant_velocity
from kinefuse.pipelines._outages import (
    SOURCE_NONE,
    OutageEpisode,
    available_runs,
    find_episodes,
    interpolate_gaps,
    outage_intervals,
    segment_start,
    training_window,
)

__all__ = [
    "GAPFILL_MAX_SAMPLES",
    "METHODS",
    "OFFSET_HOLD_SAMPLES",
    "SOURCE_NONE",
    "FusionResult",
    "OutageEpisode",
    "RecordingFusion",
    "VisionParams",
    "register_method",
    "vision_assisted",
    "vision_assisted_from_recording",
]

_ELM2_INPUTS = ("elm1_out", "fir3_out")


def _cov_matrix(value, name: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"expected {name} as a number or a (3, 3) matrix, got {value!r}") from None
    if a.ndim == 0:
        if not (math.isfinite(float(a)) and float(a) > 0):
            raise InputError(f"expected {name} finite and > 0, got {value!r}")
        a = float(a) * np.eye(3)
    if a.shape != (3, 3):
        raise InputError(f"expected {name} as a scalar or shape (3, 3), got {a.shape}")
    if not np.all(np.isfinite(a)) or not np.allclose(a, a.T) or np.linalg.eigvalsh(a).min() <= 0:
        raise InputError(f"expected {name} symmetric positive definite, got {a.tolist()}")
    a = a.copy()
    a.setflags(write=False)
    return a


def _int(value, name: str, lo: int) -> int:
    if (
        isinstance(value, (bool, np.bool_))
        or not isinstance(value, (int, np.integer))
        or value < lo
    ):
        raise InputError(f"expected {name} as an int >= {lo}, got {value!r}")
    return int(value)


def _float(value, name: str, *, lo: float, strict: bool) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"expected {name} as a number, got {value!r}") from None
    if not math.isfinite(v) or v < lo or (strict and v == lo):
        raise InputError(
            f"expected {name} finite and {'>' if strict else '>='} {lo:g}, got {value!r}"
        )
    return v


@dataclass(frozen=True, eq=False)
class VisionParams:
    """Settings of the paper-B pipeline (defaults: SPEC §12.2).

    Parameters
    ----------
    q : float
        Process-noise scale of the constant-velocity model, (m/s)² per step (default 0.1,
        paper A wrist test 1): per axis ``Q = q [[dt²/4, dt/2], [dt/2, 1]]``.
    r_imu : float or array_like, shape (3, 3)
        ``R_I``, measurement-noise covariance of the IMU-chain positions, m² (default 0.01 I).
    r_cam : float or array_like, shape (3, 3)
        ``R_V``, of the camera positions and of FIR-3 (ELM-1 output), m² (default 1e-3 I).
    horizon : int
        UFIR horizon N, samples (default 20 at 30 Hz); also the recovery length.
    transition : array_like, shape (2, 2)
        IMM Markov matrix Γ, rows sum to 1 (default ``[[0.95, 0.05], [0.05, 0.95]]``).
    mu_floor : float
        IMM μ floor (default 1e-6).
    n_hidden : int
        ELM hidden nodes d (default 20).
    alpha : float
        ELM ridge λ (default 1e-6; 0 with ``solver="pinv"`` is paper-literal).
    linear_skip : bool
        ELM "lin + sigm" hidden layer (default False, paper-literal).
    train_window : int
        W, number of available samples before an outage onset used to train ELM-1 (default
        600 = 20 s at 30 Hz).
    elm2_input : {"elm1_out", "fir3_out"}
        ELM-2 input: ELM-1's output ``ẑ`` (paper B §3.1, default) or FIR-3's position
        (the abstract's wording).
    clip_factor : float
        ELM-2 correction clipped to a norm ``<= clip_factor ·`` its training RMS (default 3,
        SPEC §13).
    min_train : int or None
        Minimum number of training samples for ELM-1 (else IMU-only fallback) and ELM-2 (else
        skipped). Default ``max(10 d, 2 N)`` with d the number of hidden columns of the ELM
        (``n_hidden``, plus inputs + 1 with ``linear_skip``).
    fixed_lag : int
        Causal mode only: > 0 smooths the fused output with a fixed-lag RTS of this many
        samples (output delayed by ``fixed_lag``; SPEC §9 online option: 30). Default 0.
    seed : int
        Seed of the ELM hidden weights (ELM-1 uses ``seed``, ELM-2 ``seed + 1``).
    """

    q: float = 0.1
    r_imu: object = 0.01
    r_cam: object = 1e-3
    horizon: int = 20
    transition: object = ((0.95, 0.05), (0.05, 0.95))
    mu_floor: float = 1e-6
    n_hidden: int = 20
    alpha: float = 1e-6
    linear_skip: bool = False
    train_window: int = 600
    elm2_input: str = "elm1_out"
    clip_factor: float = 3.0
    min_train: int | None = None
    fixed_lag: int = 0
    seed: int = 0

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "q", _float(self.q, "q", lo=0.0, strict=False))
        set_(self, "r_imu", _cov_matrix(self.r_imu, "r_imu"))
        set_(self, "r_cam", _cov_matrix(self.r_cam, "r_cam"))
        set_(self, "horizon", _int(self.horizon, "horizon", 7))
        G = np.asarray(self.transition, dtype=float)
        if G.shape != (2, 2) or not np.all(np.isfinite(G)) or np.any(G < 0):
            raise InputError(
                f"expected transition as a (2, 2) non-negative matrix, got {G.tolist()}"
            )
        if not np.allclose(G.sum(axis=1), 1.0):
            raise InputError(f"expected transition rows summing to 1, got row sums {G.sum(axis=1)}")
        G = G.copy()
        G.setflags(write=False)
        set_(self, "transition", G)
        set_(self, "mu_floor", _float(self.mu_floor, "mu_floor", lo=0.0, strict=False))
        if self.mu_floor >= 0.5:
            raise InputError(f"expected mu_floor < 0.5, got {self.mu_floor!r}")
        set_(self, "n_hidden", _int(self.n_hidden, "n_hidden", 1))
        set_(self, "alpha", _float(self.alpha, "alpha", lo=0.0, strict=False))
        if not isinstance(self.linear_skip, (bool, np.bool_)):
            raise InputError(f"expected linear_skip as a bool, got {self.linear_skip!r}")
        set_(self, "train_window", _int(self.train_window, "train_window", 2))
        if self.elm2_input not in _ELM2_INPUTS:
            raise InputError(f"expected elm2_input in {_ELM2_INPUTS}, got {self.elm2_input!r}")
        set_(self, "clip_factor", _float(self.clip_factor, "clip_factor", lo=0.0, strict=True))
        if self.min_train is not None:
            set_(self, "min_train", _int(self.min_train, "min_train", 2))
        set_(self, "fixed_lag", _int(self.fixed_lag, "fixed_lag", 0))
        set_(self, "seed", _int(self.seed, "seed", 0))

    def min_samples(self, n_features: int = 3) -> int:
        """Minimum training samples: ``min_train`` or ``max(10 d, 2 N)`` (SPEC §10.2)."""
        if self.min_train is not None:
            return self.min_train
        d = self.n_hidden + (n_features + 1 if self.linear_skip else 0)
        return max(10 * d, 2 * self.horizon)

    def models(self, dt_s: float) -> tuple[LinearGaussianModel, LinearGaussianModel]:
        """``(model_imu, model_cam)``: constant-velocity models with ``R_I`` and ``R_V``."""
        return (
            constant_velocity(dt_s, self.q, self.r_imu),
            constant_velocity(dt_s, self.q, self.r_cam),
        )


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
class _Context:
    """Validated inputs, joint-major: ``z_imu, z_cam (J, T, 3)`` (z_cam NaN where unavailable)."""

    z_imu: np.ndarray
    z_cam: np.ndarray
    available: np.ndarray
    dt_s: float
    params: VisionParams
    causal: bool
    joints: tuple[str, ...]
    method: str
    features: np.ndarray | None
    model_imu: LinearGaussianModel = field(init=False)
    model_cam: LinearGaussianModel = field(init=False)

    def __post_init__(self):
        mi, mc = self.params.models(self.dt_s)
        object.__setattr__(self, "model_imu", mi)
        object.__setattr__(self, "model_cam", mc)

    @property
    def shape(self) -> tuple[int, int]:
        return self.z_imu.shape[0], self.z_imu.shape[1]


def _pos_cov(cov: np.ndarray) -> np.ndarray:
    """Position block ``H P Hᵀ`` of interleaved ``[x, vx, y, vy, z, vz]`` covariances."""
    return cov[..., 0::2, 0::2]


def _run_filter(kind: str, model: LinearGaussianModel, z: np.ndarray, horizon: int):
    """FIR (UFIR, batch init) or KF over ``z (B, L, 3)``; rows of all-NaN series stay NaN."""
    B, L, _ = z.shape
    mean = np.full((B, L, 6), np.nan)
    cov = np.full((B, L, 6, 6), np.nan)
    has = np.any(np.all(np.isfinite(z), axis=-1), axis=-1)
    if np.any(has):
        flt = (
            UFIRFilter(model, horizon=horizon, init="batch")
            if kind == "fir"
            else KalmanFilter(model)
        )
        _, res = flt.filter(z[has])
        mean[has] = res.mean
        cov[has] = res.cov
    return mean, cov


def _output(ctx: _Context):
    J, T = ctx.shape
    return (
        np.full((J, T, 3), np.nan),
        np.full((J, T, 3, 3), np.nan),
        np.full((J, T), SOURCE_NONE, dtype=np.int8),
    )


def _finish(
    ctx: _Context, pos, cov, src, *, causal: bool, mu=None, episodes=None, **flags
) -> FusionResult:
    """Assemble a time-major :class:`FusionResult` from joint-major arrays."""
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


# ------------------------------------------------------------------------------------ methods
def _imu_only(ctx: _Context) -> FusionResult:
    """FIR-1 (UFIR over the IMU-chain positions) everywhere, source IMU."""
    p = ctx.params
    mean, cov = _run_filter("fir", ctx.model_imu, ctx.z_imu, p.horizon)
    J, T = ctx.shape
    pos = mean[..., 0::2]
    src = np.where(np.all(np.isfinite(pos), axis=-1), SOURCE_IMU, SOURCE_NONE).astype(np.int8)
    return _finish(ctx, pos, _pos_cov(cov), src, causal=True)


def _camera_only(ctx: _Context) -> FusionResult:
    """Camera positions; linear interpolation across gaps, last value held, NaN before the first."""
    pos, cov, src = _output(ctx)
    J, _ = ctx.shape
    R_V = np.asarray(ctx.params.r_cam)
    for j in range(J):
        av = ctx.available[j]
        pj, filled = interpolate_gaps(ctx.z_cam[j], av)
        pos[j] = pj
        src[j, av] = SOURCE_CAMERA
        src[j, filled] = SOURCE_BRIDGED
        cov[j, av | filled] = R_V
    # interpolation reads the next camera sample: not causal
    return _finish(ctx, pos, cov, src, causal=False)


#: Longest camera gap (samples) ``"camera-gapfill"`` bridges by linear interpolation: 20 frames
#: (0.67 s at 30 Hz). Pose2Sim's ``interp_gap_smaller_than`` does the same (its default is 10).
GAPFILL_MAX_SAMPLES = 20
#: Number of last camera-seen samples whose mean chain offset ``"offset-hold"`` holds.
OFFSET_HOLD_SAMPLES = 5


def _imu_rows(ctx: _Context, j: int) -> np.ndarray:
    return np.all(np.isfinite(ctx.z_imu[j]), axis=-1)


def _offset_interp(ctx: _Context) -> FusionResult:
    """Baseline ``"offset-interp"`` (offline): IMU chain + interpolated camera-chain offset.

    Per joint, the offset ``d_t = z^V_t − z^I_t`` at the camera-seen samples is interpolated
    linearly across each outage (held constant before the first and after the last seen
    sample) and added to the chain: ``out_t = z^I_t + d̂_t``. Where the camera sees the joint
    the output is the camera itself (source CAMERA); elsewhere source BRIDGED (IMU where the
    camera never sees the joint: ``d̂ = 0``). Reads the camera after each outage: never causal.
    The simplest fusion a skeptic would try: it assumes the chain error is constant or drifts
    linearly through an outage. Covariance: ``R_V`` in view, ``R_I`` in outages (nominal).
    """
    pos, cov, src = _output(ctx)
    J, T = ctx.shape
    t = np.arange(T)
    R_V, R_I = np.asarray(ctx.params.r_cam), np.asarray(ctx.params.r_imu)
    for j in range(J):
        ok_i = _imu_rows(ctx, j)
        seen = ctx.available[j] & ok_i
        idx = np.flatnonzero(seen)
        off = np.zeros((T, 3))
        if idx.size:
            d = ctx.z_cam[j, idx] - ctx.z_imu[j, idx]
            for k in range(3):
                off[:, k] = np.interp(t, idx, d[:, k])
        pos[j] = ctx.z_imu[j] + off
        pos[j, seen] = ctx.z_cam[j, seen]
        src[j, ok_i] = SOURCE_BRIDGED if idx.size else SOURCE_IMU
        src[j, seen] = SOURCE_CAMERA
        cov[j, ok_i] = R_I
        cov[j, seen] = R_V
    return _finish(ctx, pos, cov, src, causal=False)


def _offset_hold(ctx: _Context) -> FusionResult:
    """Baseline ``"offset-hold"`` (causal): IMU chain + the last seen camera-chain offset.

    Where the camera sees the joint the output is the camera (source CAMERA). In an outage it
    is the chain plus the mean offset ``z^V − z^I`` of the last :data:`OFFSET_HOLD_SAMPLES` (5)
    camera-seen samples before it (source BRIDGED); before the first camera sample the chain
    alone (source IMU). Every output at t reads inputs up to t only. The simplest causal
    bridge a skeptic would try (it holds the chain error constant through the outage).
    """
    pos, cov, src = _output(ctx)
    J, T = ctx.shape
    R_V, R_I = np.asarray(ctx.params.r_cam), np.asarray(ctx.params.r_imu)
    n = OFFSET_HOLD_SAMPLES
    for j in range(J):
        ok_i = _imu_rows(ctx, j)
        seen = ctx.available[j] & ok_i
        idx = np.flatnonzero(seen)
        pos[j] = ctx.z_imu[j]
        src[j, ok_i] = SOURCE_IMU
        cov[j, ok_i] = R_I
        if idx.size:
            d = ctx.z_cam[j, idx] - ctx.z_imu[j, idx]
            c = np.concatenate([np.zeros((1, 3)), np.cumsum(d, axis=0)])
            m = np.arange(1, idx.size + 1)  # seen samples so far, at each seen sample
            lo = np.maximum(m - n, 0)
            mean = (c[m] - c[lo]) / (m - lo)[:, None]  # mean of the last <= n offsets
            last = np.searchsorted(idx, np.arange(T), side="right") - 1  # last seen <= t
            gap = ok_i & ~seen & (last >= 0)
            pos[j, gap] = ctx.z_imu[j, gap] + mean[last[gap]]
            src[j, gap] = SOURCE_BRIDGED
        pos[j, seen] = ctx.z_cam[j, seen]
        src[j, seen] = SOURCE_CAMERA
        cov[j, seen] = R_V
    return _finish(ctx, pos, cov, src, causal=True)


def _camera_gapfill(ctx: _Context) -> FusionResult:
    """Baseline ``"camera-gapfill"`` (offline): camera only, short gaps interpolated.

    The camera positions where available (source CAMERA); gaps of at most
    :data:`GAPFILL_MAX_SAMPLES` (20) samples between two camera samples are filled by linear
    interpolation (source BRIDGED), as Pose2Sim's ``interp_gap_smaller_than`` does; longer gaps
    and the samples before the first / after the last camera sample have no estimate (NaN,
    :data:`SOURCE_NONE`), so its outage figures cover the short gaps only. The gap filling
    users already have with a camera-only pipeline; reads the next camera sample: not causal.
    """
    pos, cov, src = _output(ctx)
    J, T = ctx.shape
    R_V = np.asarray(ctx.params.r_cam)
    for j in range(J):
        av = ctx.available[j]
        pj, filled = interpolate_gaps(ctx.z_cam[j], av)
        g_s, g_e = available_runs(~av)
        for a, e in zip(g_s, g_e, strict=True):
            if a == 0 or e == T or e - a > GAPFILL_MAX_SAMPLES:
                filled[a:e] = False
        keep = av | filled
        pos[j, keep] = pj[keep]
        src[j, av] = SOURCE_CAMERA
        src[j, filled] = SOURCE_BRIDGED
        cov[j, keep] = R_V
    return _finish(ctx, pos, cov, src, causal=False)


def _elm_bridge(ctx: _Context, kind: str) -> FusionResult:
    """Paper B pipeline with FIR-1..3 = UFIR (``kind="fir"``) or KF (``kind="kf"``)."""
    p = ctx.params
    J, T = ctx.shape
    N = p.horizon
    mi, mc = ctx.model_imu, ctx.model_cam
    # FIR-1 / FIR-2 (batch over joints); FIR-2 keeps its time-indexed horizon through outages
    m1, P1 = _run_filter(kind, mi, ctx.z_imu, N)
    m2, P2 = _run_filter(kind, mc, ctx.z_cam, N)
    # IMM, reading R2: mixing from the FIR posteriors at t-1, one batch call
    z = np.stack([ctx.z_imu, ctx.z_cam], axis=-2)  # (J, T, 2, 3)
    prev = lag_posteriors(np.stack([m1, m2], axis=-2), np.stack([P1, P2], axis=-3))
    imm = IMM(mi, mc, transition=p.transition, mu_floor=p.mu_floor)
    _, r_imm = imm.filter(z, prev=prev)
    avail = ctx.available
    rts = rts_smooth_segments(
        mi, r_imm, avail
    )  # offline output and ELM-2 targets (closed segments)
    if not ctx.causal:
        base = rts
    elif p.fixed_lag > 0:
        base = fixed_lag_smooth(mi, r_imm, p.fixed_lag, mask=avail)
    else:
        base = r_imm
    pos, cov, src = _output(ctx)
    pos[avail] = base.position[avail]
    cov[avail] = _pos_cov(base.cov)[avail]
    src[avail] = SOURCE_FUSED
    mu = np.where(avail[..., None], r_imm.mu, np.nan)

    fir1_pos, fir1_cov = m1[..., 0::2], _pos_cov(P1)
    imu_fb = np.zeros((J, T), dtype=bool)
    e2_skip = np.zeros((J, T), dtype=bool)
    feats = ctx.features
    n_feat = 3 + (0 if feats is None else feats.shape[-1])
    n_min = p.min_samples(n_feat)
    episodes = []
    for j in range(J):
        av = avail[j]
        x_in = ctx.z_imu[j] if feats is None else np.concatenate([ctx.z_imu[j], feats[j]], axis=-1)
        in_ok = np.all(np.isfinite(x_in), axis=-1)
        eps_j = []
        for a, e, r, rec in find_episodes(av, N):
            win = training_window(av, a, p.train_window)
            win = win[in_ok[win]]
            if win.size < n_min:
                pos[j, a:e] = fir1_pos[j, a:e]
                cov[j, a:e] = fir1_cov[j, a:e]
                src[j, a:e] = np.where(
                    np.all(np.isfinite(fir1_pos[j, a:e]), -1), SOURCE_IMU, SOURCE_NONE
                )
                imu_fb[j, a:e] = True
                eps_j.append(
                    OutageEpisode(a, e, r, rec, "imu-fallback", -1, int(win.size), 0, True)
                )
                continue
            elm1 = ELMRegressor(
                p.n_hidden, alpha=p.alpha, linear_skip=p.linear_skip, random_state=p.seed
            )
            elm1.fit(x_in[win], ctx.z_cam[j, win])
            w0 = int(win[0])
            zhat = np.full((e - w0, 3), np.nan)
            ok = in_ok[w0:e]
            zhat[ok] = elm1.predict(x_in[w0:e][ok])
            m3, P3 = _run_filter(kind, mc, zhat[None], N)
            p3, c3 = m3[0, :, 0::2], _pos_cov(P3[0])
            s = segment_start(av, a)
            tr = win[win >= s]
            tr = tr[
                np.all(np.isfinite(rts.position[j, tr]), axis=-1)
                & np.all(np.isfinite(p3[tr - w0]), -1)
            ]
            out = p3[a - w0 :]
            out_cov = c3[a - w0 :].copy()
            skipped = tr.size < n_min
            if skipped:
                resid = ctx.z_cam[j, win] - elm1.predict(x_in[win])
                out_cov += np.diag(resid.var(axis=0))
            else:
                e2_in = zhat if p.elm2_input == "elm1_out" else p3
                target = rts.position[j, tr] - p3[tr - w0]
                elm2 = ELMRegressor(
                    p.n_hidden, alpha=p.alpha, linear_skip=p.linear_skip, random_state=p.seed + 1
                )
                elm2.fit(e2_in[tr - w0], target)
                resid = target - elm2.predict(e2_in[tr - w0])
                x2 = e2_in[a - w0 :]
                corr = np.zeros_like(out)
                okc = np.all(np.isfinite(x2), axis=-1)
                corr[okc] = elm2.predict(x2[okc], clip_factor=p.clip_factor)
                out = out + corr
                out_cov += np.diag(resid.var(axis=0))
            pos[j, a:e] = out
            cov[j, a:e] = out_cov
            src[j, a:e] = np.where(np.all(np.isfinite(out), -1), SOURCE_BRIDGED, SOURCE_NONE)
            e2_skip[j, a:e] = skipped
            eps_j.append(
                OutageEpisode(
                    a, e, r, rec, "bridged", w0, int(win.size), int(tr.size), bool(skipped)
                )
            )
        episodes.append(tuple(eps_j))
    cov[~np.all(np.isfinite(pos), axis=-1)] = np.nan
    return _finish(
        ctx,
        pos,
        cov,
        src,
        causal=ctx.causal and p.fixed_lag == 0,
        mu=mu,
        imu_fallback=imu_fb,
        elm2_skipped=e2_skip,
        episodes=tuple(episodes),
    )


def _elm_fir(ctx: _Context) -> FusionResult:
    """Paper B's ELM/FIR: UFIR for FIR-1, FIR-2 and FIR-3."""
    return _elm_bridge(ctx, "fir")


def _elm_kf(ctx: _Context) -> FusionResult:
    """Paper B's comparator ELM/KF: the same pipeline with Kalman filters (same Q, R)."""
    return _elm_bridge(ctx, "kf")


def _kinefuse(ctx: _Context) -> FusionResult:
    """``"kinefuse"``: :func:`kinefuse.pipelines.kinefuse_fusion.kinefuse_fusion` (this package's
    own method, not paper B's), offline or causal as ``ctx.causal``; ``ctx.features`` are its
    IMU features φ (default: chain features). ``params.fixed_lag`` is its ``lag`` when causal."""
    from kinefuse.pipelines.kinefuse_fusion import kinefuse_fusion  # lazy: avoids an import cycle

    lag = int(ctx.params.fixed_lag) if ctx.causal else 0
    res = kinefuse_fusion(
        ctx.z_imu.transpose(1, 0, 2),
        ctx.z_cam.transpose(1, 0, 2),
        ctx.available.T,
        ctx.dt_s,
        causal=ctx.causal,
        lag=lag,
        features=None if ctx.features is None else ctx.features.transpose(1, 0, 2),
    )
    return _finish(
        ctx,
        res.position.transpose(1, 0, 2),
        res.cov.transpose(1, 0, 2, 3),
        res.source.T,
        causal=ctx.causal,
    )


#: Registry of fusion methods: name -> function ``(ctx) -> FusionResult``. ``ctx`` carries the
#: validated joint-major inputs ``z_imu, z_cam (J, T, 3)`` (z_cam NaN where unavailable),
#: ``available (J, T)``, ``dt_s``, ``params``, ``causal``, ``joints``, ``method``, ``features``
#: and the two constant-velocity models ``model_imu``, ``model_cam``.
METHODS: dict[str, Callable[[_Context], FusionResult]] = {
    "elm-fir": _elm_fir,
    "elm-kf": _elm_kf,
    "imu-only": _imu_only,
    "camera-only": _camera_only,
    "kinefuse": _kinefuse,
    "offset-interp": _offset_interp,
    "offset-hold": _offset_hold,
    "camera-gapfill": _camera_gapfill,
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


# ------------------------------------------------------------------------------------ public API
def _check_inputs(z_imu, z_cam, available, dt_s, method, joints, features):
    if not isinstance(method, str) or method not in METHODS:
        raise InputError(f"unknown method {method!r}; expected one of {sorted(METHODS)}")
    dt = _float(dt_s, "dt_s", lo=0.0, strict=True)
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
    if method not in ("camera-only", "camera-gapfill"):
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
    Per joint (SPEC §10.3), vectorised over joints and time (Python loops only over joints ×
    outage episodes)::

        FIR-1 = UFIR(R_I) over z^I ; FIR-2 = UFIR(R_V) over z^V (NaN in outages: predict,
                keeping its time-indexed horizon)
        IMM (reading R2, SPEC §8.3): z = (z^I, z^V), mixing from (FIR-1, FIR-2) posteriors at t−1
        camera available:  out = RTS(IMM) over the maximal available segment (offline)
                           or IMM filtered (causal)            source FUSED
        episode [a, e) (outage onset a; e = N samples after the camera is back for N
                consecutive samples; closer outages merge):
            win = last W available samples before a
            |win| < n_min:  out = FIR-1                          source IMU, imu_fallback
            else: ELM-1.fit(z^I[win], z^V[win]) ; ẑ_t = ELM-1(z^I_t), t ∈ [win[0], e)
                  FIR-3 = fresh UFIR(R_V) over ẑ on [win[0], e)
                  ELM-2.fit(ẑ (or FIR-3), RTS − FIR-3) on (segment before a) ∩ win
                  out_t = FIR-3_t + clip(ELM-2(ẑ_t), 3·RMS)        source BRIDGED
                  cov_t = FIR-3 cov_t + diag(var of ELM-2's training residual)
                  (ELM-2 skipped if too few samples: out = FIR-3, cov adds ELM-1's residual
                  variance, elm2_skipped)

    An outage at the very start has no training data: IMU-only output, flagged. A joint that
    is never available is IMU-only throughout.

    Deviations from the paper
    -------------------------
    * 3-D constant-velocity model (paper B's is 2-D but reports z; SPEC §3.3).
    * Inputs are ENU chest-relative IMU-chain positions and camera positions rotated into the
      IMU world frame (camera relative to its spine-shoulder joint, Kabsch alignment); the paper
      mentions no alignment (SPEC §2.2-2).
    * The IMM uses separate R_I and R_V (paper: one R); FIR posteriors enter the mixing
      (reading R2, SPEC §8.2).
    * Causal ELM training window: the last W available samples before the onset, ELM-2 on
      the RTS of the segment up to ``a − 1`` only; retrained at each episode onset (SPEC §10.2,
      unspecified by the paper).
    * Recovery rule: the prediction-stage output continues until the camera has been available
      for N consecutive samples (SPEC §10.3 [J]); FIR-2 and the IMM keep running meanwhile.
    * ELM-2's correction is clipped to 3× its training RMS (SPEC §13); with too little data
      ELM-2 is skipped or the IMU-only output is used (SPEC §10.2, §13), both flagged.
    """
    if params is None:
        params = VisionParams()
    elif not isinstance(params, VisionParams):
        raise InputError(f"expected params as a VisionParams, got {type(params).__name__}")
    if not isinstance(causal, (bool, np.bool_)):
        raise InputError(f"expected causal as a bool, got {causal!r}")
    zi, zc, av, dt, names, feats = _check_inputs(
        z_imu, z_cam, available, dt_s, method, joints, features
    )
    ctx = _Context(zi, zc, av, dt, params, bool(causal), names, method, feats)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="ELM fitted on", category=UserWarning)
        return METHODS[method](ctx)


# ------------------------------------------------------------------------------------ recordings
@dataclass(frozen=True, eq=False)
class RecordingFusion:
    """Output of :func:`vision_assisted_from_recording`.

    Attributes
    ----------
    result : FusionResult
        Fused positions, ENU chest-relative (origin = upper chest / spine_shoulder), m.
    t_s : ndarray, shape (T,)
        Camera timestamps, s.
    z_imu, z_cam : ndarray, shape (T, J, 3)
        The pipeline inputs (IMU chain; aligned camera, NaN where unavailable), m.
    available : ndarray of bool, shape (T, J)
    reference : ndarray, shape (T, J, 3) or None
        Reference joints at the camera timestamps, relative to the reference's
        ``spine_shoulder``, in the reference frame (ENU), m; None without a reference.
    R_world_from_camera : ndarray, shape (3, 3)
        Camera-to-IMU-world rotation used.
    skeleton : Skeleton
        The chain used for ``z_imu`` (lengths, axes, offsets).
    """

    result: FusionResult
    t_s: np.ndarray
    z_imu: np.ndarray
    z_cam: np.ndarray
    available: np.ndarray
    reference: np.ndarray | None
    R_world_from_camera: np.ndarray
    skeleton: object


def vision_assisted_from_recording(
    recording,
    skeleton=None,
    calibration=None,
    method: str = "elm-fir",
    rate_hz: float = 30.0,
    *,
    joints: Sequence[str] | None = None,
    calibration_window_s: tuple[float, float] | None = None,
    causal: bool = False,
    params: VisionParams | None = None,
) -> RecordingFusion:
    """Run :func:`vision_assisted` on a recording with IMU orientations and a camera skeleton.

    Parameters
    ----------
    recording : Recording
        IMU streams with ``q_world_from_sensor`` for ``chest`` and the eight limb segments of
        :func:`kinefuse.kinematics.full_body`; ``vision`` with ``spine_shoulder`` and the
        output joints; optional ``reference``.
    skeleton : Skeleton, optional
        Full-body chain (chest origin). Default: :func:`~kinefuse.kinematics.full_body` with
        lengths = median camera bone lengths and shoulder/hip offsets from the camera, both over
        the calibration window, axes ``e2`` (or the calibration's).
    calibration : Calibration, optional
        Segment axes / lengths (applied to the skeleton) and ``R_world_from_camera`` if it has
        one; otherwise the rotation is estimated here.
    method : str
        As in :func:`vision_assisted`.
    rate_hz : float
        Filter rate, Hz (default 30, SPEC §12.2); the camera timestamps are used and must
        have this median rate within 5 %.
    joints : sequence of str, optional
        Output joints (default :data:`kinefuse.conventions.PAPER_B_JOINTS`).
    calibration_window_s : (float, float), optional
        ``(start, stop)`` s of the alignment window (default: the first 10 s of camera data).
    causal, params
        As in :func:`vision_assisted`.

    Returns
    -------
    RecordingFusion

    Notes
    -----
    1. IMU orientations are SLERP-resampled to the camera timestamps (SPEC §12.2).
    2. Camera alignment [J, SPEC §2.2]: ``R_world_from_camera`` by Kabsch between the camera
       segment directions ``unit(p_distal − p_proximal)`` and the IMU segment directions
       ``R_i a_i`` over the window, pooled over the eight segments (no offsets or lengths
       needed). The camera joints are taken relative to its ``spine_shoulder``:
       ``z^V = R (p_cam − p_cam,spine_shoulder)``.
    3. Default offsets: window mean of ``R_chestᵀ R (p_cam,joint − p_cam,spine_shoulder)`` for
       the shoulders and hips; default lengths: window median camera bone lengths.
    4. ``z^I`` = forward kinematics from the chest origin (0) in the IMU world (ENU).

    Deviations from the paper: paper B computes positions in the chest IMU frame and never
    aligns the camera (SPEC §2.2-2); here both live in ENU, chest-relative.
    """
    from kinefuse.conventions import PAPER_B_JOINTS
    from kinefuse.io.recording import Recording
    from kinefuse.kinematics import forward_kinematics, full_body, kabsch_rotation
    from kinefuse.kinematics.forward import as_rotation_matrices
    from kinefuse.orientation import slerp_resample

    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    cam = recording.vision
    if cam is None:
        raise InputError("expected a recording with a vision (camera) stream, got vision=None")
    rate = _float(rate_hz, "rate_hz", lo=0.0, strict=True)
    t = cam.t_s
    if t.size < 2:
        raise InputError(f"expected at least 2 camera samples, got {t.size}")
    cam_rate = 1.0 / float(np.median(np.diff(t)))
    if abs(cam_rate - rate) > 0.05 * rate:
        raise InputError(
            f"expected camera timestamps at rate_hz = {rate:g} Hz (±5 %), got {cam_rate:.3g} Hz"
        )
    out_joints = tuple(PAPER_B_JOINTS if joints is None else joints)
    sk = skeleton
    if sk is None:
        sk = full_body(height_m=1.75)  # topology only; lengths and offsets replaced below
    if calibration is not None:
        sk = calibration.apply(sk)
    segs = list(sk.segments) + ([sk.root_segment] if sk.root_segment else [])
    R = {}
    for s in segs:
        if s not in recording.imu or recording.imu[s].q_world_from_sensor is None:
            raise InputError(
                f"expected an IMU orientation for segment {s!r}, got IMUs {sorted(recording.imu)}"
            )
        st = recording.imu[s]
        R[s] = as_rotation_matrices(slerp_resample(st.t_s, st.q_world_from_sensor, t), f"IMU {s!r}")
    need = {"spine_shoulder", *out_joints, *sk.proximal, *sk.distal}
    lack = sorted(need - set(cam.joints))
    if lack:
        raise InputError(f"expected joints {lack} in the vision stream, got {list(cam.joints)}")
    lo, hi = (t[0], t[0] + 10.0) if calibration_window_s is None else calibration_window_s
    win = (t >= lo) & (t < hi)
    # camera alignment on segment directions (Kabsch, rotation only)
    Rc = None if calibration is None else calibration.R_world_from_camera
    if Rc is None:
        P_, Q_ = [], []
        for i, s in enumerate(sk.segments):
            d = cam.position(sk.distal[i])[win] - cam.position(sk.proximal[i])[win]
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            P_.append(d)
            Q_.append(R[s][win] @ sk.axes[i])
        Rc = kabsch_rotation(np.concatenate(P_), np.concatenate(Q_))
    Rc = np.asarray(Rc, dtype=float)
    p0 = cam.position("spine_shoulder")
    rel = {j: (cam.position(j) - p0) @ Rc.T for j in need}
    if skeleton is None:
        R0 = R[sk.root_segment][win]
        offs = {}
        for j in sk.offsets_m:
            v = np.einsum("kji,kj->ki", R0, rel[j][win])
            offs[j] = np.nanmean(v, axis=0)
        lens = {}
        for i, s in enumerate(sk.segments):
            if calibration is not None and s in calibration.lengths_m:
                continue
            d = np.linalg.norm(rel[sk.distal[i]][win] - rel[sk.proximal[i]][win], axis=-1)
            lens[s] = float(np.nanmedian(d))
        bad = [k for k, v in {**offs, **lens}.items() if not np.all(np.isfinite(v))]
        if bad:
            raise InputError(
                f"no camera samples in the calibration window {lo:g}-{hi:g} s to estimate {bad}; "
                "pass skeleton= or calibration_window_s="
            )
        sk = sk.with_offsets(offs).with_lengths(lens) if lens else sk.with_offsets(offs)
    pos = forward_kinematics(sk, R, np.zeros((t.size, 3)))
    missing = [j for j in out_joints if j not in pos]
    if missing:
        raise InputError(
            f"joints {missing} are not computed by the skeleton; it gives {sorted(pos)}"
        )
    z_imu = np.stack([pos[j] for j in out_joints], axis=1)
    z_cam = np.stack([rel[j] for j in out_joints], axis=1)
    av = np.all(np.isfinite(z_cam), axis=-1)
    z_cam = np.where(av[..., None], z_cam, np.nan)
    res = vision_assisted(
        z_imu, z_cam, av, 1.0 / rate, method, joints=out_joints, causal=causal, params=params
    )
    ref = None
    if recording.reference is not None and all(
        j in recording.reference.joints for j in ("spine_shoulder", *out_joints)
    ):
        rs = recording.reference
        r_t = rs.t_s
        cols = []
        for j in ("spine_shoulder", *out_joints):
            pj = rs.position(j)
            cols.append(
                np.stack(
                    [np.interp(t, r_t, pj[:, k], left=np.nan, right=np.nan) for k in range(3)], -1
                )
            )
        ref = np.stack(cols[1:], axis=1) - cols[0][:, None, :]
    return RecordingFusion(res, t, z_imu, z_cam, av, ref, Rc, sk)
