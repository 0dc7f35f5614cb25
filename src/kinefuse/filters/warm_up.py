"""Compile (or load from numba's cache) the filter kernels ahead of use, with progress.

``kinefuse warm-up`` runs this once after installation so that the first ``kinefuse run`` does
not wait for numba in silence; the pipelines' own first call then only loads cached machine
code. Each step runs a public filter on a tiny input of the shapes the pipelines use (float64,
C-contiguous, batch of joints), which compiles exactly the specialisations a run needs.
Importing this module imports the kernel modules (``kinefuse.cli`` imports it only for
``kinefuse warm-up``, after the interpreted-mode decision of :mod:`kinefuse._compile`).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable

import numpy as np

from kinefuse.filters import (
    IMM,
    EMKalmanFilter,
    FilterResult,
    IntegratedFilter,
    KalmanFilter,
    UFIRFilter,
    fixed_lag_smooth,
    rts_smooth,
    rts_smooth_segments,
)
from kinefuse.models import constant_velocity

__all__ = ["WARM_UP_STEPS", "warm_up"]


def _model():
    return constant_velocity(1 / 30, q=0.5, r=1e-3)


def _z(B: int = 2, T: int = 48) -> np.ndarray:
    z = np.cumsum(np.random.default_rng(0).normal(0.0, 0.01, (B, T, 3)), axis=1)
    z[:, 5:7] = np.nan  # missing rows exercise the predict-only branches
    return z


def _kf():
    m = _model()
    kf = KalmanFilter(m)
    st, res = kf.filter(_z())
    kf.step(st, np.zeros((2, 3)))
    rts_smooth(m, res)
    rts_smooth_segments(m, res)
    fixed_lag_smooth(m, res, 3)
    KalmanFilter(m, method="dense").filter(_z())


def _ufir(init: str) -> None:
    f = UFIRFilter(_model(), horizon=20, init=init)
    st, _ = f.filter(_z())
    f.step(st, np.zeros((2, 3)))


def _ufir_general():
    _ufir("stored")  # the general loop (also the integrated filter's FIR kernels)


def _ufir_cv():
    _ufir("batch")  # the O(1)-per-step constant-velocity loop


def _em():
    f = EMKalmanFilter(_model(), n_iter=3)
    st, _ = f.filter(_z())
    f.step(st, np.zeros((2, 3)))
    g = IntegratedFilter(_model(), horizon=20, threshold1=2.0, threshold2=2.0, n_em_iter=3)
    st, _ = g.filter(_z())
    g.step(st, np.zeros((2, 3)))


def _imm():
    imm = IMM(_model(), constant_velocity(1 / 30, q=0.5, r=4e-4))
    z = _z()
    st, _ = imm.filter(np.stack([z, z + 0.01], axis=-2))  # (B, T, sources, 3)
    imm.step(st, np.zeros((2, 2, 3)))


def _rts_dense():
    """The RTS on full covariances (paper B smooths the IMM output, whose covariances couple
    the axes): filtered means and covariances with cross-axis terms, 6 states."""
    z = _z()
    rng = np.random.default_rng(1)
    A = rng.normal(0.0, 0.1, (6, 6))
    cov = np.broadcast_to(A @ A.T + 1e-3 * np.eye(6), (*z.shape[:2], 6, 6)).copy()
    mean = np.zeros((*z.shape[:2], 6))
    mean[..., 0::2] = np.nan_to_num(z)
    res = FilterResult(mean, cov, mean[..., 0::2], np.ones(z.shape[:2], bool))
    rts_smooth_segments(_model(), res)
    rts_smooth_segments(_model(), res, cov=False)


#: ``(what, function)``: the warm-up steps in the order they run.
WARM_UP_STEPS: tuple[tuple[str, Callable[[], None]], ...] = (
    ("Kalman filter, RTS smoothers", _kf),
    ("UFIR filter (general form)", _ufir_general),
    ("UFIR filter (constant-velocity form)", _ufir_cv),
    ("EM-KF and the integrated EM-KF/FIR filter", _em),
    ("IMM (paper B)", _imm),
    ("RTS smoother on full covariances (paper B, offline)", _rts_dense),
)


def warm_up(
    report: Callable[[str], None] | None = None, steps=WARM_UP_STEPS
) -> list[tuple[str, float]]:
    """Compile or load every filter kernel; returns ``(step, seconds)`` per step.

    Parameters
    ----------
    report : callable, optional
        Called with a progress line before each step and after the last (e.g. ``print``).
    steps : sequence of (str, callable), optional
        The steps to run (default :data:`WARM_UP_STEPS`; the layers above add theirs, e.g.
        :data:`kinefuse.pipelines.warm_up.WARM_UP_STEPS`).
    """
    out = []
    n = len(steps)
    t_all = time.perf_counter()
    for i, (what, fn) in enumerate(steps, 1):
        if report is not None:
            report(f"[{i}/{n}] compiling {what} (numba; cached for later runs) ...")
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fn()
        out.append((what, time.perf_counter() - t0))
    if report is not None:
        report(f"kernels ready in {time.perf_counter() - t_all:.1f} s")
    return out
