"""One batch task: one recording x one method through ``kinefuse run``'s code path.

:func:`run_task` runs on a Dask worker (or in-process). It calls
:func:`kinefuse.pipelines.run.run_session` on the task's validated session, so a
recording's outputs are exactly those of ``kinefuse run`` (joint CSV, TRC, ``report.html``,
``figures/``, ``metrics.json``), plus ``result.json``: the task's rows of the study table.

Writes are atomic per task: everything goes to a hidden temporary sibling folder that is renamed
to ``recordings/<recording>/<method>/`` when complete. A task whose worker dies leaves at most a
temporary folder (removed once the study's tasks have finished, or by the next run), never a
half-written result; a task that runs twice (re-scheduled after a worker died just after
finishing) keeps the first complete result and discards the second. ``result.json`` in the
final folder is the "finished" marker; it holds a fingerprint of the task's settings (its
merged session document and method, :func:`task_settings`), and a result whose settings differ
from the study's (the study file was edited since) is stale: the task runs again and replaces
it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import time
import uuid
from pathlib import Path

from kinefuse.batch.study import Task, safe_name
from kinefuse.exceptions import InputError
from kinefuse.pipelines.run import run_session
from kinefuse.session_file import load_session

__all__ = ["RESULT_NAME", "is_finished", "is_stale", "read_result", "run_task", "task_dir",
           "task_settings"]  # fmt: skip

#: Marker and rows of a finished task, inside its folder.
RESULT_NAME = "result.json"
_TMP_PREFIX = ".tmp-"


def task_dir(out_dir: str | Path, task: Task) -> Path:
    """``out_dir/recordings/<recording>/<method>``."""
    return Path(out_dir) / "recordings" / safe_name(task.recording) / safe_name(task.method or "-")


def task_settings(task: Task) -> str:
    """Fingerprint (SHA-256, hex) of what a task computes from: its method and merged session
    document (paths, calibration, parameters...). The recordings' contents are not in it."""
    doc = {"method": task.method, "document": task.document}
    text = json.dumps(doc, sort_keys=True, default=str, ensure_ascii=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _stored_settings(out_dir: str | Path, task: Task) -> str | None:
    """The settings fingerprint of the task's stored result; None without one."""
    path = task_dir(out_dir, task) / RESULT_NAME
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8")).get("settings", "")
    except (OSError, ValueError):
        return ""


def is_finished(out_dir: str | Path, task: Task) -> bool:
    """True when the task's folder holds a complete result computed with the task's settings."""
    return _stored_settings(out_dir, task) == task_settings(task)


def is_stale(out_dir: str | Path, task: Task) -> bool:
    """True when the task's folder holds a result computed with other settings (the study's
    session changed since), or one from before results held their settings."""
    stored = _stored_settings(out_dir, task)
    return stored is not None and stored != task_settings(task)


def read_result(out_dir: str | Path, task: Task) -> dict:
    """The stored result of a finished task, marked ``status = "skipped"``."""
    res = json.loads((task_dir(out_dir, task) / RESULT_NAME).read_text(encoding="utf-8"))
    res["status"] = "skipped"
    return res


def one_line(exc: BaseException) -> str:
    """The error line a failed task records (kinefuse errors as such, others with their type)."""
    msg = " ".join(str(exc).split())
    if isinstance(exc, (InputError, FileExistsError)):
        return msg
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _calibrated_on(summary) -> str:
    """What the calibration used, from the run's provenance (also in its metrics.json)."""
    cal = (summary.get("provenance") or {}).get("calibration")
    if not cal:
        return ""
    return {"vision": "camera", "reference": "reference (mocap)"}.get(cal, str(cal))


def _rows(evaluation, run_wall_s: float) -> list[dict]:
    """Tidy rows of one task: estimate x joint x subset x metric."""
    rows = []

    def add(estimate, joint, subset, metric, value, unit):
        v = float(value)
        rows.append(
            {
                "estimate": estimate,
                "joint": joint,
                "subset": subset,
                "metric": metric,
                "value": v if math.isfinite(v) else None,
                "unit": unit,
            }
        )

    if evaluation is not None:
        ev = evaluation
        subsets = [("all", {})]
        if ev.outage_mask is not None:
            subsets += [("in_view", {"in_view": True}), ("outage", {"outage": True})]
        for est in ev.methods:
            for joint in ev.joints:
                for subset, kw in subsets:
                    r = ev.row(est, joint, **kw)
                    for ax in ev.axes:
                        add(est, joint, subset, f"rmse_{ax}", r[ax], "m")
                    add(est, joint, subset, "rmse_mean", r["mean"], "m")
                    add(est, joint, subset, "rmse_3d", r["rmse_3d"], "m")
                    add(est, joint, subset, f"error_cdf_{ev.p:g}", r["error_at_p"], "m")
                    add(est, joint, subset, "n_samples", r["n_samples"], "samples")
        for est, t in ev.run_time_s.items():
            add(est, "all", "all", "run_time_s", t, "s")
    add("task", "all", "all", "task_wall_s", run_wall_s, "s")
    return rows


def _publish(tmp: Path, final: Path, force: bool) -> bool:
    """Rename ``tmp`` to ``final``; False (tmp removed) when another run already published."""
    final.parent.mkdir(parents=True, exist_ok=True)
    if force and final.exists():
        old = final.with_name(f"{_TMP_PREFIX}old-{final.name}-{uuid.uuid4().hex[:8]}")
        os.rename(final, old)
        os.rename(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
        return True
    try:
        os.rename(tmp, final)  # atomic; fails when final exists and is not empty
        return True
    except OSError:
        if (final / RESULT_NAME).is_file():
            shutil.rmtree(tmp, ignore_errors=True)
            return False
        raise


def run_task(task: Task, out_dir: str, force: bool = False, study: str = "") -> dict:
    """Run one task and publish its outputs atomically (see the module docstring).

    Parameters
    ----------
    task : Task
    out_dir : str
        The study's output folder.
    force : bool
        Redo a finished task (its folder is replaced atomically).
    study : str
        Study name, written into every row.

    Returns
    -------
    dict
        ``recording``, ``method``, ``status`` (``"done"``, ``"skipped"``, ``"failed"``),
        ``error`` (one line or None), ``calibrated_on``, ``wall_s``, ``rows`` (tidy rows
        without the recording/method columns), ``outputs`` (file names), ``warnings`` (the
        run's, as ``kinefuse run`` prints them), ``worker`` (pid).
        Never raises for a problem of the recording itself.
    """
    final = task_dir(out_dir, task)
    base = {"recording": task.recording, "method": task.method, "study": study}
    if not force and is_finished(out_dir, task):
        return read_result(out_dir, task)
    stale = is_stale(out_dir, task)
    if task.error is not None:
        return {**base, "status": "failed", "error": " ".join(task.error.split()), "rows": []}
    tmp = final.with_name(f"{_TMP_PREFIX}{final.name}-{uuid.uuid4().hex[:8]}")
    t0 = time.perf_counter()
    try:
        cfg = load_session(task.source, document=task.document)
        summary = run_session(cfg, tmp, force=True)
        wall = time.perf_counter() - t0
        result = {
            **base,
            "status": "done",
            "error": None,
            "calibrated_on": _calibrated_on(summary),
            "wall_s": wall,
            "rows": _rows(summary.get("evaluation"), wall),
            "outputs": sorted(p.name for p in tmp.iterdir()),
            "warnings": list(summary.get("warnings") or ()),
            "worker": os.getpid(),
            "settings": task_settings(task),
        }
        if stale and not force:
            result["rerun"] = "its settings changed since the stored result"
        (tmp / RESULT_NAME).write_text(json.dumps(result, indent=1), encoding="utf-8")
        if not _publish(tmp, final, force or stale):
            return read_result(out_dir, task) | {"status": "done"}
        return result
    except Exception as exc:  # a recording's problem must not stop the study
        shutil.rmtree(tmp, ignore_errors=True)
        return {**base, "status": "failed", "error": one_line(exc), "rows": []}


def clean_temporaries(out_dir: str | Path) -> int:
    """Remove temporary folders left by tasks whose worker died; returns how many."""
    root = Path(out_dir) / "recordings"
    n = 0
    if root.is_dir():
        for p in root.glob(f"*/{_TMP_PREFIX}*"):
            shutil.rmtree(p, ignore_errors=True)
            n += 1
    return n
