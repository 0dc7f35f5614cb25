"""The demo back-end: both papers on the packaged CMU clip, report written."""

from __future__ import annotations

import time

import numpy as np
import pytest

from _chromium import browser, canvas_stats, color_fraction
from kinefuse.apps.demo import demo_recording, run_demo, run_scenario
from kinefuse.conventions import PAPER_B_JOINTS, SOURCE_CAMERA, SOURCE_FUSED
from kinefuse.pipelines.labels import PAPER_A_LABELS, paper_b_methods


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """One `run_demo` for this module (it takes about a minute on a loaded machine)."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    return out, run_demo(out, force=False, quiet=True)


def test_run_demo_writes_report(demo):
    out, summary = demo
    report = summary["report"]
    assert report == out / "report.html" and report.stat().st_size > 10_000
    assert (out / "metrics.json").is_file() and any((out / "figures").glob("*.png"))
    ev = summary["evaluation"]
    assert ev.joints == PAPER_B_JOINTS
    assert {"ELM/FIR", "ELM/KF", "IMU only", "camera only"} <= set(ev.methods)
    assert ev.has_outages  # the demo's camera has outages at the joints
    allm = summary["all_methods"]
    assert set(PAPER_A_LABELS.values()) <= set(allm.methods)
    # paper A only at the arms
    m = allm.methods.index("EM-KF/FIR")
    arms = [allm.joints.index(j) for j in ("elbow_l", "elbow_r", "wrist_l", "wrist_r")]
    legs = [allm.joints.index(j) for j in ("knee_l", "knee_r", "ankle_l", "ankle_r")]
    assert np.all(np.isfinite(allm.mean_rmse[m, arms])) and np.all(allm.n_samples[m, legs] == 0)
    titles = [t.title for t in summary["tables"]]
    assert any("Paper A" in t for t in titles) and any("Paper B" in t for t in titles)
    with pytest.raises(FileExistsError, match="--force"):
        run_demo(out, force=False, quiet=True)


def test_scenario_small_configuration():
    from kinefuse.data import demo_motion
    from kinefuse.sim import virtual_recording

    rec = virtual_recording(demo_motion(0.0, 8.0), seed=3)
    sc = run_scenario(rec, paper_a=("kf",), paper_b=("camera-only", "elm-kf"))
    T = rec.vision.t_s.size
    assert sc.reference.shape == (T, 8, 3) and sc.outage.shape == (T, 8)
    assert set(sc.estimates) == {"KF", "camera only", "ELM/KF"}
    # camera only: the aligned camera wherever it sees the joint
    cam = sc.estimates["camera only"]
    seen = ~sc.outage
    np.testing.assert_allclose(cam[seen], sc.camera[seen], atol=1e-12)
    assert np.all(sc.sources["camera only"][seen] == SOURCE_CAMERA)
    assert np.all(sc.sources["ELM/KF"][seen] == SOURCE_FUSED)
    ev = sc.evaluation()
    # fused ELM/KF is within a few cm of the truth where the camera sees the joints
    k = ev.methods.index("ELM/KF")
    assert np.all(ev.mean_rmse[k] < 0.15), ev.mean_rmse[k]
    # paper A's KF on the virtual chain (VQF orientation, soft tissue, calibrated against a
    # camera with Kinect-like tracking error, as real chains are): elbows within 8 cm
    kf = ev.methods.index("KF")
    for j in ("elbow_l", "elbow_r"):
        assert ev.mean_rmse[kf, ev.joints.index(j)] < 0.08


def test_demo_recording_is_seeded():
    a, b = demo_recording(), demo_recording()
    np.testing.assert_array_equal(a.vision.available, b.vision.available)
    assert not np.all(a.vision.available)


def test_paper_b_methods_lists_the_papers():
    m = paper_b_methods()
    assert m[:4] == ("elm-fir", "elm-kf", "imu-only", "camera-only")


def test_demo_through_cli_prints_paper_tables_and_protects_its_report(tmp_path):
    """`kinefuse demo` prints both papers' tables, writes the report and --json, and a second
    run into the same folder stops with one line naming the report and --force, leaving it
    untouched (one demo run for all of it: the CLI run is the slow part)."""
    import json
    from pathlib import Path

    from typer.testing import CliRunner

    from conftest import cli_stderr
    from kinefuse import cli

    out, summary = tmp_path / "d", tmp_path / "summary.json"
    res = CliRunner().invoke(cli.app, ["demo", "--out", str(out), "--json", str(summary)])
    assert res.exit_code == 0, res.output
    for needle in (
        "Paper A layout (Tables 4-5)",
        "Table 6",
        "Paper B layout (Tables 3-5)",
        "ELM/FIR",
    ):
        assert needle in res.output, needle
    report = out / "report.html"
    assert report.is_file() and report.stat().st_size > 10_000
    data = json.loads(summary.read_text())
    assert data["evaluation"]["joints"] and Path(data["report"]) == report
    before = report.stat().st_mtime_ns
    again = CliRunner().invoke(cli.app, ["demo", "--out", str(out)])
    err = [ln for ln in cli_stderr(again).splitlines() if ln.strip()]
    assert again.exit_code == 2 and len(err) == 1, (again.exit_code, err)
    assert err[0].startswith("kinefuse: error: ") and str(report) in err[0] and "--force" in err[0]
    assert report.stat().st_mtime_ns == before


def test_demo_report_viewer_in_chromium(demo, tmp_path):
    """The demo report in headless Chromium: no console error, no request off the machine,
    the viewer draws, play advances the time, unticking a method hides its skeleton; the size
    and the time to a ready viewer are printed (benchmarks, not asserts)."""
    _, summary = demo
    report = summary["report"]
    size = report.stat().st_size
    assert size <= 5_000_000, size
    with browser(height=1000) as (ctx, log):
        page = ctx.new_page()
        t0 = time.perf_counter()
        page.goto(report.as_uri())
        page.wait_for_function("window.kfViewer && window.kfViewer.ready", timeout=30_000)
        ready_s = time.perf_counter() - t0
        page.locator("#viewer").scroll_into_view_if_needed()
        page.locator("#viewer").screenshot(path=tmp_path / "demo_viewer.png")
        names = page.evaluate("kfViewer.series.map(s => s.name)")
        method = "ELM/FIR"
        for name in names:  # only the method under test
            if name != method:
                page.uncheck(f'.kf-toggle[data-series="{name}"]')
        page.check(f'.kf-toggle[data-series="{method}"]')
        color = page.evaluate(f"kfViewer.series.filter(s => s.name === '{method}')[0].color")
        canvas = page.locator("#kf-viewer canvas")
        shown = canvas.screenshot(path=tmp_path / "demo_viewer_method.png")
        page.uncheck(f'.kf-toggle[data-series="{method}"]')
        hidden = canvas.screenshot()
        t_a = page.evaluate("kfViewer.time_s")
        page.click("#kf-play")
        page.wait_for_function(f"kfViewer.time_s > {t_a} + 0.5", timeout=15_000)
        page.click("#kf-play")
    print(
        f"\ndemo report {size / 1e6:.2f} MB, viewer ready {ready_s:.2f} s after navigation; "
        f"screenshots {tmp_path / 'demo_viewer.png'}, {tmp_path / 'demo_viewer_method.png'}"
    )
    assert log["errors"] == [] and log["blocked"] == []
    assert {"reference", "camera", "whole body (reference)", method} <= set(names)
    on, off = canvas_stats(shown), canvas_stats(hidden)
    assert on["non_white"] > 0.01
    assert color_fraction(on["pixels"], color) > 5e-4
    assert color_fraction(off["pixels"], color) < 0.1 * color_fraction(on["pixels"], color)


def test_demo_refuses_an_unusable_out_folder_in_one_line_before_any_work(tmp_path, monkeypatch):
    """`kinefuse demo --out DIR` where DIR cannot be created (``/proc`` refuses new entries even
    to root) or lies under a file: exit 2 with one line naming the folder, printed before
    anything else (no kernel note, no demo run)."""
    from typer.testing import CliRunner

    from conftest import cli_stderr
    from kinefuse import cli
    from kinefuse.cli import offline

    monkeypatch.setattr(offline, "backend", lambda name: pytest.fail("the demo ran"))
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out, reason in (("/proc/kinefuse-demo", "not writable"), (afile / "d", "not a folder")):
        res = CliRunner().invoke(cli.app, ["demo", "--out", str(out)])
        err = [ln for ln in cli_stderr(res).splitlines() if ln.strip()]
        assert res.exit_code == 2 and len(err) == 1, (res.exit_code, err)
        assert err[0].startswith(f"kinefuse: error: --out {out}") and reason in err[0], err
    assert list(tmp_path.iterdir()) == [afile]  # no probe left behind
