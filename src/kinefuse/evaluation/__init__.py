"""Evaluation: accuracy metrics as the papers define them, paper-style tables, plots, HTML report.

The functions below are re-exported lazily (as in :mod:`kinefuse.io`): importing a light
submodule such as :mod:`kinefuse.evaluation.tables` (the CLI's result tables) does not import
matplotlib, which the plots and the report need.
"""

from __future__ import annotations

from kinefuse._lazy import lazy_exports

_LAZY = {
    "EvaluationResult": "metrics",
    "error_at": "metrics",
    "error_cdf": "metrics",
    "evaluate": "metrics",
    "mean_rmse": "metrics",
    "position_error": "metrics",
    "relative_improvement": "metrics",
    "rmse_3d": "metrics",
    "rmse_per_axis": "metrics",
    "valid_samples": "metrics",
    "ReportOptions": "report",
    "write_report": "report",
    "joint_method_table": "tables",
    "method_table": "tables",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
