"""Specialised fast paths equal the general kernels bit for bit (EM-KF, integrated filter, UFIR).

The EM-KF and the integrated filter kernels have a constant-velocity form (``CVStructure``,
selected when ``F`` is per-axis block-diagonal and ``H`` selects positions) next to the general
sparse-triplet form (``SparseStructure``); the UFIR evaluates horizons with missing samples with shared per-axis gains when the
axes have identical blocks. Each fast path is written to perform the same floating-point
operations in the same order, so results must be identical, not merely close.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from kinefuse.filters._kernels_common import cv_structure, sparse_structure
from kinefuse.filters._kernels_ufir import ufir_horizon_axes, ufir_horizon_axis
from kinefuse.filters.em_kalman import EMKalmanFilter
from kinefuse.filters.integrated import IntegratedFilter
from kinefuse.filters.ufir import UFIRFilter, ufir_model_arrays
from kinefuse.models import LinearGaussianModel, constant_velocity

# compiles general-route kernels that `kinefuse warm-up` does not: one worker (tests/conftest.py)
pytestmark = pytest.mark.xdist_group("oracle-kernels")

DT = 1.0 / 30.0


def data(seed=0, B=3, T=400, missing=0.05):
    rng = np.random.default_rng(seed)
    vel = np.cumsum(rng.normal(scale=0.05, size=(B, T, 3)), axis=1) * DT
    z = np.cumsum(vel, axis=1) + rng.normal(scale=0.01, size=(B, T, 3))
    z[:, rng.random(T) < missing] = np.nan
    z[0, 10, 1] = np.nan  # a partially missing row
    if B >= 3:
        z[1, :4] = np.nan
        z[2, 50:80] = np.nan
    return z


def general(filt):
    """The same filter forced onto the general (sparse-structure) kernel."""
    a = filt._arrays
    a["em"] = a["em"]._replace(struct=sparse_structure(a["F"], a["H"]))
    return filt


def assert_same(a, b):
    for name in ("mean", "cov", "position", "observed", "innovation", "distance"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("R_em", "distance2", "mode"):
        if getattr(a, name, None) is not None:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


MODELS = {
    "paper": constant_velocity(DT, q=1.0, r=1e-2),
    "wrist": constant_velocity(DT, q=0.1, r=0.1),
    "matched": constant_velocity(DT, q=0.5, r=1e-4),
    "full_R": constant_velocity(
        DT, q=1.0, r=np.array([[2e-4, 5e-5, 0], [5e-5, 1e-4, 0], [0, 0, 3e-4]])
    ),
}


def test_cv_structure_detection():
    assert cv_structure(MODELS["paper"].F, MODELS["paper"].H).shape == (3, 4)
    m = MODELS["paper"]
    assert cv_structure(m.F, 2.0 * m.H) is None
    F = m.F.copy()
    F[0, 2] = 0.1
    assert cv_structure(F, m.H) is None


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize(
    "kw", [{"n_iter": 1}, {"n_iter": 3}, {"n_iter": 10}, {"n_iter": 5, "regularized": True}]
)
def test_em_kf_cv_kernel_is_the_general_kernel(name, kw):
    m = MODELS[name]
    z = data(seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sa, ra = EMKalmanFilter(m, **kw).filter(z)
        sb, rb = general(EMKalmanFilter(m, **kw)).filter(z)
    assert_same(ra, rb)
    for f in ("x", "P", "initialized", "u", "U"):
        np.testing.assert_array_equal(getattr(sa, f), getattr(sb, f))


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"threshold1": 0.0, "threshold2": 0.0},
        {"threshold1": 0.0, "threshold2": 0.0, "fir_feedback": False},
        {"threshold1": 0.5, "threshold2": 2.0, "horizon": 10},
        {"gate": "S", "threshold1": 7.81},
        {"threshold1": 0.0, "n_em_iter": 10},
    ],
)
def test_integrated_cv_kernel_is_the_general_kernel(name, kw):
    m = MODELS[name]
    z = data(seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fa = IntegratedFilter(m, **kw)
        fb = general(IntegratedFilter(m, **kw))
        sa, ra = fa.filter(z)
        sb, rb = fb.filter(z)
        assert_same(ra, rb)
        np.testing.assert_array_equal(sa.x, sb.x)
        np.testing.assert_array_equal(sa.P, sb.P)
        np.testing.assert_array_equal(sa.z_buf, sb.z_buf)
        # resume from a state (ring and covariance carried over)
        sa2, ra2 = fa.filter(z[:, :50], sa)
        sb2, rb2 = fb.filter(z[:, :50], sb)
        assert_same(ra2, rb2)


@pytest.mark.parametrize("name", ["paper", "wrist"])
def test_ufir_shared_axis_gains_equal_per_axis(name):
    m = MODELS[name]
    a = ufir_model_arrays(m, 20)
    z = data(seed=3, B=1, T=200, missing=0.15)[0]
    N, K = 20, a["K"]
    zr = np.full((N, 3), np.nan)
    idx = np.empty(K, np.int64)
    xx = np.empty((2, 3))
    n_checked = 0
    for k in range(200):
        row = z[k] if np.all(np.isfinite(z[k])) else np.full(3, np.nan)
        zr[k % N] = row
        if k < N - 1:
            continue
        x1, P1 = np.empty(6), np.empty((6, 6))
        code = ufir_horizon_axes(
            zr, k, N, K, a["Fa"], a["Finva"], a["Ha"], a["Qa"], a["Ra"], idx, xx, x1, P1
        )
        ok_all, x2, P2 = True, np.zeros(6), np.zeros((6, 6))
        for ax in range(3):
            ok, x0, v0, p00, p01, p11 = ufir_horizon_axis(
                zr, ax, k, N, K, a["Fa"], a["Finva"], a["Ha"], a["Qa"], a["Ra"],
                np.empty((0, 6)), np.empty((0, 6, 6)), False, idx,
            )  # fmt: skip
            ok_all &= ok
            s = slice(2 * ax, 2 * ax + 2)
            x2[s] = x0, v0
            P2[s, s] = [[p00, p01], [p01, p11]]
        assert code == (1 if ok_all else 2)
        if ok_all:
            np.testing.assert_array_equal(x1, x2)
            np.testing.assert_array_equal(P1, P2)
            n_checked += 1
    assert n_checked > 50


def test_ufir_shared_gains_not_used_for_different_axes():
    base = MODELS["paper"]
    R = np.diag([1e-2, 2e-2, 1e-2])
    m = LinearGaussianModel(F=base.F, H=base.H, Q=base.Q, R=R, dt_s=DT)
    a = ufir_model_arrays(m, 20)
    zr = np.random.default_rng(0).normal(size=(20, 3))
    zr[5] = np.nan
    idx = np.empty(a["K"], np.int64)
    code = ufir_horizon_axes(
        zr,
        19,
        20,
        a["K"],
        a["Fa"],
        a["Finva"],
        a["Ha"],
        a["Qa"],
        a["Ra"],
        idx,
        np.empty((2, 3)),
        np.empty(6),
        np.empty((6, 6)),
    )
    assert code == 0
    zr2 = zr.copy()
    zr2[7, 1] = np.nan  # missing patterns differ between axes (identical blocks)
    b = ufir_model_arrays(base, 20)
    x_out, P_out = np.empty(6), np.empty((6, 6))
    blocks = (b["Fa"], b["Finva"], b["Ha"], b["Qa"], b["Ra"])
    code = ufir_horizon_axes(zr2, 19, 20, b["K"], *blocks, idx, np.empty((2, 3)), x_out, P_out)
    assert code == 0
    # such a model takes the per-axis form; its output is finite
    s, r = UFIRFilter(m, horizon=20).filter(data(seed=4))
    assert np.all(np.isfinite(r.mean[:, 25:][r.observed[:, 25:]]))
