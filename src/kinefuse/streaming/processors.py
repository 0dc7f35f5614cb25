"""Per-frame processors of the online engine: paper A's integrated filter and a KF fusion baseline.

A processor turns, once per output frame, the IMU-chain joint positions and the camera joint
positions into fused joint positions with covariance and a per-joint source code. It is the
only algorithmic part of :class:`~kinefuse.streaming.engine.Engine`; buffering, time alignment
and fault handling live in the engine.

Protocol (:class:`Processor`)
-----------------------------
``step(t_s, z_imu (J, 3), z_cam (J, 3), available (J,))`` -> ``(position (J, 3), cov (J, 3, 3),
source (J,) int8)`` for the frame ``lag_frames`` frames back, or None while the fixed-lag
smoother fills; ``flush()`` -> the outputs still held back (end of run); ``run(t_s (T,), z_imu
(T, J, 3), z_cam (T, J, 3), available (T, J))`` -> the same outputs for a whole series from the
initial state, offline and causal (equal to ``step`` repeated then ``flush``); ``checkpoint()``
-> pickle-able dict; ``restore(checkpoint)``; ``reset()``.

The causal paper-B pipeline (:func:`kinefuse.pipelines.vision_assisted` with ``causal=True``)
is :class:`kinefuse.streaming.paper_b.VisionAssistedProcessor`.

Speed: ``step`` validates the frame once, then takes the filters' trusted fast path
(``_filter_unchecked``, see :mod:`kinefuse.filters._base`: the same compiled loop as their
``step``/``filter``, without the input checks) on all joints at once.
"""

from __future__ import annotations

import copy
from collections import deque
from typing import Protocol, runtime_checkable

import numpy as np

from kinefuse.conventions import SOURCE_CAMERA, SOURCE_FUSED, SOURCE_IMU, SOURCE_PREDICTED
from kinefuse.exceptions import InputError
from kinefuse.filters._base import FilterResult, GaussianState
from kinefuse.filters._kernels_axis import state_is_block_diagonal
from kinefuse.filters.kalman import KalmanFilter
from kinefuse.filters.smoothing import fixed_lag_smooth
from kinefuse.models import constant_velocity
from kinefuse.pipelines.upper_limb import paper_a_filter
from kinefuse.streaming._kernels import fusion_step

__all__ = [
    "SOURCE_NONE",
    "SOURCE_PREDICT",
    "IntegratedProcessor",
    "KalmanFusionProcessor",
    "Processor",
]

#: Source code of a joint that had no measurement in its frame (predict only): the offline
#: pipelines' :data:`kinefuse.conventions.SOURCE_PREDICTED` (one code for "no input backs this
#: sample" in files and on LSL; ``-1`` is no estimate, a NaN position).
SOURCE_PREDICT = SOURCE_PREDICTED
#: Source code of a joint without an estimate (NaN position), as the paper-B pipelines'.
SOURCE_NONE = -1

_CHECKPOINT_VERSION = 1


@runtime_checkable
class Processor(Protocol):
    """What :class:`~kinefuse.streaming.engine.Engine` needs from a per-frame processor."""

    lag_frames: int

    def step(self, t_s: float, z_imu: np.ndarray, z_cam: np.ndarray, available: np.ndarray):
        """One frame -> ``(position (J, 3), cov (J, 3, 3), source (J,) int8)`` or None."""

    def flush(self) -> list:
        """Outputs still held back by a lag (end of run), oldest first."""

    def run(self, t_s, z_imu, z_cam, available):
        """Offline causal equivalent of ``step`` repeated and ``flush`` over a series."""

    def checkpoint(self) -> dict:
        """Pickle-able snapshot of the mutable state."""

    def restore(self, checkpoint: dict) -> None:
        """Return to a snapshot taken by :meth:`checkpoint`."""

    def reset(self) -> None:
        """Back to the initial state."""


def _as_arrays(z_imu, z_cam, available):
    z_imu, z_cam = np.asarray(z_imu, dtype=float), np.asarray(z_cam, dtype=float)
    return z_imu, z_cam, np.asarray(available, dtype=bool)


def _check_frame(z_imu, z_cam, available):
    z_imu, z_cam, available = _as_arrays(z_imu, z_cam, available)
    if z_imu.ndim != 2 or z_imu.shape[1] != 3 or z_cam.shape != z_imu.shape:
        raise InputError(
            f"expected z_imu and z_cam with the same shape (J, 3), got {z_imu.shape} and {z_cam.shape}"
        )
    if available.shape != z_imu.shape[:1]:
        raise InputError(
            f"expected available with shape ({z_imu.shape[0]},), got {available.shape}"
        )
    return z_imu, z_cam, available


def _check_series(t_s, z_imu, z_cam, available):
    t = np.asarray(t_s, dtype=float)
    z_imu, z_cam, available = _as_arrays(z_imu, z_cam, available)
    if z_imu.ndim != 3 or z_imu.shape[2] != 3 or z_cam.shape != z_imu.shape:
        raise InputError(
            f"expected z_imu and z_cam with the same shape (T, J, 3), got {z_imu.shape} and {z_cam.shape}"
        )
    if t.shape != z_imu.shape[:1] or available.shape != z_imu.shape[:2]:
        raise InputError(
            f"expected t_s (T,) and available (T, J) for z (T, J, 3) = {z_imu.shape}, got "
            f"{t.shape} and {available.shape}"
        )
    return t, z_imu, z_cam, available


class _LinearProcessor:
    """Shared machinery: a linear model per joint, optional fixed-lag smoothing, checkpoints."""

    lag_frames: int

    def __init__(self, state_filter, lag: int):
        if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
            raise InputError(f"expected lag as an int >= 0 (frames), got {lag!r}")
        self._state_filter = state_filter  # the filter whose state is kept: its init, its model
        self.model = state_filter.model
        self.lag_frames = int(lag)
        self._H = np.asarray(self.model.H)
        # H is a 0/1 selector of the position components (constant-velocity models): H x and
        # H P Hᵀ are then plain gathers (the same numbers as the products, without the zeros)
        H = self._H
        rows = np.argmax(H != 0, axis=1)
        self._sel = rows if np.array_equal(H, np.eye(H.shape[1])[rows]) else None
        # evenly spaced rows (constant-velocity: 0, 2, 4): a slice, i.e. a view, not a gather
        self._sel_slice = None
        if self._sel is not None and len(rows) > 1:
            step = int(rows[1] - rows[0])
            if step > 0 and np.array_equal(rows, rows[0] + step * np.arange(len(rows))):
                self._sel_slice = slice(int(rows[0]), int(rows[-1]) + 1, step)
        self.reset()

    # -- to implement: filtered step and batch -> (mean (J,n), cov (J,n,n), source (J,))
    def _filter_step(self, z_imu, z_cam, available):  # pragma: no cover - abstract
        raise NotImplementedError

    def _init_state(self, n_joints: int):
        """A fresh state of the kept filter for ``n_joints`` joints (batch shape ``(J,)``)."""
        return self._state_filter.init((n_joints,))

    def reset(self) -> None:
        """Back to the initial state (lazily sized on the next step)."""
        self._state = None
        self._window: deque = deque()
        self._n_steps = 0

    def _output(self, mean, cov):
        sl = self._sel_slice
        if sl is not None:
            return mean[..., sl], cov[..., sl, sl]
        sel = self._sel
        if sel is not None:
            return mean[..., sel], cov[..., sel[:, None], sel]
        H = self._H
        pos = mean @ H.T
        pcov = np.einsum("ij,...jk,lk->...il", H, cov, H)
        return pos, pcov

    def step(self, t_s, z_imu, z_cam, available):
        """Process one frame.

        Parameters
        ----------
        t_s : float
            Frame time, s (unused by these fixed-rate models; kept for the protocol).
        z_imu : array_like, shape (J, 3)
            IMU-chain joint positions, m; NaN rows = no IMU measurement.
        z_cam : array_like, shape (J, 3)
            Camera joint positions, m; ignored where ``available`` is False.
        available : array_like of bool, shape (J,)
            Camera availability per joint.

        Returns
        -------
        tuple or None
            ``(position (J, 3) m, cov (J, 3, 3) m², source (J,) int8)`` of the frame
            ``lag_frames`` back; None while the lag window fills.
        """
        z_imu, z_cam, available = _check_frame(z_imu, z_cam, available)
        if self._state is None:
            self._state = self._init_state(z_imu.shape[0])
        elif self._state.x.shape[0] != z_imu.shape[0]:
            raise InputError(
                f"expected {self._state.x.shape[0]} joints as in the previous frames, got "
                f"{z_imu.shape[0]}"
            )
        mean, cov, source = self._filter_step(z_imu, z_cam, available)
        self._n_steps += 1
        L = self.lag_frames
        if L == 0:
            pos, pcov = self._output(mean, cov)
            return pos, pcov, source
        self._window.append((mean, cov, source))
        if len(self._window) < L + 1:
            return None
        sm_mean, sm_cov = self._smooth_window()
        out = self._output(sm_mean[:, 0], sm_cov[:, 0])
        src = self._window[0][2]
        self._window.popleft()
        return out[0], out[1], src

    def _smooth_window(self):
        means = np.stack([w[0] for w in self._window], axis=1)  # (J, W, n)
        covs = np.stack([w[1] for w in self._window], axis=1)
        res = FilterResult(
            mean=means,
            cov=covs,
            position=means @ self._H.T,
            observed=np.ones(means.shape[:2], bool),
        )
        sm = fixed_lag_smooth(self.model, res, self.lag_frames)
        return sm.mean, sm.cov

    def flush(self) -> list:
        """The outputs held back by the lag (fixed-interval smoothed to the last frame)."""
        if self.lag_frames == 0 or not self._window:
            return []
        sm_mean, sm_cov = self._smooth_window()
        outs = []
        for i, w in enumerate(self._window):
            pos, pcov = self._output(sm_mean[:, i], sm_cov[:, i])
            outs.append((pos, pcov, w[2]))
        self._window.clear()
        return outs

    def run(self, t_s, z_imu, z_cam, available):
        """Offline causal run over a series from the initial state (online state untouched).

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
            Equal to ``step`` over the frames followed by ``flush`` (fixed-lag smoothing
            applied with :func:`kinefuse.filters.fixed_lag_smooth`).
        """
        t, z_imu, z_cam, available = _check_series(t_s, z_imu, z_cam, available)
        mean, cov, source = self._filter_batch(
            t, z_imu, z_cam, available
        )  # (J,T,n), (J,T,n,n), (T,J)
        if self.lag_frames:
            res = FilterResult(mean=mean, cov=cov, position=mean @ self._H.T,
                               observed=np.ones(mean.shape[:2], bool))  # fmt: skip
            sm = fixed_lag_smooth(self.model, res, self.lag_frames)
            mean, cov = sm.mean, sm.cov
        pos, pcov = self._output(mean, cov)
        return np.swapaxes(pos, 0, 1), np.swapaxes(pcov, 0, 1), source

    def _filter_batch(self, t, z_imu, z_cam, available):
        """Default batch: repeated filtered steps on a copy (subclasses may use ``filter``)."""
        saved = (self._state, self._window, self._n_steps)
        try:
            self._state = self._init_state(z_imu.shape[1])
            ms, cs, ss = [], [], []
            for k in range(t.size):
                m, c, s = self._filter_step(z_imu[k], z_cam[k], available[k])
                ms.append(m)
                cs.append(c)
                ss.append(s)
        finally:
            self._state, self._window, self._n_steps = saved
        return np.stack(ms, axis=1), np.stack(cs, axis=1), np.stack(ss)

    def checkpoint(self) -> dict:
        """Pickle-able snapshot: ``{"version", "type", "state", "window", "n_steps"}``."""
        return {
            "version": _CHECKPOINT_VERSION,
            "type": type(self).__name__,
            "state": copy.deepcopy(self._state),
            "window": [tuple(np.copy(a) for a in w) for w in self._window],
            "n_steps": self._n_steps,
        }

    def restore(self, checkpoint: dict) -> None:
        """Return to a snapshot from :meth:`checkpoint` (of a processor of the same type)."""
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
        self._state = copy.deepcopy(checkpoint["state"])
        self._window = deque(tuple(np.copy(a) for a in w) for w in checkpoint["window"])
        self._n_steps = int(checkpoint["n_steps"])


class IntegratedProcessor(_LinearProcessor):
    """Paper A's EM-KF/FIR integrated filter per joint on the IMU-chain positions.

    Parameters
    ----------
    dt_s : float
        Frame interval, s (the camera or output period).
    q : float
        Process-noise scale of :func:`kinefuse.models.constant_velocity`, (m/s)² per frame.
    r : float
        Nominal measurement variance of the IMU-chain positions, m².
    lag : int
        Fixed-lag smoothing lag, frames (0 = filtered output, no delay).
    **filter_kwargs
        Passed to :class:`~kinefuse.filters.integrated.IntegratedFilter` (``horizon``,
        ``threshold1``, ``threshold2``, ``n_em_iter``, ``gate``, ``fir_feedback``).

    Notes
    -----
    Implements Sun 2024 (paper A) §3.4 through the filter of the batch pipeline
    (:func:`kinefuse.pipelines.upper_limb.paper_a_filter`, an :class:`IntegratedFilter`)
    batched over the J joints: ``step`` calls ``IntegratedFilter.step`` and ``run`` calls
    ``IntegratedFilter.filter`` (the same compiled loop). The camera is not a measurement here
    (paper A has none); it only places the chain root (engine). Source per joint:
    ``SOURCE_IMU`` where the filter was updated, :data:`SOURCE_PREDICT` where the IMU chain had
    no valid position (stale stream). The branch of the last step is in :attr:`last_mode`.
    """

    def __init__(
        self, dt_s: float, q: float = 0.05, r: float = 4e-4, *, lag: int = 0, **filter_kwargs
    ):
        self.filter = paper_a_filter(dt_s, q, r, **filter_kwargs)  # upper_limb's filter
        self.last_mode = None
        super().__init__(self.filter, lag)

    def _filter_step(self, z_imu, z_cam, available):
        # unchecked and in place: the frame was validated by step and the state is this
        # processor's own (a checkpoint is a deep copy; kinefuse.filters._base, trusted fast path)
        st = self._state
        z = np.ascontiguousarray(z_imu).reshape(-1, 1, z_imu.shape[-1])
        mean, cov, obs, _, _, _, mode = self.filter._run_inplace(
            z, st.x, st.P, st.initialized, st.z_buf, st.k
        )
        self._state = st._replace(k=st.k + 1)
        self.last_mode = mode[:, 0]
        source = np.where(obs[:, 0], np.int8(SOURCE_IMU), np.int8(SOURCE_PREDICT))
        return mean[:, 0], cov[:, 0], source

    def _filter_batch(self, t, z_imu, z_cam, available):
        z = np.ascontiguousarray(np.swapaxes(z_imu, 0, 1))  # (J, T, 3)
        if not np.all(np.any(np.all(np.isfinite(z), axis=-1), axis=-1)):
            return super()._filter_batch(t, z_imu, z_cam, available)  # a joint never observed
        _, res = self.filter.filter(z)
        source = np.where(res.observed, SOURCE_IMU, SOURCE_PREDICT).astype(np.int8).T
        return res.mean, res.cov, source


class KalmanFusionProcessor(_LinearProcessor):
    """IMU + camera fusion baseline: one constant-velocity Kalman filter per joint.

    Parameters
    ----------
    dt_s : float
        Frame interval, s.
    q : float
        Process-noise scale, (m/s)² per frame.
    r_imu, r_camera : float
        Measurement variances of the IMU-chain and camera positions, m².
    lag : int
        Fixed-lag smoothing lag, frames.

    Notes
    -----
    Both sensors measure the joint position (``H`` of :func:`constant_velocity`). The stacked
    update with ``z = [z_cam; z_imu]``, ``R = diag(r_c I, r_i I)`` equals one update with the
    information-weighted measurement::

        z_eq = (z_cam / r_c + z_imu / r_i) / (1 / r_c + 1 / r_i),   r_eq = r_c r_i / (r_c + r_i)

    so each joint takes, per frame, one of three :class:`~kinefuse.filters.KalmanFilter`
    updates (both, camera only, IMU only) or a prediction; joints are grouped by case and each
    group is stepped batched. Source per joint: ``SOURCE_FUSED`` (both), ``SOURCE_CAMERA``,
    ``SOURCE_IMU``, :data:`SOURCE_PREDICT`. The two sensors' errors are taken as independent
    and unbiased (a baseline, not paper B's learned bridge).
    """

    def __init__(
        self,
        dt_s: float,
        q: float = 0.05,
        r_imu: float = 4e-4,
        r_camera: float = 9e-4,
        *,
        lag: int = 0,
    ):
        self.r_imu, self.r_camera = float(r_imu), float(r_camera)
        r_both = self.r_imu * self.r_camera / (self.r_imu + self.r_camera)
        self._kf_imu = KalmanFilter(constant_velocity(dt_s, q=q, r=self.r_imu))
        self._kf_cam = KalmanFilter(constant_velocity(dt_s, q=q, r=self.r_camera))
        self._kf_both = KalmanFilter(constant_velocity(dt_s, q=q, r=r_both))
        # one compiled call per frame for all joints (cases 0 both, 1 camera, 2 IMU/predict)
        # when the filters run their per-axis path; the three differ only in R (and P0)
        kfs = (self._kf_both, self._kf_cam, self._kf_imu)
        if all(kf._blocks is not None for kf in kfs):
            Fb, Qb, Hb, _, _ = self._kf_imu._blocks
            self._fast = (np.stack([kf._blocks[3] for kf in kfs]),
                          np.stack([kf._blocks[4] for kf in kfs]), Fb, Qb, Hb)  # fmt: skip
        else:
            self._fast = None
        super().__init__(self._kf_imu, lag)

    def _filter_step(self, z_imu, z_cam, available):
        st = self._state
        wi, wc = 1.0 / self.r_imu, 1.0 / self.r_camera
        if self._fast is not None and state_is_block_diagonal(st.P, st.initialized):
            return self._fast_step(z_imu, z_cam, available, wi, wc)
        has_imu = np.all(np.isfinite(z_imu), axis=1)
        has_cam = available & np.all(np.isfinite(z_cam), axis=1)
        both = has_imu & has_cam
        cam_only = has_cam & ~has_imu
        rest = ~has_cam  # IMU only, or nothing (NaN rows -> predict)
        J = z_imu.shape[0]
        groups = []
        for kf, idx in ((self._kf_both, both), (self._kf_cam, cam_only), (self._kf_imu, rest)):
            n = int(np.count_nonzero(idx))
            if n:
                groups.append((kf, idx, n))
        if len(groups) == 1 and groups[0][2] == J:  # the usual case: one batched step
            kf, idx, _ = groups[0]
            z = (z_cam * wc + z_imu * wi) / (wc + wi) if kf is self._kf_both else (
                z_cam if kf is self._kf_cam else z_imu
            )  # fmt: skip
            self._state, res = kf._filter_unchecked(z[:, None, :], st)  # validated by step
            mean, cov = res.mean[:, 0], res.cov[:, 0]
        else:
            x, P, init = st.x.copy(), st.P.copy(), st.initialized.copy()
            mean = np.empty((J, self.model.n_x))
            cov = np.empty((J, self.model.n_x, self.model.n_x))
            for kf, idx, _ in groups:
                z = (z_cam[idx] * wc + z_imu[idx] * wi) / (wc + wi) if kf is self._kf_both else (
                    z_cam[idx] if kf is self._kf_cam else z_imu[idx]
                )  # fmt: skip
                sub = GaussianState(st.x[idx], st.P[idx], st.initialized[idx], st.k)
                sub, res = kf._filter_unchecked(z[:, None, :], sub)
                x[idx], P[idx], init[idx] = sub.x, sub.P, sub.initialized
                mean[idx], cov[idx] = res.mean[:, 0], res.cov[:, 0]
            self._state = GaussianState(x, P, init, st.k + 1)
        return mean, cov, self._sources(has_imu, both, cam_only)

    @staticmethod
    def _sources(has_imu, both, cam_only):
        source = np.full(has_imu.shape, SOURCE_PREDICT, np.int8)
        source[has_imu] = SOURCE_IMU
        source[cam_only] = SOURCE_CAMERA
        source[both] = SOURCE_FUSED
        return source

    def _fast_step(self, z_imu, z_cam, available, wi, wc):
        """:meth:`_filter_step` as one compiled call (the same per-axis filter kernel, the
        same numbers: tested against the grouped form)."""
        r, P0b, Fb, Qb, Hb = self._fast
        J, n_x = z_imu.shape[0], self.model.n_x
        st = self._state
        x, P, init = st.x.copy(), st.P.copy(), st.initialized.copy()
        mean = np.empty((J, 1, n_x))
        cov = np.zeros((J, 1, n_x, n_x))
        source = np.empty(J, np.int8)
        fusion_step(np.ascontiguousarray(z_imu), np.ascontiguousarray(z_cam), available, wi, wc,
                    r, P0b, x, P, init, Fb, Qb, Hb, mean, cov, source)  # fmt: skip
        self._state = GaussianState(x, P, init, st.k + 1)
        return mean[:, 0], cov[:, 0], source
