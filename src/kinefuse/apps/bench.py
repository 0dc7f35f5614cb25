"""Filter benchmark: kinefuse vs filterpy, side by side in one process (STYLE.md "Benchmarks").

Usage::

    kinefuse bench [--quick] [--json FILE]
    python benchmarks/bench_filters.py [--quick] [--json FILE]     # the same, as a script

Needs filterpy, the peer it is measured against (``pip install "kinefuse[bench]"``).

Measures microseconds per joint-step (median of repeats) of

* the Kalman filter (``KalmanFilter.filter``) and the RTS smoother (``rts_smooth``) against
  filterpy's ``KalmanFilter`` predict/update loop and ``rts_smoother`` on the same data, for
  batches of 1, 8, 64 and 1024 joints (filterpy runs on a subset of joints and steps and is
  normalised per joint-step; the table says how many);
* the online path (one ``step`` / ``OnlineFilter.update`` call) against one filterpy
  predict/update;
* UFIR (horizons 10/40/200; with and without the covariance output; with frames lost for every
  joint and, "own gaps", for each joint on its own), EM-KF (1/3/10 iterations) and the
  integrated EM-KF/FIR filter with paper A's settings, if those classes exist in
  :mod:`kinefuse.filters` (rows are skipped otherwise);
* the online engine of ``kinefuse stream`` per camera frame (8 joints; KF fusion, paper A,
  paper B) on the packaged demo recording, next to filterpy's KF predict/update for 8 joints;
* a second process: ``import kinefuse.filters`` + first filter/smoother call, with a warm
  numba cache.

Times are the thread's CPU time (``time.thread_time``), so other processes on a shared machine
inflate them less than wall time; wall-clock medians are kept in the JSON output. numba runs
single-threaded (``NUMBA_NUM_THREADS=1``); BLAS threads are limited to one as well.

The importable core is :func:`run_benchmarks`; :func:`run_bench` is the ``kinefuse bench`` back-end.
The rows are measured in :mod:`kinefuse.apps.bench_filters` (filters vs filterpy) and
:mod:`kinefuse.apps.bench_engine` (online engine per frame, pipelines per recorded hour).
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import warnings  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402

from kinefuse.apps.bench_engine import (  # noqa: E402
    ENGINE_PROCESSORS,
    engine_frame_times,
    engine_rows,
    filterpy_frame_times,
    pipeline_rows,
)
from kinefuse.apps.bench_filters import (  # noqa: E402
    UFIR_HORIZONS,
    kf_rts_rows,
    online_rows,
    other_filter_rows,
    second_process_time,
)
from kinefuse.exceptions import InputError  # noqa: E402

__all__ = [
    "ENGINE_PROCESSORS",
    "engine_frame_times",
    "filterpy_frame_times",
    "format_report",
    "main",
    "run_bench",
    "run_benchmarks",
]


def _load() -> list[float] | None:
    """1/5/15-minute load averages of the machine (None where unavailable)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except (OSError, AttributeError):  # pragma: no cover - not on POSIX
        return None


def _targets(results: dict) -> list[dict]:
    """The targets of the speed issue, each from ratios or values of this run."""
    kr = {(r["case"], r["joints"]): r for r in results["kf_rts"]}
    other = {r["case"]: r for r in results["other_filters"]}
    onl = {(r["case"], r["joints"]): r for r in results["online"]}
    out = []

    def add(case, want, value, met, at):
        out.append({"case": case, "target": want, "measured": value, "met": met, "at": at})

    for case, need in (("KF", 1000.0), ("RTS", 500.0)):
        for j in (8, 1024):
            r = kr.get((case, j))
            if r is None:
                continue
            add(f"{case} vs filterpy", f">= {need:.0f}x", f"{r['speedup']:.0f}x",
                bool(r["speedup"] >= need), f"{j} joints x {r['steps']} steps")  # fmt: skip
    for suffix in (" no cov", "", " own gaps"):
        us = [other.get(f"UFIR(N={N}){suffix}", {}).get("kinefuse_us") for N in UFIR_HORIZONS]
        if all(u is not None for u in us):
            spread = max(us) / min(us) - 1.0
            add(f"UFIR{suffix} N={'/'.join(map(str, UFIR_HORIZONS))}", "<= 0.1 µs, within 20 %",
                " / ".join(f"{u:.3f}" for u in us) + f" µs (spread {100 * spread:.0f} %)",
                bool(max(us) <= 0.1 and spread <= 0.2), "8 joints x steps as above")  # fmt: skip
    e3 = other.get("EM-KF(n_iter=3)", {}).get("kinefuse_us")
    e10 = other.get("EM-KF(n_iter=10)", {}).get("kinefuse_us")
    if e3 and e10:
        add("EM-KF n_iter=10 / n_iter=3", "<= 3.5x", f"{e10 / e3:.2f}x", bool(e10 / e3 <= 3.5),
            "8 joints")  # fmt: skip
    r = onl.get(("KF.step", 8))
    if r is not None:
        add("KF.step, 8 joints", "<= 5 µs per call", f"{r['us_per_call']:.2f} µs",
            bool(r["us_per_call"] <= 5.0), "one time slice")  # fmt: skip
    pb = next((r for r in results.get("pipelines", []) if r.get("method") == "elm-fir"), None)
    if pb is not None and "error" not in pb:
        add("paper B pipeline (elm-fir)", ">= 1000x real time", f"{pb['x_real_time']:.0f}x",
            bool(pb["x_real_time"] >= 1000), f"{pb['duration_s'] / 3600:.2g} h recording")  # fmt: skip
    sp = results["second_process"]
    if "error" not in sp:
        tot = sp["import_s"] + sp["first_call_s"]
        add("second process import + first call", "<= 2.0 s", f"{tot:.3f} s", bool(tot < 2.0),
            "warm numba cache")  # fmt: skip
    return out


def run_benchmarks(quick: bool = False) -> dict:
    """Run every benchmark; return a JSON-serialisable dict (rows, targets, second process)."""
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    results = {
        "quick": quick,
        "numba_threads": numba.config.NUMBA_NUM_THREADS,
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "numba": numba.__version__,
        "timer": "median thread CPU time (time.thread_time)",
        "load_before": _load(),
        "kf_rts": kf_rts_rows(quick),
        "online": online_rows(quick),
        "other_filters": other_filter_rows(quick),
        "engine": engine_rows(quick),
        "pipelines": pipeline_rows(quick),
    }
    results["second_process"] = second_process_time()
    results["load_after"] = _load()
    results["targets"] = _targets(results)
    return results


def _filter_lines(results: dict, lines: list[str]) -> None:
    """KF / RTS, the online path and the other filters."""
    lines.append(
        "KF / RTS, µs per joint-step (kinefuse: all joints x steps; filterpy: subset, normalised);"
    )
    lines.append(
        "KF = outputs mean + cov (what filterpy's loop stores), KF* = every output; RTS = smoothed"
        " mean + cov; covariances as per-axis blocks"
    )
    hdr = f"{'case':<5} {'joints':>6} {'steps':>6} | {'kinefuse':>9} {'(wall)':>8} | {'filterpy on':>13} {'filterpy':>9} | {'speedup':>8}"
    lines.append(hdr)
    lines.append("-" * len(hdr))
    for r in results["kf_rts"]:
        lines.append(
            f"{r['case']:<5} {r['joints']:>6} {r['steps']:>6} | {r['kinefuse_us']:>9.4f} {r['kinefuse_wall_us']:>8.4f} | "
            f"{r['peer_joints']:>4} x {r['peer_steps']:<6} {r['peer_us']:>9.2f} | {r['speedup']:>7.0f}x"
        )
    lines.append("")
    lines.append("Online path, µs per call (one time slice for all joints)")
    for r in results["online"]:
        lines.append(
            f"{r['case']:<20} joints={r['joints']:<2} {r['us_per_call']:>8.2f} µs/call   "
            f"filterpy predict+update {r['filterpy_us_per_joint_step']:.2f} µs per joint "
            f"({r['speedup_vs_filterpy_per_joint']:.1f}x per joint-step)"
        )
    lines.append("")
    lines.append("Other filters (8 joints), µs per joint-step")
    for r in results["other_filters"]:
        if "skipped" in r:
            lines.append(f"{r['case']:<18} skipped: {r['skipped']}")
        else:
            lines.append(
                f"{r['case']:<18} {r['kinefuse_us']:>9.4f} (wall {r['kinefuse_wall_us']:.4f}) at 8 x {r['steps']}"
            )


def _engine_lines(results: dict, lines: list[str]) -> None:
    """The online engine per camera frame and the whole pipelines per recorded hour."""
    lines.append("")
    lines.append(
        "Online engine (kinefuse stream), 8 joints of paper B, per camera frame: ms of thread CPU "
        "time (packaged demo: 9 IMUs at 100 Hz, camera at 30 Hz with outages)"
    )
    for r in results.get("engine", []):
        extra = f"  ({r['onset_frames']} outage-onset frames)" if r["onset_frames"] else ""
        lines.append(
            f"{r['processor']:<20} p50 {r['p50_ms']:.3f}  p99 {r['p99_ms']:.3f}  max {r['max_ms']:.3f}"
            f"  ({r['frames']} frames){extra}"
        )
    pl = results.get("pipelines") or []
    if pl:
        dur = next((r["duration_s"] for r in pl if "duration_s" in r), 0.0)
        lines.append("")
        lines.append(
            f"Whole pipelines on a {dur / 3600:.2g} h recording (9 IMUs at 100 Hz, camera at 30 Hz"
            " with outages), one core, thread CPU time; peak RSS of the process (recording"
            " loaded without the simulator's truth, kernels warm); each row a fresh process"
            " per run, runs in rounds"
        )
        for r in pl:
            if "error" in r:
                lines.append(f"{r['method']:<38} failed: {r['error']}")
                continue
            mem = "" if r.get("peak_rss_mb") is None else f"  peak {r['peak_rss_mb']:.0f} MB"
            note = f"  ({r['note']})" if r.get("note") else ""
            runs = [c * 3600.0 / r["duration_s"] for c in r.get("cpu_s_runs", [])]
            if len(runs) > 1:
                note += f"  (median of {len(runs)}: {min(runs):.1f}-{max(runs):.1f} s)"
            lines.append(
                f"{r['method']:<38} {r['s_per_hour']:>8.1f} s per recorded hour"
                f"  {r['x_real_time']:>7.0f}x real time{mem}{note}"
            )


def _summary_lines(results: dict, lines: list[str]) -> None:
    """The second process, the targets and paper A's Table 6."""
    sp = results["second_process"]
    lines.append("")
    if "error" in sp:
        lines.append(f"Second process: failed: {sp['error']}")
    else:
        lines.append(
            f"Second process (warm cache): import {sp['import_s']:.3f} s + first KF/step/RTS call "
            f"{sp['first_call_s']:.3f} s = {sp['import_s'] + sp['first_call_s']:.3f} s "
            f"(interpreter included: {sp['process_total_s']:.3f} s)"
        )
    lines.append("")
    lines.append("Targets (single core); ratios to filterpy from this run")
    for t in results["targets"]:
        status = "met" if t["met"] else "NOT met"
        lines.append(
            f"  {t['case']:<34} {t['target']:<24} measured {t['measured']:<34} {status}  ({t['at']})"
        )
    if results["quick"]:
        lines.append("  (quick mode: fewer steps than the 8 x 20,000 target configuration)")
    lines.append("")
    lines.append(
        "Paper A Table 6 (MATLAB, per step per joint): KF 37 µs, FIR 237 µs, EM-KF/FIR 7954 µs."
    )


def format_report(results: dict) -> str:
    """Plain-text tables of :func:`run_benchmarks` output."""
    lines = []
    lines.append(
        f"kinefuse filter benchmark ({'quick' if results['quick'] else 'full'}); numba threads = "
        f"{results['numba_threads']}; timer: {results['timer']}"
    )
    la, lb = results.get("load_before"), results.get("load_after")
    if la or lb:
        lines.append(f"machine load (1/5/15 min): {la} before, {lb} after (2 cores shared)")
    lines.append("")
    _filter_lines(results, lines)
    _engine_lines(results, lines)
    _summary_lines(results, lines)
    return "\n".join(lines)


def run_bench(quick: bool = False) -> dict:
    """``kinefuse bench``: run the benchmark, return the printable report, the numbers, and
    ``passed`` (every target met; the CLI exits 1 otherwise)."""
    try:
        import filterpy  # noqa: F401
    except ImportError:
        raise InputError(
            'kinefuse bench measures against filterpy, which is not installed: pip install "kinefuse[bench]"'
        ) from None
    results = run_benchmarks(quick=quick)
    missed = [t["case"] for t in results["targets"] if t["met"] is False]
    return {
        "tables": [format_report(results)],
        "results": results,
        "passed": not missed,
        "reason": "targets not met: " + ", ".join(missed),
    }


def main(argv=None) -> int:
    """``python benchmarks/bench_filters.py [--quick] [--json FILE]``: print the report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (seconds, for CI)")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = parser.parse_args(argv)
    results = run_benchmarks(quick=args.quick)
    print(format_report(results))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(results, fh, indent=2)
    return 0
