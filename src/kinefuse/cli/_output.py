"""What the commands share: the common options, ``--json``, output-folder checks, result tables.

Everything imported here is light (no numba, matplotlib or SciPy), so that ``kinefuse --help``
stays fast.
"""

import json
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.text import Text

from kinefuse.cli._app import EXIT_FAILURE, fail, one_line, stderr, stdout
from kinefuse.evaluation import tables
from kinefuse.evaluation._names import REPORT_NAME
from kinefuse.exceptions import InputError
from kinefuse.io._write import write_text_safely
from kinefuse.io.output_folder import check_folder_usable, check_writable_file

__all__ = [
    "Force",
    "Json",
    "JsonForce",
    "Scheduler",
    "Workers",
    "Quiet",
    "check_json",
    "check_report_free",
    "existing_file",
    "finish",
    "fresh_dir",
    "jsonable",
    "present",
    "write_json",
]

Quiet = Annotated[
    bool,
    typer.Option("--quiet", "-q", help="Print no tables or progress (errors still go to stderr)."),
]
Json = Annotated[
    Path | None,
    typer.Option(
        "--json", metavar="FILE", help="Also write the results as JSON to FILE ('-' for stdout)."
    ),
]
Force = Annotated[
    bool,
    typer.Option(
        "--force", "-f", help="Replace earlier results in the output folder and the --json file."
    ),
]
JsonForce = Annotated[
    bool, typer.Option("--force", "-f", help="Overwrite an existing --json file.")
]
#: Dask options of ``kinefuse batch`` and ``kinefuse experiment`` (:func:`kinefuse.batch.runner.connect`
#: reads ``DASK_SCHEDULER_ADDRESS`` when no ``--scheduler`` is given).
Workers = Annotated[
    int | None,
    typer.Option("--workers", "-w", min=1, help="Dask LocalCluster workers (default: cores)."),
]
Scheduler = Annotated[
    str | None,
    typer.Option(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="An existing Dask scheduler instead of a LocalCluster (default: "
        "$DASK_SCHEDULER_ADDRESS).",
    ),
]


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON data (NaN and inf as None, tables as markdown, paths as text)."""
    if hasattr(obj, "to_dict"):
        return jsonable(obj.to_dict())
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if np.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    if hasattr(obj, "title") and hasattr(obj, "rows"):  # ResultTable
        return tables.to_markdown(obj)
    return str(obj)


def check_json(path: Path | None, force: bool = False, protect=()) -> None:
    """``--json FILE`` before any work: never an input, never overwritten without --force."""
    if path is None or str(path) == "-":
        return
    check_writable_file(path, force=force, protect=protect, what="--json")


def write_json(path: Path, data: Any, force: bool = False) -> None:
    """Write ``data`` as JSON to ``path`` (``-``: stdout), atomically."""
    text = json.dumps(jsonable(data), indent=2)
    if str(path) == "-":
        sys.stdout.write(text + "\n")
        return
    check_json(path, force)
    write_text_safely(path, text + "\n", force=force)


def check_report_free(out_dir: Path, force: bool) -> None:
    """``--out DIR`` before any work: a folder (or nothing yet) without a report, or --force."""
    target = out_dir / REPORT_NAME
    if target.exists() and not force:
        raise FileExistsError(
            f"{target} already exists; pass --force to overwrite it, or choose another --out folder"
        )
    check_folder_usable(out_dir, "--out")  # a file there: "--out X: exists and is not a folder"


def fresh_dir(stem: str) -> Path:
    """``./stem``, or ``./stem-2``, ``./stem-3`` ... whichever holds no report yet."""
    candidate = Path(stem)
    n = 1
    while (candidate / REPORT_NAME).exists() or (candidate.exists() and not candidate.is_dir()):
        n += 1
        candidate = Path(f"{stem}-{n}")
    return candidate


def _parts(summary: Any) -> tuple[Any, Any, list, Any]:
    """``(evaluation, report, tables, passed)`` of a back-end summary (see the package docs)."""
    if hasattr(summary, "to_dict") and hasattr(summary, "methods"):
        return summary, None, [], None
    if isinstance(summary, Path):
        return None, summary, [], None
    if isinstance(summary, Mapping):
        return (
            summary.get("evaluation"),
            summary.get("report"),
            list(summary.get("tables") or []),
            summary.get("passed"),
        )
    return None, None, [], None


def _print_tables(summary: Any, evaluation: Any, report: Any, extra_tables: list) -> None:
    out = stdout()
    if evaluation is not None:
        out.print(tables.to_rich(tables.joint_method_table(evaluation)))
        if evaluation.run_time_s:
            out.print(tables.to_rich(tables.timing_table(evaluation)))
    for t in extra_tables:
        out.print(tables.to_rich(t) if hasattr(t, "rows") else t)
    if isinstance(summary, Mapping) and evaluation is None and not extra_tables and report is None:
        for k, v in summary.items():
            out.print(Text(f"{k}: {v}"))
    if report is not None:
        out.print(Text.assemble("Report: ", (str(report), "bold")))


def present(summary: Any, *, quiet: bool, json_file: Path | None, force: bool = False) -> None:
    """Print the tables of a back-end summary, write ``--json``; exit 1 if a target was missed."""
    if json_file is not None:
        write_json(json_file, summary if summary is not None else {}, force)
        quiet = quiet or str(json_file) == "-"
    if isinstance(summary, Mapping) and summary.get("warnings"):
        for w in summary["warnings"]:  # shown even with --quiet: the user must see them
            stderr().print(Text(f"kinefuse: warning: {one_line(w)}", style="yellow"))
    evaluation, report, extra_tables, passed = _parts(summary)
    if not quiet:
        _print_tables(summary, evaluation, report, extra_tables)
    if passed is False:
        reason = (
            summary.get("reason", "target not met")
            if isinstance(summary, Mapping)
            else "target not met"
        )
        fail(str(reason), EXIT_FAILURE)


def finish(
    summary: Any, table_of: Callable, *, quiet: bool, json_file: Path | None, force: bool = False
) -> None:
    """Write ``--json`` and print ``table_of(summary)`` (unless quiet or JSON goes to stdout)."""
    present(summary, quiet=True, json_file=json_file, force=force)
    if not quiet and str(json_file) != "-" and isinstance(summary, Mapping):
        stdout().print(table_of(summary))


def existing_file(path: Path, what: str) -> Path:
    """``path`` if it is an existing file, else an :class:`InputError` naming ``what``."""
    if not path.exists():
        raise InputError(f"{what} {path}: file not found")
    if path.is_dir():
        raise InputError(f"{what} {path}: is a folder, expected a file")
    return path
