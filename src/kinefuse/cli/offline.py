"""Commands on recordings and built-in data: ``demo``, ``run``, ``init-session``, ``evaluate``,
``experiment``, ``bench`` and ``warm-up``."""

import importlib
from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

from kinefuse import _kernel_mode
from kinefuse.cli._app import BackendUnavailable, backend, backend_module, stderr, stdout
from kinefuse.cli._output import (
    Force,
    Json,
    JsonForce,
    Quiet,
    Scheduler,
    Workers,
    check_json,
    check_report_free,
    fresh_dir,
    present,
)
from kinefuse.exceptions import ConfigError, InputError
from kinefuse.io import FORMATS, detect_format
from kinefuse.io.output_folder import check_writable_file
from kinefuse.progress import progress
from kinefuse.session_file import CALIBRATIONS, METHODS, ROOTS, load_session, session_template
from kinefuse.session_file.from_recording import filled_template

__all__ = [
    "EXPERIMENTS",
    "INTERPRET_MAX_BYTES",
    "TRIAL_EXPERIMENTS",
    "bench",
    "demo",
    "evaluate",
    "compile_kernels_now",
    "experiment",
    "first_run_kernels",
    "init_session",
    "run",
    "warm_up",
]

#: ``kinefuse experiment NAME`` choices (checked before the back-end is imported).
EXPERIMENTS = ("paper-a", "paper-b", "neura-imu-only", "realism")
#: Those made of independent trials, which ``--workers``/``--scheduler`` run on Dask
#: (:data:`kinefuse.apps.experiments.TRIAL_EXPERIMENTS`; checked before a cluster starts).
TRIAL_EXPERIMENTS = ("paper-a", "paper-b")


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
    force: Force = False,
    quiet: Quiet = False,
    json_file: Json = None,
) -> None:
    """Run the demo on built-in data and write an HTML report (report.html) to --out DIR."""
    out_dir = fresh_dir("kinefuse-demo") if out is None else out
    check_report_free(out_dir, force)
    check_json(json_file, force)
    # Before any kernel module is imported (the back-end is, below): on a first run on this
    # machine, interpreting the kernels on the demo's few hundred samples is much faster than
    # compiling them (minutes on 2 cores). Results are identical.
    if not _kernel_mode.kernels_cached() and _kernel_mode.interpret_kernels() and not quiet:
        stderr().print(
            "[yellow]The filter kernels are not compiled on this machine yet: they run "
            "interpreted (identical results; `kinefuse warm-up` compiles them once).[/yellow]"
        )
    summary = backend("demo")(out_dir, force, quiet)
    present(summary, quiet=quiet, json_file=json_file, force=force)


#: Inputs up to this many bytes run interpreted on a machine whose kernels are not compiled yet
#: (the Neura walk, 2.5 MB for 9.6 s: 8.5 s interpreted, byte-identical outputs; compiling
#: every kernel takes about 2 min of CPU on this 2-core machine).
INTERPRET_MAX_BYTES = 20_000_000


def _input_bytes(paths) -> int:
    """Total size of the input files and folders (0 for what is missing)."""
    total = 0
    for p in map(Path, paths):
        if p.is_file():
            total += p.stat().st_size
        elif p.is_dir():
            total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
    return total


def first_run_kernels(inputs, quiet: bool) -> str:
    """Before a command's back-end is imported: on a machine without compiled kernels, run a
    small recording interpreted; a large one is to be compiled first (issue 15).

    Returns ``"compiled"`` (kernels already cached, or already loaded in this process: they
    compile as they are used), ``"interpreted"`` (inputs up to :data:`INTERPRET_MAX_BYTES`:
    identical results without the compile wait) or ``"compile"`` (larger inputs: the caller
    runs :func:`compile_kernels_now` once its input checks have passed).
    """
    if _kernel_mode.kernels_cached():
        return "compiled"
    size = _input_bytes(inputs)
    if size > INTERPRET_MAX_BYTES:
        return "compile"
    if not _kernel_mode.interpret_kernels():
        return "compiled"  # kernel modules already loaded here: they compile as used
    if not quiet:
        amount = f"{size / 1e6:.1f} MB" if size >= 100_000 else f"{max(size, 1) / 1e3:.0f} kB"
        stderr().print(
            f"[yellow]The filter kernels are not compiled on this machine yet: they run "
            f"interpreted for these {amount} of input (identical results, no compile wait); "
            "`kinefuse warm-up` compiles them once (about 2 min) for long recordings.[/yellow]"
        )
    return "interpreted"


def compile_kernels_now(quiet: bool) -> None:
    """Compile every kernel once, printing ``kinefuse warm-up``'s progress lines (a first run on
    a large input; see :func:`first_run_kernels`)."""
    # lazy: loads the kernel modules, after the interpreted-kernel decision
    from kinefuse.pipelines.warm_up import warm_up as compile_kernels

    console = stderr()
    if not quiet:
        console.print(
            "First run on this machine with a large input: compiling the filter kernels once "
            "(about 2 min on 2 cores; cached for later runs)"
        )
    compile_kernels(report=None if quiet else lambda m: console.print(Text(m)))


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
    force: Force = False,
    quiet: Quiet = False,
    json_file: Json = None,
) -> None:
    """Process a recording described by a session file; write the results and a report."""
    cfg = load_session(session)
    out_dir = cfg.out_dir if out is None else out
    check_report_free(out_dir, force)
    kernels = first_run_kernels(cfg.inputs, quiet)  # before the back-end imports any kernel
    run_session = backend("run")
    results = importlib.import_module(run_session.__module__).output_paths(cfg, out_dir)
    check_json(json_file, force, (*cfg.inputs, *results))  # never an input nor a result
    if kernels == "compile":
        compile_kernels_now(quiet)
    # the back-end checks every earlier result and writability before any processing
    with progress(f"Processing {cfg.name}", quiet=quiet) as bar:
        summary = run_session(
            cfg.path, out_dir, force, stage=lambda s: bar.describe(f"Processing {cfg.name}: {s}")
        )
    present(summary, quiet=quiet, json_file=json_file, force=force)


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
    source: Annotated[
        Path | None,
        typer.Option(
            "--from",
            metavar="RECORDING",
            help="Fill the template from a recording (a file or folder kinefuse.io.load reads): "
            "its reader and path, the sensors it recognises as segments, its camera and "
            "reference; the root, calibration and method that follow.",
        ),
    ] = None,
    fmt: Annotated[
        str | None,
        typer.Option("--format", metavar="FORMAT", help="Reader of --from (default: detected)."),
    ] = None,
) -> None:
    """Write a commented session-file template to PATH (default: session.toml)."""
    if fmt is not None and source is None:
        raise InputError("--format is for --from RECORDING; give the recording too")
    if fmt is not None and fmt not in FORMATS:
        raise InputError(
            f"--format: unknown reader {fmt!r}; expected one of {', '.join(sorted(FORMATS))}"
        )
    check_writable_file(path, force=force, what="PATH")  # a folder, an existing file...
    session_name = name or (path.stem if path.stem != "session" else "my-session")
    if source is None:
        text, what = (
            session_template(session_name, filename=path.name),
            "Edit the [imu] path and [imu.segments]",
        )
    else:
        try:
            sk = backend("init-session")(source, path.parent, fmt)
        except InputError as exc:  # name the recording unless the message does
            if str(source) in str(exc):
                raise
            raise InputError(f"{source}: {exc}") from None
        text = filled_template(session_name, path.name, sk)
        mapped = ", ".join(f"{s} = {n}" for s, n in sk.segments.items()) or "none"
        what = (
            f"From {sk.path} ({sk.format}): segments {mapped}"
            + (f"; not recognised: {', '.join(sk.unmapped)}" if sk.unmapped else "")
            + (f"; functional calibration: {sk.no_still_window}" if sk.no_still_window else "")
            + (
                f"; this file is one sensor of the recording in {sk.whole_folder}: --from that "
                "folder maps every sensor"
                if sk.whole_folder
                else ""
            )
            + (
                ". Name each sensor's segment in [imu.segments] (kinefuse run needs one at least)"
                if not sk.segments
                else ". Check it"
            )
        )
    path.write_text(text, encoding="utf-8")
    stdout().print(
        Text.assemble("Wrote ", (str(path), "bold"), f". {what}, then run: ",
                      (f"kinefuse run {path}", "bold"))
    )  # fmt: skip


_Recording = Annotated[
    Path,
    typer.Argument(
        metavar="RECORDING",
        help="Recording with a reference (ground truth): a file or a dataset folder, "
        "anything kinefuse.io.load reads.",
    ),
]
_Method = Annotated[
    str,
    typer.Option(
        "--method",
        "-m",
        metavar="NAME",
        help=(
            f"Method to evaluate: {', '.join(METHODS)} (what each needs: the template of "
            "`kinefuse init-session`; the camera methods need a camera besides the reference)."
        ),
    ),
]
_Format = Annotated[
    str | None,
    typer.Option(
        "--format",
        metavar="FORMAT",
        help="Reader (a kinefuse.io.FORMATS name; default: detected).",
    ),
]
_Calibration = Annotated[
    str,
    typer.Option(
        "--calibration",
        metavar="METHOD",
        help="auto (default: vision with a camera the method fuses; else static when the IMUs "
        "hold still for 2 s somewhere, functional when they never do), static (a still pose "
        "in the IMU data), functional (movement), vision, or reference (then every table is "
        "labelled 'calibrated on reference').",
    ),
]
_Root = Annotated[
    str,
    typer.Option(
        "--root",
        metavar="ROOT",
        help="Where the chain starts: reference (default: the root joints as the "
        "reference measures them), vision, fixed or pelvis.",
    ),
]
_Align = Annotated[
    str,
    typer.Option(
        "--align",
        metavar="none|rigid",
        help="rigid: Kabsch-align the estimates to the reference before scoring (labelled).",
    ),
]
_BodyHeight = Annotated[
    float | None,
    typer.Option(
        "--body-height",
        metavar="M",
        help="Body height in m, for segment lengths from Winter (2009) ratios.",
    ),
]


def _check_choice(option: str, value: str | None, choices, what: str) -> None:
    """``value`` (None: not given) must be one of ``choices``; ``what`` names the kind."""
    if value is not None and value not in choices:
        raise InputError(
            f"{option}: unknown {what} {value!r}; expected one of {', '.join(choices)}"
        )


def evaluate(
    recording: _Recording,
    method: _Method,
    fmt: _Format = None,
    calibration: _Calibration = "auto",
    root: _Root = "reference",
    align: _Align = "none",
    body_height: _BodyHeight = None,
    quiet: Quiet = False,
    json_file: Json = None,
    force: JsonForce = False,
) -> None:
    """Run one method on a recording and print RMSE tables against its reference."""
    if not recording.exists():
        raise InputError(f"RECORDING {recording}: file not found (a file or a dataset folder)")
    check_json(json_file, force, (recording,))
    _check_choice("--method", method, METHODS, "method")
    _check_choice("--format", fmt, sorted(FORMATS), "format")
    for opt, value, choices in (
        ("--calibration", calibration, ("auto", *CALIBRATIONS)),
        ("--root", root, ROOTS),
        ("--align", align, ("none", "rigid")),
    ):
        if value not in choices:
            raise InputError(f"{opt}: expected one of {', '.join(choices)}, got {value!r}")
    if body_height is not None and not 0.5 <= body_height <= 2.8:
        raise InputError(f"--body-height: expected metres (0.5-2.8), got {body_height:g}")
    if fmt is None:
        detect_format(recording)  # an unreadable recording fails here, before any kernel note
    if first_run_kernels((recording,), quiet) == "compile":  # before any kernel is imported
        compile_kernels_now(quiet)
    try:
        summary = backend("evaluate")(
            recording,
            method,
            format=fmt,
            calibration=calibration,
            root=root,
            align=align,
            body_height_m=body_height,
        )
    except InputError as exc:  # a session's key named in a message: evaluate's option instead
        msg = _as_options(str(exc))
        if msg == str(exc):
            raise
        raise (ConfigError if isinstance(exc, ConfigError) else InputError)(msg) from None
    present(summary, quiet=quiet, json_file=json_file, force=force)


#: Session keys in the pipelines' messages and what ``kinefuse evaluate`` calls them.
_EVALUATE_OPTIONS = (
    ("[skeleton] body_height_m", "--body-height"),
    ("body_height_m", "--body-height"),
    ("[skeleton.lengths] in m", "in m, in a session file's [skeleton.lengths]: kinefuse run"),
)


def _as_options(msg: str) -> str:
    """``msg`` with the session keys that ``kinefuse evaluate`` sets by options renamed."""
    for key, option in _EVALUATE_OPTIONS:
        msg = msg.replace(key, option)
    return msg


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
    workers: Workers = None,
    scheduler: Scheduler = None,
    quiet: Quiet = False,
    json_file: Json = None,
    force: JsonForce = False,
) -> None:
    """Reproduce a paper's experiment and compare with the paper's tables.

    With --workers or --scheduler, paper-a's and paper-b's trials run on Dask (as kinefuse
    batch; pip install 'kinefuse\\[batch]'): the numbers do not change.
    """
    if name not in EXPERIMENTS:
        raise InputError(f"unknown experiment {name!r}; expected one of {', '.join(EXPERIMENTS)}")
    if data is not None and not data.is_dir():
        raise InputError(f"--data {data}: folder not found")
    if data_set not in ("report", "tuning"):
        raise InputError(f"--set: expected 'report' or 'tuning', got {data_set!r}")
    on_dask = workers is not None or scheduler is not None
    if on_dask and name not in TRIAL_EXPERIMENTS:
        raise InputError(
            f"--workers/--scheduler: {name} is not split into trials; only "
            f"{' and '.join(TRIAL_EXPERIMENTS)} run on Dask"
        )
    kb = backend_module("batch") if on_dask else None  # loads compiled kernels: when used
    if kb is not None and kb.missing_packages():
        raise BackendUnavailable(
            f"--workers/--scheduler need {', '.join(kb.missing_packages())}: "
            "pip install 'kinefuse[batch]'"
        )
    check_json(json_file, force, () if data is None else (data,))
    run = backend("experiment")
    opts = {"quick": quick or None, "quiet": quiet, "split": data_set}
    if not on_dask:
        summary = run(name, data, **opts)
    else:
        trials = backend_module("batch", "kinefuse.batch.trials")
        with trials.trial_cluster(scheduler, workers) as (trial_map, where):
            summary = run(name, data, **opts, trial_map=trial_map)
        summary["notes"].append(f"Trials ran on Dask: {where}.")
    present(summary, quiet=quiet, json_file=json_file, force=force)


def bench(
    quick: Annotated[
        bool, typer.Option("--quick", help="A short run (seconds) instead of the full benchmark.")
    ] = False,
    quiet: Quiet = False,
    json_file: Json = None,
    force: JsonForce = False,
) -> None:
    """Measure per-step latency and batch throughput of the filters, next to peer libraries."""
    check_json(json_file, force)
    summary = backend("bench")(quick)
    present(summary, quiet=quiet, json_file=json_file, force=force)


def warm_up(quiet: Quiet = False) -> None:
    """Compile the numba kernels once (minutes on a small machine), with progress; later runs load them."""
    from kinefuse.pipelines.warm_up import warm_up as compile_kernels  # lazy: numba

    console = stdout()
    compile_kernels(report=None if quiet else lambda m: console.print(Text(m)))
