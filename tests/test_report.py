"""The HTML report: self-contained, every figure loads in headless Chromium, no silent overwrite."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest

from _chromium import count_loaded_images, ensure_chromium, screenshot
from kinefuse.conventions import MODE_FIR, MODE_KF, MODE_PREDICT, SOURCE_BRIDGED, SOURCE_FUSED
from kinefuse.evaluation import plots
from kinefuse.evaluation.metrics import evaluate
from kinefuse.evaluation.report import write_report
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
        skeleton_edges=EDGES,
        title="test report",
        notes="q = 1, R = 0.01",
        dpi=60,
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
    assert "http://" not in html and "https://" not in html and "<script" not in html.lower()
    assert "<link" not in html.lower()
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


def test_report_renders_in_chromium_with_every_figure(report, tmp_path):
    browser = ensure_chromium()
    n_images, n_loaded = count_loaded_images(browser, report)
    assert n_images == 10
    assert n_loaded == n_images
    shot = screenshot(browser, report, tmp_path / "report.png", height=1600)
    assert shot.stat().st_size > 20_000  # a rendered page, not a blank one
