"""``kinefuse batch``: a whole study on Dask (:mod:`kinefuse.batch`; needs the ``batch`` extra)."""

import dataclasses
from pathlib import Path
from typing import Annotated

import typer

from kinefuse.cli._app import BackendUnavailable, backend_module
from kinefuse.cli._output import Json, Quiet, Scheduler, Workers, check_json, present
from kinefuse.exceptions import InputError
from kinefuse.io.output_folder import check_folder_usable

__all__ = ["batch"]


def batch(
    study: Annotated[
        str,
        typer.Argument(
            metavar="STUDY",
            help="Study TOML, or a folder / glob of session files (quote the glob).",
        ),
    ],
    method: Annotated[
        list[str] | None,
        typer.Option(
            "--method", "-m", metavar="NAME", help="Folder/glob: methods to run (repeat)."
        ),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", "-o", metavar="DIR", help="Output folder.")
    ] = None,
    workers: Workers = None,
    scheduler: Scheduler = None,
    dashboard: Annotated[
        bool, typer.Option("--dashboard", help="Serve the Dask dashboard on 127.0.0.1.")
    ] = False,
    compare: Annotated[
        str | None,
        typer.Option(
            "--compare-workers", metavar="N,M", help="Time the whole study with N, then M workers."
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", "-f", help="Redo finished recordings.")] = False,
    quiet: Quiet = False,
    json_file: Json = None,
) -> None:
    """Run a whole study (recordings x methods) on Dask: one table, per-recording outputs, a report."""
    kb = backend_module("batch")  # imported when the command runs: it loads compiled kernels
    runner = backend_module("batch", "kinefuse.batch.runner")
    if kb.missing_packages():
        raise BackendUnavailable(
            f"`kinefuse batch` needs {', '.join(kb.missing_packages())}: "
            "pip install 'kinefuse[batch]'"
        )
    counts = _worker_counts(compare) if compare else None
    _check_json_free(json_file)
    if Path(study).suffix == ".toml" and Path(study).is_file():
        if method:
            raise InputError(
                "--method: only for a folder or glob; a study file has [study] methods"
            )
        st = kb.load_study(study)
        if out is not None:
            st = dataclasses.replace(st, out_dir=out.resolve())
    else:
        st = kb.study_from_sessions(study, method, out)
    check_folder_usable(Path(st.out_dir), "--out" if out is not None else f"{study}: out_dir")
    if counts:
        runs = kb.compare_workers(st, counts, quiet=quiet)
        c = {"tables": runner.compare_tables(runs), "runs": runs}
        bad = [
            f"{len(r['failed'])} of {r['counts']['total']} tasks failed with {r['workers']} "
            "worker(s)"
            for r in runs
            if r["failed"]
        ]
        if bad:  # as a plain run: the failed tasks are listed and the exit code is 1
            c["passed"], c["reason"] = False, "; ".join(bad)
        present(c, quiet=quiet, json_file=json_file)
        return
    s = kb.run_study(st, force=force, workers=workers, scheduler=scheduler, dashboard=dashboard,
                     quiet=quiet)  # fmt: skip
    s["tables"] = runner.summary_tables(s)
    if s["failed"]:
        s["passed"], s["reason"] = False, f"{len(s['failed'])} of {len(st.tasks)} tasks failed"
    present(s, quiet=quiet, json_file=json_file)


def _worker_counts(compare: str) -> list[int]:
    """``--compare-workers N,M``: the worker counts, each at least 1 (as ``--workers``)."""
    try:
        counts = [int(n) for n in compare.split(",")]
    except ValueError:
        raise InputError(f"--compare-workers: expected e.g. 1,2, got {compare!r}") from None
    bad = [n for n in counts if n < 1]
    if bad:
        raise InputError(
            f"--compare-workers: expected worker counts of at least 1 (e.g. 1,2), got {bad[0]} "
            f"in {compare!r}"
        )
    return counts


def _check_json_free(json_file: Path | None) -> None:
    """``--json FILE`` before any work: an existing file is refused (``--force`` of this command
    redoes finished tasks; it does not overwrite the --json file)."""
    if json_file is not None and str(json_file) != "-" and json_file.is_file():
        raise FileExistsError(
            f"--json {json_file}: file exists; remove it or choose another file (for `kinefuse "
            "batch`, --force redoes every finished task and does not overwrite the --json file)"
        )
    check_json(json_file)  # a folder, a folder that does not exist...
