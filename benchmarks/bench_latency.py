"""Processing latency of the online path over an LSL loopback (eight joints of paper B).

A virtual full-body recording (packaged CMU clip -> 9 IMUs at 100 Hz + camera at 30 Hz with
outages, looped) is published by ``run_replay`` at real time in a child process; ``run_stream``
pulls it, runs the
engine and pushes the fused joints. Latency per output = time from the first input pull of the
loop iteration that completed the frame to the fused sample being pushed (perf_counter).
Printed next to it: the engine's own per-frame cost without LSL, and a peer (filterpy KF, one
``predict``/``update`` per joint) per frame. All LSL traffic is machine-local
(``ensure_local_lsl_config``). Target: p99 <= 1 ms.

Processors: ``kf-fusion``, ``paper-a`` (:mod:`kinefuse.streaming.processors`) and ``elm-fir``
(paper B, :class:`kinefuse.streaming.paper_b.VisionAssistedProcessor`). For paper B the
engine-only figures are also given separately for the frames with an outage onset (ELM
training, once per episode and joint).

Usage::

    python benchmarks/bench_latency.py [--duration 60] [--processor kf-fusion|paper-a|elm-fir]
        [--engine-only] [--cpu 1]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from kinefuse.apps.bench import engine_frame_times as engine_only
from kinefuse.apps.bench import filterpy_frame_times as peer_filterpy
from kinefuse.streaming import StreamConfig, run_stream
from kinefuse.streaming.config import ensure_local_lsl_config
from kinefuse.streaming.replay import demo_recording

PROCESSOR_CHOICES = ("kf-fusion", "paper-a", "elm-fir")


def fmt(x: np.ndarray) -> str:
    return f"p50 {1e3 * np.median(x):.3f} ms  p99 {1e3 * np.percentile(x, 99):.3f} ms  max {1e3 * x.max():.3f} ms  (n={x.size})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--duration", type=float, default=60.0, help="loopback run time, s (default 60)"
    )
    ap.add_argument("--processor", default="kf-fusion", choices=PROCESSOR_CHOICES)
    ap.add_argument(
        "--engine-only", action="store_true", help="engine-only figures of all processors, no LSL"
    )
    ap.add_argument(
        "--cpu",
        type=int,
        default=None,
        help="pin this process (engine, LSL inlets/outlet) to one core; the replay child keeps "
        "the original affinity (unlike `taskset`, which it would inherit)",
    )
    args = ap.parse_args()
    all_cpus = os.sched_getaffinity(0)
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    ensure_local_lsl_config(
        tempfile.mkdtemp(prefix="kinefuse-bench-"), session_id=f"kinefuse-bench-{os.getpid()}"
    )

    rec = demo_recording()
    print(f"load average {os.getloadavg()} on {os.cpu_count()} cores")
    for name in PROCESSOR_CHOICES if args.engine_only else (args.processor,):
        x, c, onset = engine_only(rec, name, n_frames=3000, loops=8)
        print(f"engine only ({name}, no LSL), per frame, wall: {fmt(x)}")
        print(f"{'':>{len(name) + 24}}thread CPU: {fmt(c)}")
        if onset.any():
            print(f"    frames without an outage onset, CPU: {fmt(c[~onset])}")
            print(f"    frames with an onset (ELM training), CPU: {fmt(c[onset])}")
    peer = peer_filterpy()
    if peer is not None:
        print(f"peer: filterpy KF, 8 joints predict+update per frame, wall: {fmt(peer[0])}")
        print(f"{'':>50}thread CPU: {fmt(peer[1])}")
    print("Sun 2024 Table 6 (MATLAB, per step): KF 0.037 ms, FIR 0.237 ms, EM-KF/FIR 7.954 ms")

    if args.engine_only:
        return
    prefix = f"kfbench{os.getpid()}"
    # the replay runs in its own process (own GIL), with the same machine-local LSL config
    code = (
        "from kinefuse.streaming import run_replay\n"
        f"run_replay('demo', rate=1.0, name_prefix={prefix!r}, loop=True, duration_s={args.duration + 30},"
        " wait_for_consumers_s=60)\n"
    )
    rep = subprocess.Popen(
        [sys.executable, "-c", code],
        env=dict(os.environ),
        preexec_fn=lambda: os.sched_setaffinity(0, all_cpus),
    )
    try:
        cfg = StreamConfig(name_prefix=prefix, processor=args.processor, resolve_timeout_s=30)
        t0 = time.monotonic()
        summary = run_stream(cfg, duration_s=args.duration, status=False)
    finally:
        rep.terminate()
        rep.wait(10)
    lat = summary["latency_ms"]
    print(
        f"LSL loopback {time.monotonic() - t0:.0f} s, {summary['outputs']} outputs, processor {args.processor}, "
        f"8 joints: pull -> push latency p50 {lat['p50']:.3f} ms  p99 {lat['p99']:.3f} ms  max {lat['max']:.3f} ms  "
        f"(n={lat['n']}; {lat['catch_up_outputs']} start-up backlog outputs not timed); "
        f"target p99 <= 1 ms: {'met' if lat['p99'] <= 1.0 else 'NOT met'}"
    )
    c = summary["counters"]
    print(
        f"counters: forced {c['forced_frames']} synthesized {c['synthesized_frames']} late {c['late']} "
        f"time_jump {c['time_jump']} stale {c['stream_stale']}  (load avg {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores)"
    )


if __name__ == "__main__":
    main()
