"""The ``kinefuse`` command-line tool (also ``python -m kinefuse``), thin over the pipelines.

Commands: ``demo``, ``run``, ``init-session``, ``evaluate``, ``experiment``, ``batch``, ``bench``,
``stream``, ``replay``; ``kinefuse COMMAND --help`` documents each.

Exit codes
----------
0
    Success.
1
    Runtime failure, a feature not available in this version, or a target not met (a back-end
    summary with ``passed = False``).
2
    Bad input or usage: unknown option, missing file, invalid session file, an existing output
    that ``--force`` would overwrite. Every :class:`~kinefuse.exceptions.InputError` (and so
    ``FormatError`` and ``ConfigError``) is shown as one red line on stderr, never a traceback;
    ``kinefuse --debug COMMAND`` (or ``KINEFUSE_DEBUG=1``) also prints the traceback.

Back-end contracts
------------------
Each command imports its back-end lazily, so ``--help`` is fast and a missing back-end gives a
clear "not available in this version" message (exit 1) instead of an ImportError:

============  =========================================================================
command       back-end call
============  =========================================================================
demo          ``kinefuse.pipelines.demo.run_demo(out_dir, force, quiet) -> summary``
run           ``kinefuse.pipelines.session.run_session(path, out_dir, force) -> summary``
evaluate      ``kinefuse.pipelines.session.evaluate_recording(path, method) -> summary``
experiment    ``kinefuse.pipelines.experiments.run_experiment(name, data_dir) -> summary``
bench         ``kinefuse.evaluation.bench.run_bench(quick) -> summary``
stream        ``kinefuse.streaming.run_stream(cfg: StreamConfig, duration_s, out, status,
              *, idle_timeout_s, wait_for_reader_s, record_inputs) -> summary``
replay        ``kinefuse.streaming.replay_recording(path | "demo", rate, prefix, loop,
              duration_s, *, include_raw, wait_for_consumers_s, quiet) -> summary``
============  =========================================================================

A *summary* may be ``None``, a :class:`~pathlib.Path` (e.g. the report), an
:class:`~kinefuse.evaluation.metrics.EvaluationResult`, or a mapping; a mapping may hold an
``"evaluation"`` (EvaluationResult), a ``"report"`` path, ``"tables"`` (``ResultTable`` list)
and ``"passed"`` (False -> exit 1). ``--json FILE`` writes the summary as JSON (``-`` for stdout).
"""

import contextlib
import dataclasses
import functools
import importlib
import json
import logging
import math
import os
import sys
import traceback
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.text import Text

from kinefuse.exceptions import InputError

__all__ = ["EXIT_FAILURE", "EXIT_OK", "EXIT_USAGE", "app", "main", "progress"]

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2

_EPILOG = (
    "Exit codes: 0 success; 1 runtime failure, feature not available or target not met; "
    "2 bad input or usage (one red line on stderr; add --debug for the traceback)."
)

app = typer.Typer(
    name="kinefuse",
    help="IMU (+ optional camera) human joint position capture: EM-KF/FIR (Sun 2024) and "
    "ELM/FIR vision-assisted fusion (Xu 2023).",
    epilog=_EPILOG,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

_STATE = {"debug": False}

# click's exception base and typer's control-flow exceptions pass through untouched
_CLICK_EXCEPTION = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")
_PASS_THROUGH = (typer.Exit, typer.Abort, _CLICK_EXCEPTION)

_BACKENDS = {
    "demo": ("kinefuse.pipelines.demo", "run_demo"),
    "run": ("kinefuse.pipelines.run", "run_session"),
    "evaluate": ("kinefuse.pipelines.run", "evaluate_recording"),
    "experiment": ("kinefuse.pipelines.experiments", "run_experiment"),
    "bench": ("kinefuse.evaluation.bench", "run_bench"),
    "stream": ("kinefuse.streaming", "run_stream"),
    "replay": ("kinefuse.streaming", "replay_recording"),
}

EXPERIMENTS = ("paper-a", "paper-b", "neura-imu-only", "realism")


class BackendUnavailable(RuntimeError):
    """The back-end of a command is not part of this installation (exit 1)."""


def _stdout() -> Console:
    # not a terminal (pipe, file, CI log): do not squeeze tables into 80 columns
    return Console(highlight=False, width=None if sys.stdout.isatty() else 160)


def _stderr() -> Console:
    return Console(stderr=True, highlight=False, soft_wrap=True)


def _debug() -> bool:
    return _STATE["debug"] or os.environ.get("KINEFUSE_DEBUG", "") not in ("", "0")


def _one_line(message: str) -> str:
    return " ".join(str(message).split())


def _fail(message: str, code: int) -> None:
    if _debug():
        traceback.print_exc(file=sys.stderr)
    _stderr().print(Text(f"kinefuse: error: {_one_line(message)}", style="bold red"))
    raise typer.Exit(code)


def _guarded(fn: Callable) -> Callable:
    """Map exceptions of a command to exit codes and one-line messages (see module docs)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except _PASS_THROUGH:
            raise
        except (InputError, FileExistsError) as exc:  # InputError covers FormatError, ConfigError
            _fail(str(exc), EXIT_USAGE)
        except BackendUnavailable as exc:
            _fail(str(exc), EXIT_FAILURE)
        except KeyboardInterrupt:
            _stderr().print(Text("kinefuse: interrupted", style="bold red"))
            raise typer.Exit(130) from None
        except Exception as exc:
            hint = "" if _debug() else " (run `kinefuse --debug ...` for the traceback)"
            _fail(f"{type(exc).__name__}: {exc}{hint}", EXIT_FAILURE)

    return wrapper


def _backend(command: str) -> Callable:
    """Import the back-end function of ``command`` or raise :class:`BackendUnavailable`."""
    module, func = _BACKENDS[command]
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if missing.startswith("kinefuse") or not missing:
            raise BackendUnavailable(
                f"`kinefuse {command}` is not available in this version ({module}.{func} is missing)"
            ) from exc
        raise BackendUnavailable(
            f"`kinefuse {command}` needs the optional package {missing!r}; install it (e.g. pip install {missing})"
        ) from exc
    fn = getattr(mod, func, None)
    if fn is None:
        raise BackendUnavailable(
            f"`kinefuse {command}` is not available in this version ({module}.{func} is missing)"
        )
    return fn


@contextlib.contextmanager
def progress(
    description: str, total: float | None = None, *, quiet: bool = False
) -> Iterator[Callable[..., None]]:
    """A rich progress bar on stderr for long work; yields ``advance(n=1)``.

    Parameters
    ----------
    description : str
        Shown left of the bar.
    total : float, optional
        Number of steps (None: an indeterminate spinner).
    quiet : bool
        Show nothing (``advance`` is a no-op).

    Examples
    --------
    >>> with progress("Filtering joints", total=3, quiet=True) as advance:
    ...     for _ in range(3):
    ...         advance()
    """
    if quiet:
        yield lambda n=1: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        SpinnerColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    columns = [SpinnerColumn(), TextColumn("{task.description}"), BarColumn()]
    if total is not None:
        columns.append(MofNCompleteColumn())
    columns.append(TimeElapsedColumn())
    with Progress(*columns, console=_stderr(), transient=True) as bar:
        task = bar.add_task(description, total=total)
        yield lambda n=1: bar.advance(task, n)


# --------------------------------------------------------------------------------------------
# output helpers
# --------------------------------------------------------------------------------------------


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "to_dict"):
        return _jsonable(obj.to_dict())
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
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
        from kinefuse.evaluation.tables import to_markdown

        return to_markdown(obj)
    return str(obj)


def _check_json(path: Path | None, force: bool = False, protect=()) -> None:
    """``--json FILE`` before any work: never an input, never overwritten without --force."""
    if path is None or str(path) == "-":
        return
    from kinefuse.io.output_folder import check_writable_file

    check_writable_file(path, force=force, protect=protect, what="--json")


def _write_json(path: Path, data: Any, force: bool = False) -> None:
    text = json.dumps(_jsonable(data), indent=2)
    if str(path) == "-":
        sys.stdout.write(text + "\n")
        return
    from kinefuse.io._common import write_text_safely

    _check_json(path, force)
    write_text_safely(path, text + "\n", force=force)


def _check_report_free(out_dir: Path, force: bool) -> None:
    from kinefuse.evaluation.report import REPORT_NAME

    target = out_dir / REPORT_NAME
    if target.exists() and not force:
        raise FileExistsError(
            f"{target} already exists; pass --force to overwrite it, or choose another --out folder"
        )
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a folder")


def _fresh_dir(stem: str) -> Path:
    """``./stem``, or ``./stem-2``, ``./stem-3`` ... whichever holds no report yet."""
    from kinefuse.evaluation.report import REPORT_NAME

    candidate = Path(stem)
    n = 1
    while (candidate / REPORT_NAME).exists() or (candidate.exists() and not candidate.is_dir()):
        n += 1
        candidate = Path(f"{stem}-{n}")
    return candidate


def _present(summary: Any, *, quiet: bool, json_file: Path | None, force: bool = False) -> None:
    """Print the tables of a back-end summary, write ``--json``; exit 1 if a target was missed."""
    if json_file is not None:
        _write_json(json_file, summary if summary is not None else {}, force)
        quiet = quiet or str(json_file) == "-"
    evaluation = None
    report = None
    extra_tables = []
    passed = None
    if isinstance(summary, Mapping) and summary.get("warnings"):
        for w in summary["warnings"]:  # shown even with --quiet: the user must see them
            _stderr().print(Text(f"kinefuse: warning: {_one_line(w)}", style="yellow"))
    if hasattr(summary, "to_dict") and hasattr(summary, "methods"):
        evaluation = summary
    elif isinstance(summary, Path):
        report = summary
    elif isinstance(summary, Mapping):
        evaluation = summary.get("evaluation")
        report = summary.get("report")
        extra_tables = list(summary.get("tables") or [])
        passed = summary.get("passed")
    if not quiet:
        from kinefuse.evaluation import tables

        out = _stdout()
        if evaluation is not None:
            out.print(tables.to_rich(tables.joint_method_table(evaluation)))
            if evaluation.run_time_s:
                out.print(tables.to_rich(tables.timing_table(evaluation)))
        for t in extra_tables:
            out.print(tables.to_rich(t) if hasattr(t, "rows") else t)
        if (
            isinstance(summary, Mapping)
            and evaluation is None
            and not extra_tables
            and report is None
        ):
            for k, v in summary.items():
                out.print(f"{k}: {v}")
        if report is not None:
            out.print(Text.assemble("Report: ", (str(report), "bold")))
    if passed is False:
        reason = (
            summary.get("reason", "target not met")
            if isinstance(summary, Mapping)
            else "target not met"
        )
        _fail(str(reason), EXIT_FAILURE)


def _existing_file(path: Path, what: str) -> Path:
    if not path.exists():
        raise InputError(f"{what} {path}: file not found")
    if path.is_dir():
        raise InputError(f"{what} {path}: is a folder, expected a file")
    return path


# --------------------------------------------------------------------------------------------
# commands
# --------------------------------------------------------------------------------------------

_Quiet = Annotated[
    bool,
    typer.Option("--quiet", "-q", help="Print no tables or progress (errors still go to stderr)."),
]
_Json = Annotated[
    Path | None,
    typer.Option(
        "--json", metavar="FILE", help="Also write the results as JSON to FILE ('-' for stdout)."
    ),
]
_Force = Annotated[
    bool,
    typer.Option(
        "--force", "-f", help="Replace earlier results in the output folder and the --json file."
    ),
]
_JsonForce = Annotated[
    bool, typer.Option("--force", "-f", help="Overwrite an existing --json file.")
]


def _version_callback(value: bool) -> None:
    if value:
        from kinefuse import __version__

        typer.echo(f"kinefuse {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: Annotated[
        bool, typer.Option("--debug", help="Show the full traceback of errors.")
    ] = False,
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            callback=_version_callback,
            is_eager=True,
            help="Print the version and exit.",
        ),
    ] = False,
) -> None:
    """IMU (+ optional camera) human joint position capture.

    Start with `kinefuse demo`, then `kinefuse init-session` and `kinefuse run session.toml`.
    """
    _STATE["debug"] = bool(debug)


@app.command(epilog=_EPILOG)
@_guarded
def demo(
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            metavar="DIR",
            help="Output folder (default: ./kinefuse-demo, or -2, -3 ... if that has a report).",
        ),
    ] = None,
    force: _Force = False,
    quiet: _Quiet = False,
    json_file: _Json = None,
) -> None:
    """Run the demo on built-in data and write an HTML report (report.html) to DIR."""
    out_dir = _fresh_dir("kinefuse-demo") if out is None else out
    _check_report_free(out_dir, force)
    _check_json(json_file, force)
    from kinefuse import _compile

    # A first run on this machine: interpreting the kernels on the demo's few hundred samples
    # is much faster than compiling them (minutes on 2 cores). Results are identical.
    if not _compile.kernels_cached() and _compile.interpret_kernels() and not quiet:
        _stderr().print(
            "[yellow]First run on this machine: filter kernels run interpreted (identical "
            "results; `kinefuse run/experiment/bench` compile them once).[/yellow]"
        )
    summary = _backend("demo")(out_dir, force, quiet)
    _present(summary, quiet=quiet, json_file=json_file, force=force)


@app.command(epilog=_EPILOG)
@_guarded
def run(
    session: Annotated[
        Path,
        typer.Argument(metavar="SESSION.toml", help="Session file (see `kinefuse init-session`)."),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", "-o", metavar="DIR", help="Output folder (default: the session's out_dir)."
        ),
    ] = None,
    force: _Force = False,
    quiet: _Quiet = False,
    json_file: _Json = None,
) -> None:
    """Process a recording described by a session file; write the results and a report."""
    from kinefuse.session_file import load_session

    cfg = load_session(session)
    out_dir = cfg.out_dir if out is None else out
    _check_report_free(out_dir, force)
    backend = _backend("run")
    results = importlib.import_module(backend.__module__).output_paths(cfg, out_dir)
    _check_json(json_file, force, (*cfg.inputs, *results))  # never an input nor a result
    # the back-end checks every earlier result and writability before any processing
    with progress(f"Processing {cfg.name}", quiet=quiet):
        summary = backend(cfg.path, out_dir, force)
    _present(summary, quiet=quiet, json_file=json_file, force=force)


@app.command("init-session", epilog=_EPILOG)
@_guarded
def init_session(
    path: Annotated[
        Path, typer.Argument(metavar="PATH", help="Where to write the template.")
    ] = Path("session.toml"),
    name: Annotated[
        str | None, typer.Option("--name", help="Session name (default: from the file name).")
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", "-f", help="Overwrite an existing file.")
    ] = False,
) -> None:
    """Write a commented session-file template to PATH (default: session.toml)."""
    from kinefuse.session_file import session_template

    if path.exists() and not force:
        raise FileExistsError(
            f"{path} already exists; pass --force to overwrite it, or give another PATH"
        )
    if path.is_dir():
        raise InputError(f"{path} is a folder; give a file name such as {path / 'session.toml'}")
    if not path.parent.is_dir():
        raise InputError(f"folder {path.parent} does not exist; create it first")
    session_name = name or (path.stem if path.stem != "session" else "my-session")
    path.write_text(session_template(session_name, filename=path.name), encoding="utf-8")
    _stdout().print(
        Text.assemble(
            "Wrote ",
            (str(path), "bold"),
            ". Edit the [imu] path and [imu.segments], then run: ",
            (f"kinefuse run {path}", "bold"),
        )
    )


@app.command(epilog=_EPILOG)
@_guarded
def evaluate(
    recording: Annotated[
        Path,
        typer.Argument(
            metavar="RECORDING",
            help="Recording with a reference (ground truth): a file or a dataset folder, "
            "anything kinefuse.io.load reads.",
        ),
    ],
    method: Annotated[
        str,
        typer.Option(
            "--method",
            "-m",
            metavar="NAME",
            help="Method to evaluate (see `kinefuse init-session` for the names).",
        ),
    ],
    fmt: Annotated[
        str | None,
        typer.Option(
            "--format",
            metavar="FORMAT",
            help="Reader (a kinefuse.io.FORMATS name; default: detected).",
        ),
    ] = None,
    calibration: Annotated[
        str,
        typer.Option(
            "--calibration",
            metavar="METHOD",
            help="static (default, a still pose in the IMU data), functional, vision, or "
            "reference (then every table is labelled 'calibrated on reference').",
        ),
    ] = "static",
    root: Annotated[
        str,
        typer.Option(
            "--root",
            metavar="ROOT",
            help="Where the chain starts: reference (default: the root joints as the "
            "reference measures them), vision, fixed or pelvis.",
        ),
    ] = "reference",
    align: Annotated[
        str,
        typer.Option(
            "--align",
            metavar="none|rigid",
            help="rigid: Kabsch-align the estimates to the reference before scoring (labelled).",
        ),
    ] = "none",
    body_height: Annotated[
        float | None,
        typer.Option(
            "--body-height",
            metavar="M",
            help="Body height in m, for segment lengths from Winter (2009) ratios.",
        ),
    ] = None,
    quiet: _Quiet = False,
    json_file: _Json = None,
    force: _JsonForce = False,
) -> None:
    """Run one method on a recording and print RMSE tables against its reference."""
    from kinefuse.io import FORMATS
    from kinefuse.session_file import CALIBRATIONS, METHODS, ROOTS

    if not recording.exists():
        raise InputError(f"RECORDING {recording}: file not found (a file or a dataset folder)")
    _check_json(json_file, force, (recording,))
    if method not in METHODS:
        raise InputError(
            f"--method: unknown method {method!r}; expected one of {', '.join(METHODS)}"
        )
    if fmt is not None and fmt not in FORMATS:
        raise InputError(
            f"--format: unknown format {fmt!r}; expected one of {', '.join(sorted(FORMATS))}"
        )
    for opt, value, choices in (
        ("--calibration", calibration, CALIBRATIONS),
        ("--root", root, ROOTS),
        ("--align", align, ("none", "rigid")),
    ):
        if value not in choices:
            raise InputError(f"{opt}: expected one of {', '.join(choices)}, got {value!r}")
    summary = _backend("evaluate")(
        recording,
        method,
        format=fmt,
        calibration=calibration,
        root=root,
        align=align,
        body_height_m=body_height,
    )
    _present(summary, quiet=quiet, json_file=json_file, force=force)


@app.command(epilog=_EPILOG)
@_guarded
def experiment(
    name: Annotated[
        str,
        typer.Argument(
            metavar="paper-a|paper-b|neura-imu-only|realism",
            help="Which experiment: a paper's, the Neura walk from its IMUs alone, or 'realism' "
            "(virtual vs real sensors).",
        ),
    ],
    data: Annotated[
        Path | None,
        typer.Option(
            "--data", metavar="DIR", help="Data folder (default: the back-end's, ../shared/data)."
        ),
    ] = None,
    quick: Annotated[
        bool,
        typer.Option("--quick", help="A reduced configuration (seconds) instead of the full run."),
    ] = False,
    data_set: Annotated[
        str,
        typer.Option(
            "--set",
            metavar="report|tuning",
            help="paper-a/paper-b: declared set of recordings, 'report' (default; nothing is tuned on it) or "
            "'tuning' (the only set kinefuse was developed on).",
        ),
    ] = "report",
    quiet: _Quiet = False,
    json_file: _Json = None,
    force: _JsonForce = False,
) -> None:
    """Reproduce a paper's experiment and compare with the paper's tables."""
    if name not in EXPERIMENTS:
        raise InputError(f"unknown experiment {name!r}; expected one of {', '.join(EXPERIMENTS)}")
    if data is not None and not data.is_dir():
        raise InputError(f"--data {data}: folder not found")
    if data_set not in ("report", "tuning"):
        raise InputError(f"--set: expected 'report' or 'tuning', got {data_set!r}")
    _check_json(json_file, force, () if data is None else (data,))
    summary = _backend("experiment")(name, data, quick=quick or None, quiet=quiet, split=data_set)
    _present(summary, quiet=quiet, json_file=json_file, force=force)


@app.command(epilog=_EPILOG)
@_guarded
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
    workers: Annotated[
        int | None,
        typer.Option("--workers", "-w", min=1, help="LocalCluster workers (default: cores)."),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler",
            metavar="tcp://HOST:PORT",
            envvar="DASK_SCHEDULER_ADDRESS",
            help="An existing Dask scheduler instead of a LocalCluster.",
        ),
    ] = None,
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
    quiet: _Quiet = False,
    json_file: _Json = None,
) -> None:
    """Run a whole study (recordings x methods) on Dask: one table, per-recording outputs, a report."""
    from kinefuse import batch as kb

    if kb.missing_packages():
        raise BackendUnavailable(
            f"`kinefuse batch` needs {', '.join(kb.missing_packages())}: "
            "pip install 'kinefuse[batch]'"
        )
    from kinefuse.batch.runner import compare_table, summary_tables

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
    if compare:
        try:
            counts = [int(n) for n in compare.split(",")]
        except ValueError:
            raise InputError(f"--compare-workers: expected e.g. 1,2, got {compare!r}") from None
        runs = kb.compare_workers(st, counts, quiet=quiet)
        _present({"tables": [compare_table(runs)], "runs": runs}, quiet=quiet, json_file=json_file)
        return
    s = kb.run_study(st, force=force, workers=workers, scheduler=scheduler, dashboard=dashboard,
                     quiet=quiet)  # fmt: skip
    s["tables"] = summary_tables(s)
    if s["failed"]:
        s["passed"], s["reason"] = False, f"{len(s['failed'])} of {len(st.tasks)} tasks failed"
    _present(s, quiet=quiet, json_file=json_file)


@app.command(epilog=_EPILOG)
@_guarded
def bench(
    quick: Annotated[
        bool, typer.Option("--quick", help="A short run (seconds) instead of the full benchmark.")
    ] = False,
    quiet: _Quiet = False,
    json_file: _Json = None,
    force: _JsonForce = False,
) -> None:
    """Measure per-step latency and batch throughput of the filters, next to peer libraries."""
    _check_json(json_file, force)
    summary = _backend("bench")(quick)
    _present(summary, quiet=quiet, json_file=json_file, force=force)


@app.command("warm-up", epilog=_EPILOG)
@_guarded
def warm_up(quiet: _Quiet = False) -> None:
    """Compile the numba kernels once (minutes on a small machine), with progress; later runs load them."""
    from kinefuse.filters.warm_up import warm_up as _warm_up

    console = _stdout()
    _warm_up(report=None if quiet else (lambda line: console.print(line)))


_Seconds = float | None


def _positive(value: float | None, option: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{option}: expected a number of seconds > 0, got {value:g}")


def _stream_session(path: Path, resolve_timeout_s: float | None):
    """The StreamConfig of SESSION.toml: a ``[stream]`` table -> streaming loader, else offline."""
    import dataclasses

    from kinefuse.session_file import load_session, read_toml
    from kinefuse.streaming.config import load_stream_config, stream_config_from_session

    p = path.expanduser()
    _existing_file(p, "SESSION.toml")
    doc = read_toml(p)
    overrides = {} if resolve_timeout_s is None else {"resolve_timeout_s": resolve_timeout_s}
    if "stream" in doc:
        return dataclasses.replace(load_stream_config(p), **overrides)
    return stream_config_from_session(load_session(p), **overrides)


def _out_files(out: Path, force: bool) -> None:
    if not out.name or out.is_dir():
        raise InputError(f"--out {out}: is a folder; give a file name such as {out / 'live'}")
    for target in (out.with_suffix(".npz"), out.with_suffix(".json")):
        if target.exists() and not force:
            raise FileExistsError(
                f"{target} already exists; pass --force to overwrite it, or choose another --out"
            )


def _kv_table(title: str, rows: list[tuple[str, str]], caption: str | None = None):
    from rich import box
    from rich.table import Table

    t = Table(title=title, caption=caption, caption_justify="left", box=box.SIMPLE,
              pad_edge=False, show_header=False)  # fmt: skip
    t.add_column("item", no_wrap=True)
    t.add_column("value", no_wrap=True)
    for k, v in rows:
        t.add_row(k, v)
    return t


def _ms(v) -> str:
    return "–" if v is None else f"{v:.3f}"


def _stream_table(summary: Mapping):
    lat = summary.get("latency_ms") or {}
    rows = [
        ("output stream", str(summary.get("output_stream", "–"))),
        ("outputs", str(summary.get("outputs", 0))),
        ("frames", str(summary.get("frames", 0))),
        ("latency p50 / p99 / max (ms)",
         f"{_ms(lat.get('p50'))} / {_ms(lat.get('p99'))} / {_ms(lat.get('max'))}"),
        ("timed outputs (start-up backlog not timed)",
         f"{lat.get('n', 0)} ({lat.get('catch_up_outputs', 0)})"),
    ]  # fmt: skip
    counters = summary.get("counters") or {}
    rows += [
        (name.replace("_", " "), str(n))
        for name, n in counters.items()
        if n and name not in ("outputs", "frames")
    ]
    missing = summary.get("missing") or []
    rows.append(("missing streams", ", ".join(missing) if missing else "none"))
    if summary.get("out"):
        rows.append(("written", str(summary["out"])))
    if summary.get("view_url"):
        v = summary.get("view") or {}
        rows.append(
            ("live view", f"{summary['view_url']} ({v.get('sent', 0)} frames sent to viewers)")
        )
    caption = "stopped by Ctrl-C (pending frames flushed)" if summary.get("interrupted") else None
    return _kv_table("kinefuse stream", rows, caption)


def _replay_table(summary: Mapping, rate: float):
    from rich import box
    from rich.table import Table

    caption = (
        f"{summary.get('recording_s', 0.0):.1f} s of recording published in "
        f"{summary.get('duration_s', 0.0):.1f} s wall time (--rate {rate:g})"
    )
    if summary.get("interrupted"):
        caption += "; stopped by Ctrl-C"
    t = Table(title="kinefuse replay", caption=caption, caption_justify="left",
              box=box.SIMPLE_HEAD, pad_edge=False)  # fmt: skip
    t.add_column("stream", no_wrap=True)
    t.add_column("samples pushed", justify="right", no_wrap=True)
    for name, n in (summary.get("samples") or {}).items():
        t.add_row(name, str(n))
    return t


def _finish(
    summary: Any, table_of: Callable, *, quiet: bool, json_file: Path | None, force: bool = False
) -> None:
    """Write ``--json`` and print ``table_of(summary)`` (unless quiet or JSON goes to stdout)."""
    _present(summary, quiet=True, json_file=json_file, force=force)
    if not quiet and str(json_file) != "-" and isinstance(summary, Mapping):
        _stdout().print(table_of(summary))


@app.command(epilog=_EPILOG)
@_guarded
def stream(
    session: Annotated[
        Path,
        typer.Argument(
            metavar="SESSION.toml",
            help="Streaming session (with a stream table) or offline session "
            "(`kinefuse init-session`).",
        ),
    ],
    duration: Annotated[
        _Seconds,
        typer.Option(
            "--duration",
            metavar="SECONDS",
            help="Stop after this wall time (default: Ctrl-C or --idle-timeout).",
        ),
    ] = None,
    idle_timeout: Annotated[
        _Seconds,
        typer.Option(
            "--idle-timeout",
            metavar="SECONDS",
            help="Stop once no input sample arrived for this long.",
        ),
    ] = None,
    resolve_timeout: Annotated[
        _Seconds,
        typer.Option(
            "--resolve-timeout",
            metavar="SECONDS",
            help="How long to look for the input streams (default: the session's "
            "resolve_timeout_s, 5 s).",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            metavar="FILE",
            help="Write the outputs to FILE.npz and the summary to FILE.json.",
        ),
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", "-f", help="Overwrite existing --out files.")
    ] = False,
    record_inputs: Annotated[
        bool,
        typer.Option(
            "--record-inputs",
            help="Also store the accepted input samples in FILE.npz (re-run the session "
            "offline with kinefuse.streaming.offline_causal); needs --out.",
        ),
    ] = False,
    wait_for_reader: Annotated[
        _Seconds,
        typer.Option(
            "--wait-for-reader",
            metavar="SECONDS",
            help="Wait up to this long for a reader of the output stream before "
            "starting (inputs are buffered meanwhile).",
        ),
    ] = None,
    no_status: Annotated[
        bool, typer.Option("--no-status", help="No live status table on stderr.")
    ] = False,
    view: Annotated[
        bool,
        typer.Option(
            "--view",
            help="Serve a live 3-D view (skeleton, source per joint, latency) on "
            "http://127.0.0.1:PORT/ (loopback only; the address is printed). Viewers never "
            "slow the stream down.",
        ),
    ] = False,
    view_port: Annotated[
        int,
        typer.Option("--view-port", metavar="PORT", help="Port of --view (0 = any free port)."),
    ] = 0,
    quiet: _Quiet = False,
    json_file: _Json = None,
) -> None:
    """Fuse live LSL streams online and publish the joints; Ctrl-C stops (frames are flushed).

    Inputs: PREFIX_imu_SEGMENT (type IMU) per segment and PREFIX_camera (type MoCap), see replay.

    Output: PREFIX_fused (type MoCap), one sample per camera frame: x, y, z, std (m) per joint.

    PREFIX: name_prefix of a streaming session (stream table), or an offline session's name.
    """
    for value, option in ((duration, "--duration"), (idle_timeout, "--idle-timeout"),
                          (resolve_timeout, "--resolve-timeout"),
                          (wait_for_reader, "--wait-for-reader")):  # fmt: skip
        _positive(value, option)
    if record_inputs and out is None:
        raise InputError("--record-inputs needs --out FILE (the inputs are stored in FILE.npz)")
    if not 0 <= view_port <= 65535:
        raise InputError(f"--view-port must be in [0, 65535], got {view_port}")
    cfg = _stream_session(session, resolve_timeout)
    if out is not None:
        _out_files(out, force)
    _check_json(json_file, force, (session,))
    if quiet:
        logging.getLogger("kinefuse.streaming").setLevel(logging.ERROR)
    summary = _backend("stream")(
        cfg, duration, out, not (no_status or quiet), idle_timeout_s=idle_timeout,
        wait_for_reader_s=wait_for_reader, record_inputs=record_inputs,
        **({"view_port": view_port} if view else {}),
    )  # fmt: skip
    _finish(summary, _stream_table, quiet=quiet, json_file=json_file, force=force)


@app.command(epilog=_EPILOG)
@_guarded
def replay(
    recording: Annotated[
        str,
        typer.Argument(
            metavar="RECORDING",
            help="A file or folder `kinefuse.io.load` reads, or `demo` (built-in: 9 virtual IMUs "
            "at 100 Hz and a virtual camera at 30 Hz with outages, 12.5 s).",
        ),
    ],
    rate: Annotated[
        float,
        typer.Option("--rate", metavar="FACTOR", help="Speed-up factor (2 = twice real time)."),
    ] = 1.0,
    prefix: Annotated[
        str, typer.Option("--prefix", metavar="TEXT", help="Stream name prefix.")
    ] = "kinefuse",
    loop: Annotated[
        bool,
        typer.Option("--loop", help="Start again at the end (timestamps keep increasing)."),
    ] = False,
    duration: Annotated[
        _Seconds,
        typer.Option(
            "--duration",
            metavar="SECONDS",
            help="Publish this much recording time (default: the recording once, or "
            "until Ctrl-C with --loop).",
        ),
    ] = None,
    no_raw: Annotated[
        bool,
        typer.Option("--no-raw", help="Publish the orientation channels only (no acc_*, gyr_*)."),
    ] = False,
    wait_for_consumers: Annotated[
        _Seconds,
        typer.Option(
            "--wait-for-consumers",
            metavar="SECONDS",
            help="Before publishing, wait up to this long until every stream has a reader.",
        ),
    ] = None,
    quiet: _Quiet = False,
    json_file: _Json = None,
    force: _JsonForce = False,
) -> None:
    """Publish a recording as live LSL streams, at its real rate or --rate times faster.

    PREFIX_imu_SEGMENT, one per IMU (type IMU): qw qx qy qz, acc_x/y/z m/s^2, gyr_x/y/z rad/s.

    PREFIX_camera (type MoCap): per joint JOINT_x/_y/_z in m (NaN if unseen), JOINT_available.

    Timestamps: the recording's, moved to the LSL clock and divided by --rate. Ctrl-C stops.
    """
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"--rate: expected a speed-up factor > 0, got {rate:g}")
    _positive(duration, "--duration")
    _positive(wait_for_consumers, "--wait-for-consumers")
    if not prefix.strip():
        raise InputError("--prefix: expected a non-empty stream name prefix")
    if recording != "demo" and not Path(recording).exists():
        raise InputError(
            f"RECORDING {recording}: file not found (give a file or folder kinefuse.io.load "
            "reads, or `demo`)"
        )
    _check_json(json_file, force, () if recording == "demo" else (Path(recording),))
    source = recording if recording == "demo" else Path(recording)
    if not quiet:
        _stderr().print(
            f"Publishing {recording} as {prefix}_* LSL streams at {rate:g}x (Ctrl-C stops)..."
        )
    summary = _backend("replay")(
        source, rate, prefix, loop, duration, include_raw=not no_raw,
        wait_for_consumers_s=wait_for_consumers, quiet=quiet,
    )  # fmt: skip
    _finish(
        summary, lambda s: _replay_table(s, rate), quiet=quiet, json_file=json_file, force=force
    )


def main() -> None:
    """Console-script entry point (``kinefuse``)."""
    app(prog_name="kinefuse")
