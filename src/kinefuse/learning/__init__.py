"""Learned components of paper B (Xu 2023): the ELM regressor (ELM-1/ELM-2 bridge building block)."""

from kinefuse.learning.elm import ELMRegressor, NotFittedError, clip_norm

__all__ = ["ELMRegressor", "NotFittedError", "clip_norm"]
