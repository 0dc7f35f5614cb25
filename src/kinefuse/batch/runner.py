"""``kinefuse batch``: a study's tasks on dask.distributed, resumable and fault-tolerant.

:func:`run_study` schedules one task per recording x method (:func:`kinefuse.batch.tasks.run_task`)
on

- a ``LocalCluster`` on this machine (default): one single-threaded worker process per core
  (``--workers N``), bound to 127.0.0.1, numba single-threaded in every worker
  (``NUMBA_NUM_THREADS=1``) and one on-disk numba cache shared by all workers (this process's,
  passed as ``NUMBA_CACHE_DIR``); when that cache is cold, one task runs first so the kernels
  are compiled once, not once per worker; the Dask dashboard only with ``dashboard=True``
  (127.0.0.1, needs bokeh);
- an existing cluster: ``scheduler="tcp://HOST:PORT"`` or the ``DASK_SCHEDULER_ADDRESS``
  environment variable (Dask's own convention). The workers must see the study's files and
  ``out_dir`` at the same paths (a shared file system) and have kinefuse installed.

Fault tolerance: a recording that fails is a failed row with its one-line error and the study
goes on. A worker that dies mid-task has its tasks re-scheduled by Dask on the others; tasks lost
otherwise (``client.restart()``, a scheduler that gave up on a task) are resubmitted up to
:data:`MAX_ATTEMPTS` times. Tasks are idempotent (atomic folder per task), so a re-run never
writes a result twice. Finished tasks are skipped unless ``force``; a rerun with nothing to do
starts no cluster.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import queue
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

from rich import progress as rp
from rich.console import Console

from kinefuse import _compile  # sets NUMBA_CACHE_DIR when the package is read-only
from kinefuse.batch.report import NO_SCORES, summary_table, write_study_report
from kinefuse.batch.study import Study
from kinefuse.batch.table import TABLE_NAME, flatten, write_table
from kinefuse.batch.tasks import clean_temporaries, is_finished, read_result, run_task
from kinefuse.evaluation.tables import ResultTable, TableRow
from kinefuse.exceptions import InputError

__all__ = ["MAX_ATTEMPTS", "compare_workers", "connect", "run_study", "start_local_cluster"]

#: How often a task lost by the cluster (not failed by its recording) is resubmitted.
MAX_ATTEMPTS = 4
_POLL_S = 0.25


def _numba_cache_dir() -> str:
    """The numba cache directory every worker shares (this process's, set by :mod:`kinefuse._compile`)."""
    explicit = os.environ.get("NUMBA_CACHE_DIR")
    if explicit:
        return explicit
    return ""  # numba's default: __pycache__ beside the kernels, one per installation


def start_local_cluster(n_workers: int | None = None, *, dashboard: bool = False):
    """A ``LocalCluster`` for a batch: processes, one thread each, 127.0.0.1 only.

    Parameters
    ----------
    n_workers : int, optional
        Default: the number of cores.
    dashboard : bool
        Serve the Dask dashboard on 127.0.0.1 (a free port; needs bokeh).

    Returns
    -------
    distributed.LocalCluster
    """
    import dask
    from distributed import LocalCluster

    if dashboard and not _has_bokeh():
        raise InputError("--dashboard: the Dask dashboard needs bokeh; pip install 'bokeh>=3.1'")
    n = n_workers or os.cpu_count() or 1
    env = {"NUMBA_NUM_THREADS": "1"}
    cache = _numba_cache_dir()
    if cache:
        env["NUMBA_CACHE_DIR"] = cache
    # Dask's nannies give each worker MALLOC_TRIM_THRESHOLD_=65536, which also turns off
    # glibc's adaptive mmap threshold: every temporary above 128 kB is then mmap'd and zeroed
    # afresh, and an IMU-only run of the qmt recording takes 32 s instead of 11 s. The workers
    # keep glibc's defaults (the nanny reads this when it is created; dask/distributed#8143)
    spawn = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    spawn.pop("MALLOC_TRIM_THRESHOLD_", None)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": spawn}):
        return LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            scheduler_port=0,
            dashboard_address="127.0.0.1:0" if dashboard else None,
            worker_dashboard_address=None,
            silence_logs=50,
            env=env,
        )


def _has_bokeh() -> bool:
    return importlib.util.find_spec("bokeh") is not None


def _dashboard_link(client) -> str | None:
    """The dashboard's address when the scheduler serves one (it needs bokeh), else None."""
    try:
        info = client.scheduler_info()
        if "dashboard" not in (info.get("services") or {}):
            return None
        if not client.run_on_scheduler(_has_bokeh):
            return None  # only the scheduler's health/metrics HTTP endpoint
    except Exception:  # pragma: no cover - scheduler gone
        return None
    return client.dashboard_link


class _Progress:
    """Study progress on stderr: done / running / failed, ETA (rich); silent when quiet."""

    def __init__(self, total: int, done: int, quiet: bool):
        self.quiet = quiet
        self.bar = None
        if quiet:
            return
        self.bar = rp.Progress(
            rp.SpinnerColumn(),
            rp.TextColumn("study"),
            rp.BarColumn(),
            rp.MofNCompleteColumn(),
            rp.TextColumn("{task.fields[running]} running · {task.fields[failed]} failed"),
            rp.TextColumn("ETA"),
            rp.TimeRemainingColumn(),
            rp.TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        )
        self.bar.start()
        self.task = self.bar.add_task("study", total=total, completed=done, running=0, failed=0)

    def update(self, done: int, running: int, failed: int) -> None:
        if self.bar is not None:
            self.bar.update(self.task, completed=done, running=running, failed=failed)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _lost(future) -> bool:
    """True when the cluster lost the task (cancelled, worker died too often), not the recording."""
    return (
        future.cancelled()
        or future.status == "lost"
        or (future.status == "error" and type(future.exception()).__name__ in ("KilledWorker",))
    )


def _schedule(
    client,
    pending: list,
    study: Study,
    force: bool,
    results: dict,
    prog: _Progress,
    n_done: int,
    on_event: Callable[[str, object], None] | None,
) -> None:
    """Submit ``pending`` tasks, wait, resubmit lost ones; fills ``results`` by task key.

    Each future reports its end (done, failed or cancelled) through a done-callback into a
    queue, so waiting costs O(1) per finished task: ``distributed.wait`` on every live future
    at each poll costs O(live) and, with a study of 1500 tasks, took a third of a core from
    the workers in this process (the LocalCluster's scheduler runs here too).
    """
    out = str(study.out_dir)
    attempts = dict.fromkeys((t.key for t in pending), 0)
    by_key = {t.key: t for t in pending}
    ended: queue.SimpleQueue = queue.SimpleQueue()

    def submit(task):
        attempts[task.key] += 1
        fut = client.submit(
            run_task,
            task,
            out,
            force,
            study.name,
            key=f"kinefuse-batch-{task.key}-{attempts[task.key]}-{os.getpid()}",
            pure=False,
        )
        fut.add_done_callback(ended.put)
        return fut

    live = {}
    first = list(pending)
    held: list = []
    if len(first) > 1 and not _kernels_cached():
        # compile once in one worker; the others are submitted when it is done and load the cache
        held, first = first[1:], first[:1]
    for t in first:
        live[submit(t)] = t.key
    failed = sum(1 for r in results.values() if r["status"] == "failed")
    polled = -_POLL_S
    while live:
        for fut in _ended(ended):
            if fut not in live:  # already handled
                continue
            key = live.pop(fut)
            task = by_key[key]
            if _lost(fut):
                if attempts[key] >= MAX_ATTEMPTS:
                    results[key] = {
                        "recording": task.recording,
                        "method": task.method,
                        "study": study.name,
                        "status": "failed",
                        "error": f"the cluster lost this task {attempts[key]} times "
                        "(workers died while running it)",
                        "rows": [],
                    }
                else:
                    live[submit(task)] = key
                    if on_event:
                        on_event("resubmitted", key)
                continue
            if fut.status == "error":  # run_task never raises; a broken worker environment
                exc = fut.exception()
                res = {
                    "recording": task.recording,
                    "method": task.method,
                    "study": study.name,
                    "status": "failed",
                    "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}",
                    "rows": [],
                }
            else:
                res = fut.result()
                if res["status"] == "skipped":  # published by an earlier attempt of this run
                    res["status"] = "done"
            results[key] = res
            if res["status"] == "failed":
                failed += 1
            if on_event:
                on_event("finished", key)
        if held and pending[0].key not in live.values():
            for t in held:
                live[submit(t)] = t.key
            held = []
        if time.perf_counter() - polled < _POLL_S and live:
            continue
        polled = time.perf_counter()
        for fut in [f for f in live if f.done()]:  # a callback that never came (cheap check)
            ended.put(fut)
        running = 0
        try:
            running = sum(len(v) for v in client.processing().values())
        except Exception:  # pragma: no cover - scheduler restarting
            pass
        prog.update(n_done + len(results), min(running, len(live)), failed)
        if on_event and live:
            on_event("poll", len(live))


def _ended(ended: queue.SimpleQueue) -> list:
    """The futures that ended since the last call: waits up to one poll interval for the first."""
    try:
        out = [ended.get(timeout=_POLL_S)]
    except queue.Empty:
        return []
    while True:
        try:
            out.append(ended.get_nowait())
        except queue.Empty:
            return out


def _kernels_cached() -> bool:
    return _compile.kernels_cached()


def connect(scheduler: str | None, workers: int | None, dashboard: bool):
    """A Dask client for the requested cluster: ``(client, cluster or None, where)``.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing scheduler (default: ``DASK_SCHEDULER_ADDRESS``); else a
        :func:`start_local_cluster` of ``workers`` workers.
    workers : int, optional
        LocalCluster size (default: the number of cores).
    dashboard : bool
        Serve the LocalCluster's dashboard on 127.0.0.1.

    Returns
    -------
    tuple
        The client, the LocalCluster it owns (None for an existing scheduler; the caller
        closes both) and a one-line description (``"LocalCluster, 2 workers on 127.0.0.1"``).

    Raises
    ------
    InputError
        The scheduler cannot be reached.
    """
    from distributed import Client

    address = scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS") or None
    if address:
        try:
            client = Client(address, timeout="10s")
        except OSError as exc:
            raise InputError(
                f"--scheduler {address}: cannot connect ({exc}); start one with `dask scheduler` "
                "and `dask worker ADDRESS`"
            ) from None
        return client, None, f"scheduler {address}"
    cluster = start_local_cluster(workers, dashboard=dashboard)
    client = Client(cluster)
    n = len(cluster.workers)
    return client, cluster, f"LocalCluster, {n} worker{'s' if n != 1 else ''} on 127.0.0.1"


def run_study(
    study: Study,
    *,
    force: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    dashboard: bool = False,
    quiet: bool = False,
    client=None,
    on_event: Callable[[str, object], None] | None = None,
    report: bool = True,
) -> dict:
    """Run every task of a study, write the study table and report.

    Parameters
    ----------
    study : Study
        From :func:`kinefuse.batch.load_study` or :func:`kinefuse.batch.study_from_sessions`.
    force : bool
        Redo finished tasks.
    workers : int, optional
        Workers of the LocalCluster (default: the number of cores).
    scheduler : str, optional
        Address of an existing scheduler (default: ``DASK_SCHEDULER_ADDRESS``, else a
        LocalCluster).
    dashboard : bool
        Serve the LocalCluster's dashboard on 127.0.0.1 (link printed).
    quiet : bool
        No progress bar.
    client : distributed.Client, optional
        Use this client (tests, notebooks); the caller owns it.
    on_event : callable, optional
        ``on_event(kind, payload)`` with ``("started", client)``, ``("finished", key)``,
        ``("resubmitted", key)``, ``("poll", number of unfinished tasks)`` (every 0.25 s).
    report : bool
        Write the HTML study report.

    Returns
    -------
    dict
        ``counts`` (``done``, ``skipped``, ``failed``, ``total``), ``failed`` (``(key, error)``
        list), ``wall_s`` (whole run), ``tasks_wall_s`` (from the first submission to the last
        result), ``cluster``, ``dashboard``, ``table`` (Parquet and CSV paths), ``report``,
        ``results`` (per task, study order).
    """
    t_start = time.perf_counter()
    out_dir = study.out_dir
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output folder {out_dir} exists and is not a folder")
    _claim_out_dir(study, force)
    clean_temporaries(out_dir)
    results, pending = _known_results(study, force)
    cluster_desc, link = "none (nothing to run)", None
    tasks_wall = 0.0
    if pending:
        fresh, cluster_desc, link, tasks_wall = _run_pending(
            study, pending, len(results), force=force, workers=workers, scheduler=scheduler,
            dashboard=dashboard, quiet=quiet, client=client, on_event=on_event,
        )  # fmt: skip
        results.update(fresh)
        clean_temporaries(out_dir)  # a killed worker's half-written folder; its task was rerun
    ordered = [results[t.key] for t in study.tasks]
    summary = _summary(study, ordered, cluster_desc, link, tasks_wall)
    if report:
        summary["report"] = write_study_report(out_dir, study, ordered)
    summary["wall_s"] = time.perf_counter() - t_start
    return summary


#: In a study's output folder: which study its table and report belong to.
STUDY_MARKER = ".kinefuse-study.json"


def _claim_out_dir(study: Study, force: bool) -> None:
    """Create ``study.out_dir`` and mark it as this study's; refuse (unless ``force``) a folder
    holding another study's table, which this run would replace (a rerun of the same study
    resumes it)."""
    out_dir = study.out_dir
    marker = out_dir / STUDY_MARKER
    tables = [out_dir / f"{TABLE_NAME}.{ext}" for ext in ("csv", "parquet")]
    if not force and any(p.is_file() for p in tables):
        other = _owner(marker, tables[0])
        if other != study.name:
            whose = f"study {other!r}" if other else "another study"
            raise FileExistsError(
                f"--out {out_dir}: holds the table and report of {whose}, which study "
                f"{study.name!r} would replace; pass --force to replace them, or choose "
                "another --out"
            )
    out_dir.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"study": study.name, "source": str(study.path or "")}, indent=1)
    marker.write_text(text + "\n", encoding="utf-8")


def _owner(marker: Path, csv_path: Path) -> str | None:
    """The study a folder's table belongs to: its marker's, else the ``study`` column of the
    table's first row (a folder written before the marker existed); None if neither says."""
    try:
        return json.loads(marker.read_text(encoding="utf-8")).get("study")
    except (OSError, ValueError):
        pass
    try:
        with open(csv_path, newline="", encoding="utf-8") as fh:
            row = next(csv.DictReader(fh), None)
    except (OSError, ValueError, csv.Error):
        return None
    return None if row is None else row.get("study")


def _summary(study: Study, ordered: list, cluster_desc: str, link, tasks_wall: float) -> dict:
    """Write the study table; the run's summary (without ``report`` and ``wall_s``)."""
    paths = write_table(study.out_dir, flatten(ordered))
    counts = {k: sum(1 for r in ordered if r["status"] == k) for k in ("done", "skipped", "failed")}
    counts["total"] = len(ordered)
    return {
        "study": study.name,
        "out_dir": study.out_dir,
        "counts": counts,
        "rerun": [f"{r['recording']}/{r['method'] or '-'}" for r in ordered if r.get("rerun")],
        "failed": [
            (f"{r['recording']}/{r['method'] or '-'}", r["error"])
            for r in ordered
            if r["status"] == "failed"
        ],
        "cluster": cluster_desc,
        "dashboard": link,
        "tasks_wall_s": tasks_wall,
        "table": paths,
        "results": ordered,
    }


def _known_results(study: Study, force: bool) -> tuple[dict[str, dict], list]:
    """Results of tasks that need no cluster (broken sessions, finished earlier) and the rest."""
    out_dir = study.out_dir
    results: dict[str, dict] = {}
    pending = []
    for t in study.tasks:
        if t.error is not None:
            results[t.key] = run_task(t, str(out_dir), force, study.name)
        elif not force and is_finished(out_dir, t):
            results[t.key] = read_result(out_dir, t)
        else:
            pending.append(t)
    return results, pending


def _run_pending(
    study, pending, n_pre, *, force, workers, scheduler, dashboard, quiet, client, on_event
):
    """Run ``pending`` on the requested cluster: (results, cluster, dashboard link, tasks wall s)."""
    own = client is None
    cluster = None
    if own:
        client, cluster, cluster_desc = connect(scheduler, workers, dashboard)
    else:
        cluster_desc = "given client"
    link = _dashboard_link(client)
    if on_event:
        on_event("started", client)
    prog = _Progress(len(study.tasks), n_pre, quiet)
    if link and not quiet:
        Console(stderr=True).print(f"Dask dashboard: {link}")
    fresh: dict[str, dict] = {}
    t0 = time.perf_counter()
    try:
        _schedule(client, pending, study, force, fresh, prog, n_pre, on_event)
    finally:
        tasks_wall = time.perf_counter() - t0
        prog.close()
        if own:
            client.close()
            if cluster is not None:
                cluster.close()
    return fresh, cluster_desc, link, tasks_wall


def compare_workers(study: Study, counts: Sequence[int], *, quiet: bool = False) -> list[Mapping]:
    """Run the whole study once per worker count (fresh outputs each time), time each run.

    Each run writes into ``out_dir/compare/workers-N`` with ``force`` (table, per-recording
    outputs and study report, as a plain run); the numba cache is warmed first so no run pays
    the compile cost. Returns one mapping per count: ``workers``, ``wall_s`` (cluster start to
    report), ``tasks_wall_s``, ``counts``, ``failed`` (``(key, error)`` list, as
    :func:`run_study`), ``table`` and ``report`` (paths).

    Raises
    ------
    InputError
        A worker count below 1.
    """
    bad = [n for n in counts if n < 1]
    if bad:
        raise InputError(f"worker counts: expected each at least 1, got {list(counts)}")
    if not _kernels_cached() and study.tasks:  # compile before any timed run
        warm = replace(study, out_dir=study.out_dir / "compare" / "warm-up")
        first = next((t for t in study.tasks if t.error is None), None)
        if first is not None:
            run_task(first, str(warm.out_dir), True, study.name)
    runs = []
    for n in counts:
        sub = replace(study, out_dir=study.out_dir / "compare" / f"workers-{n}")
        s = run_study(sub, force=True, workers=n, quiet=quiet)
        runs.append(
            {
                "workers": n,
                "wall_s": s["wall_s"],
                "tasks_wall_s": s["tasks_wall_s"],
                "counts": s["counts"],
                "failed": s["failed"],
                "table": s["table"],
                "report": s["report"],
            }
        )
    return runs


def summary_tables(summary: Mapping) -> list:
    """The tables ``kinefuse batch`` prints: run, errors over recordings, failed tasks."""
    c = summary["counts"]
    items = [
        (
            "tasks",
            f"{c['total']}: {c['done']} run, {c['skipped']} finished earlier (skipped), "
            f"{c['failed']} failed"
            + (
                f"; {len(summary['rerun'])} of those run had a stored result computed with "
                "other settings (the study changed since): replaced"
                if summary.get("rerun")
                else ""
            ),
        ),
        ("cluster", str(summary["cluster"])),
        ("wall time", f"{summary['wall_s']:.1f} s (tasks {summary['tasks_wall_s']:.1f} s)"),
        ("table", " and ".join(str(p) for p in summary["table"])),
    ]
    if summary.get("dashboard"):
        items.append(("dashboard", summary["dashboard"]))
    ok = [r for r in summary["results"] if r["status"] != "failed"]
    warned = [r for r in ok if r.get("warnings")]
    if warned:
        items.append(("warnings", _warned_line(warned, len(ok))))
    scores = summary_table(ok, "all", "Over recordings, all samples (m)") if ok else None
    if ok and not scores.rows:
        items.append(("scores", NO_SCORES))
    out = [
        ResultTable(
            title=f"kinefuse batch: {summary['study']}",
            label_headers=("", ""),
            value_headers=(),
            rows=tuple(TableRow(labels=kv, values=()) for kv in items),
        )
    ]
    if scores is not None and scores.rows:
        out.append(scores)
    if summary["failed"]:
        out.append(failed_table(summary["failed"]))
    return out


def _warned_line(warned: Sequence[Mapping], n_ok: int, most: int = 5) -> str:
    """``"2 of 5 tasks: walk01/imu-only (3), ...; the study report lists them"`` (the first
    ``most`` tasks named)."""
    names = ", ".join(
        f"{r['recording']}/{r['method']} ({len(r['warnings'])})" for r in warned[:most]
    )
    more = f" and {len(warned) - most} more" if len(warned) > most else ""
    return f"{len(warned)} of {n_ok} tasks: {names}{more}; the study report lists them"


def failed_table(failed: Sequence[tuple[str, str]], where: str = "") -> ResultTable:
    """The table "Failed tasks (n)": one row per failed task with its one-line error."""
    return ResultTable(
        title=f"Failed tasks{where} ({len(failed)})",
        label_headers=("Task", "Error"),
        value_headers=(),
        rows=tuple(TableRow(labels=(k, e), values=()) for k, e in failed),
    )


def compare_tables(runs: Sequence[Mapping]) -> list:
    """The tables ``kinefuse batch --compare-workers`` prints: timings, then failed tasks.

    The failed tasks are listed once when every run failed the same tasks with the same errors,
    else once per run that had failures.
    """
    out = [compare_table(runs)]
    failing = [r for r in runs if r["failed"]]
    if failing and all(list(r["failed"]) == list(runs[0]["failed"]) for r in runs):
        out.append(failed_table(runs[0]["failed"]))
    else:
        out += [failed_table(r["failed"], f", {r['workers']} worker(s)") for r in failing]
    return out


def _ratio(a: float, b: float) -> float:
    """``a / b``; NaN when ``b`` is 0 (no task ran on the cluster: nothing was timed)."""
    return a / b if b > 0 else float("nan")


def compare_table(runs: Sequence[Mapping]):
    """Wall time per worker count and the speed-up over the first count."""
    base = runs[0]
    rows = tuple(
        TableRow(
            labels=(str(r["workers"]), f"{r['counts']['done']}/{r['counts']['total']}"),
            values=(
                r["wall_s"],
                r["tasks_wall_s"],
                _ratio(base["wall_s"], r["wall_s"]),
                _ratio(base["tasks_wall_s"], r["tasks_wall_s"]),
            ),
        )
        for r in runs
    )
    return ResultTable(
        title="kinefuse batch --compare-workers",
        label_headers=("Workers", "Tasks run"),
        value_headers=("Wall (s)", "Tasks wall (s)", "Speed-up", "Speed-up (tasks)"),
        rows=rows,
        digits=2,
        notes=(
            f"speed-up = wall time with {base['workers']} worker(s) / wall time; 'wall' includes "
            "cluster start-up, writing the table and the study report, 'tasks' is first "
            "submission to last result",
            *(f"{r['workers']} worker(s): report {r['report']}" for r in runs if r.get("report")),
        ),
    )
