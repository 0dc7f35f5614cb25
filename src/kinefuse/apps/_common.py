"""Helpers the apps share: result tables, JSON-safe numbers, timed method runs, the IMU chain."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from kinefuse.evaluation.tables import ResultTable, TableRow
from kinefuse.pipelines.labels import PAPER_B_LABELS
from kinefuse.pipelines.run import SessionOutput, process_recording

__all__ = ["finite_or_none", "imu_only_output", "labelled_runs", "result_table", "timed_quietly"]


def result_table(
    title, label_headers, value_headers, rows, notes=(), digits=3, best=True
) -> ResultTable:
    """A :class:`~kinefuse.evaluation.tables.ResultTable` from ``(labels, values, paper)`` rows
    (``best``: mark each column's smallest value, for error tables)."""
    return ResultTable(
        title=title,
        label_headers=tuple(label_headers),
        value_headers=tuple(value_headers),
        rows=tuple(
            TableRow(tuple(labels), tuple(values), paper=bool(paper))
            for labels, values, paper in rows
        ),
        digits=digits,
        notes=tuple(notes),
        best=best,
    )


def finite_or_none(x) -> float | None:
    """``float(x)``, or None where it is not finite (JSON has no NaN)."""
    x = float(x)
    return x if np.isfinite(x) else None


def labelled_runs(
    methods: Sequence[str], causal: Iterable[str] = ()
) -> list[tuple[str, bool, str]]:
    """``(method, causal, table label)``: each method offline, then those run causally as well
    (label ``"<label> causal"``)."""
    runs = [(m, False) for m in methods] + [(m, True) for m in causal]
    return [(m, c, PAPER_B_LABELS.get(m, m) + (" causal" if c else "")) for m, c in runs]


def timed_quietly(fn: Callable[..., Any], *args, **kwargs) -> tuple[Any, float]:
    """``fn(*args, **kwargs)`` with its warnings silenced, and its wall time (s)."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def imu_only_output(recording, calibration_window_s: float) -> SessionOutput:
    """The IMU chain of ``recording`` at 30 Hz, calibrated against its camera (warnings silenced).

    ``process_recording(recording, "imu-only", ...)`` with ``calibration = "vision"`` over the
    first ``calibration_window_s`` seconds.
    """
    opts = {"calibration": "vision", "calibration_window_s": calibration_window_s, "rate_hz": 30.0}
    return timed_quietly(process_recording, recording, "imu-only", opts)[0]
