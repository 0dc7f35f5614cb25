"""Evaluation: accuracy metrics as the papers define them, paper-style tables, plots, HTML report."""

from kinefuse.evaluation.metrics import (
    EvaluationResult,
    error_at,
    error_cdf,
    evaluate,
    mean_rmse,
    position_error,
    relative_improvement,
    rmse_3d,
    rmse_per_axis,
    valid_samples,
)
from kinefuse.evaluation.report import write_report
from kinefuse.evaluation.tables import joint_method_table, method_table

__all__ = [
    "EvaluationResult",
    "error_at",
    "error_cdf",
    "evaluate",
    "joint_method_table",
    "mean_rmse",
    "method_table",
    "position_error",
    "relative_improvement",
    "rmse_3d",
    "rmse_per_axis",
    "valid_samples",
    "write_report",
]
