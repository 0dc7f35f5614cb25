"""The typer application, exit codes, error mapping and the back-end registry of the CLI."""

import functools
import importlib
import os
import sys
import traceback
import warnings
from collections.abc import Callable
from types import ModuleType
from typing import Annotated

import typer
from rich.console import Console
from rich.text import Text

from kinefuse import __version__
from kinefuse.exceptions import InputError

__all__ = [
    "EPILOG",
    "EXIT_FAILURE",
    "EXIT_OK",
    "EXIT_USAGE",
    "BackendUnavailable",
    "app",
    "backend",
    "backend_module",
    "fail",
    "guarded",
    "stderr",
    "stdout",
]

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2

#: Shown under every command's help.
EPILOG = (
    "Exit codes: 0 success; 1 runtime failure, feature not available or target not met; "
    "2 bad input or usage (one red line on stderr; add --debug for the traceback); 130 "
    "interrupted by Ctrl-C before a result (stream and replay stop cleanly on it: 0)."
)

app = typer.Typer(
    name="kinefuse",
    help="IMU (+ optional camera) human joint position capture: EM-KF/FIR (Sun 2024) and "
    "ELM/FIR vision-assisted fusion (Xu 2023).",
    epilog=EPILOG,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

_STATE = {"debug": False}

# click's exception base and typer's control-flow exceptions pass through untouched
_CLICK_EXCEPTION = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")
_PASS_THROUGH = (typer.Exit, typer.Abort, _CLICK_EXCEPTION)

#: command -> (module, function) of its back-end, imported when the command runs (see
#: :func:`backend` and :func:`backend_module`): ``kinefuse --help`` stays fast, a missing back-end or optional package
#: is a clear exit 1, and ``kinefuse demo`` can switch the kernels to interpreted mode first.
BACKENDS = {
    "demo": ("kinefuse.apps.demo", "run_demo"),
    "init-session": ("kinefuse.pipelines.run.calibration", "sketch_for_session"),
    "run": ("kinefuse.pipelines.run", "run_session"),
    "evaluate": ("kinefuse.pipelines.run", "evaluate_recording"),
    "experiment": ("kinefuse.apps.experiments", "run_experiment"),
    "batch": ("kinefuse.batch", "run_study"),
    "bench": ("kinefuse.apps.bench", "run_bench"),
    "stream": ("kinefuse.streaming", "run_stream"),
    "replay": ("kinefuse.streaming", "replay_recording"),
}


class BackendUnavailable(RuntimeError):
    """The back-end of a command is not part of this installation (exit 1)."""


def stdout() -> Console:
    """The console for tables and results."""
    # not a terminal (pipe, file, CI log): do not squeeze tables into 80 columns
    return Console(highlight=False, width=None if sys.stdout.isatty() else 160)


def stderr() -> Console:
    """The console for errors, warnings and progress."""
    return Console(stderr=True, highlight=False, soft_wrap=True)


def _debug() -> bool:
    return _STATE["debug"] or os.environ.get("KINEFUSE_DEBUG", "") not in ("", "0")


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the console script: one ``kinefuse: warning:`` line on stderr
    (Python's ``file:line: Category:`` form, with the source line, under ``--debug``)."""
    if _debug():
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))
        return
    stderr().print(Text(f"kinefuse: warning: {one_line(str(message))}", style="yellow"))


def one_line(message: str) -> str:
    """``message`` with its whitespace runs (newlines included) as single spaces."""
    return " ".join(str(message).split())


def fail(message: str, code: int) -> None:
    """One red line on stderr (and the traceback with ``--debug``), then exit ``code``."""
    if _debug():
        traceback.print_exc(file=sys.stderr)
    stderr().print(Text(f"kinefuse: error: {one_line(message)}", style="bold red"))
    raise typer.Exit(code)


def guarded(fn: Callable) -> Callable:
    """Map exceptions of a command to exit codes and one-line messages (see the package docs)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except _PASS_THROUGH:
            raise
        except (InputError, FileExistsError) as exc:  # InputError covers FormatError, ConfigError
            fail(str(exc), EXIT_USAGE)
        except BackendUnavailable as exc:
            fail(str(exc), EXIT_FAILURE)
        except KeyboardInterrupt:
            stderr().print(Text("kinefuse: interrupted", style="bold red"))
            raise typer.Exit(130) from None
        except Exception as exc:
            hint = "" if _debug() else " (run `kinefuse --debug ...` for the traceback)"
            fail(f"{type(exc).__name__}: {exc}{hint}", EXIT_FAILURE)

    return wrapper


def backend_module(command: str, module: str | None = None) -> ModuleType:
    """Import the back-end module of ``command`` (:data:`BACKENDS`), or ``module``, another
    module the command needs, or raise :class:`BackendUnavailable`."""
    default, func = BACKENDS[command]
    name = module or default
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if missing.startswith("kinefuse") or not missing:
            what = name if module else f"{name}.{func}"
            raise BackendUnavailable(
                f"`kinefuse {command}` is not available in this version ({what} is missing)"
            ) from exc
        raise BackendUnavailable(
            f"`kinefuse {command}` needs the optional package {missing!r}; install it (e.g. pip install {missing})"
        ) from exc


def backend(command: str) -> Callable:
    """Import the back-end function of ``command`` (:data:`BACKENDS`) or raise
    :class:`BackendUnavailable`."""
    module, func = BACKENDS[command]
    fn = getattr(backend_module(command), func, None)
    if fn is None:
        raise BackendUnavailable(
            f"`kinefuse {command}` is not available in this version ({module}.{func} is missing)"
        )
    return fn


def _version_callback(value: bool) -> None:
    if value:
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
