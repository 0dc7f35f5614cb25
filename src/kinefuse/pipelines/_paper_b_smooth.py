"""Paper B's offline RTS over each available run, done as the runs complete (batch form only).

The offline output of paper B (SPEC §9) is the fixed-interval RTS of the IMM's filtered output
over each maximal run of camera-available frames, written at the fused frames. A run's RTS needs
that run's filtered means and covariances only, and it is final once the run has ended, so the
batch form (:func:`kinefuse.pipelines.paper_b._elm_bridge`) hands each block of
:meth:`~kinefuse.pipelines.paper_b.PaperBCore.advance` to :class:`RunSmoother`, which keeps the
IMM output of the runs still open and smooths the others. The memory held is that of the open
runs, not of the recording (a one-hour, 8-joint recording at 30 Hz kept 0.3 GB of IMM output
for a smoothing at the end). Each run is smoothed once, by the same kernel on the same numbers
as one call over the whole series (:func:`kinefuse.filters.rts_smooth_segments`), so the result
is the same.
"""

from __future__ import annotations

import numpy as np

from kinefuse.conventions import SOURCE_FUSED
from kinefuse.filters import FilterResult, IMMResult, rts_smooth_segments
from kinefuse.models import LinearGaussianModel

__all__ = ["RunSmoother"]


class RunSmoother:
    """RTS of the IMM output per available run, written into full-length outputs as runs end.

    Parameters
    ----------
    model : LinearGaussianModel
        The model of the RTS (paper B: the IMU model of the IMM).
    position, cov : ndarray, shape (J, T, 3), (J, T, 3, 3)
        The batch outputs; at fused frames (``source == SOURCE_FUSED``) they are overwritten
        with the smoothed position and its covariance block.
    source : ndarray of int8, shape (J, T)
        Source codes of the whole series (filled block by block before :meth:`add` reads them).
    """

    def __init__(self, model: LinearGaussianModel, position, cov, source):
        self.model = model
        self.position, self.cov, self.source = position, cov, source
        J = position.shape[0]
        self._mean = np.empty((J, 0, model.n_x))
        self._P = np.empty((J, 0, model.n_x, model.n_x))
        self._av = np.empty((J, 0), bool)
        self._n = 0  # buffer frames in use
        self._base = 0  # series frame of buffer index 0
        self._done = np.zeros(J, np.int64)  # per joint: buffer frames before this are smoothed

    def add(self, imm: IMMResult, available, final: bool = False) -> None:
        """Take the IMM output ``imm`` (``(J, L, ...)``) and availability ``(J, L)`` of the next
        L frames; smooth every run that has ended (all of them when ``final``)."""
        L = available.shape[1]
        self._make_room(L)
        sl = slice(self._n, self._n + L)
        self._mean[:, sl], self._P[:, sl], self._av[:, sl] = imm.mean, imm.cov, available
        self._n += L
        n = self._n
        # per joint, frames before `upto` lie in runs that have ended: up to its last gap
        if final:
            upto = np.full(self._done.shape, n)
        else:
            last_gap = np.where(~self._av[:, :n], np.arange(n), -1).max(axis=1)
            upto = np.maximum(last_gap + 1, self._done)
        lo, hi = int(self._done.min()), int(upto.max())
        if hi > lo:
            self._smooth(lo, hi, upto)
        self._done = upto

    def _smooth(self, lo: int, hi: int, upto: np.ndarray) -> None:
        """RTS over buffer frames ``[lo, hi)``: per joint the runs in ``[done, upto)``."""
        t = np.arange(lo, hi)
        mask = self._av[:, lo:hi] & (t >= self._done[:, None]) & (t < upto[:, None])
        if not mask.any():
            return
        mean = self._mean[:, lo:hi]
        res = FilterResult(mean, self._P[:, lo:hi], mean[..., 0::2], mask)
        sm = rts_smooth_segments(self.model, res, mask, cov="position")
        a = self._base + lo
        src = self.source[:, a : a + hi - lo]
        fused = mask & (src == SOURCE_FUSED)
        self.position[:, a : a + hi - lo][fused] = sm.position[fused]
        self.cov[:, a : a + hi - lo][fused] = sm.cov[fused]

    def _make_room(self, L: int) -> None:
        """Room for L more frames: forget the frames every joint has smoothed, grow if needed."""
        cap = self._av.shape[1]
        if self._n + L <= cap:
            return
        k = int(self._done.min())
        n = self._n - k
        if n + L > cap * 3 // 4:
            cap = max(2 * cap, n + L)
        for name in ("_mean", "_P", "_av"):
            a = getattr(self, name)
            b = a if cap == a.shape[1] else np.empty((a.shape[0], cap, *a.shape[2:]), a.dtype)
            b[:, :n] = a[:, k : self._n]  # (numpy copies overlapping ranges correctly)
            setattr(self, name, b)
        self._n = n
        self._base += k
        self._done -= k
