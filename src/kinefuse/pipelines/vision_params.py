"""Settings of paper B's pipeline (Xu 2023; defaults SPEC §12.2): :class:`VisionParams`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.models import LinearGaussianModel, constant_velocity

__all__ = ["ELM2_INPUTS", "VisionParams", "check_float"]

#: Values of :attr:`VisionParams.elm2_input`.
ELM2_INPUTS = ("elm1_out", "fir3_out")


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


def check_float(value, name: str, *, lo: float, strict: bool) -> float:
    """``value`` as a finite float ``>= lo`` (``> lo`` if ``strict``); InputError otherwise."""
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
        set_(self, "q", check_float(self.q, "q", lo=0.0, strict=False))
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
        set_(self, "mu_floor", check_float(self.mu_floor, "mu_floor", lo=0.0, strict=False))
        if self.mu_floor >= 0.5:
            raise InputError(f"expected mu_floor < 0.5, got {self.mu_floor!r}")
        set_(self, "n_hidden", _int(self.n_hidden, "n_hidden", 1))
        set_(self, "alpha", check_float(self.alpha, "alpha", lo=0.0, strict=False))
        if not isinstance(self.linear_skip, (bool, np.bool_)):
            raise InputError(f"expected linear_skip as a bool, got {self.linear_skip!r}")
        set_(self, "train_window", _int(self.train_window, "train_window", 2))
        if self.elm2_input not in ELM2_INPUTS:
            raise InputError(f"expected elm2_input in {ELM2_INPUTS}, got {self.elm2_input!r}")
        set_(self, "clip_factor", check_float(self.clip_factor, "clip_factor", lo=0.0, strict=True))
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
