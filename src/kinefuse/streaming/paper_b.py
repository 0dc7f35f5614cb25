"""Paper B (Xu 2023) as a per-frame processor: the causal ELM/FIR (or ELM/KF) pipeline online.

:class:`VisionAssistedProcessor` is the incremental form of
:func:`kinefuse.pipelines.vision_assisted` with ``causal=True``: it holds the per-joint filter
states (FIR-1, FIR-2, IMM, and FIR-3 while bridging), a history of the inputs and IMM outputs
reaching back to the oldest of the last W camera-available samples of any joint, and the
ELM-1/ELM-2 pair of each bridged episode. Fed the same frames it returns the batch pipeline's
outputs (``run`` is the batch pipeline itself; the tests check ``step`` against it).
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Sequence

import numpy as np

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU
from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.filters import IMM, KalmanFilter, rts_smooth
from kinefuse.filters._base import FilterResult
from kinefuse.filters._kernels_axis import kf_filter_axis, kf_filter_dense
from kinefuse.filters._kernels_imm import imm_run
from kinefuse.filters._kernels_ufir_run import ufir_run
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.learning import ELMRegressor
from kinefuse.pipelines._outages import SOURCE_NONE
from kinefuse.pipelines.vision_assisted import VisionParams, vision_assisted
from kinefuse.streaming.processors import _check_series

__all__ = ["VisionAssistedProcessor"]

_METHODS = {"elm-fir": "fir", "elm-kf": "kf"}
_CHECKPOINT_VERSION = 1
#: Episode modes per joint.
_NONE, _FALLBACK, _BRIDGED = 0, 1, 2
#: Mutable attributes (what :meth:`VisionAssistedProcessor.checkpoint` saves).
_MUTABLE = (
    "_k", "_st1", "_st2", "_st_imm", "_prev_x", "_prev_P", "_cap", "_r_imu", "_r_cam",
    "_r_mean", "_r_cov", "_retain", "_n_av", "_av_idx", "_seg_len", "_mode", "_run_av",
    "_bridge", "_episodes", "last_mu",
)  # fmt: skip


class _Bridge:
    """One joint's prediction-stage bridge: ELM-1, FIR-3 state, ELM-2 (or None), extra cov."""

    __slots__ = ("elm1", "elm2", "fir3", "cov_add", "e2_fir3", "clip")

    def __init__(self, elm1, elm2, fir3, cov_add, e2_fir3, clip):
        self.elm1, self.elm2, self.fir3 = elm1, elm2, fir3
        self.cov_add, self.e2_fir3, self.clip = cov_add, e2_fir3, clip

    def __getstate__(self):
        return {s: getattr(self, s) for s in self.__slots__}

    def __setstate__(self, d):
        for s in self.__slots__:
            setattr(self, s, d[s])


def _elm_row(elm: ELMRegressor, x: np.ndarray) -> np.ndarray:
    """``elm.predict(x[None])[0]`` without the input checks (x finite, shape (n_in,))."""
    return (elm._hidden(x[None]) @ elm.output_weights_ * elm.y_scale_ + elm.y_mean_)[0]


def _clip(v: np.ndarray, max_norm: float) -> np.ndarray:
    """:func:`kinefuse.learning.clip_norm` of one vector."""
    n = math.sqrt(float(v @ v))
    return v * (max_norm / n) if n > max_norm else v


class _Loop:
    """Unchecked access to one filter's compiled loop (UFIR or KF) on flat state arrays.

    The arguments are the ones the filter object passes to its kernel, prepared once here, so
    ``run`` is that filter's ``filter``/``step`` minus validation and reshaping: the same
    machine code, hence the same numbers. State: a dict of arrays (pickle-able).
    """

    def __init__(self, flt):
        m = flt.model
        self.nx, self.nz = m.n_x, m.n_z
        if isinstance(flt, UFIRFilter):
            a = flt._arrays
            self.ufir = True
            self.N = flt.horizon
            self.head = (self.N, a["K"], flt.init_mode == "stored", True, bool(m.axis_blocks))
            self.tail = tuple(
                a[k]
                for k in ("W", "P_full", "F", "Finv", "H", "Q", "R", "Fa", "Finva", "Ha", "Qa",
                          "Ra", "Hpinv", "P0")
            )  # fmt: skip
        else:
            self.ufir = False
            # KalmanFilter._run takes the per-axis loop whenever the model has axis blocks and
            # the state covariance is block-diagonal, which the axis loop keeps it
            self.axis = flt._blocks is not None
            self.tail = flt._blocks if self.axis else (m.F, m.Q, m.H, m.R, flt._P0, flt._Hpinv)

    def init(self, B: int) -> dict:
        nx, nz = self.nx, self.nz
        st = {
            "x": np.full((B, nx), np.nan),
            "P": np.full((B, nx, nx), np.nan),
            "init": np.zeros(B, bool),
            "k": 0,
        }
        if self.ufir:
            st["zring"] = np.full((B, self.N, nz), np.nan)
            st["xring"] = np.empty((B, 0, nx))
            st["Pring"] = np.empty((B, 0, nx, nx))
        return st

    def run(self, st: dict, z: np.ndarray):
        """Filter ``z (B, T, n_z)`` (C-contiguous float64) from ``st`` (updated in place).

        Returns ``mean (B, T, n_x)``, ``cov (B, T, n_x, n_x)``.
        """
        B, T, nz = z.shape
        nx = self.nx
        mean = np.empty((B, T, nx))
        obs = np.empty((B, T), bool)
        nu = np.empty((B, T, nz))
        if self.ufir:
            cov = np.empty((B, T, nx, nx))
            n_fail = ufir_run(
                z, st["x"], st["P"], st["init"], st["zring"], st["xring"], st["Pring"], st["k"],
                *self.head, *self.tail, mean, cov, obs, nu, np.empty((B, T), bool),
            )  # fmt: skip
            if n_fail:
                warnings.warn(
                    f"UFIRFilter: KF update skipped on {n_fail} step(s): S could not be "
                    "factorised (SPEC §13)",
                    NumericalWarning,
                    stacklevel=3,
                )
        elif self.axis:
            cov = np.zeros((B, T, nx, nx))
            kf_filter_axis(z, st["x"], st["P"], st["init"], *self.tail, mean, cov,
                           np.empty((B, T, nz)), obs, nu, np.empty((B, T)))  # fmt: skip
        else:
            cov = np.empty((B, T, nx, nx))
            kf_filter_dense(z, st["x"], st["P"], st["init"], *self.tail, mean, cov,
                            np.empty((B, T, nz)), obs, nu, np.empty((B, T)))  # fmt: skip
        st["k"] += T
        return mean, cov


class _IMMLoop:
    """Unchecked one-step access to :class:`IMM`'s compiled loop (reading R2, prev given)."""

    def __init__(self, imm: IMM):
        self.imm = imm
        self.args = (imm._F, imm._Q, imm._H, imm._R, imm._Hpinv, imm._P_init, imm.transition,
                     imm.mu_floor)  # fmt: skip

    def init(self, B: int) -> dict:
        s = self.imm.init((B,))
        return {"x": s.x, "P": s.P, "mu": s.mu, "init": s.initialized}

    def step(self, st: dict, z: np.ndarray, px: np.ndarray, pP: np.ndarray):
        """``z (B, 1, M, n_z)``, ``px (B, 1, M, n_x)``, ``pP``: ``(mean, cov, mu)`` of the step."""
        B, _, M, nz = z.shape
        nx = px.shape[-1]
        out_x = np.empty((B, 1, nx))
        out_P = np.empty((B, 1, nx, nx))
        out_mu = np.empty((B, 1, M))
        imm_run(
            z, True, px, pP, *self.args, st["x"], st["P"], st["mu"], st["init"], out_x, out_P,
            out_mu, np.empty((B, 1, M, nx)), np.empty((B, 1, M, nx, nx)), np.zeros((B, 1), bool),
            np.zeros((B, 1, M), bool), np.empty((B, 1, M)), np.empty((B, 1, M, nz)),
            np.empty((B, 1, M)),
        )  # fmt: skip
        return out_x[:, 0], out_P[:, 0], out_mu[:, 0]


class VisionAssistedProcessor:
    """Paper B's causal pipeline (ELM/FIR or ELM/KF) per frame, all joints batched.

    Parameters
    ----------
    method : {"elm-fir", "elm-kf"}
        As in :func:`kinefuse.pipelines.vision_assisted`: UFIRs (paper B) or KFs (its
        comparator) for FIR-1..3.
    params : VisionParams, optional
        Pipeline settings (default ``VisionParams()``). ``fixed_lag`` must be 0: the processor
        reproduces the causal, undelayed output.
    dt_s : float
        Frame interval, s (default 1/30).
    joints : int or sequence of str, optional
        Number of joints, or their names; fixes J at construction. Default: J taken from the
        first frame.

    Attributes
    ----------
    lag_frames : int
        0 (outputs are not delayed).
    episodes : list of list of dict
        Per joint, the prediction-stage episodes so far: ``start``, ``mode`` ("bridged" or
        "imu-fallback"), ``train_start``, ``n_train``, ``n_train_elm2``, ``elm2_skipped``, and
        ``stop`` once ended (the recovery rule fired).
    last_mu : ndarray, shape (J, 2)
        IMM model probabilities (IMU, camera) after the last step.

    Notes
    -----
    Per frame t, for all J joints at once (SPEC §10.3, as :func:`vision_assisted` causal)::

        FIR-1 step (z^I_t) ; FIR-2 step (z^V_t, NaN where unavailable)
        IMM step (z^I_t, z^V_t) mixing from the FIR-1/FIR-2 posteriors at t−1  (reading R2)
        camera available, no episode:   out = H x̂^IMM_t, source FUSED
        outage onset a = t (not in an episode, camera unavailable), per joint:
            win = last W available samples before a with finite z^I
            |win| < n_min: IMU fallback for the episode (FIR-1, source IMU)
            else: ELM-1.fit(z^I[win], z^V[win]) (seed) ; ẑ = ELM-1(z^I) on [win[0], a)
                  FIR-3 = fresh filter run over ẑ on [win[0], a), then stepped per frame
                  RTS over the available segment ending at a − 1 (only its last |win| samples
                  are needed and kept); ELM-2.fit(ẑ or FIR-3, RTS − FIR-3) (seed + 1)
        in an episode: out = FIR-3_t + clip(ELM-2(ẑ_t)) (source BRIDGED), cov = FIR-3 cov +
            diag(training residual variance); the episode ends after N consecutive available
            frames (recovery rule)

    The per-frame work is a fixed number of compiled filter calls over all joints plus, per
    joint in an outage, one FIR-3 step and two single-row ELM evaluations. At an outage onset the
    joint's ELMs are trained and FIR-3 is run over the window (O(W), once per episode).

    The history kept for training spans from the oldest of the last W available frames of any
    joint to now: about W frames, more when outages fall inside the window (it grows as needed).

    ``run`` is :func:`vision_assisted` (``causal=True``) on the series; ``step`` repeated equals
    it (positions and covariances to rounding, sources exactly; tested to 1e-9). The only
    differences are floating-point: single-row versus batched matrix products in the ELM
    predictions, and the RTS of ELM-2's targets run over the samples it needs rather than the
    whole segment (the recursion is the same).
    """

    lag_frames = 0

    def __init__(
        self,
        method: str = "elm-fir",
        params: VisionParams | None = None,
        dt_s: float = 1 / 30,
        joints: int | Sequence[str] | None = None,
    ):
        if method not in _METHODS:
            raise InputError(f"expected method in {tuple(_METHODS)}, got {method!r}")
        if params is None:
            params = VisionParams()
        elif not isinstance(params, VisionParams):
            raise InputError(f"expected params as a VisionParams, got {type(params).__name__}")
        if params.fixed_lag != 0:
            raise InputError(
                f"expected params.fixed_lag = 0 (the processor gives the undelayed causal output), "
                f"got {params.fixed_lag}"
            )
        try:
            dt = float(dt_s)
        except (TypeError, ValueError):
            raise InputError(f"expected dt_s as a number > 0, got {dt_s!r}") from None
        if not (math.isfinite(dt) and dt > 0):
            raise InputError(f"expected dt_s finite and > 0, got {dt_s!r}")
        self.method = method
        self.params = params
        self.dt_s = dt
        if joints is None:
            self.joints = None
            self.n_joints = None
        elif isinstance(joints, (int, np.integer)) and not isinstance(joints, bool):
            if joints < 1:
                raise InputError(f"expected joints >= 1, got {joints}")
            self.n_joints = int(joints)
            self.joints = tuple(f"joint_{j}" for j in range(self.n_joints))
        else:
            if isinstance(joints, str):
                raise InputError(f"expected joints as a sequence of names, got {joints!r}")
            self.joints = tuple(str(j) for j in joints)
            if not self.joints:
                raise InputError("expected at least one joint")
            self.n_joints = len(self.joints)
        kind = _METHODS[method]
        self._kind = kind
        mi, mc = params.models(dt)
        self.model_imu, self.model_cam = mi, mc
        N = params.horizon
        if kind == "fir":
            f1 = UFIRFilter(mi, horizon=N, init="batch")
            f3 = UFIRFilter(mc, horizon=N, init="batch")
        else:
            f1, f3 = KalmanFilter(mi), KalmanFilter(mc)
        # FIR-2 and FIR-3 are the same filter (model R_V), run on different series
        self._f1, self._f3 = _Loop(f1), _Loop(f3)
        self._f2 = self._f3
        self._imm = _IMMLoop(IMM(mi, mc, transition=params.transition, mu_floor=params.mu_floor))
        self._n_min = params.min_samples(3)
        self._W = params.train_window
        self._N = N
        self._nx = mi.n_x
        self._J = None
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the initial state (sized now if J is known, else on the first frame)."""
        self._J = None
        self._k = 0
        if self.n_joints is not None:
            self._allocate(self.n_joints)

    def _allocate(self, J: int) -> None:
        nx, W = self._nx, self._W
        self._J = J
        self._k = 0
        self._st1 = self._f1.init(J)
        self._st2 = self._f2.init(J)
        self._st_imm = self._imm.init(J)
        self._prev_x = np.full((J, 1, 2, nx), np.nan)
        self._prev_P = np.full((J, 1, 2, nx, nx), np.nan)
        cap = 2 * W + 64
        self._cap = cap
        self._r_imu = np.full((cap, J, 3), np.nan)
        self._r_cam = np.full((cap, J, 3), np.nan)
        self._r_mean = np.full((cap, J, nx), np.nan)
        self._r_cov = np.full((cap, J, nx, nx), np.nan)
        self._retain = 0  # no frame before this one is needed any more (non-decreasing)
        self._n_av = np.zeros(J, np.int64)  # available frames so far
        self._av_idx = np.zeros((J, W), np.int64)  # frame of the n-th available in slot n % W
        self._seg_len = np.zeros(J, np.int64)  # available run ending at the previous frame
        self._mode = np.zeros(J, np.int8)
        self._run_av = np.zeros(J, np.int64)  # consecutive available frames in the episode
        self._bridge = [None] * J
        self._episodes = [[] for _ in range(J)]
        self.last_mu = np.full((J, 2), np.nan)

    @property
    def episodes(self) -> list:
        """Per joint, the episodes so far (see the class docstring)."""
        return [[dict(e) for e in ep] for ep in self._episodes] if self._J else []

    def checkpoint(self) -> dict:
        """Pickle-able snapshot of the mutable state (filter states, history, trained ELMs)."""
        state = None
        if self._J is not None:
            state = copy.deepcopy({name: getattr(self, name) for name in _MUTABLE})
        return {
            "version": _CHECKPOINT_VERSION,
            "type": type(self).__name__,
            "method": self.method,
            "n_joints": self._J,
            "state": state,
        }

    def restore(self, checkpoint: dict) -> None:
        """Return to a snapshot from :meth:`checkpoint` (same method and parameters)."""
        if not isinstance(checkpoint, dict) or checkpoint.get("type") != type(self).__name__:
            got = (
                checkpoint.get("type")
                if isinstance(checkpoint, dict)
                else type(checkpoint).__name__
            )
            raise InputError(f"expected a checkpoint of a {type(self).__name__}, got {got!r}")
        if checkpoint.get("version") != _CHECKPOINT_VERSION:
            raise InputError(
                f"expected checkpoint version {_CHECKPOINT_VERSION}, got {checkpoint.get('version')!r}"
            )
        if checkpoint.get("method") != self.method:
            raise InputError(
                f"expected a checkpoint of method {self.method!r}, got {checkpoint.get('method')!r}"
            )
        J = checkpoint["n_joints"]
        if J is None:
            self._J = None
            self._k = 0
            if self.n_joints is not None:
                self._allocate(self.n_joints)
            return
        if self.n_joints is not None and J != self.n_joints:
            raise InputError(f"expected a checkpoint for {self.n_joints} joints, got {J}")
        self._allocate(J)
        for name, value in copy.deepcopy(checkpoint["state"]).items():
            setattr(self, name, value)

    # ------------------------------------------------------------------ per frame
    def step(self, t_s, z_imu, z_cam, available):
        """Process one frame.

        Parameters
        ----------
        t_s : float
            Frame time, s (unused: fixed-rate models; kept for the protocol).
        z_imu : array_like, shape (J, 3)
            IMU-chain joint positions, m; NaN rows = no IMU measurement.
        z_cam : array_like, shape (J, 3)
            Camera joint positions, m; ignored where ``available`` is False or not finite.
        available : array_like of bool, shape (J,)

        Returns
        -------
        position : ndarray, shape (J, 3)
            m; NaN where there is no estimate.
        cov : ndarray, shape (J, 3, 3)
            m².
        source : ndarray of int8, shape (J,)
            ``SOURCE_FUSED``, ``SOURCE_BRIDGED``, ``SOURCE_IMU``, or -1 (no estimate).
        """
        zi = z_imu if type(z_imu) is np.ndarray and z_imu.dtype == np.float64 else None
        if zi is None:
            zi = np.asarray(z_imu, dtype=np.float64)
        zc = z_cam if type(z_cam) is np.ndarray and z_cam.dtype == np.float64 else None
        if zc is None:
            zc = np.asarray(z_cam, dtype=np.float64)
        av = np.asarray(available, dtype=bool)
        J = self._J
        if J is None:
            if zi.ndim != 2:
                raise InputError(f"expected z_imu with shape (J, 3), got {zi.shape}")
            self._allocate(zi.shape[0])
            J = self._J
        if zi.shape != (J, 3) or zc.shape != (J, 3) or av.shape != (J,):
            raise InputError(
                f"expected z_imu, z_cam (J, 3) and available (J,) with J = {J}, got "
                f"{zi.shape}, {zc.shape}, {av.shape}"
            )
        return self._step(zi, zc, av)

    def _step(self, zi: np.ndarray, zc: np.ndarray, available: np.ndarray):
        """Unchecked frame step: ``zi, zc (J, 3)`` float64, ``available (J,)`` bool."""
        J, k = self._J, self._k
        fin_c = np.isfinite(zc).all(axis=1)
        av = available & fin_c
        if not av.all():
            zc = zc.copy()
            zc[~av] = np.nan
        # FIR-1, FIR-2 (time axis of length 1: the filters' own compiled loops)
        zi = np.ascontiguousarray(zi)
        zc = np.ascontiguousarray(zc)
        zz = np.empty((J, 1, 2, 3))
        zz[:, 0, 0] = zi
        zz[:, 0, 1] = zc
        # C-contiguous (J, 1, 3) views: the kernels' cached specialisations
        m1, P1 = self._f1.run(self._st1, zi.reshape(J, 1, 3))
        m2, P2 = self._f2.run(self._st2, zc.reshape(J, 1, 3))
        # IMM, reading R2: mixing from the FIR posteriors at t-1
        px, pP = self._prev_x, self._prev_P
        mean_i, cov_i, self.last_mu = self._imm.step(self._st_imm, zz, px, pP)
        m1, P1 = m1[:, 0], P1[:, 0]
        px[:, 0, 0] = m1
        px[:, 0, 1] = m2[:, 0]
        pP[:, 0, 0] = P1
        pP[:, 0, 1] = P2[:, 0]
        pos = mean_i[:, 0::2].copy()  # = H x (H selects the interleaved positions)
        cov = cov_i[:, 0::2, 0::2].copy()
        src = np.where(av, SOURCE_FUSED, SOURCE_NONE).astype(np.int8)
        # prediction stage: joints in an episode or at an outage onset
        mode = self._mode
        todo = np.flatnonzero((mode != _NONE) | ~av)
        for j in todo:
            if mode[j] == _NONE:
                self._onset(j, k)
            if mode[j] == _FALLBACK:
                p = m1[j, 0::2]
                pos[j] = p
                cov[j] = P1[j, 0::2, 0::2]
                src[j] = SOURCE_IMU if np.isfinite(p).all() else SOURCE_NONE
            else:
                p, c = self._bridge_step(j, zi[j])
                pos[j] = p
                cov[j] = c
                src[j] = SOURCE_BRIDGED if np.isfinite(p).all() else SOURCE_NONE
            if av[j]:
                self._run_av[j] += 1
                if self._run_av[j] == self._N:  # recovery rule: episode ends after this frame
                    mode[j] = _NONE
                    self._bridge[j] = None
                    self._episodes[j][-1]["stop"] = k + 1
            else:
                self._run_av[j] = 0
        bad = ~np.isfinite(pos).all(axis=1)
        if bad.any():
            cov[bad] = np.nan
        # history
        n = self._n_av
        avj = np.flatnonzero(av)
        self._av_idx[avj, n[avj] % self._W] = k
        n[avj] += 1
        self._seg_len = np.where(av, self._seg_len + 1, 0)
        self._record(k, zi, zc, mean_i, cov_i)
        self._k = k + 1
        return pos, cov, src

    def _record(self, k, zi, zc, mean_i, cov_i) -> None:
        """Store frame k in the history ring (growing it if a needed frame would be lost)."""
        cap = self._cap
        if k - cap >= self._retain:
            self._retain = self._oldest_needed(k)
            if k - cap >= self._retain:
                self._grow(k)
                cap = self._cap
        s = k % cap
        self._r_imu[s] = zi
        self._r_cam[s] = zc
        self._r_mean[s] = mean_i
        self._r_cov[s] = cov_i

    def _oldest_needed(self, k: int) -> int:
        """Oldest frame of the last W available frames over the joints (k if none)."""
        n, W = self._n_av, self._W
        has = n > 0
        if not has.any():
            return k
        slot = np.where(n >= W, n % W, 0)
        return int(self._av_idx[np.flatnonzero(has), slot[has]].min())

    def _grow(self, k: int) -> None:
        old = self._cap
        new = 2 * old
        frames = np.arange(max(self._retain, k - old), k)
        for name in ("_r_imu", "_r_cam", "_r_mean", "_r_cov"):
            a = getattr(self, name)
            b = np.full((new, *a.shape[1:]), np.nan)
            b[frames % new] = a[frames % old]
            setattr(self, name, b)
        self._cap = new

    # ------------------------------------------------------------------ episodes
    def _onset(self, j: int, a: int) -> None:
        """Outage onset of joint j at frame a: train the bridge (or fall back to the IMU)."""
        p = self.params
        n = min(int(self._n_av[j]), self._W)
        W, cap = self._W, self._cap
        n_tot = int(self._n_av[j])
        slots = np.arange(n_tot - n, n_tot) % W
        win = self._av_idx[j, slots]  # ascending frames
        x_win = self._r_imu[win % cap, j]
        ok = np.isfinite(x_win).all(axis=1)
        win, x_win = win[ok], x_win[ok]
        self._run_av[j] = 0
        if win.size < self._n_min:
            self._mode[j] = _FALLBACK
            self._episodes[j].append(
                {"start": a, "mode": "imu-fallback", "train_start": -1, "n_train": int(win.size),
                 "n_train_elm2": 0, "elm2_skipped": True}
            )  # fmt: skip
            return
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="ELM fitted on", category=UserWarning)
            elm1 = ELMRegressor(
                p.n_hidden, alpha=p.alpha, linear_skip=p.linear_skip, random_state=p.seed
            )
            elm1.fit(x_win, self._r_cam[win % cap, j])
            w0 = int(win[0])
            span = np.arange(w0, a)
            x_span = self._r_imu[span % cap, j]
            in_ok = np.isfinite(x_span).all(axis=1)
            zhat = np.full((a - w0, 3), np.nan)
            zhat[in_ok] = elm1.predict(x_span[in_ok])
            st3 = self._f3.init(1)
            p3 = self._f3.run(st3, zhat[None])[0][0, :, 0::2]
            # RTS of the IMM output over the available segment ending at a - 1, from the first
            # sample ELM-2 can use (the recursion runs backward: earlier samples do not matter)
            s = max(a - int(self._seg_len[j]), w0)
            tr = win[win >= s]
            elm2 = None
            if s < a:
                seg = np.arange(s, a) % cap
                mean_s = self._r_mean[seg, j][None]
                res = FilterResult(
                    mean=mean_s,
                    cov=self._r_cov[seg, j][None],
                    position=mean_s[..., 0::2],
                    observed=np.ones((1, a - s), bool),
                )
                rts_pos = rts_smooth(self.model_imu, res).position[0]
                fin = np.isfinite(rts_pos[tr - s]).all(axis=1) & np.isfinite(p3[tr - w0]).all(
                    axis=1
                )
                tr = tr[fin]
            skipped = tr.size < self._n_min
            if skipped:
                resid = self._r_cam[win % cap, j] - elm1.predict(x_win)
            else:
                e2_fir3 = p.elm2_input != "elm1_out"
                e2_in = p3 if e2_fir3 else zhat
                target = rts_pos[tr - s] - p3[tr - w0]
                elm2 = ELMRegressor(
                    p.n_hidden, alpha=p.alpha, linear_skip=p.linear_skip, random_state=p.seed + 1
                )
                elm2.fit(e2_in[tr - w0], target)
                resid = target - elm2.predict(e2_in[tr - w0])
        clip = p.clip_factor * elm2.train_rms_ if elm2 is not None else 0.0
        self._bridge[j] = _Bridge(
            elm1, elm2, st3, np.diag(resid.var(axis=0)), p.elm2_input != "elm1_out", clip
        )
        self._mode[j] = _BRIDGED
        self._episodes[j].append(
            {"start": a, "mode": "bridged", "train_start": w0, "n_train": int(win.size),
             "n_train_elm2": int(tr.size), "elm2_skipped": bool(skipped)}
        )  # fmt: skip

    def _bridge_step(self, j: int, x: np.ndarray):
        """One prediction-stage frame of joint j: ``(position (3,), cov (3, 3))``."""
        b = self._bridge[j]
        x_ok = bool(np.isfinite(x).all())
        zhat = _elm_row(b.elm1, x) if x_ok else np.full(3, np.nan)
        m3, c3 = self._f3.run(b.fir3, zhat.reshape(1, 1, 3))
        p3 = m3[0, 0, 0::2]
        c = c3[0, 0, 0::2, 0::2] + b.cov_add
        if b.elm2 is None:
            return p3, c
        e2_in = p3 if b.e2_fir3 else zhat
        if np.isfinite(e2_in).all():
            return p3 + _clip(_elm_row(b.elm2, e2_in), b.clip), c
        return p3, c

    def warm_up(self) -> None:
        """Run every compiled path once on a throwaway copy (state of ``self`` untouched).

        The first call of a numba kernel in a process loads (or compiles) its machine code,
        which takes tens of milliseconds: call this before a real-time run so that the first
        frames and the first outage onset do not pay it.
        """
        n = self._n_min + self._N + 5
        t = np.arange(n + 2 * self._N) * self.dt_s
        zi = np.stack([np.sin(t), np.cos(0.7 * t), 0.1 * t], axis=-1)[:, None, :]
        zc = zi + 0.01
        av = np.ones((t.size, 1), bool)
        av[n : n + 3] = False
        tmp = VisionAssistedProcessor(self.method, self.params, self.dt_s, 1)
        for k in range(t.size):
            tmp.step(t[k], zi[k], zc[k], av[k])

    # ------------------------------------------------------------------ series
    def flush(self) -> list:
        """Nothing is held back (no lag): ``[]``."""
        return []

    def run(self, t_s, z_imu, z_cam, available):
        """Offline causal run over a series: :func:`vision_assisted` with ``causal=True``.

        Parameters
        ----------
        t_s : array_like, shape (T,)
        z_imu, z_cam : array_like, shape (T, J, 3)
        available : array_like of bool, shape (T, J)

        Returns
        -------
        position : ndarray, shape (T, J, 3)
        cov : ndarray, shape (T, J, 3, 3)
        source : ndarray of int8, shape (T, J)

        Notes
        -----
        A joint without any finite IMU sample is refused by the batch pipeline; then the series
        is run through :meth:`step` on a fresh copy of the processor instead. The online state
        is not touched.
        """
        t, zi, zc, av = _check_series(t_s, z_imu, z_cam, available)
        if self.n_joints is not None and zi.shape[1] != self.n_joints:
            raise InputError(f"expected {self.n_joints} joints, got {zi.shape[1]}")
        if np.all(np.any(np.all(np.isfinite(zi), axis=-1), axis=0)):
            r = vision_assisted(zi, zc, av, self.dt_s, self.method, causal=True, params=self.params)
            return r.position, r.cov, r.source
        fresh = VisionAssistedProcessor(self.method, self.params, self.dt_s, zi.shape[1])
        outs = [fresh.step(t[k], zi[k], zc[k], av[k]) for k in range(t.size)]
        return tuple(np.stack([o[i] for o in outs]) for i in range(3))
