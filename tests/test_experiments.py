"""`kinefuse experiment paper-a|paper-b` back-end on reduced (quick) configurations."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from kinefuse import cli
from kinefuse.apps.experiments import PAPER_A_TESTS, run_experiment
from kinefuse.exceptions import InputError

runner = CliRunner()


def test_paper_a_quick_packaged_clip(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no ../shared/data here: packaged clip only
    out = run_experiment("paper-a", quick=True, quiet=True)
    assert out["data_dir"] is None and out["quick"]
    res = out["results"]["CMU (virtual IMUs)"]
    assert set(res) == set(PAPER_A_TESTS)
    for test, v in res.items():
        assert set(v["rmse_m"]) == {"KF", "FIR", "EM-KF/FIR", "IMU chain"}, test
        for m in v["rmse_m"].values():
            assert 0.0 < m["mean"] < 0.5
        assert abs(sum(v["branch_fractions"].values()) - 1.0) < 1e-9
    timing = out["results"]["time_per_step_ms"]
    for label in ("KF", "FIR", "EM-KF/FIR"):
        # no timing assert (speed lives in benchmarks/ and `kinefuse bench`): a positive
        # measured time per step, whatever the machine
        assert np.isfinite(timing[label]["elbow"]["batch_ms"])
        assert timing[label]["elbow"]["batch_ms"] > 0
    titles = [t.title for t in out["tables"]]
    assert any("Table 4" in t for t in titles) and any("Table 6" in t for t in titles)


def test_paper_a_quick_with_utd(shared_data):
    out = run_experiment("paper-a", shared_data, quick=True, quiet=True)
    utd = out["results"]["UTD-MHAD (real wrist IMU)"]
    assert set(utd) == {"wrist, test 1", "wrist, test 2"}
    assert utd["wrist, test 1"]["n_samples"] > 100


def test_paper_b_quick(shared_data):
    out = run_experiment("paper-b", shared_data, quick=True, quiet=True)
    res = out["results"]
    assert {"CMU (virtual)", "UTD-MHAD (real IMU)", "Neura walk (real IMUs)"} <= set(res)
    ev = res["CMU (virtual)"]["evaluation"]
    assert len(ev["joints"]) == 8 and {"ELM/FIR", "ELM/KF"} <= set(ev["methods"])
    for d in res.values():
        r = d["evaluation"]["results"]
        for m in ("ELM/FIR", "ELM/KF"):
            for joint in d["evaluation"]["joints"]:
                mean = r[m][joint]["overall"]["mean"]
                assert mean is not None and 0 < mean < 0.5
                assert r[m][joint]["outage"]["n_samples"] > 0
    assert "wrist_r" in res["CMU (virtual)"]["cdf_0.9"]


def test_experiment_through_cli_json(shared_data, tmp_path, monkeypatch):
    monkeypatch.setenv("KINEFUSE_EXPERIMENT_QUICK", "1")
    target = tmp_path / "b.json"
    res = runner.invoke(
        cli.app, ["experiment", "paper-a", "--data", str(shared_data), "--json", str(target)]
    )
    assert res.exit_code == 0, res.output
    assert "Table 6" in res.output and "EM-KF/FIR" in res.output
    data = json.loads(target.read_text())
    assert data["quick"] is True
    v = data["results"]["CMU (virtual IMUs)"]["elbow, test 1"]["rmse_m"]["KF"]["mean"]
    assert np.isfinite(v)


def test_unknown_experiment_and_missing_folder(tmp_path):
    with pytest.raises(InputError, match="unknown experiment"):
        run_experiment("paper-c")
    with pytest.raises(InputError, match="not found"):
        run_experiment("paper-a", tmp_path / "nope")
    with pytest.raises(InputError, match="unknown set"):
        run_experiment("paper-b", split="everything")
    res = runner.invoke(cli.app, ["experiment", "paper-b", "--set", "everything"])
    assert res.exit_code != 0 and "--set" in res.output


def test_paper_b_quick_tuning_set_tables_name_the_set_and_baselines(shared_data):
    from kinefuse.apps.experiments import REPORT_SET, TUNING_SET

    assert not set(TUNING_SET.utd_subjects) & set(REPORT_SET.utd_subjects)
    assert not {t[:2] for t in TUNING_SET.cmu_trials} & {t[:2] for t in REPORT_SET.cmu_trials}
    out = run_experiment("paper-b", shared_data, quick=True, quiet=True, split="tuning")
    # --quick runs the packaged clip and two UTD-MHAD trials: no table claims the tuning set
    assert out["split"] == "quick"
    assert all("quick set" in t.title and "tuning set" not in t.title for t in out["tables"])
    assert any("quick set (not the tuning set): CMU 02_08 (the packaged clip" in n
               for n in out["notes"])  # fmt: skip
    assert "Neura walk (real IMUs)" not in out["results"]  # evaluation-only: report set
    ev = out["results"]["UTD-MHAD (real IMU)"]["evaluation"]
    assert {"offset interp", "offset hold", "camera gap-fill", "kinefuse causal"} <= set(
        ev["methods"]
    )
    t = out["targets"]["UTD-MHAD (real IMU)"]
    assert t["offline_vs_offset_interp_pct"] is not None
    # the oracle bound (chain + the best linear offset per outage, from the hidden reference)
    # can only be at or below offset interp, which is of that form
    assert t["oracle_linear_offset_vs_offset_interp_pct"] <= 0.0
    # the constant bound is of offset hold's form: at or below offset hold
    assert t["oracle_constant_offset_vs_offset_interp_pct"] is not None


def test_oracle_linear_offset_closed_form():
    """Reference - offset interp = a line per outage + known noise: the bound is the noise's
    RMS (exactly the line's residual); with no noise it is 0; samples outside outages and
    non-finite ones do not count."""
    from kinefuse.apps.paper_b_tables import oracle_linear_offset

    rng = np.random.default_rng(3)
    T = 400
    out = np.zeros((T, 2), bool)
    out[50:120, 0] = out[200:260, 1] = out[300:380, 0] = True
    base = rng.normal(size=(T, 2, 3))
    line = np.zeros((T, 2, 3))
    for j, (a, b) in ((0, (50, 120)), (1, (200, 260)), (0, (300, 380))):
        k = np.arange(b - a)[:, None]
        line[a:b, j] = rng.normal(size=3) + rng.normal(size=3) * k
    part = {"estimates": {"offset interp": base}, "reference": base + line, "outage": out}
    assert oracle_linear_offset([part]) == pytest.approx(0.0, abs=1e-9)
    noise = rng.normal(scale=0.01, size=(T, 2, 3))
    noise[~out] = 5.0  # outside the outages: not counted
    part["reference"] = base + line + noise
    part["estimates"]["offset interp"][60, 0] = np.nan  # a missing sample: left out
    sel = out.copy()
    sel[60, 0] = False
    expect = []
    for j, (a, b) in ((0, (50, 120)), (1, (200, 260)), (0, (300, 380))):
        k = np.arange(a, b)
        keep = sel[a:b, j]
        A = np.stack([np.ones(keep.sum()), k[keep]], 1)
        r = noise[a:b, j][keep]
        expect.append(r - A @ np.linalg.lstsq(A, r, rcond=None)[0])
    rms = np.sqrt(np.mean(np.sum(np.concatenate(expect) ** 2, -1)))
    assert oracle_linear_offset([part]) == pytest.approx(rms, rel=1e-9)
    assert oracle_linear_offset([{**part, "outage": np.zeros((T, 2), bool)}]) is None


def test_oracle_constant_offset_closed_form():
    """Reference - offset hold = a constant per outage + known noise: the bound is the RMS of
    the noise less its mean per outage; a line per outage is not absorbed (only its mean)."""
    from kinefuse.apps.paper_b_tables import oracle_constant_offset

    rng = np.random.default_rng(4)
    T = 300
    out = np.zeros((T, 2), bool)
    spans = ((0, (20, 90)), (1, (120, 200)), (0, (230, 290)))
    for j, (a, b) in spans:
        out[a:b, j] = True
    base = rng.normal(size=(T, 2, 3))
    const = np.zeros((T, 2, 3))
    for j, (a, b) in spans:
        const[a:b, j] = rng.normal(size=3)
    part = {"estimates": {"offset hold": base}, "reference": base + const, "outage": out}
    assert oracle_constant_offset([part]) == pytest.approx(0.0, abs=1e-9)
    noise = rng.normal(scale=0.01, size=(T, 2, 3))
    noise[~out] = 5.0  # outside the outages: not counted
    part["reference"] = base + const + noise
    expect = [noise[a:b, j] - noise[a:b, j].mean(0) for j, (a, b) in spans]
    rms = np.sqrt(np.mean(np.sum(np.concatenate(expect) ** 2, -1)))
    assert oracle_constant_offset([part]) == pytest.approx(rms, rel=1e-9)
    # a slope inside each outage: the best constant leaves the line minus its mean
    k = np.arange(T, dtype=float)[:, None, None] * np.array([0.01, -0.02, 0.005])
    part["reference"] = base + const + k * out[..., None]
    expect = [k[a:b, 0] - k[a:b, 0].mean(0) for j, (a, b) in spans]
    rms = np.sqrt(np.mean(np.sum(np.concatenate(expect) ** 2, -1)))
    assert oracle_constant_offset([part]) == pytest.approx(rms, rel=1e-9)


def test_an_experiment_on_a_data_folder_without_its_data_is_refused_or_labelled(tmp_path):
    """A full run on a --data folder with none of the data sets is an error (it ran the
    packaged clip and called it the report set); the default without shared data runs the
    clip under its own name."""
    from kinefuse.apps.splits import REPORT_SET, as_run

    with pytest.raises(InputError, match="holds neither cmu_mocap/ nor utd_mhad/"):
        run_experiment("paper-a", tmp_path, quiet=True)
    ran = as_run(REPORT_SET, None, quick=False)
    assert ran.name == "reduced" and ran.cmu_trials == ("02_08",) and ran.utd_subjects == ()
    assert ran.describe().startswith("reduced set (not the report set): CMU 02_08")
    assert as_run(REPORT_SET, tmp_path, quick=True).name == "quick"
