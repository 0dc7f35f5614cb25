"""``kinefuse bench``: the online engine per camera frame and whole pipelines per recorded hour.

:func:`engine_frame_times` times the engine ``kinefuse stream`` builds, fed a recording without
LSL, next to filterpy's KF predict/update for the same joints; the pipeline rows run each session
method on a long virtual recording in a fresh process (its own peak RSS).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import subprocess
import sys
import tempfile
import time
from itertools import islice

import numpy as np

from kinefuse._memory import HUGEPAGE_ENV, user_chose_pages
from kinefuse.apps.bench_filters import filterpy_filter, make_data, measure, paper_model
from kinefuse.data import demo_motion
from kinefuse.models import constant_velocity
from kinefuse.sim import virtual_recording
from kinefuse.streaming.config import StreamConfig
from kinefuse.streaming.replay import demo_recording
from kinefuse.streaming.runner import build_engine, warm_up

__all__ = [
    "ENGINE_PROCESSORS",
    "PIPELINE_METHODS",
    "engine_frame_times",
    "engine_rows",
    "filterpy_frame_times",
    "pipeline_recording",
    "pipeline_rows",
]

#: Processors of the online engine timed per camera frame (``kinefuse stream`` choices).
ENGINE_PROCESSORS = ("kf-fusion", "paper-a", "elm-fir")


def engine_frame_times(rec, processor: str, n_frames: int = 600, loops: int = 1):
    """Per-frame cost of :meth:`Engine.poll <kinefuse.streaming.Engine.poll>` (no LSL).

    The engine ``kinefuse stream`` builds for ``processor`` (warmed up as it does) is fed the
    samples of ``rec`` (replayed ``loops`` times back to back, timestamps shifted) in time
    order; every poll that emits a frame is timed.

    Returns
    -------
    wall_s, cpu_s : ndarray, shape (n,)
        Wall-clock and this thread's CPU time per frame, s (the first 30 frames skipped).
    onset : ndarray of bool, shape (n,)
        Frames in which a bridging processor trained at an outage onset.
    """
    frames = list(islice(_engine_frames(rec, processor, loops), n_frames))
    return _columns(frames[30:], 3)


def _engine_frames(rec, processor: str, loops: int):
    """Generator of ``(wall_s, cpu_s, onset)`` per emitted frame (see :func:`engine_frame_times`);
    the engine is built and warmed up before the first frame is timed."""
    eng = build_engine(StreamConfig(processor=processor), camera=True, camera_rate_hz=30.0,
                       imu_rate_hz=100.0)  # fmt: skip
    v = rec.vision
    span = float(v.t_s[-1] - v.t_s[0]) + 1.0 / 30.0
    ev = []
    for r in range(loops):
        off = r * span
        for seg, st in rec.imu.items():
            ev += [(float(t) + off, 0, seg, q) for t, q in zip(st.t_s, st.q_world_from_sensor, strict=True)]  # fmt: skip
        ev += [(float(t) + off, 1, k, None) for k, t in enumerate(v.t_s)]
    ev.sort(key=lambda e: (e[0], e[1]))
    idx = [v.joints.index(j) for j in eng.config.camera_joints]
    proc = eng.processor
    warm_up(eng)

    def episodes():
        return sum(len(e) for e in getattr(proc, "_episodes", None) or ())

    for t, kind, key, q in ev:
        if kind == 0:
            eng.push_imu(key, t, q)
        else:
            eng.push_camera(t, v.position_m[key][idx], v.available[key][idx])
        n_ep = episodes()
        a, c = time.perf_counter(), time.thread_time()
        outs = eng.poll()
        if outs:
            cpu = time.thread_time() - c
            yield time.perf_counter() - a, cpu, episodes() > n_ep


def filterpy_frame_times(n_frames: int = 600, n_joints: int = 8):
    """filterpy's KalmanFilter, ``n_joints`` x (predict + update) per frame: ``(wall_s, cpu_s)``
    per frame (first 30 skipped), or None without filterpy."""
    gen = _filterpy_frames(n_frames, n_joints)
    if gen is None:
        return None
    return _columns(list(gen)[30:], 2)


def _filterpy_frames(n_frames: int, n_joints: int):
    """Generator of ``(wall_s, cpu_s)`` per frame of filterpy's KF (None without filterpy)."""
    try:
        from filterpy.kalman import KalmanFilter as FKF
    except ImportError:
        return None

    m = constant_velocity(1 / 30, q=0.05, r=4e-4)
    kfs = []
    for _ in range(n_joints):
        f = FKF(dim_x=6, dim_z=3)
        f.F, f.Q, f.H, f.R = np.array(m.F), np.array(m.Q), np.array(m.H), np.array(m.R)
        kfs.append(f)
    z = np.random.default_rng(0).normal(0, 0.01, (n_frames, n_joints, 3))

    def frames():
        for k in range(n_frames):
            a, c = time.perf_counter(), time.thread_time()
            for j, f in enumerate(kfs):
                f.predict()
                f.update(z[k, j])
            cpu = time.thread_time() - c
            yield time.perf_counter() - a, cpu

    return frames()


def _columns(rows: list, n: int) -> tuple:
    """``n`` arrays from a list of ``n``-tuples (float, the last of 3 bool)."""
    cols = [np.asarray([r[i] for r in rows], dtype=float) for i in range(n)]
    if n == 3:
        cols[2] = cols[2].astype(bool)
    return tuple(cols)


def engine_rows(quick: bool) -> list[dict]:
    """Per-frame thread CPU time (p50, p99, max) of each engine processor, next to filterpy.

    The processors and the peer are timed in interleaved rounds of ``ENGINE_ROUND_FRAMES``
    frames each (every engine kept alive between its rounds), so that a slow phase of a
    shared machine falls on all of them alike rather than on whichever was running.
    """
    rec = demo_recording()
    n = 300 if quick else 3_000
    gens = {name: _engine_frames(rec, name, 1 if quick else 8) for name in ENGINE_PROCESSORS}
    peer = _filterpy_frames(300 if quick else 600, 8)
    want = {name: n for name in gens}
    if peer is not None:
        gens["filterpy KF (peer)"] = peer
        want["filterpy KF (peer)"] = 300 if quick else 600
    got = {name: [] for name in gens}
    live = dict(gens)
    while live:
        for name, gen in list(live.items()):
            k = min(ENGINE_ROUND_FRAMES * want[name] // n, want[name] - len(got[name]))
            chunk = list(islice(gen, max(k, 1)))
            got[name] += chunk
            if not chunk or len(got[name]) >= want[name]:
                del live[name]
    rows = []
    for name, frames in got.items():
        cols = _columns(frames[30:], 3 if name in ENGINE_PROCESSORS else 2)
        cpu = cols[1]
        onset = int(cols[2].sum()) if len(cols) == 3 else 0
        rows.append({"processor": name, "frames": int(cpu.size), "onset_frames": onset,
                     "p50_ms": float(1e3 * np.median(cpu)), "p99_ms": float(1e3 * np.percentile(cpu, 99)),
                     "max_ms": float(1e3 * cpu.max())})  # fmt: skip
    return rows


#: Frames per processor and round in :func:`engine_rows` (the peer's rounds are scaled to its
#: smaller total, so that all end together).
ENGINE_ROUND_FRAMES = 100


#: Session methods timed on a long recording (paper A, paper B, kinefuse fusion).
PIPELINE_METHODS = ("paper-a", "elm-fir", "kinefuse")


def pipeline_recording(duration_s: float, seed: int = 0):
    """A virtual recording of ``duration_s`` seconds: 9 IMUs at 100 Hz, a camera at 30 Hz with
    occlusions and dropouts, from the packaged CMU clip played forwards and backwards in turn
    (continuous poses, no jumps at the seams)."""
    m = demo_motion()
    dt = float(np.median(np.diff(m.t_s)))
    n = int(round(duration_s / dt))
    period = 2 * (len(m.t_s) - 1)
    k = np.arange(n) % period
    idx = np.where(k < len(m.t_s), k, period - k)  # ping-pong through the clip
    long = dataclasses.replace(
        m,
        t_s=m.t_s[0] + dt * np.arange(n),
        q_world_from_segment=np.ascontiguousarray(m.q_world_from_segment[idx]),
        position_m=np.ascontiguousarray(m.position_m[idx]),
    )
    return virtual_recording(long, seed=seed)


#: Simulator truth a virtual recording carries in its metadata (about 1.2 GB for an hour) and a
#: recording read from files does not: left out of the pipeline rows' input (and peak memory).
_SIM_TRUTH = ("imu_truth", "reference_imu_rate", "camera_truth", "knee_secondary")


def _as_read_from_files(rec):
    """``rec`` without :data:`_SIM_TRUTH` (no pipeline step reads it)."""
    md = {k: v for k, v in (rec.metadata or {}).items() if k not in _SIM_TRUTH}
    return dataclasses.replace(rec, metadata=md)


_PIPELINE_WORKER = r"""
import json, pickle, sys, time, warnings
warnings.simplefilter("ignore")


def hwm_mb():
    # VmHWM: this process's peak RSS (ru_maxrss also carries the parent's peak across exec)
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


from kinefuse._memory import prefer_small_pages
from kinefuse.apps.bench_engine import pipeline_recording
from kinefuse.pipelines.run import process_recording
method, path = sys.argv[1], sys.argv[2]
prefer_small_pages()  # as `kinefuse run` does (unless NUMPY_MADVISE_HUGEPAGE is set)
process_recording(pipeline_recording(5.0, seed=1), method)  # load the kernels (cached)
rss0 = hwm_mb()
with open(path, "rb") as fh:
    rec = pickle.load(fh)
c0, w0 = time.thread_time(), time.perf_counter()
out = process_recording(rec, method)
cpu, wall = time.thread_time() - c0, time.perf_counter() - w0
print(json.dumps({"cpu_s": cpu, "wall_s": wall, "peak_rss_mb": hwm_mb(),
                  "rss_before_mb": rss0,
                  "camera_frames": int(len(rec.vision)), "joints": len(out.joints)}))
"""


def _pipeline_runs() -> list[tuple[str, str, dict]]:
    """``(row label, method, environment)`` of the pipeline rows: each method as ``kinefuse
    run`` runs it, and paper B once more with numpy's transparent-hugepage advice on (numpy's
    default, which the CLI turns off: :mod:`kinefuse._memory`), for comparison. A
    ``NUMPY_MADVISE_HUGEPAGE`` set by the user applies to every row."""
    env = dict(os.environ)
    runs = []
    for m in PIPELINE_METHODS:
        runs.append((m, m, env))
        if m == "elm-fir" and not user_chose_pages():  # the comparison row, right after it
            runs.append((f"{m}, numpy hugepage advice on", m, {**env, HUGEPAGE_ENV: "1"}))
    return runs


def _pipeline_row(label: str, procs: list, duration: float) -> dict:
    """One pipeline row from its worker processes (:func:`pipeline_rows`); a failed run makes
    the row a failure naming its last stderr line."""
    runs = []
    for proc in procs:
        if proc.returncode != 0:
            err = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed"
            return {"method": label, "error": err}
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    cpu = float(np.median([r["cpu_s"] for r in runs]))
    return {
        **runs[0],
        "method": label,
        "cpu_s": cpu,
        "wall_s": float(np.median([r["wall_s"] for r in runs])),
        "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
        "cpu_s_runs": [r["cpu_s"] for r in runs],
        "duration_s": duration,
        "s_per_hour": cpu * 3600.0 / duration,
        "x_real_time": duration / cpu,
    }


#: Fresh processes per pipeline row in a full run (one in ``--quick``): the row is their median.
PIPELINE_REPEATS = 3


def pipeline_rows(quick: bool) -> list[dict]:
    """Seconds of one core per recorded hour for each pipeline, next to filterpy's KF doing the
    per-joint filtering of the same camera joints (measured on a subset, scaled).

    Each row runs in :data:`PIPELINE_REPEATS` fresh processes, in rounds (round r runs every
    row once before round r + 1, so that a slow phase of the machine falls on every row alike);
    the row gives the median CPU and wall time, the largest peak RSS, and every run's CPU time
    (``cpu_s_runs``).
    """
    duration = 30.0 if quick else 3600.0
    repeats = 1 if quick else PIPELINE_REPEATS
    runs = _pipeline_runs()
    done = {label: [] for label, _, _ in runs}
    # the recording is simulated once (minutes for an hour: orientation filters on 9 IMUs) and
    # handed to one fresh process per method and run, so that each peak RSS is that method's own
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "recording.pickle")
        with open(path, "wb") as fh:
            pickle.dump(_as_read_from_files(pipeline_recording(duration)), fh)
        for _ in range(repeats):
            for label, m, env in runs:
                cmd = [sys.executable, "-c", _PIPELINE_WORKER, m, path]
                proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
                done[label].append(proc)
    rows = [_pipeline_row(label, procs, duration) for label, procs in done.items()]
    ok = [r for r in rows if "error" not in r]
    if ok:
        frames, joints = ok[0]["camera_frames"], max(r["joints"] for r in ok)
        n = 300 if quick else 3000
        z = make_data(1, n, seed=5)
        fp_cpu, _ = measure(lambda: filterpy_filter(paper_model(), z), 1)
        per_js = fp_cpu / n
        s = per_js * frames * joints
        rows.append({"method": "filterpy KF, per camera joint (peer)", "duration_s": duration,
                     "cpu_s": s, "s_per_hour": s * 3600.0 / duration, "x_real_time": duration / s,
                     "peak_rss_mb": None, "note": f"KF of {joints} output joints x {frames} camera frames, timed on 1 x {n}"})  # fmt: skip
    return rows
