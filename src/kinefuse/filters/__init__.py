"""Filters of paper A (Sun 2024) and paper B (Xu 2023): KF, EM-KF, UFIR, integrated, RTS, IMM."""

from kinefuse.filters._base import FilterResult, GaussianState

__all__ = ["FilterResult", "GaussianState"]
