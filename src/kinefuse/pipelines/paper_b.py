"""Paper B (Xu 2023) written once: the step-wise ELM/FIR (or ELM/KF) core, batch and online.

:class:`PaperBCore` is the configuration (frozen: the filters, the settings); :meth:`~PaperBCore.init`
gives a :class:`PaperBState` for J joints and :meth:`~PaperBCore.advance` runs the causal pipeline
over a block of L frames, updating that state. The batch pipeline
(:func:`~kinefuse.pipelines.vision_assisted` ``"elm-fir"`` / ``"elm-kf"``) advances once over
the whole series and then smooths the fused samples if offline; the streaming processor
(:class:`kinefuse.streaming.paper_b.VisionAssistedProcessor`) advances one frame at a time. Both
run this code, so stream == causal batch is a consequence (positions to rounding: the ELM and
filter products see blocks of different lengths).

Per joint (SPEC §10.3), for all joints of a block at once (Python loops only over joints ×
outage episodes)::

    FIR-1 = UFIR(R_I) over z^I ; FIR-2 = UFIR(R_V) over z^V (NaN in outages: predict,
            keeping its time-indexed horizon)
    IMM (reading R2, SPEC §8.3): z = (z^I, z^V), mixing from (FIR-1, FIR-2) posteriors at t−1
    camera available:  out = IMM filtered (causal; the batch form's offline output is the
                       RTS of the IMM over the maximal available segment)    source FUSED
    episode [a, e) (outage onset a; e = N samples after the camera is back for N
            consecutive samples; closer outages merge):
        win = last W available samples before a (with finite ELM-1 input)
        |win| < n_min:  out = FIR-1                          source IMU, imu_fallback
        else: ELM-1.fit(z^I[win], z^V[win]) ; ẑ_t = ELM-1(z^I_t), t ∈ [win[0], e)
              FIR-3 = fresh UFIR(R_V) over ẑ from win[0] (trained up to a, stepped after)
              ELM-2.fit(ẑ (or FIR-3), RTS − FIR-3) on (segment before a) ∩ win
              out_t = FIR-3_t + clip(ELM-2(ẑ_t), 3·RMS)        source BRIDGED
              cov_t = FIR-3 cov_t + diag(var of ELM-2's training residual)
              (ELM-2 skipped if too few samples: out = FIR-3, cov adds ELM-1's residual
              variance, elm2_skipped)
    no camera, no chain (NaN z^I: a stale IMU): the prediction, source PREDICTED (never available)

An outage at the very start has no training data: IMU-only output, flagged. A joint that is
never available is IMU-only throughout. The history kept for training reaches back to the
oldest of the last W camera-available frames of any joint (about W frames; more when outages
fall inside the window: it grows as needed).

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

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU, SOURCE_PREDICTED
from kinefuse.exceptions import InputError
from kinefuse.filters import (
    IMM,
    FilterResult,
    IMMResult,
    IMMState,
    KalmanFilter,
    UFIRFilter,
    UFIRState,
    fixed_lag_smooth,
    rts_smooth_segments,
)
from kinefuse.filters._base import expand_shared_block
from kinefuse.learning import ELMRegressor
from kinefuse.models import LinearGaussianModel
from kinefuse.pipelines import fusion_context as fc
from kinefuse.pipelines._outages import SOURCE_NONE, OutageEpisode, segment_start
from kinefuse.pipelines._paper_b_smooth import RunSmoother
from kinefuse.pipelines.fusion_context import FusionContext, FusionResult, finish, pos_cov
from kinefuse.pipelines.vision_params import VisionParams

__all__ = [
    "PAPER_B_METHODS",
    "Bridge",
    "PaperBCore",
    "PaperBState",
    "PaperBStep",
    "elm_fir",
    "elm_kf",
]

#: Paper B's methods and the filter family of FIR-1..3: UFIR (paper B) or KF (its comparator).
PAPER_B_METHODS = {"elm-fir": "fir", "elm-kf": "kf"}
#: Episode modes per joint.
MODE_NONE, MODE_FALLBACK, MODE_BRIDGED = 0, 1, 2


@dataclass(eq=False)
class Bridge:
    """One joint's prediction-stage bridge, trained at an outage onset.

    Attributes
    ----------
    elm1 : ELMRegressor
        ELM-1: IMU input (z^I and features) -> camera position ẑ.
    elm2 : ELMRegressor or None
        ELM-2: ẑ (or FIR-3) -> RTS − FIR-3 correction; None when skipped (too few samples).
    fir3 : filter state
        FIR-3's state (a fresh filter run over ẑ from the window start), stepped in the episode.
    cov_add : ndarray, shape (3, 3)
        ``diag`` of the training residual variance (ELM-2's, or ELM-1's when ELM-2 is skipped).
    elm2_on_fir3 : bool
        ELM-2 reads FIR-3's position (``elm2_input="fir3_out"``) rather than ẑ.
    """

    elm1: ELMRegressor
    elm2: ELMRegressor | None
    fir3: object
    cov_add: np.ndarray
    elm2_on_fir3: bool


@dataclass(eq=False)
class History:
    """Joint-major inputs and IMM outputs of the frames ``[base, base + n)`` (grows as needed).

    ``x (J, cap, n_in)`` ELM-1 inputs, ``z_cam (J, cap, 3)`` camera (NaN unavailable),
    ``mean (J, cap, n_x)``, ``cov (J, cap, n_x, n_x)`` IMM filtered, ``available (J, cap)``.
    """

    x: np.ndarray
    z_cam: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    available: np.ndarray
    base: int = 0
    n: int = 0

    @classmethod
    def empty(cls, J: int, n_in: int, n_x: int, capacity: int) -> History:
        return cls(
            np.full((J, capacity, n_in), np.nan),
            np.full((J, capacity, 3), np.nan),
            np.full((J, capacity, n_x), np.nan),
            np.full((J, capacity, n_x, n_x), np.nan),
            np.zeros((J, capacity), bool),
        )

    @property
    def capacity(self) -> int:
        return self.available.shape[1]

    def append(self, W: int, x, z_cam, mean, cov, available) -> None:
        """Store a block of L frames, dropping frames no future onset can read (the last W
        available frames of every joint are kept)."""
        L = available.shape[1]
        if self.n + L > self.capacity:
            self._make_room(W, L)
        sl = slice(self.n, self.n + L)
        self.x[:, sl], self.z_cam[:, sl], self.mean[:, sl] = x, z_cam, mean
        self.cov[:, sl], self.available[:, sl] = cov, available
        self.n += L

    def _make_room(self, W: int, L: int) -> None:
        keep = self.n  # relative index of the oldest frame still needed
        for j in range(self.available.shape[0]):
            idx = np.flatnonzero(self.available[j, : self.n])
            if idx.size:
                keep = min(keep, int(idx[max(idx.size - W, 0)]))
        n = self.n - keep
        cap = self.capacity
        if n + L > cap * 3 // 4:
            cap = max(2 * cap, n + L + cap)
        for name in ("x", "z_cam", "mean", "cov", "available"):
            a = getattr(self, name)
            if cap != a.shape[1]:
                b = np.full((a.shape[0], cap, *a.shape[2:]), np.nan if a.dtype != bool else False)
                b[:, :n] = a[:, keep : self.n]
                setattr(self, name, b)
            else:
                a[:, :n] = a[:, keep : self.n].copy()
        self.available[:, n:] = False
        self.base += keep
        self.n = n


@dataclass(eq=False)
class PaperBState:
    """Mutable state of :class:`PaperBCore` for J joints (pickle-able: a checkpoint is a copy).

    Attributes
    ----------
    k : int
        Frames processed.
    fir1, fir2, imm : filter states
        FIR-1, FIR-2 and IMM states (batch shape ``(J,)``).
    prev_x, prev_P : ndarray, shape (J, 1, 2, n_x), (J, 1, 2, n_x, n_x)
        FIR-1/FIR-2 posteriors of the last frame (the IMM's mixing input of the next one).
    history : History
    mode : ndarray of int8, shape (J,)
        0 no episode, 1 IMU fallback, 2 bridged.
    run_av : ndarray of int, shape (J,)
        Consecutive available frames inside the current episode (recovery rule).
    bridges : list of Bridge or None
    closed : list of list of OutageEpisode
        Per joint, the episodes that ended (recovery rule fired).
    open : list of OutageEpisode or None
        Per joint, the running episode (``stop = -1`` until it ends).
    """

    k: int
    fir1: object
    fir2: object
    imm: object
    prev_x: np.ndarray
    prev_P: np.ndarray
    history: History
    mode: np.ndarray
    run_av: np.ndarray
    bridges: list
    closed: list
    open: list

    @property
    def n_joints(self) -> int:
        return self.mode.shape[0]

    def episodes(self) -> tuple[tuple[OutageEpisode, ...], ...]:
        """Per joint, the episodes so far; a running one ends at ``k`` (not recovered)."""
        out = []
        for closed, op in zip(self.closed, self.open, strict=True):
            run = (
                () if op is None else (dataclasses.replace(op, stop=self.k, recovery_start=self.k),)
            )
            out.append((*closed, *run))
        return tuple(out)


@dataclass(frozen=True, eq=False)
class PaperBCore:
    """Paper B's causal pipeline as ``init`` / ``advance`` (configuration only).

    Parameters
    ----------
    method : {"elm-fir", "elm-kf"}
        UFIRs (paper B) or KFs with the same Q, R (its comparator) for FIR-1..3.
    params : VisionParams
    dt_s : float
        Frame interval, s (> 0, validated by the caller).
    n_features : int
        ELM-1 inputs per joint: 3 (z^I) plus any extra features.
    """

    method: str
    params: VisionParams
    dt_s: float
    n_features: int = 3
    model_imu: LinearGaussianModel = field(init=False)
    model_cam: LinearGaussianModel = field(init=False)
    fir1: object = field(init=False)
    fir3: object = field(init=False)
    imm: IMM = field(init=False)
    n_min: int = field(init=False)

    def __post_init__(self):
        if self.method not in PAPER_B_METHODS:
            raise InputError(f"expected method in {tuple(PAPER_B_METHODS)}, got {self.method!r}")
        p = self.params
        mi, mc = p.models(self.dt_s)
        if PAPER_B_METHODS[self.method] == "fir":
            f1 = UFIRFilter(mi, horizon=p.horizon, init="batch")
            f3 = UFIRFilter(mc, horizon=p.horizon, init="batch")
        else:
            f1, f3 = KalmanFilter(mi), KalmanFilter(mc)
        set_ = object.__setattr__
        set_(self, "model_imu", mi)
        set_(self, "model_cam", mc)
        set_(self, "fir1", f1)
        set_(self, "fir3", f3)  # FIR-2 and FIR-3 are the same filter (R_V), on other series
        set_(self, "imm", IMM(mi, mc, transition=p.transition, mu_floor=p.mu_floor))
        set_(self, "n_min", p.min_samples(self.n_features))

    def init(self, n_joints: int) -> PaperBState:
        """Initial state for ``n_joints`` joints."""
        J, nx, W = n_joints, self.model_imu.n_x, self.params.train_window
        return PaperBState(
            k=0,
            fir1=self.fir1.init((J,)),
            fir2=self.fir3.init((J,)),
            imm=self.imm.init((J,)),
            prev_x=np.full((J, 1, 2, nx), np.nan),
            prev_P=np.full((J, 1, 2, nx, nx), np.nan),
            history=History.empty(J, self.n_features, nx, 2 * W + 64),
            mode=np.zeros(J, np.int8),
            run_av=np.zeros(J, np.int64),
            bridges=[None] * J,
            closed=[[] for _ in range(J)],
            open=[None] * J,
        )

    def advance(self, state: PaperBState, z_imu, z_cam, available, features=None) -> PaperBStep:
        """Run L frames from ``state`` (updated in place).

        Parameters
        ----------
        state : PaperBState
        z_imu, z_cam : ndarray, shape (J, L, 3)
            IMU-chain and camera positions, m (float64; NaN rows missing).
        available : ndarray of bool, shape (J, L)
            Camera availability (non-finite camera rows count as unavailable).
        features : ndarray, shape (J, L, n_features − 3), optional
            Extra ELM-1 inputs.

        Returns
        -------
        PaperBStep

        Raises
        ------
        InputError
            ``z_imu`` (or ``features``) holds ±inf.

        Notes
        -----
        The filters run on their trusted fast path (``_filter_unchecked``, see
        :class:`~kinefuse.filters.UFIRFilter`): the block is checked here once, and the filter
        states are their own.

        At an outage onset a of joint j (SPEC §10.3)::

            win = last W available frames before a with finite ELM-1 input
            |win| < n_min: IMU fallback for the episode (FIR-1, source IMU)
            else: ELM-1.fit(x[win], z^V[win]) (seed) ; ẑ = ELM-1(x) on [win[0], a)
                  FIR-3 = fresh filter over ẑ on [win[0], a), then stepped in the episode
                  RTS of the IMM over the available segment ending at a − 1 (from win[0]);
                  ELM-2.fit(ẑ or FIR-3, RTS − FIR-3) (seed + 1) on that segment ∩ win
        In the episode: out = FIR-3 + clip(ELM-2(ẑ or FIR-3)), cov = FIR-3 cov + cov_add.
        """
        all_imu = bool(np.isfinite(z_imu).all())  # the common frame: no per-joint masks
        if (not all_imu and np.isinf(z_imu).any()) or (
            features is not None and np.isinf(features).any()
        ):
            raise InputError("expected z_imu and features finite or NaN (missing), got ±inf")
        all_av = bool(available.all()) and bool(np.isfinite(z_cam).all())
        av = available if all_av else available & np.all(np.isfinite(z_cam), axis=-1)
        z_cam = z_cam if all_av else np.where(av[..., None], z_cam, np.nan)
        x = z_imu if features is None else np.concatenate([z_imu, features], axis=-1)
        J, L = av.shape
        state.fir1, m1, P1 = _run_filter(self.fir1, z_imu, state.fir1)
        state.fir2, m2, P2 = _run_filter(self.fir3, z_cam, state.fir2)
        # IMM, reading R2: mixing from the FIR posteriors at t-1 (the last frame's carried in)
        if L == 1:  # read by the IMM before they are overwritten below
            px, pP = state.prev_x, state.prev_P
        else:
            px, pP = _lagged(state.prev_x, m1, m2), _lagged(state.prev_P, P1, P2)
        zz = np.empty((J, L, 2, 3))
        zz[:, :, 0], zz[:, :, 1] = z_imu, z_cam
        im = state.imm  # stepped in place (trusted fast path, see kinefuse.filters._base)
        r_imm = self.imm._run_inplace(
            zz, (px, pP), im.x, im.P, im.mu, im.initialized, per_model=False
        )
        state.imm = IMMState(im.x, im.P, im.mu, im.initialized, im.k + L)
        state.prev_x[:, 0, 0], state.prev_x[:, 0, 1] = m1[:, -1], m2[:, -1]
        state.prev_P[:, 0, 0], state.prev_P[:, 0, 1] = P1[:, -1], P2[:, -1]
        state.history.append(self.params.train_window, x, z_cam, r_imm.mean, r_imm.cov, av)
        pos = r_imm.position.copy()
        cov = pos_cov(r_imm.cov).copy()
        src = np.full((J, L), _FUSED_I8) if all_av else np.where(av, _FUSED_I8, _NONE_I8)
        flags = np.zeros((2, J, L), bool)  # imu_fallback, elm2_skipped
        out = (pos, cov, src, flags)
        if not all_av or state.mode.any():  # (the common frame has no episode: skip the scan)
            for j in np.flatnonzero((state.mode != MODE_NONE) | ~av.all(axis=1)):
                self._episodes_of_joint(state, j, x[j], av[j], (m1[j], P1[j]), out)
        if not all_imu:  # neither the chain nor the camera measured it: a prediction
            imu_ok = np.all(np.isfinite(z_imu), axis=-1)  # (J, L): the chain measured the joint
            src[~imu_ok & ~av & (src != _NONE_I8)] = _PREDICTED_I8
        state.k += L
        if not np.isfinite(pos).all():
            cov[~np.all(np.isfinite(pos), axis=-1)] = np.nan
        return PaperBStep(pos, cov, src, flags[0], flags[1], r_imm)

    # ------------------------------------------------------------------ episodes
    def _episodes_of_joint(self, state, j, x, av, fir1, out) -> None:
        """Joint j's prediction stage over the block: onsets, bridged spans, recoveries."""
        pos, cov, src, flags = out
        N, L, k0 = self.params.horizon, av.size, state.k
        i = 0
        while i < L:
            if state.mode[j] == MODE_NONE:
                gaps = np.flatnonzero(~av[i:])
                if gaps.size == 0:
                    return
                i += int(gaps[0])
                self._onset(state, j, k0 + i)
            end, recovered = _recovery(av[i:], int(state.run_av[j]), N)
            span = slice(i, i + end)
            if state.mode[j] == MODE_FALLBACK:
                p = fir1[0][span, 0::2]
                pos[j, span], cov[j, span] = p, pos_cov(fir1[1][span])
                src[j, span] = np.where(np.isfinite(p).all(-1), _IMU_I8, _NONE_I8)
                flags[0, j, span] = True
            else:
                b = state.bridges[j]
                p, c = self._bridge(b, x[span])
                pos[j, span], cov[j, span] = p, c
                src[j, span] = np.where(np.isfinite(p).all(-1), _BRIDGED_I8, _NONE_I8)
                flags[1, j, span] = b.elm2 is None
            i += end
            if recovered:
                e = k0 + i
                state.closed[j].append(
                    dataclasses.replace(state.open[j], stop=e, recovery_start=e - N, recovered=True)
                )
                state.open[j], state.bridges[j] = None, None
                state.mode[j], state.run_av[j] = MODE_NONE, 0
            else:
                state.run_av[j] = _run_length(av, int(state.run_av[j]))

    def _onset(self, state: PaperBState, j: int, a: int) -> None:
        """Outage onset of joint j at frame a: train the bridge (or fall back to the IMU)."""
        p, h = self.params, state.history
        hi = a - h.base  # history index of frame a
        av = h.available[j, :hi]
        x = h.x[j]
        win = np.flatnonzero(av)[-p.train_window :]
        win = win[np.all(np.isfinite(x[win]), axis=-1)]
        state.run_av[j] = 0
        if win.size < self.n_min:
            state.mode[j] = MODE_FALLBACK
            state.open[j] = OutageEpisode(
                a, -1, -1, False, "imu-fallback", -1, int(win.size), 0, True
            )
            return
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="ELM fitted on", category=UserWarning)
            bridge, n2 = self._train(h, j, win, hi, max(segment_start(av, hi), int(win[0])))
        state.bridges[j] = bridge
        state.mode[j] = MODE_BRIDGED
        w0 = h.base + int(win[0])
        state.open[j] = OutageEpisode(
            a, -1, -1, False, "bridged", w0, int(win.size), n2, bridge.elm2 is None
        )

    def _train(self, h: History, j: int, win, hi: int, s: int) -> tuple[Bridge, int]:
        """ELM-1, FIR-3 and ELM-2 on history indices ``win`` (< hi); ``s``: first index of the
        RTS of the segment ending at ``hi − 1``. Returns the bridge and ELM-2's sample count."""
        p = self.params
        x, zc = h.x[j], h.z_cam[j]
        elm1 = ELMRegressor(
            p.n_hidden, alpha=p.alpha, linear_skip=p.linear_skip, random_state=p.seed
        )
        elm1.fit(x[win], zc[win])
        w0 = int(win[0])
        x_span = x[w0:hi]
        ok = np.all(np.isfinite(x_span), axis=-1)
        zhat = np.full((hi - w0, 3), np.nan)
        zhat[ok] = elm1.predict(x_span[ok])
        st3, m3, _ = _run_filter(self.fir3, zhat[None], self.fir3.init((1,)), None)
        p3 = m3[0, :, 0::2]
        tr = win[win >= s]
        if s < hi:
            mean = h.mean[j, s:hi][None]
            res = FilterResult(
                mean, h.cov[j, s:hi][None], mean[..., 0::2], np.ones((1, hi - s), bool)
            )
            rts_pos = rts_smooth_segments(self.model_imu, res, cov=False).position[0]
            tr = tr[np.all(np.isfinite(rts_pos[tr - s]), -1) & np.all(np.isfinite(p3[tr - w0]), -1)]
        on_fir3 = p.elm2_input != "elm1_out"
        if tr.size < self.n_min:
            resid = zc[win] - elm1.predict(x[win])
            return Bridge(elm1, None, st3, np.diag(resid.var(axis=0)), on_fir3), int(tr.size)
        e2_in = (p3 if on_fir3 else zhat)[tr - w0]
        target = rts_pos[tr - s] - p3[tr - w0]
        elm2 = ELMRegressor(
            p.n_hidden, alpha=p.alpha, linear_skip=p.linear_skip, random_state=p.seed + 1
        )
        elm2.fit(e2_in, target)
        resid = target - elm2.predict(e2_in)
        return Bridge(elm1, elm2, st3, np.diag(resid.var(axis=0)), on_fir3), int(tr.size)

    def _bridge(self, b: Bridge, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bridged output over the frames of ``x (L, n_in)``: ``(position (L, 3), cov)``;
        advances ``b.fir3``."""
        zhat = b.elm1._predict_finite_rows(x, np.nan)
        b.fir3, m3, C3 = _run_filter(self.fir3, zhat[None], b.fir3, position_cov=True)
        p3 = m3[0, :, 0::2]
        c = C3[0] + b.cov_add
        if b.elm2 is None:
            return p3, c
        e2_in = p3 if b.elm2_on_fir3 else zhat
        return p3 + b.elm2._predict_finite_rows(e2_in, 0.0, self.params.clip_factor), c


class PaperBStep(NamedTuple):
    """Output of :meth:`PaperBCore.advance` for a block of L frames, joint-major."""

    position: np.ndarray
    """(J, L, 3) m; NaN where there is no estimate."""
    cov: np.ndarray
    """(J, L, 3, 3) m²; NaN where ``position`` is NaN."""
    source: np.ndarray
    """(J, L) int8 :data:`~kinefuse.conventions.SOURCE_NAMES` code, or ``SOURCE_NONE``."""
    imu_fallback: np.ndarray
    """(J, L) bool: an episode without enough training data output FIR-1."""
    elm2_skipped: np.ndarray
    """(J, L) bool: a bridged episode without ELM-2 (FIR-3 alone)."""
    imm: IMMResult
    """The block's IMM filtered output (the offline form smooths it); its per-model fields are
    None (not computed)."""


def _lagged(prev: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(J, L, 2, ...)``: frame t holds ``a``, ``b`` of frame t − 1 (``prev (J, 1, 2, ...)`` at
    t = 0), the IMM's mixing input (reading R2)."""
    J, L = a.shape[:2]
    out = np.empty((J, L, 2, *a.shape[2:]))
    out[:, :1] = prev
    out[:, 1:, 0], out[:, 1:, 1] = a[:, :-1], b[:, :-1]
    return out


# source codes as int8 scalars: np.where of these is the int8 source array directly
_FUSED_I8, _BRIDGED_I8, _IMU_I8, _PREDICTED_I8, _NONE_I8 = map(
    np.int8, (SOURCE_FUSED, SOURCE_BRIDGED, SOURCE_IMU, SOURCE_PREDICTED, SOURCE_NONE)
)
_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


def _run_filter(flt, z: np.ndarray, state, position_cov: bool | None = False):
    """``(state, mean, cov)`` of ``flt.filter(z (J, L, n_z), state)``, on the filters' trusted
    fast path (``_filter_unchecked``: ``z`` is float64 without ±inf, checked by the callers of
    :meth:`PaperBCore.advance`, and ``state`` is the filter's own). ``position_cov``: ``cov`` is
    the position block ``(J, L, n_z, n_z)`` (:func:`pos_cov`, the same numbers); None: no ``cov``
    (a UFIR does not compute it). One frame's full covariance is the filter state's own.

    A constant-velocity UFIR (paper B's FIRs) runs its compiled loop on the state's own arrays,
    updated in place (``UFIRFilter._run_cv_inplace``: the core owns its states, a checkpoint is
    a deep copy), with the same numbers as ``filter``. Otherwise, elements not yet initialised
    whose block holds no measurement (which :meth:`UFIRFilter.filter` refuses,
    :meth:`UFIRFilter.step` takes) are stepped frame by frame, the others filtered in one call;
    per element the numbers are the same.
    """
    J, L, n_z = z.shape
    if type(state) is UFIRState and flt._cv_route and state.x.ndim == 2:
        z = np.ascontiguousarray(z)
        wanted = position_cov is not None and (position_cov or L > 1)  # (L = 1: the state's)
        mean, covb = flt._run_cv_inplace(z, state.x, state.P, state.initialized, state.z_buf,
                                         state.k, wanted)[:2]  # fmt: skip
        if position_cov is None:
            cov = None
        elif position_cov:  # p00 on the diagonal (the position rows of every axis block)
            cov = covb[:, :, 0, 0, None, None] * (_EYE3 if n_z == 3 else np.eye(n_z))
        elif L == 1:  # the state's full covariance is that of the one frame (a state not
            cov = state.P[:, None].copy()  # initialised keeps init()'s NaN: no estimate)
        else:
            cov = expand_shared_block(covb[:, :, 0], n_z)
        return UFIRState(*state[:3], state.k + L, *state[4:]), mean, cov
    bad = None
    init = state.initialized
    if isinstance(flt, UFIRFilter) and not init.all():
        bad = ~init & ~np.any(np.all(np.isfinite(z), axis=-1), axis=-1)
    if bad is None or not bad.any():
        state, r = flt._filter_unchecked(z, state)
        return state, r.mean, pos_cov(r.cov) if position_cov else r.cov
    n_x = flt.model.n_x
    mean, cov = np.empty((J, L, n_x)), np.empty((J, L, n_x, n_x))
    parts = []
    good = ~bad
    if good.any():
        s_good, r = flt._filter_unchecked(z[good], _rows(state, good))
        mean[good], cov[good] = r.mean, r.cov
        parts.append((good, s_good))
    s_bad = _rows(state, bad)
    for t in range(L):
        s_bad, r = flt._filter_unchecked(z[bad, t : t + 1], s_bad)
        mean[bad, t], cov[bad, t] = r.mean[:, 0], r.cov[:, 0]
    parts.append((bad, s_bad))
    return _merge_rows(state, parts), mean, pos_cov(cov) if position_cov else cov


def _rows(state, rows):
    """The elements ``rows`` of a batched filter state (NamedTuple; scalars shared)."""
    return type(state)(*(f[rows] if isinstance(f, np.ndarray) else f for f in state))


def _merge_rows(like, parts):
    """A state shaped like ``like`` from ``[(rows, sub_state), ...]``."""
    fields = []
    for i, f in enumerate(like):
        if not isinstance(f, np.ndarray):
            fields.append(parts[0][1][i])
            continue
        out = np.empty((f.shape[0], *parts[0][1][i].shape[1:]), dtype=f.dtype)
        for rows, sub in parts:
            out[rows] = sub[i]
        fields.append(out)
    return type(like)(*fields)


def _recovery(av: np.ndarray, run0: int, N: int) -> tuple[int, bool]:
    """Frames of ``av`` the episode still covers and whether the recovery rule ends it there:
    the first frame at which ``N`` consecutive available frames (``run0`` carried in) are seen."""
    if av.size == 1:  # one frame (the online step): the rule below in closed form
        return 1, bool(av[0]) and run0 + 1 >= N
    t = np.arange(av.size)
    last_gap = np.maximum.accumulate(np.where(av, -1, t))
    run = np.where(last_gap >= 0, t - last_gap, t + 1 + run0)
    hit = np.flatnonzero(run >= N)
    return (int(hit[0]) + 1, True) if hit.size else (av.size, False)


def _run_length(av: np.ndarray, run0: int) -> int:
    """Consecutive available frames at the end of ``av`` (``run0`` carried in if all are)."""
    if av.size == 1:
        return run0 + 1 if av[0] else 0
    gaps = np.flatnonzero(~av)
    return av.size - 1 - int(gaps[-1]) if gaps.size else run0 + av.size


# ------------------------------------------------------------------------------------ batch form
def _elm_bridge(ctx: FusionContext) -> FusionResult:
    """The batch form: one :meth:`PaperBCore.advance` over the series, then (offline) the RTS
    of the IMM over each maximal available segment, or the fixed-lag RTS, for the fused samples."""
    p = ctx.params
    n_feat = 3 + (0 if ctx.features is None else ctx.features.shape[-1])
    core = PaperBCore(ctx.method, p, ctx.dt_s, n_feat)
    state = core.init(ctx.shape[0])
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="ELM fitted on", category=UserWarning)
        out, mu = _advance_in_blocks(core, state, ctx)
    pos, cov = out.position, out.cov
    avail = ctx.available
    if ctx.causal and p.fixed_lag > 0:  # (the position block of the smoothed covariance)
        base = fixed_lag_smooth(core.model_imu, out.imm, p.fixed_lag, avail, cov="position")
        fused = out.source == SOURCE_FUSED
        pos[fused] = base.position[fused]
        cov[fused] = base.cov[fused]
    if not ctx.causal or p.fixed_lag > 0:
        cov[~np.all(np.isfinite(pos), axis=-1)] = np.nan
    return finish(ctx, pos, cov, out.source, causal=ctx.causal and p.fixed_lag == 0,
                  mu=np.where(avail[..., None], mu, np.nan), imu_fallback=out.imu_fallback,
                  elm2_skipped=out.elm2_skipped, episodes=state.episodes())  # fmt: skip


#: Frames per :meth:`PaperBCore.advance` call of the batch form. The core's temporaries (the
#: FIRs' full covariances, the IMM's lagged inputs, the history it keeps) then stay bounded
#: whatever the recording's length; the core is split-invariant (the streaming form is the
#: same core one frame at a time), so the result does not depend on this size beyond rounding.
BATCH_BLOCK_FRAMES = 4096


def _advance_in_blocks(core: PaperBCore, state: PaperBState, ctx: FusionContext):
    """:meth:`PaperBCore.advance` over the whole series in blocks of
    :data:`BATCH_BLOCK_FRAMES`, the outputs written into arrays of the full length; returns
    them and the IMM's model probabilities ``mu (J, T, M)``. Offline, the fused frames are the
    RTS of the IMM per available run (:class:`RunSmoother`: the IMM output is kept for the open
    runs only); causal with a fixed lag, the step's ``imm`` is the IMM output of the series."""
    J, T = ctx.shape
    keep_imm = ctx.causal and core.params.fixed_lag > 0
    out = smoother = None
    for a in range(0, T, BATCH_BLOCK_FRAMES):
        sl = slice(a, min(a + BATCH_BLOCK_FRAMES, T))
        feat = None if ctx.features is None else ctx.features[:, sl]
        step = core.advance(state, ctx.z_imu[:, sl], ctx.z_cam[:, sl], ctx.available[:, sl], feat)
        if out is None:
            names = [f.name for f in dataclasses.fields(step.imm)] if keep_imm else ["mu"]
            out = [_full_length(arr, T) for arr in step[:-1]]
            imm = {k: _full_length(getattr(step.imm, k), T) for k in names}
            if not ctx.causal:
                smoother = RunSmoother(core.model_imu, out[0], out[1], out[2])
        for dst, src in zip(out, step[:-1], strict=True):
            dst[:, sl] = src
        for k, dst in imm.items():
            if dst is not None:
                dst[:, sl] = getattr(step.imm, k)
        if smoother is not None:
            smoother.add(step.imm, ctx.available[:, sl], final=sl.stop == T)
    result = PaperBStep(*out, type(step.imm)(**imm) if keep_imm else None)
    return result, imm["mu"]


def _full_length(a: np.ndarray | None, T: int) -> np.ndarray | None:
    """An empty ``(J, T, ...)`` array like the block output ``a (J, L, ...)`` (None: None); a
    :func:`~kinefuse.pipelines.fusion_context.joint_major` view (no copy in ``finish``)."""
    return None if a is None else fc.joint_major(a.shape[0], T, a.shape[2:], a.dtype)


def elm_fir(ctx: FusionContext) -> FusionResult:
    """``"elm-fir"``: paper B's ELM/FIR, UFIR for FIR-1, FIR-2 and FIR-3."""
    return _elm_bridge(ctx)


def elm_kf(ctx: FusionContext) -> FusionResult:
    """``"elm-kf"``: paper B's comparator ELM/KF, the same pipeline with Kalman filters."""
    return _elm_bridge(ctx)
