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
130
    Interrupted by Ctrl-C before a result (the shell's convention, 128 + SIGINT): "kinefuse:
    interrupted". ``stream`` and ``replay`` treat Ctrl-C as their normal stop (exit 0, with
    their summary) once they run; while ``stream`` is still looking for its streams it is 130.

Back-end contracts
------------------
Each command imports its back-end when it runs (:data:`kinefuse.cli._app.BACKENDS`), so
``--help`` is fast (it imports no numba, no matplotlib and no SciPy subpackage) and a missing
back-end gives a clear "not available in this version" message (exit 1) instead of an
ImportError:

============  =========================================================================
command       back-end call
============  =========================================================================
demo          ``kinefuse.apps.demo.run_demo(out_dir, force, quiet) -> summary``
run           ``kinefuse.pipelines.run.run_session(path, out_dir, force, stage=) -> summary``
evaluate      ``kinefuse.pipelines.run.evaluate_recording(path, method) -> summary``
experiment    ``kinefuse.apps.experiments.run_experiment(name, data_dir) -> summary``
batch         ``kinefuse.batch.run_study(study, *, force, workers, scheduler, dashboard,
              quiet) -> summary`` (and the other functions of :mod:`kinefuse.batch`)
bench         ``kinefuse.apps.bench.run_bench(quick) -> summary``
stream        ``kinefuse.streaming.run_stream(cfg: StreamConfig, duration_s, out, status,
              *, idle_timeout_s, wait_for_reader_s, record_inputs) -> summary``
replay        ``kinefuse.streaming.replay_recording(path | "demo", rate, prefix, loop,
              duration_s, *, include_raw, wait_for_consumers_s, quiet) -> summary``
============  =========================================================================

A *summary* may be ``None``, a :class:`~pathlib.Path` (e.g. the report), an
:class:`~kinefuse.evaluation.metrics.EvaluationResult`, or a mapping; a mapping may hold an
``"evaluation"`` (EvaluationResult), a ``"report"`` path, ``"tables"`` (``ResultTable`` list)
and ``"passed"`` (False -> exit 1). ``--json FILE`` writes the summary as JSON (``-`` for stdout).

Modules
-------
:mod:`kinefuse.cli._app` (the typer app, exit codes, error mapping, back-ends),
:mod:`kinefuse.cli._output` (shared options, ``--json``, result tables), and one module per
command group: :mod:`kinefuse.cli.offline` (demo, run, init-session, evaluate, experiment,
bench, warm-up), :mod:`kinefuse.cli.study` (batch), :mod:`kinefuse.cli.live` (stream, replay).
The commands are registered below, in the order ``kinefuse --help`` lists them.
"""

import warnings

from kinefuse._memory import prefer_small_pages
from kinefuse.cli import live, offline, study
from kinefuse.cli._app import (
    BACKENDS,
    EPILOG,
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    BackendUnavailable,
    app,
    guarded,
    show_warning,
)
from kinefuse.progress import progress

__all__ = [
    "BACKENDS",
    "EXIT_FAILURE",
    "EXIT_OK",
    "EXIT_USAGE",
    "BackendUnavailable",
    "app",
    "main",
    "progress",
]

for _name, _command in (
    ("demo", offline.demo),
    ("run", offline.run),
    ("init-session", offline.init_session),
    ("evaluate", offline.evaluate),
    ("experiment", offline.experiment),
    ("batch", study.batch),
    ("bench", offline.bench),
    ("warm-up", offline.warm_up),
    ("stream", live.stream),
    ("replay", live.replay),
):
    app.command(_name, epilog=EPILOG)(guarded(_command))


def main() -> None:
    """Console-script entry point (``kinefuse``): Python warnings print as one line each, and
    numpy's arrays get small pages (:func:`kinefuse._memory.prefer_small_pages`)."""
    warnings.showwarning = show_warning
    prefer_small_pages()
    app(prog_name="kinefuse")
