"""The benchmark's timing helpers (`kinefuse bench`, benchmarks/bench_latency.py).

No timing assertions (STYLE.md): only that every frame is timed, the numbers are sane and the
outage-onset frames of the paper-B processor are found; that rows are timed in the order and
rounds they should be, and that the pipeline rows run as `kinefuse run` does.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from kinefuse.apps.bench import ENGINE_PROCESSORS, engine_frame_times, filterpy_frame_times
from kinefuse.streaming.replay import demo_recording


@pytest.fixture(scope="module")
def rec():
    return demo_recording(stop_s=4.0, seed=2)


@pytest.mark.parametrize("processor", ENGINE_PROCESSORS)
def test_engine_frame_times(rec, processor):
    wall, cpu, onset = engine_frame_times(rec, processor, n_frames=10_000)
    n_frames = len(rec.vision)  # one output per camera frame, the first 30 not timed
    assert wall.shape == cpu.shape == onset.shape == (n_frames - 30,)
    assert np.all(np.isfinite(wall)) and np.all(wall > 0) and np.all(cpu >= 0)
    if processor != "elm-fir":
        assert not onset.any()  # only a bridging processor trains at outage onsets


def test_engine_frame_times_finds_outage_onsets(rec):
    av = rec.vision.available
    onsets = int(np.sum(av[:-1] & ~av[1:]))  # visible -> hidden, per joint
    assert onsets > 0, "the demo recording has camera outages"
    _, _, onset = engine_frame_times(rec, "elm-fir", n_frames=10_000, loops=2)
    assert onset.any()


def test_filterpy_peer_times():
    pytest.importorskip("filterpy")
    wall, cpu = filterpy_frame_times(n_frames=40, n_joints=2)
    assert wall.shape == cpu.shape == (10,) and np.all(wall > 0)


def test_engine_rows_interleave_every_processor_and_the_peer(monkeypatch):
    """The engine rows are timed in rounds: each processor and the peer advance round by round
    (the recorded order of chunks is the oracle), and every row gets its frames."""
    pytest.importorskip("filterpy")
    from kinefuse.apps import bench_engine

    order = []
    real = bench_engine.islice

    def islice(gen, k):
        order.append(gen.gi_frame is not None and gen.gi_code.co_name)
        return real(gen, k)

    # the module's own name, not itertools.islice: a global patch also caught other callers
    # (pytest formatting a traceback, with three arguments) and failed there
    monkeypatch.setattr(bench_engine, "islice", islice)
    rows = bench_engine.engine_rows(quick=True)
    assert [r["processor"] for r in rows] == [*ENGINE_PROCESSORS, "filterpy KF (peer)"]
    assert all(r["frames"] == 270 for r in rows)  # 300 timed, the first 30 skipped
    assert len(order) >= 2 * len(rows) and order[: len(rows)] == order[len(rows) : 2 * len(rows)]


def test_pipeline_rows_input_has_no_simulator_truth():
    """The whole-pipeline rows run on what a recording read from files holds: the simulator's
    truth (about 1.2 GB an hour) is left out, the sensor, camera and reference data are kept."""
    from kinefuse.apps.bench_engine import _SIM_TRUTH, _as_read_from_files, pipeline_recording

    full = pipeline_recording(2.0, seed=1)
    assert set(_SIM_TRUTH) <= set(full.metadata)
    rec = _as_read_from_files(full)
    assert not set(_SIM_TRUTH) & set(rec.metadata)
    assert all(rec.imu[k] is v for k, v in full.imu.items()) and len(rec.imu) == len(full.imu)
    assert rec.vision is full.vision and rec.reference is full.reference
    assert set(full.metadata) - set(rec.metadata) == set(_SIM_TRUTH)


def test_interleaved_rounds_time_each_row_right_after_its_own_call(monkeypatch):
    """`measure_interleaved`: round by round every row is called twice in a row and only the
    second call is timed (a timed call never follows another row's); one row alone is called
    once a round. The recorded calls and clock reads are the oracle."""
    from kinefuse.apps import bench_filters

    log = []
    monkeypatch.setattr(bench_filters.time, "thread_time", lambda: log.append("|") or 0.0)
    calls = {k: (lambda k=k: log.append(k)) for k in "abc"}
    assert set(bench_filters.measure_interleaved(calls, 2, warm_up=False)) == set(calls)
    assert "".join(log) == "a|a|b|b|c|c|" * 2
    log.clear()
    bench_filters.measure_interleaved({"a": calls["a"]}, 3, warm_up=True)
    assert "".join(log) == "a" + "|a|" * 3


def test_pipeline_rows_compare_numpys_hugepage_advice(monkeypatch):
    """Each method runs as `kinefuse run` does (the CLI's small pages), and paper B once more
    with numpy's hugepage advice on; a NUMPY_MADVISE_HUGEPAGE the user set applies to all rows."""
    from kinefuse import _memory
    from kinefuse.apps.bench_engine import PIPELINE_METHODS, _pipeline_runs

    monkeypatch.setattr(_memory, "_set_here", True)  # as after the CLI's prefer_small_pages()
    monkeypatch.setenv(_memory.HUGEPAGE_ENV, "0")
    runs = _pipeline_runs()
    assert [m for _, m, _ in runs] == ["paper-a", "elm-fir", "elm-fir", "kinefuse"]
    assert [label for label, _, _ in runs if label not in PIPELINE_METHODS] == [
        "elm-fir, numpy hugepage advice on"
    ]
    assert [env[_memory.HUGEPAGE_ENV] for _, _, env in runs] == ["0", "0", "1", "0"]
    monkeypatch.setattr(_memory, "_set_here", False)  # the user's own setting
    for value in ("0", "1"):
        monkeypatch.setenv(_memory.HUGEPAGE_ENV, value)
        runs = _pipeline_runs()
        assert [(label, env[_memory.HUGEPAGE_ENV]) for label, _, env in runs] == [
            (m, value) for m in PIPELINE_METHODS
        ]


def test_pipeline_rows_run_in_rounds_of_fresh_processes_and_give_the_median(monkeypatch):
    """A full run times every pipeline row in PIPELINE_REPEATS fresh processes, round by round;
    a row is the median CPU time of its runs, with the largest peak RSS (the recorded calls and
    made-up worker outputs are the oracle); a failed run makes its row a failure."""
    pytest.importorskip("filterpy")
    from kinefuse import _memory
    from kinefuse.apps import bench_engine as be

    monkeypatch.setattr(_memory, "_set_here", True)  # as after the CLI's prefer_small_pages()
    monkeypatch.setenv(_memory.HUGEPAGE_ENV, "0")
    real = be.pipeline_recording
    monkeypatch.setattr(be, "pipeline_recording", lambda duration, seed=0: real(1.0, seed))
    cpu = iter([3.0, 9.0, 30.0, 40.0, 2.0, 8.0, 31.0, 39.0, 4.0, 7.0, 32.0, 41.0])
    calls = []

    def run(cmd, **kw):
        calls.append((cmd[3], kw["env"][_memory.HUGEPAGE_ENV]))
        c = next(cpu)
        if c == 39.0:  # kinefuse's second run fails
            return subprocess.CompletedProcess(cmd, 1, stdout="", stderr="Traceback\nValueError: x")
        out = {"cpu_s": c, "wall_s": c + 0.5, "peak_rss_mb": 100.0 + c, "rss_before_mb": 1.0,
               "camera_frames": 30, "joints": 8}  # fmt: skip
        return subprocess.CompletedProcess(cmd, 0, stdout=json.dumps(out) + "\n", stderr="")

    monkeypatch.setattr(be.subprocess, "run", run)
    rows = be.pipeline_rows(quick=False)
    one_round = [("paper-a", "0"), ("elm-fir", "0"), ("elm-fir", "1"), ("kinefuse", "0")]
    assert be.PIPELINE_REPEATS == 3 and calls == one_round * 3
    by = {r["method"]: r for r in rows}
    assert by["paper-a"]["cpu_s"] == 3.0 and by["paper-a"]["cpu_s_runs"] == [3.0, 2.0, 4.0]
    assert by["paper-a"]["x_real_time"] == 3600.0 / 3.0 and by["paper-a"]["peak_rss_mb"] == 104.0
    assert by["elm-fir"]["cpu_s"] == 8.0 and by["elm-fir"]["wall_s"] == 8.5
    assert by["elm-fir, numpy hugepage advice on"]["cpu_s"] == 31.0
    assert by["kinefuse"] == {"method": "kinefuse", "error": "ValueError: x"}
    assert "filterpy KF, per camera joint (peer)" in by
