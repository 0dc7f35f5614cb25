"""The study table: one tidy row per recording x method x estimate x joint x subset x metric.

Columns (:data:`COLUMNS`): ``study``, ``recording``, ``method`` (the method run),
``estimate`` (what is scored, :meth:`kinefuse.pipelines.run.output.SessionOutput.trajectories`:
the method's label; ``IMU chain`` unless it equals the method's output; with a camera method the
baselines ``camera gap-fill``, ``offset interp``, ``offset hold``; ``camera`` only when the camera
differs from the reference; labels may end in a tag such as ``" [calibrated on reference]"``; and
``task``, the row of ``task_wall_s``), ``joint`` (``all`` for run times), ``subset`` (``all``,
``in_view``, ``outage``: samples outside / inside camera outages), ``metric`` (``rmse_<axis>``,
``rmse_mean``, ``rmse_3d``, ``error_cdf_0.9``, ``n_samples``, ``run_time_s`` of the method,
``task_wall_s`` of the whole task), ``value``, ``unit``, ``calibrated_on`` (what the
sensor-to-segment calibration used), ``status`` (``done``, ``skipped`` = finished earlier,
``failed``) and ``error`` (the failed task's one-line error; a failed task has one row with an
empty metric). Written with pyarrow as Parquet and CSV, each atomically (temporary sibling +
rename).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

__all__ = ["COLUMNS", "TABLE_NAME", "flatten", "write_table"]

COLUMNS = (
    "study",
    "recording",
    "method",
    "estimate",
    "joint",
    "subset",
    "metric",
    "value",
    "unit",
    "calibrated_on",
    "status",
    "error",
)
#: File stem of the table inside the study's out_dir (``.parquet`` and ``.csv``).
TABLE_NAME = "study_results"


def flatten(results: Iterable[Mapping]) -> dict[str, list]:
    """Task results (:func:`kinefuse.batch.tasks.run_task`) -> columns of the study table."""
    cols: dict[str, list] = {c: [] for c in COLUMNS}
    for res in results:
        head = {
            "study": res.get("study", ""),
            "recording": res["recording"],
            "method": res["method"],
            "calibrated_on": res.get("calibrated_on") or "",
            "status": res["status"],
            "error": res.get("error") or "",
        }
        rows = res.get("rows") or [
            {"estimate": "", "joint": "", "subset": "", "metric": "", "value": None, "unit": ""}
        ]
        for r in rows:
            for c in COLUMNS:
                cols[c].append(head[c] if c in head else r[c])
    return cols


def _arrow(columns: Mapping[str, list]):
    import pyarrow as pa

    fields = [
        pa.field(c, pa.float64() if c == "value" else pa.string(), nullable=True) for c in COLUMNS
    ]
    return pa.table({c: columns[c] for c in COLUMNS}, schema=pa.schema(fields))


def write_table(out_dir: str | Path, columns: Mapping[str, list]) -> tuple[Path, Path]:
    """Write ``study_results.parquet`` and ``study_results.csv`` into ``out_dir`` atomically.

    Returns
    -------
    (Path, Path)
        Parquet and CSV paths.
    """
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = _arrow(columns)
    paths = (out / f"{TABLE_NAME}.parquet", out / f"{TABLE_NAME}.csv")
    for path, write in zip(paths, (pq.write_table, pacsv.write_csv), strict=True):
        tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
        write(table, str(tmp))
        tmp.replace(path)
    return paths


def read_table(path: str | Path) -> dict[str, list]:
    """Columns of a written study table (Parquet)."""
    import pyarrow.parquet as pq

    return pq.read_table(str(path)).to_pydict()
