"""Metrics against closed forms on hand-computed arrays; evaluate() and the paper-style tables."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from rich.console import Console

from kinefuse.evaluation import metrics, tables
from kinefuse.evaluation.metrics import (
    error_at,
    error_cdf,
    evaluate,
    mean_rmse,
    position_error,
    relative_improvement,
    rmse_3d,
    rmse_per_axis,
    valid_samples,
)
from kinefuse.exceptions import InputError
from kinefuse.io.recording import JointStream

# errors per sample: (1,0,0) (0,2,0) (0,0,3) (1,1,1) -> |e| = 1, 2, 3, sqrt(3)
EST = np.array([[1.0, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
REF = np.zeros((4, 3))


def test_rmse_per_axis_closed_form():
    np.testing.assert_allclose(
        rmse_per_axis(EST, REF),
        [math.sqrt(2 / 4), math.sqrt(5 / 4), math.sqrt(10 / 4)],
        rtol=0,
        atol=1e-15,
    )


def test_mean_rmse_is_mean_of_axis_rmses_not_3d():
    expected = (math.sqrt(0.5) + math.sqrt(1.25) + math.sqrt(2.5)) / 3
    assert mean_rmse(EST, REF) == pytest.approx(expected, abs=1e-15)
    assert rmse_3d(EST, REF) == pytest.approx(math.sqrt(17 / 4), abs=1e-15)
    assert mean_rmse(EST, REF) < rmse_3d(EST, REF)


def test_mean_rmse_reproduces_paper_a_table4_kf_row():
    # constant per-axis offsets give exactly the table's per-axis RMSEs; "Mean" = 0.066 (SPEC §14)
    east, north, up, mean = tables.PAPER_A_RMSE_M["elbow"]["KF"]
    est = np.tile([east, north, up], (50, 1))
    np.testing.assert_allclose(
        rmse_per_axis(est, np.zeros_like(est)), [east, north, up], atol=1e-15
    )
    assert round(float(mean_rmse(est, np.zeros_like(est))), 3) == mean


def test_rmse_3d_equals_root_sum_of_axis_squares(rng):
    est, ref = rng.normal(size=(2, 3, 50, 3))
    np.testing.assert_allclose(
        rmse_3d(est, ref) ** 2, (rmse_per_axis(est, ref) ** 2).sum(-1), rtol=1e-12
    )


def test_nan_samples_excluded_and_counted():
    est = np.vstack([EST, [[np.nan, 0, 0]], [[5.0, 5, 5]]])
    ref = np.vstack([REF, [[0.0, 0, 0]], [[0.0, np.nan, 0]]])
    valid = valid_samples(est, ref)
    assert valid.tolist() == [True, True, True, True, False, False]
    assert int((~valid).sum()) == 2
    np.testing.assert_allclose(rmse_per_axis(est, ref), rmse_per_axis(EST, REF), atol=1e-15)
    assert rmse_3d(est, ref) == pytest.approx(math.sqrt(17 / 4))
    assert np.isnan(position_error(est, ref)[4:]).all()


def test_mask_restricts_to_outage_samples():
    mask = np.array([True, True, False, False])
    np.testing.assert_allclose(
        rmse_per_axis(EST, REF, mask), [math.sqrt(0.5), math.sqrt(2.0), 0.0], atol=1e-15
    )
    assert rmse_3d(EST, REF, mask) == pytest.approx(math.sqrt(5 / 2))
    assert error_at(EST, REF, p=0.9, mask=mask) == pytest.approx(2.0)


def test_empty_selection_gives_nan_without_warnings():
    nothing = np.zeros(4, dtype=bool)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(rmse_per_axis(EST, REF, nothing)).all()
        assert np.isnan(mean_rmse(EST, REF, nothing))
        assert np.isnan(rmse_3d(np.full((3, 3), np.nan), np.zeros((3, 3))))
        assert np.isnan(error_at(EST, REF, mask=nothing))
        x, p = error_cdf(EST, REF, nothing)
    assert x.size == 0 and p.size == 0


def test_error_cdf_closed_form():
    x, p = error_cdf(EST, REF)
    np.testing.assert_allclose(x, [1.0, math.sqrt(3), 2.0, 3.0], atol=1e-15)
    np.testing.assert_allclose(p, [0.25, 0.5, 0.75, 1.0])


@pytest.mark.parametrize(
    ("p", "expected"),
    [(0.25, 1.0), (0.5, math.sqrt(3)), (0.75, 2.0), (0.76, 3.0), (0.9, 3.0), (1.0, 3.0)],
)
def test_error_at_inverts_the_empirical_cdf(p, expected):
    assert error_at(EST, REF, p=p) == pytest.approx(expected, abs=1e-15)


def test_error_at_exact_level_not_pushed_up_by_round_off():
    # 0.9 * 10 = 9.000000000000002 in floating point; the 9th smallest error is the answer
    est = np.zeros((10, 3))
    est[:, 0] = np.arange(1.0, 11.0)
    assert error_at(est, np.zeros((10, 3)), p=0.9) == 9.0


def test_batched_equals_loop(rng):
    est = rng.normal(size=(2, 3, 40, 3))
    ref = rng.normal(size=(2, 3, 40, 3))
    est[0, 1, 5] = np.nan
    mask = rng.random((2, 3, 40)) < 0.6
    for fn in (rmse_per_axis, mean_rmse, rmse_3d):
        out = fn(est, ref, mask)
        for i in range(2):
            for j in range(3):
                np.testing.assert_allclose(
                    out[i, j], fn(est[i, j], ref[i, j], mask[i, j]), rtol=1e-14
                )
    e90 = error_at(est, ref, p=0.9, mask=mask)
    for i in range(2):
        for j in range(3):
            x, prob = error_cdf(est[i, j], ref[i, j], mask[i, j])
            assert e90[i, j] == x[np.searchsorted(prob, 0.9 - 1e-12)]


def test_relative_improvement():
    # paper B right elbow: 0.0866 -> 0.0678 is 21.7 %, not the stated 12.71 % (SPEC §14)
    assert relative_improvement(0.0678, 0.0866) == pytest.approx(0.21709, abs=1e-5)
    assert relative_improvement(2.0, 1.0) == pytest.approx(-1.0)
    assert math.isnan(relative_improvement(1.0, 0.0))
    np.testing.assert_allclose(relative_improvement([1.0, 3.0], [2.0, 4.0]), [0.5, 0.25])


@pytest.mark.parametrize(
    ("est", "ref", "mask", "match"),
    [
        (np.zeros((4, 2)), np.zeros((4, 2)), None, r"shape \(\.\.\., T, 3\)"),
        (np.zeros((4, 3)), np.zeros((5, 3)), None, "same shape"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.ones(4), "boolean"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.ones(3, dtype=bool), "mask with shape"),
        (np.array([["a", "b", "c"]]), np.zeros((1, 3)), None, "numeric"),
    ],
)
def test_bad_input_says_expected_and_got(est, ref, mask, match):
    with pytest.raises(InputError, match=match):
        rmse_per_axis(est, ref, mask)


def test_error_cdf_refuses_batches_and_error_at_checks_p():
    with pytest.raises(InputError, match=r"\(T, 3\)"):
        error_cdf(np.zeros((2, 4, 3)), np.zeros((2, 4, 3)))
    with pytest.raises(InputError, match="p in"):
        error_at(EST, REF, p=0.0)


# ------------------------------------------------------------------------------------------
# evaluate()
# ------------------------------------------------------------------------------------------


def _two_methods():
    T = 4
    ref = np.zeros((T, 2, 3))
    a = np.zeros((T, 2, 3))
    a[:, 0] = EST  # joint 0: the hand-computed errors
    a[:, 1, 2] = 0.5  # joint 1: constant 0.5 m up
    b = a * 2.0
    outage = np.zeros((T, 2), dtype=bool)
    outage[2:, 0] = True
    return {"A": a, "B": b}, ref, outage


def test_evaluate_tables_match_functions():
    est, ref, outage = _two_methods()
    res = evaluate(est, ref, outage, {"A": 0.004, "B": 0.008}, joints=("elbow", "wrist"))
    assert res.methods == ("A", "B") and res.joints == ("elbow", "wrist") and res.n_steps == 4
    np.testing.assert_allclose(res.rmse[0, 0], rmse_per_axis(EST, REF))
    np.testing.assert_allclose(res.rmse[1, 0], 2 * rmse_per_axis(EST, REF))
    np.testing.assert_allclose(res.rmse[0, 1], [0, 0, 0.5])
    assert res.mean_rmse[0, 1] == pytest.approx(0.5 / 3)
    assert res.error_at_p[0, 0] == pytest.approx(3.0)
    # outage: samples 2, 3 of elbow -> errors 3 and sqrt(3)
    np.testing.assert_allclose(
        res.rmse_outage[0, 0], [math.sqrt(0.5), math.sqrt(0.5), math.sqrt(5)]
    )
    assert res.n_samples_outage.tolist() == [[2, 0], [2, 0]]
    assert np.isnan(res.mean_rmse_outage[0, 1])
    assert res.improvement("A", "B", "elbow") == pytest.approx(0.5)
    assert res.time_per_step_ms("B") == pytest.approx(2.0)
    x, p = res.cdf("A", "elbow", outage=True)
    np.testing.assert_allclose(x, [math.sqrt(3), 3.0])
    row = res.row("A", "wrist")
    assert set(row) == {"east", "north", "up", "mean", "rmse_3d", "error_at_p", "n_samples"}


def test_evaluate_in_view_is_the_complement_of_outage():
    est, ref, outage = _two_methods()
    res = evaluate(est, ref, outage, joints=("elbow", "wrist"))
    # in view at the elbow: samples 0, 1 -> errors (1, 0, 0) and (0, 2, 0)
    np.testing.assert_allclose(res.rmse_in_view[0, 0], [math.sqrt(0.5), math.sqrt(2), 0.0])
    assert res.mean_rmse_in_view[0, 0] == pytest.approx((math.sqrt(0.5) + math.sqrt(2)) / 3)
    assert res.rmse_3d_in_view[0, 0] == pytest.approx(math.sqrt(2.5))
    assert res.error_at_p_in_view[0, 0] == pytest.approx(2.0)
    # the wrist is always in view: the in-view figures are the overall ones
    np.testing.assert_allclose(res.rmse_in_view[:, 1], res.rmse[:, 1])
    assert res.n_samples_in_view.tolist() == [[2, 4], [2, 4]]
    # in view and outage partition the samples: the mean squared errors add up
    n, n_o, n_v = res.n_samples, res.n_samples_outage, res.n_samples_in_view
    ms_o = np.nan_to_num(res.rmse_outage**2) * n_o[..., None]
    np.testing.assert_allclose(
        ms_o + res.rmse_in_view**2 * n_v[..., None], res.rmse**2 * n[..., None]
    )
    row = res.row("B", "elbow", in_view=True)
    assert row["mean"] == pytest.approx(2 * res.mean_rmse_in_view[0, 0]) and row["n_samples"] == 2
    x, _ = res.cdf("A", "elbow", in_view=True)
    np.testing.assert_allclose(x, [1.0, 2.0])
    assert res.improvement("A", "B", "elbow", in_view=True) == pytest.approx(0.5)
    with pytest.raises(InputError, match="at most one of outage=True and in_view=True"):
        res.row("A", "elbow", outage=True, in_view=True)
    d = res.to_dict()["results"]["A"]
    assert d["elbow"]["in_view"]["error_at_p"] == pytest.approx(2.0)
    assert d["wrist"]["in_view"]["n_samples"] == 4
    no_mask = evaluate(est, ref, joints=("elbow", "wrist"))
    assert (
        np.isnan(no_mask.mean_rmse_in_view).all()
        and no_mask.to_dict()["results"]["A"]["elbow"]["in_view"] is None
    )


def test_evaluate_to_dict_is_strict_json():
    est, ref, outage = _two_methods()
    d = evaluate(est, ref, outage, joints=("elbow", "wrist")).to_dict()
    text = json.dumps(d, allow_nan=False)  # NaN (no wrist outage) became null
    back = json.loads(text)
    assert back["results"]["A"]["wrist"]["outage"]["mean"] is None
    assert back["results"]["B"]["elbow"]["overall"]["error_at_p"] == pytest.approx(6.0)
    assert back["mean_definition"].startswith("arithmetic mean")


def test_evaluate_joint_stream_reference_excludes_unavailable():
    est, ref, _ = _two_methods()
    avail = np.ones((4, 2), dtype=bool)
    avail[2, 0] = False  # the error-3 sample of the elbow
    js = JointStream(np.arange(4) / 30.0, ref, avail, joints=("elbow", "wrist"))
    res = evaluate(est, js)
    assert res.joints == ("elbow", "wrist")
    assert res.n_samples[0].tolist() == [3, 4] and res.n_excluded[0].tolist() == [1, 0]
    assert res.error_at_p[0, 0] == pytest.approx(2.0)
    assert not res.has_outages and np.isnan(res.rmse_outage).all()


def test_evaluate_validates():
    est, ref, outage = _two_methods()
    with pytest.raises(InputError, match="non-empty mapping"):
        evaluate({}, ref)
    with pytest.raises(InputError, match=r"estimates\['A'\] with shape"):
        evaluate({"A": est["A"][:3]}, ref)
    with pytest.raises(InputError, match="outage_mask"):
        evaluate(est, ref, outage[:, :1])
    with pytest.raises(InputError, match="run_time_s has method 'C'"):
        evaluate(est, ref, run_time_s={"C": 1.0})
    res = evaluate(est, ref)
    with pytest.raises(InputError, match="unknown method 'C'"):
        res.row("C", "joint_0")


# ------------------------------------------------------------------------------------------
# tables
# ------------------------------------------------------------------------------------------


def _result():
    est, ref, outage = _two_methods()
    return evaluate(
        {"KF": est["A"], "FIR": est["B"]},
        ref,
        outage,
        {"KF": 0.001, "FIR": 0.002},
        joints=("elbow", "wrist_r"),
    )


def test_method_table_paper_a_layout_with_paper_rows():
    t = tables.method_table(_result(), "elbow", paper=tables.PAPER_A_RMSE_M["elbow"])
    assert t.label_headers == ("Method",)
    assert t.value_headers == ("East (m)", "North (m)", "Up (m)", "Mean (m)")
    labels = [r.labels[0] for r in t.rows]
    assert labels == ["KF", "KF (paper)", "FIR", "FIR (paper)", "EM-KF/FIR (paper)"]
    assert t.rows[1].paper and t.rows[1].values == (0.178, 0.011, 0.010, 0.066)
    assert t.rows[0].values[3] == pytest.approx(float(mean_rmse(EST, REF)))
    md = tables.to_markdown(t)
    assert "| *KF (paper)* | *0.178* | *0.011* | *0.010* | *0.066* |" in md
    assert f"| KF | {math.sqrt(0.5):.3f} |" in md


def test_method_table_paper_column_and_counts():
    t = tables.method_table(
        _result(), "elbow", paper={"KF": (1, 2, 3, 4)}, paper_mode="column", include_counts=True
    )
    assert t.value_headers[-2:] == ("Mean, paper (m)", "N")
    assert t.rows[0].values[-2:] == (4, "4") and t.rows[1].values[-2:] == (None, "4")
    with pytest.raises(InputError, match="paper_mode"):
        tables.method_table(_result(), "elbow", paper_mode="side")
    with pytest.raises(InputError, match="expected 4 numbers"):
        tables.method_table(_result(), "elbow", paper={"KF": (1, 2)})


def test_joint_method_table_paper_b_layout():
    paper = {"wrist_r": tables.PAPER_B_RMSE_M["wrist_r"]}
    t = tables.joint_method_table(_result(), paper=paper)
    assert t.label_headers == ("Joint", "Method")
    assert t.value_headers == (
        "X",
        "Y",
        "Z",
        "Mean",
        "@CDF 0.9",
        "Mean in view",
        "Mean out",
        "@CDF 0.9 out",
    )
    labels = [r.labels for r in t.rows]
    assert labels[:2] == [("elbow", "KF"), ("elbow", "FIR")]
    assert ("wrist_r", "ELM/KF (paper)") in labels and ("wrist_r", "ELM/FIR (paper)") in labels
    paper_row = next(r for r in t.rows if r.labels == ("wrist_r", "ELM/FIR (paper)"))
    assert paper_row.values == (0.0903, 0.0739, 0.0282, 0.0641, None, None, None, None)
    kf_elbow = next(r for r in t.rows if r.labels == ("elbow", "KF"))
    assert kf_elbow.values[5] == pytest.approx(_result().mean_rmse_in_view[0, 0])
    assert any("in view = only samples outside camera outages" in n for n in t.notes)
    t2 = tables.joint_method_table(_result(), notes=("reference: the camera in view",))
    assert t2.notes[-1] == "reference: the camera in view"
    text = tables.to_text(t)
    assert "0.0641" in text and "–" in text  # wrist has no outage samples
    html = tables.to_html(t)
    assert '<tr class="paper">' in html and 'class="num best"' in html


def test_rich_rendering_and_timing_table():
    res = _result()
    console = Console(record=True, width=160)
    console.print(tables.to_rich(tables.joint_method_table(res)))
    console.print(tables.to_rich(tables.timing_table(res, paper=tables.PAPER_A_TIME_PER_STEP_MS)))
    out = console.export_text()
    assert "RMSE per joint and method" in out and "@CDF 0.9" in out
    assert "0.237" in out  # the paper's FIR time per step
    assert f"{res.mean_rmse[0, 0]:.4f}" in out


def test_rich_rendering_prints_bracketed_labels_as_written():
    """Labels are text, not rich markup: "[calibrated on reference]" tags must print (rich
    took them for style tags and printed nothing of them)."""
    row = tables.TableRow(("wrist_r", "IMU only [calibrated on reference]"), (0.1, 0.2))
    t = tables.ResultTable(
        title="t [x]", label_headers=("Joint", "Method"), value_headers=("X", "[m]"),
        rows=(row,), notes=("scores [aligned to reference]",),
    )  # fmt: skip
    console = Console(record=True, width=160)
    console.print(tables.to_rich(t))
    out = console.export_text()
    for s in ("IMU only [calibrated on reference]", "t [x]", "[m]", "[aligned to reference]"):
        assert s in out, s


def test_public_reexports():
    import kinefuse.evaluation as ev

    for name in ev.__all__:
        assert hasattr(ev, name)
    assert ev.evaluate is metrics.evaluate


def test_table_cells_never_show_minus_zero():
    """A value that rounds to zero prints unsigned (a range table read "-0.0" for an angle that
    stayed at zero); other values keep their sign and rounding."""
    t = tables.ResultTable("t", ("a",), ("b",), (), digits=1)
    assert [t.cell(v) for v in (-0.0, -0.04, 0.04, -0.06, -1.25, 2)] == [
        "0.0", "0.0", "0.0", "-0.1", "-1.2", "2.0",
    ]  # fmt: skip
    assert t.cell(float("nan")) == "–" and t.cell(None) == "–" and t.cell("n/a") == "n/a"


def test_a_diverged_estimate_scores_an_infinite_error_not_a_missing_sample():
    """±inf in an estimate was left out like NaN: 47 % inf scored as well as a good estimate.
    NaN is missing; inf is a sample whose error is infinite. A reference with inf is refused."""
    from kinefuse.evaluation.metrics import error_at, evaluate, rmse_3d

    ref = np.zeros((100, 3))
    est = ref + 0.01
    est[:47] = np.inf
    assert rmse_3d(est, ref) == np.inf and error_at(est, ref, p=0.9) == np.inf
    ev = evaluate({"a": est[:, None]}, ref[:, None])
    assert ev.rmse_3d[0, 0] == np.inf and ev.n_samples[0, 0] == 100
    missing = ref + 0.01
    missing[:47] = np.nan  # missing samples are left out
    assert rmse_3d(missing, ref) == pytest.approx(0.01 * np.sqrt(3))
    bad_ref = ref.copy()
    bad_ref[3] = np.inf
    with pytest.raises(InputError, match=r"expected ref finite or NaN \(missing\), got ±inf"):
        rmse_3d(est, bad_ref)
