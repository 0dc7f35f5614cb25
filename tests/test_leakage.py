"""Outage-blind protocols (issue 11, point 3): samples an evaluation hides reach nothing.

For every protocol (experiment paper-a and paper-b on CMU / UTD-MHAD / Neura, ``kinefuse
evaluate``'s core, the fusion study) the camera samples inside the outages are moved by 10 cm
and every estimate must stay bit-identical: no calibration, alignment, length, noise fit or
learned correction may read them, so nothing else can change either (in view or in outages).
Each test also checks that the perturbation really changed the hidden inputs.
"""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kinefuse.apps import paper_a, paper_b, splits

SHIFT_M = 0.10


def _shift_hidden(stream, hidden=None):
    """The stream with the positions behind ``~available`` (or ``hidden``) moved by 10 cm."""
    hidden = ~stream.available if hidden is None else hidden
    p = stream.position_m.copy()
    base = np.where(np.isfinite(p), p, 0.0)
    p[hidden] = base[hidden] + SHIFT_M
    assert np.any(hidden), "nothing hidden: the test would be vacuous"
    return replace(stream, position_m=p)


def _assert_same(a: dict, b: dict):
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture(scope="module")
def packaged_motion():
    from kinefuse.data import demo_motion

    return demo_motion()


def test_paper_a_cmu_chain_ignores_hidden_camera(packaged_motion):
    rec = paper_a.arm_recording(packaged_motion, 5)
    _, z1, _ = paper_a.arm_chain(rec)
    _, z2, _ = paper_a.arm_chain(replace(rec, vision=_shift_hidden(rec.vision)))
    _assert_same(z1, z2)  # paper A's filters read nothing else


def test_paper_b_cmu_ignores_hidden_camera(packaged_motion):
    rec = paper_b.cmu_recording(packaged_motion, 0)
    a = paper_b.cmu_scenario(rec, "02_08")
    b = paper_b.cmu_scenario(replace(rec, vision=_shift_hidden(rec.vision)), "02_08")
    assert {"offset interp", "kinefuse causal"} <= set(a["estimates"])
    _assert_same(a["estimates"], b["estimates"])


def _utd_pair(shared_data):
    root = Path(shared_data) / "utd_mhad"
    return root / "Inertial" / "a1_s1_t1_inertial.mat", root / "Skeleton" / "a1_s1_t1_skeleton.mat"


def test_paper_b_utd_calibration_is_blind_to_the_hidden_wrist(shared_data):
    from kinefuse.pipelines.labels import paper_b_methods

    rec = splits.utd_recording(*_utd_pair(shared_data))
    v = rec.vision
    hide = np.zeros(v.available.shape, dtype=bool)
    hide[splits.utd_hidden(v.t_s, v.t_s), v.index("wrist_r")] = True
    rec2 = replace(rec, vision=_shift_hidden(v, hide))
    methods = paper_b_methods()
    a = paper_b.utd_scenario(rec, "a1_s1_t1", methods)
    b = paper_b.utd_scenario(rec2, "a1_s1_t1", methods)
    _assert_same(a["estimates"], b["estimates"])
    # the reference keeps the (moved) wrist: the perturbation reached the evaluation only
    assert not np.allclose(a["reference"][a["outage"]], b["reference"][b["outage"]])
    # sensitivity: a whole-trial calibration (the old protocol) does move the chain
    _, c1, *_ = splits.utd_wrist_chain(rec, None)
    _, c2, *_ = splits.utd_wrist_chain(rec2, None)
    assert not np.allclose(c1, c2)


def test_paper_b_neura_ignores_hidden_camera(shared_data):
    from kinefuse.pipelines.labels import paper_b_methods

    rec, joints = paper_b.neura_inputs(Path(shared_data))
    methods = paper_b_methods()
    a = paper_b.neura_scenario(rec, joints, methods)
    b = paper_b.neura_scenario(replace(rec, vision=_shift_hidden(rec.vision)), joints, methods)
    _assert_same(a["estimates"], b["estimates"])


def test_evaluate_core_ignores_hidden_camera(packaged_motion):
    from kinefuse.pipelines.run import process_recording

    rec = paper_b.cmu_recording(packaged_motion, 1)
    a = process_recording(rec, "kinefuse", {})
    b = process_recording(replace(rec, vision=_shift_hidden(rec.vision)), "kinefuse", {})
    np.testing.assert_array_equal(a.position, b.position)
    assert set(a.baselines) == {"offset interp", "offset hold", "camera gap-fill"}
    _assert_same(a.baselines, b.baselines)


def _fusion_study():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "fusion_study.py"
    spec = importlib.util.spec_from_file_location("fusion_study", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_fusion_study_utd_ignores_hidden_wrist(shared_data):
    from kinefuse.io.utd_mhad import read_utd_mhad
    from kinefuse.pipelines.kinefuse_fusion import kinefuse_fusion

    fs = _fusion_study()
    path = _utd_pair(shared_data)[0]
    a = fs.utd_inputs(read_utd_mhad(path), 1, 1)
    rec = read_utd_mhad(path)
    v = rec.vision
    hide = np.zeros(v.available.shape, dtype=bool)
    hide[~a["available"][:, 0], v.index("wrist_r")] = True
    b = fs.utd_inputs(replace(rec, vision=_shift_hidden(v, hide)), 1, 1)
    for k in ("z_imu", "features", "available"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    for causal in (False, True):
        pa, pb = (
            kinefuse_fusion(
                tr["z_imu"],
                tr["z_cam"],
                tr["available"],
                tr["dt"],
                causal=causal,
                features=tr["features"],
            ).position
            for tr in (a, b)
        )
        np.testing.assert_array_equal(pa, pb)


def test_fusion_study_cmu_calibrates_before_any_outage():
    fs = _fusion_study()
    rng = np.random.default_rng(0)
    dt = 1 / 30
    av = fs.renewal_outages(3000, 8, dt, rng)
    t = np.arange(3000) * dt
    assert np.all(av[t < fs.CAL_S])  # the calibration window (first CAL_S s) is outage-free
    assert not np.all(av)
