"""Filters of paper A (Sun 2024) and paper B (Xu 2023): KF, EM-KF, UFIR, integrated, RTS, IMM."""

from kinefuse.filters._base import FilterResult, GaussianState
from kinefuse.filters.em_kalman import EMKalmanFilter, EMKalmanResult, EMKalmanState
from kinefuse.filters.imm import IMM, IMMResult, IMMState, IMMStep, lag_posteriors
from kinefuse.filters.integrated import IntegratedFilter, IntegratedResult, IntegratedState
from kinefuse.filters.kalman import KalmanFilter
from kinefuse.filters.online import OnlineFilter
from kinefuse.filters.smoothing import fixed_lag_smooth, rts_smooth, rts_smooth_segments
from kinefuse.filters.ufir import UFIRFilter, UFIRResult, UFIRState

__all__ = [
    "EMKalmanFilter",
    "EMKalmanResult",
    "EMKalmanState",
    "FilterResult",
    "GaussianState",
    "IMM",
    "IMMResult",
    "IMMState",
    "IMMStep",
    "IntegratedFilter",
    "IntegratedResult",
    "IntegratedState",
    "KalmanFilter",
    "OnlineFilter",
    "UFIRFilter",
    "UFIRResult",
    "UFIRState",
    "fixed_lag_smooth",
    "lag_posteriors",
    "rts_smooth",
    "rts_smooth_segments",
]
