"""The HTML report: self-contained, every figure loads in headless Chromium, no silent overwrite."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

from _chromium import (
    browser,
    canvas_stats,
    color_fraction,
    count_loaded_images,
    ensure_chromium,
    screenshot,
)
from kinefuse.conventions import MODE_FIR, MODE_KF, MODE_PREDICT, SOURCE_BRIDGED, SOURCE_FUSED
from kinefuse.evaluation import plots
from kinefuse.evaluation.metrics import evaluate
from kinefuse.evaluation.report import ReportOptions, write_report
from kinefuse.exceptions import InputError
from kinefuse.io.recording import JointStream

JOINTS = ("shoulder_r", "elbow_r", "wrist_r")
EDGES = (("shoulder_r", "elbow_r"), ("elbow_r", "wrist_r"))


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(5)
    T = 240
    t = np.arange(T) / 30.0
    ref = np.zeros((T, 3, 3))
    ref[:, 0] = [0.0, 0.0, 1.4]
    ref[:, 1] = ref[:, 0] + 0.3 * np.stack([np.sin(t), 0 * t, -np.cos(t)], -1)
    ref[:, 2] = ref[:, 1] + 0.25 * np.stack([np.sin(1.5 * t), 0.2 + 0 * t, -np.cos(1.5 * t)], -1)
    outage = np.zeros((T, 3), dtype=bool)
    outage[100:140, 2] = True
    kf = ref + 0.01 * rng.standard_normal(ref.shape)
    kf[outage] += 0.1
    fir = ref + 0.02 * rng.standard_normal(ref.shape)
    fir[:5] = np.nan  # warm-up: excluded and counted
    est = {"KF": kf, "FIR": fir}
    modes = {
        m: np.where(outage, MODE_PREDICT, MODE_KF if m == "KF" else MODE_FIR).astype(np.int64)
        for m in est
    }
    sources = {m: np.where(outage, SOURCE_BRIDGED, SOURCE_FUSED).astype(np.int64) for m in est}
    ev = evaluate(est, ref, outage, {"KF": 0.01, "FIR": 0.05}, joints=JOINTS)
    return {
        "t": t,
        "ref": ref,
        "est": est,
        "outage": outage,
        "modes": modes,
        "sources": sources,
        "ev": ev,
    }


def _write(case, out_dir, **kw):
    return write_report(
        out_dir,
        case["ev"],
        case["est"],
        case["ref"],
        case["t"],
        case["outage"],
        modes=case["modes"],
        sources=case["sources"],
        options=ReportOptions(
            skeleton_edges=EDGES, title="test report", notes="q = 1, R = 0.01", dpi=60
        ),
        **kw,
    )


@pytest.fixture(scope="module")
def report(case, tmp_path_factory):
    return _write(case, tmp_path_factory.mktemp("report") / "out")


def test_report_files(report):
    out = report.parent
    assert report.name == "report.html" and report.is_file()
    names = sorted(p.name for p in (out / "figures").glob("*.png"))
    expected = ["skeleton.png", "summary_rmse.png", "timeline_modes.png", "timeline_sources.png"]
    expected += [f"{kind}_{j}.png" for j in JOINTS for kind in ("cdf", "trajectory")]
    assert names == sorted(expected)
    metrics = json.loads((out / "metrics.json").read_text())
    assert (
        metrics["joints"] == list(JOINTS)
        and metrics["results"]["FIR"]["elbow_r"]["overall"]["n_excluded"] == 5
    )


def test_report_is_self_contained(report):
    html = report.read_text(encoding="utf-8")
    # the only URL is an XML namespace name inside three.js (an identifier, never fetched;
    # the browser test below blocks and records any request)
    assert set(re.findall(r"https?://[^\s\"'<>)]+", html)) == {"http://www.w3.org/1999/xhtml"}
    assert "<link" not in html.lower() and not re.search(r"<script[^>]*\bsrc=", html, re.I)
    assert len(re.findall(r"<script", html)) == 3  # viewer data, three.js + viewer, start
    srcs = re.findall(r'<img [^>]*src="([^"]+)"', html)
    assert len(srcs) == 10
    for src in srcs:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    for text in (
        "test report",
        "q = 1, R = 0.01",
        "Inside camera outages",
        "shoulder_r",
        "KF",
        "FIR",
    ):
        assert text in html


def test_report_refuses_to_overwrite_without_force(case, report):
    before = report.read_bytes()
    with pytest.raises(FileExistsError, match=re.escape(str(report))):
        _write(case, report.parent)
    assert report.read_bytes() == before
    again = _write(case, report.parent, force=True)
    assert again == report and report.is_file()


def test_report_validates_shapes(case, tmp_path):
    with pytest.raises(InputError, match=r"trajectories\['KF'\] with shape"):
        write_report(
            tmp_path,
            case["ev"],
            {"KF": case["est"]["KF"][:10], "FIR": case["est"]["FIR"]},
            case["ref"],
            case["t"],
        )
    with pytest.raises(InputError, match="lack the evaluated methods"):
        write_report(tmp_path, case["ev"], {"KF": case["est"]["KF"]}, case["ref"], case["t"])
    with pytest.raises(InputError, match=r"modes\['KF'\] as integer codes"):
        write_report(
            tmp_path,
            case["ev"],
            case["est"],
            case["ref"],
            case["t"],
            modes={"KF": np.zeros((3, 3), dtype=int)},
        )
    assert not (tmp_path / "report.html").exists()


def test_report_minimal_with_joint_stream_reference(case, tmp_path):
    js = JointStream(case["t"], case["ref"], joints=JOINTS)
    ev = evaluate(case["est"], js)  # no outages, no timelines, no skeleton
    path = write_report(tmp_path, ev, case["est"], js)
    html = path.read_text(encoding="utf-8")
    assert len(re.findall(r"<img ", html)) == 1 + 2 * len(JOINTS)
    assert "Inside camera outages" not in html


def test_outage_runs():
    assert plots.outage_runs(np.array([0, 1, 1, 0, 1], dtype=bool)) == [(1, 3), (4, 5)]
    assert plots.outage_runs(np.zeros(0, dtype=bool)) == []


@pytest.mark.parametrize("three_d", [False, True])
@pytest.mark.parametrize("palette", [False, True])
def test_figure_to_png_has_the_pixels_of_savefig(palette, three_d):
    """figure_to_png draws a 2-D figure once instead of savefig's two draws: the pixels (RGBA,
    or after the same 256-colour palette) are matplotlib's savefig ones, with or without a
    3-D axes, and the figure keeps its dpi."""
    import io

    from PIL import Image

    def figure():  # constrained layout, a legend, shading (+ a 3-D axes): what reports use
        fig = plots.trajectory_figure(
            np.arange(90) / 30.0,
            np.sin(np.arange(270.0).reshape(90, 3) / 20.0),
            {"KF": np.cos(np.arange(270.0).reshape(90, 3) / 20.0)},
            outage=np.arange(90) % 40 < 8,
            joint="wrist_r",
        )
        if three_d:
            fig.add_subplot(4, 4, 16, projection="3d").plot([0, 1], [0, 1], [0, 1])
        return fig

    buf = io.BytesIO()
    figure().savefig(buf, format="png", dpi=70)
    want = Image.open(io.BytesIO(buf.getvalue())).convert("RGBA")
    if palette:
        want = want.convert("RGB").quantize(
            colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
        )
    fig = figure()
    dpi0 = fig.dpi
    got = Image.open(io.BytesIO(plots.figure_to_png(fig, dpi=70, palette=palette)))
    assert fig.dpi == dpi0
    assert got.mode == ("P" if palette else "RGBA") and got.size == want.size
    assert np.array_equal(np.asarray(got.convert("RGBA")), np.asarray(want.convert("RGBA")))
    if not palette:
        assert got.info.get("Software") == "kinefuse"


def test_report_renders_in_chromium_with_every_figure(report, tmp_path):
    browser = ensure_chromium()
    n_images, n_loaded = count_loaded_images(browser, report)
    assert n_images == 10
    assert n_loaded == n_images
    shot = screenshot(browser, report, tmp_path / "report.png", height=1600)
    assert shot.stat().st_size > 20_000  # a rendered page, not a blank one


def test_report_tables_drop_empty_rows_and_no_viewer_no_script(case, tmp_path):
    est = dict(case["est"])
    est["arm only"] = case["est"]["KF"].copy()
    est["arm only"][:, 2] = np.nan  # no estimate at the wrist
    ev = evaluate(est, case["ref"], case["outage"], joints=JOINTS)
    path = write_report(
        tmp_path, ev, est, case["ref"], case["t"], options=ReportOptions(interactive=False, dpi=40)
    )
    html = path.read_text(encoding="utf-8")
    assert "<script" not in html and "http" not in html  # interactive=False: static as before
    assert "Not applicable at wrist_r: arm only (no estimate there)." in html
    # no row of dashes with N = 0 for the wrist
    wrist = html[html.index('id="joint-wrist_r"') :]
    wrist = wrist[: wrist.index("</section>")]
    assert "<td>arm only</td>" not in wrist and ">0</td>" not in wrist
    # shoulder and elbow have no outage: said once instead of an empty outage table
    elbow = html[html.index('id="joint-elbow_r"') :]
    assert "No camera outage at this joint." in elbow[: elbow.index("</section>")]


def test_palette_and_line_styles():
    few = plots.method_linestyles(list("abcdef"))
    assert set(few.values()) == {"-"}
    many = plots.method_linestyles(list("abcdefgh"))
    assert len({str(v) for v in many.values()}) == 4
    colors = plots.method_colors(list("abcdefghi"))
    assert len(set(colors.values())) == 9 and set(colors.values()) <= set(plots.TOL_MUTED)
    fig = plots.trajectory_figure(
        np.arange(5.0),
        np.zeros((5, 3)),
        {"drawn": np.ones((5, 3)), "absent": np.full((5, 3), np.nan)},
        measurement=np.full((5, 3), np.nan),
    )
    labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert labels == ["reference", "drawn"]  # no "absent" method, no camera that is all NaN


def test_report_viewer_in_chromium(case, report, tmp_path):
    """The viewer draws, plays and hides a method's skeleton when its box is unticked."""
    with browser() as (ctx, log):
        page = ctx.new_page()
        page.goto(report.as_uri())
        page.wait_for_function("window.kfViewer && window.kfViewer.ready", timeout=15_000)
        canvas = page.locator("#kf-viewer canvas")
        canvas.scroll_into_view_if_needed()
        for name in ("reference", "KF"):  # only FIR shown
            page.uncheck(f'.kf-toggle[data-series="{name}"]')
        page.check('.kf-toggle[data-series="FIR"]')
        page.evaluate(  # the time slider to a sample where FIR has an estimate (not warm-up)
            "() => { const s = document.getElementById('kf-time'); s.value = 120;"
            " s.dispatchEvent(new Event('input')); }"
        )
        color = page.evaluate("kfViewer.series.filter(s => s.name === 'FIR')[0].color")
        shown = canvas.screenshot(path=tmp_path / "viewer_fir.png")
        page.uncheck('.kf-toggle[data-series="FIR"]')
        hidden = canvas.screenshot(path=tmp_path / "viewer_none.png")
        t0 = page.evaluate("kfViewer.time_s")
        page.click("#kf-play")
        page.wait_for_function(f"kfViewer.time_s > {t0} + 0.5", timeout=15_000)
        page.click("#kf-play")
        err_rows = page.locator(".kf-err-table tr").count()
    print(f"\nviewer screenshots: {tmp_path / 'viewer_fir.png'} {tmp_path / 'viewer_none.png'}")
    assert log["errors"] == [] and log["blocked"] == []
    on, off = canvas_stats(shown), canvas_stats(hidden)
    assert on["non_white"] > 0.01  # grid and skeleton drawn
    assert color_fraction(on["pixels"], color) > 5e-4
    assert color_fraction(off["pixels"], color) < 0.1 * color_fraction(on["pixels"], color)
    assert err_rows == 1 + len(JOINTS)


def test_viewer_quantization_and_thinning():
    from kinefuse.evaluation import viewer

    p = np.array([[[0.0, 1.2344, -0.0006], [np.nan, 2.0, 3.0]]])  # (1, 2, 3)
    origin = np.array([0.0, 1.0, 0.0])
    q = np.frombuffer(base64.b64decode(viewer.quantize(p, origin, 0.001)), dtype="<i2")
    assert q.tolist() == [0, 234, -1, -32768, 1000, 3000]  # round((p - origin) / 1 mm); NaN
    assert viewer.quantization_scale([p], origin) == 0.001
    far = np.array([[100.0, 0.0, 0.0]])
    assert viewer.quantization_scale([far], np.zeros(3)) == pytest.approx(100.0 / 32767)
    t = np.arange(6000) / 100.0  # 60 s at 100 Hz
    assert viewer.downsample_stride(t, 30, max_rate_hz=30, max_bytes=10**9) == 4  # <= 30 Hz
    k = viewer.downsample_stride(t, 3000, max_rate_hz=30, max_bytes=1_000_000)
    assert 6000 / k * 3000 * 2 * 4 / 3 <= 1_000_000 < 6000 / (k - 1) * 3000 * 2 * 4 / 3


def test_report_without_webgl_says_so_and_keeps_the_figures(report):
    with browser(extra_args=["--disable-webgl", "--disable-3d-apis"]) as (ctx, log):
        page = ctx.new_page()
        page.goto(report.as_uri())
        page.wait_for_selector(".kf-no-webgl", timeout=15_000)
        loaded = page.evaluate("Array.from(document.images).filter(i => i.naturalWidth > 0).length")
    assert loaded == 10
    assert not [e for e in log["errors"] if e.startswith("page error")]  # no uncaught error


def test_warnings_box_above_the_notes_without_repeating_them():
    """Warnings get their own highlighted section before the notes, once each and escaped; a
    note that only repeats one (``warning: ``, ``WARNING: ``, ``calibration: ``) is left out."""
    from kinefuse.evaluation.report import notes_html

    warns = ["knee_r <axis> tilted", "no orientation for thigh_l", "knee_r <axis> tilted"]
    notes = [
        "segment lengths (m): thigh_l 0.43",
        "calibration: knee_r <axis> tilted",
        "WARNING: no orientation for thigh_l",
        "warning: something else",
    ]
    page = notes_html(notes, warns)
    box, rest = page.split("<section><h2>Notes</h2>")
    assert 'class="warnings"' in box and "Warnings (2)" in box
    assert box.count("<li>") == 2 and "knee_r &lt;axis&gt; tilted" in box
    assert "segment lengths" in rest and "warning: something else" in rest
    assert "tilted" not in rest and "no orientation" not in rest
    assert notes_html(notes[:1], ()).startswith("<section><h2>Notes</h2>")
    assert notes_html((), ()) == ""


def test_best_marks_only_where_smaller_is_better():
    """An error table marks each joint's smallest value; a table of angles or counts does not
    (the green "best" of an angle range or a sample count would mean nothing)."""
    from kinefuse.evaluation.tables import ResultTable, TableRow, to_html

    rows = (TableRow(("knee", "a"), (1.0, 5.0)), TableRow(("knee", "b"), (2.0, 4.0)))
    errors = ResultTable("RMSE", ("Joint", "Method"), ("x", "y"), rows)
    assert to_html(errors).count("num best") == 2
    angles = ResultTable("Angles", ("Joint", "Angle"), ("min", "max"), rows, best=False)
    assert "best" not in to_html(angles)


def test_short_method_labels_put_a_shared_tag_in_the_caption():
    from kinefuse.evaluation.plots import short_method_labels

    tag = " [calibrated on camera = reference, lengths from camera = reference]"
    short, cap = short_method_labels(["IMU only" + tag, "kinefuse" + tag])
    assert short == {"IMU only" + tag: "IMU only", "kinefuse" + tag: "kinefuse"}
    assert (
        cap == "every estimate: [calibrated on camera = reference, lengths from camera = reference]"
    )
    short, cap = short_method_labels(["reference", "kinefuse" + tag])  # one without the tag
    assert short == {"reference": "reference", "kinefuse" + tag: "kinefuse *"}
    assert cap.startswith("* [calibrated on camera")
    two = ["a [x]", "b [y, z]"]  # different tags: kept (wrapped on request)
    assert short_method_labels(two) == ({m: m for m in two}, "")
    assert short_method_labels(two, wrap=4)[0]["b [y, z]"] == "b\n[y,\nz]"


def test_a_report_whose_estimates_share_a_long_tag_keeps_its_plots(shared_data, tmp_path):
    """UTD-MHAD's Kinect is camera and reference: every estimate's label carries a long tag.
    In legends it squeezed the axes to nothing (matplotlib: "constrained_layout not
    applied"); it is now said once per figure."""
    import warnings

    from kinefuse.pipelines.run import run_session

    session = Path(__file__).parent / "data" / "sessions" / "utd_mhad_a9_s1_t1.toml"
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="constrained_layout not applied")
        run_session(session, tmp_path / "out")
    assert (tmp_path / "out" / "figures" / "summary_rmse.png").is_file()
