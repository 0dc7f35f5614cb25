"""EM-KF/FIR integrated filter (paper A §3.4, SPEC §7): gate limits, branch trace, per-element branching."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from kinefuse.conventions import MODE_EM, MODE_FIR, MODE_KF, MODE_PREDICT
from kinefuse.exceptions import NumericalWarning
from kinefuse.filters._base import initial_covariance
from kinefuse.filters.em_kalman import EMKalmanFilter
from kinefuse.filters.integrated import IntegratedFilter, IntegratedState
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.models import constant_velocity

DT = 1.0 / 30.0
N = 20


@pytest.fixture
def model():
    return constant_velocity(DT, q=1.0, r=1e-2)


def track(rng, batch, T, sigma=0.02):
    tt = np.arange(T) * DT
    f = rng.uniform(0.1, 0.5, size=(*batch, 1, 3))
    ph = rng.uniform(0, 2 * np.pi, size=(*batch, 1, 3))
    truth = 0.2 * np.sin(2 * np.pi * f * tt[:, None] + ph)
    return truth + sigma * rng.normal(size=truth.shape)


def kf_reference(model, z):
    """Independent NumPy KF (SPEC §4.2), also returning the NIS νᵀS⁻¹ν."""
    F, H, Q, R = model.F, model.H, model.Q, model.R
    x = P = None
    means, nis = [], []
    for zt in z:
        valid = bool(np.all(np.isfinite(zt)))
        if x is None:
            x, P = np.linalg.pinv(H) @ zt, initial_covariance(model)
            means.append(x)
            nis.append(np.nan)
            continue
        x, P = F @ x, F @ P @ F.T + Q
        if valid:
            S = H @ P @ H.T + R
            nu = zt - H @ x
            nis.append(nu @ np.linalg.solve(S, nu))
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ nu
            A = np.eye(6) - K @ H
            P = A @ P @ A.T + K @ R @ K.T
        else:
            nis.append(np.nan)
        means.append(x)
    return np.array(means), np.array(nis)


def test_open_gate_is_the_kalman_filter(model, rng):
    z = track(rng, (), 150)
    z[[40, 90]] = np.nan
    _, r = IntegratedFilter(model, horizon=N, threshold1=math.inf).filter(z)
    m_ref, _ = kf_reference(model, z)
    np.testing.assert_allclose(r.mean, m_ref, rtol=0, atol=1e-12)
    obs = np.all(np.isfinite(z), axis=1)
    assert np.all(r.mode[obs] == MODE_KF) and np.all(r.mode[~obs] == MODE_PREDICT)
    assert np.all(np.isnan(r.distance2))
    # D₁ = νᵀ R⁻¹ ν (Eq. 29) with ν = z − H x⁻
    k = 10
    np.testing.assert_allclose(r.distance[k], r.innovation[k] @ r.innovation[k] / 1e-2, rtol=1e-12)


def test_gate_s_is_the_nis(model, rng):
    z = track(rng, (), 80)
    _, r = IntegratedFilter(model, horizon=N, threshold1=math.inf, gate="S").filter(z)
    m_ref, nis = kf_reference(model, z)
    np.testing.assert_allclose(r.mean, m_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.distance[1:], nis[1:], rtol=1e-10)
    # R matched to the noise: D₁ with R exceeds 2 on most steps, the NIS (S ⪰ R) much less often
    matched = constant_velocity(DT, q=1.0, r=4e-4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        _, rR = IntegratedFilter(matched, horizon=N, threshold1=2.0).filter(z)
        _, rS = IntegratedFilter(matched, horizon=N, threshold1=2.0, gate="S").filter(z)
    assert np.sum(rS.mode == MODE_KF) > np.sum(rR.mode == MODE_KF) + 10


def test_closed_gates_are_the_ufir_after_dead_zone(model, rng):
    z = track(rng, (2,), 90)
    z[1, 50] = np.nan
    f = IntegratedFilter(model, horizon=N, threshold1=0.0, threshold2=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        _, r = f.filter(z)
        _, r_em = EMKalmanFilter(model, n_iter=3).filter(z)
    _, r_fir = UFIRFilter(model, horizon=N).filter(z)
    obs = np.all(np.isfinite(z), axis=-1)
    after = np.zeros(z.shape[:2], bool)
    after[:, N - 1 :] = True
    np.testing.assert_allclose(r.mean[after & obs], r_fir.mean[after & obs], rtol=0, atol=1e-13)
    np.testing.assert_allclose(r.cov[after & obs], r_fir.cov[after & obs], rtol=1e-13, atol=1e-16)
    assert np.all(r.mode[after & obs] == MODE_FIR)
    assert np.all(r.mode[:, 0] == MODE_KF)  # initialisation row
    assert np.all(r.mode[:, 1 : N - 1] == MODE_EM)  # FIR not selectable in the dead zone
    np.testing.assert_allclose(r.mean[:, : N - 1], r_em.mean[:, : N - 1], rtol=0, atol=1e-13)
    assert r.mode[1, 50] == MODE_PREDICT and not r.observed[1, 50]
    assert np.all(np.isfinite(r.distance2[:, 1:][obs[:, 1:]]))


def test_no_feedback_keeps_em_state(model, rng):
    z = track(rng, (), 70)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        s, r = IntegratedFilter(
            model, horizon=N, threshold1=0.0, threshold2=0.0, fir_feedback=False
        ).filter(z)
        s_em, _ = EMKalmanFilter(model, n_iter=3).filter(z)
    _, r_fir = UFIRFilter(model, horizon=N).filter(z)
    np.testing.assert_allclose(r.mean[N - 1 :], r_fir.mean[N - 1 :], rtol=0, atol=1e-13)
    np.testing.assert_allclose(s.x, s_em.x, rtol=0, atol=1e-13)  # internal recursion = EM-KF
    s_fb, _ = IntegratedFilter(model, horizon=N, threshold1=0.0, threshold2=0.0).filter(z)
    np.testing.assert_allclose(s_fb.x, r_fir.mean[-1], atol=1e-13)


def test_nan_rows_predict_only(model, rng):
    z = track(rng, (), 40)
    z[[0, 1, 15, 16]] = np.nan
    _, r = IntegratedFilter(model, horizon=N).filter(z)
    assert list(r.mode[[0, 1, 15, 16]]) == [MODE_PREDICT] * 4
    assert np.all(np.isnan(r.mean[:2]))
    F = model.F
    np.testing.assert_allclose(r.mean[15], F @ r.mean[14], rtol=0, atol=1e-15)
    np.testing.assert_allclose(r.mean[16], F @ r.mean[15], rtol=0, atol=1e-15)
    assert np.all(np.isnan(r.distance[[15, 16]]))


def test_per_element_branching(model, rng):
    # element 0: quiet data -> KF; element 1: jumps every 3 samples -> EM and FIR branches
    z = track(rng, (2,), 120, sigma=0.005)
    z[1, N::3] += 0.3
    f = IntegratedFilter(model, horizon=N)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        _, r = f.filter(z)
        singles = [f.filter(z[i])[1] for i in range(2)]
    assert np.mean(r.mode[0] == MODE_KF) > 0.9 and not np.any(r.mode[0] == MODE_FIR)
    assert np.mean(r.mode[1] == MODE_FIR) > 0.5
    for i in range(2):
        np.testing.assert_allclose(r.mean[i], singles[i].mean, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(r.mode[i], singles[i].mode)
    assert r.mode.dtype == np.int8 and r.distance2.shape == (2, 120)


def test_stream_batch_split_equal(model, rng):
    z = track(rng, (2,), 70)
    z[1, N::4] += 0.2
    z[0, 33] = np.nan
    f = IntegratedFilter(model, horizon=N)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        s_all, r_all = f.filter(z)
        s1, r1 = f.filter(z[:, :37])
        s2, r2 = f.filter(z[:, 37:], s1)
        state = f.init((2,))
        outs = []
        for t in range(70):
            state, out = f.step(state, z[:, t])
            outs.append(out)
    np.testing.assert_allclose(
        np.concatenate([r1.mean, r2.mean], 1), r_all.mean, rtol=0, atol=1e-14
    )
    np.testing.assert_array_equal(np.concatenate([r1.mode, r2.mode], 1), r_all.mode)
    np.testing.assert_allclose(np.stack([o.mean for o in outs], 1), r_all.mean, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(np.stack([o.mode for o in outs], 1), r_all.mode)
    assert outs[0].mode.shape == (2,) and outs[0].cov.shape == (2, 6, 6)
    assert isinstance(state, IntegratedState) and state.k == 70
    np.testing.assert_array_equal(state.z_buf, s_all.z_buf)
    assert set(np.unique(r_all.mode)) >= {MODE_KF, MODE_FIR}


def test_batched_equals_loop(model, rng):
    z = track(rng, (2, 2), 60)
    z[0, 1, N::3] += 0.3
    f = IntegratedFilter(model, horizon=N, threshold1=3.0, threshold2=1.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        _, r = f.filter(z)
        for i in range(2):
            for j in range(2):
                _, rij = f.filter(z[i, j])
                np.testing.assert_allclose(r.mean[i, j], rij.mean, rtol=0, atol=1e-15)
                np.testing.assert_array_equal(r.mode[i, j], rij.mode)


def test_covariance_psd_long_run():
    rng = np.random.default_rng(13)
    # q small, R matched: all four branches occur
    f = IntegratedFilter(constant_velocity(DT, q=0.01, r=4e-4), horizon=N)
    state = f.init((2,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        for _ in range(3):  # 3 x 2 x 40,000 joint-steps, all branches exercised
            z = track(rng, (2,), 40_000)
            z[:, ::50] += 0.2
            z[rng.random(z.shape[:-1]) < 0.02] = np.nan
            state, r = f.filter(z, state)
            C = r.cov[:, ::5]
            np.testing.assert_array_equal(C, np.swapaxes(C, -1, -2))
            assert np.linalg.eigvalsh(C).min() > -1e-15
            assert np.all(np.isfinite(r.mean))
    assert set(np.unique(r.mode)) == {MODE_KF, MODE_EM, MODE_FIR, MODE_PREDICT}


# --- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        ({"threshold1": -1.0}, r"threshold1 >= 0.0, got -1.0"),
        ({"threshold2": -0.5}, r"threshold2 >= 0.0, got -0.5"),
        ({"threshold1": math.nan}, "threshold1 finite"),
        ({"threshold2": "2"}, "threshold2 as a number"),
        ({"gate": "Q"}, r"expected gate one of \('R', 'S'\), got 'Q'"),
        ({"gate": None}, "expected gate one of"),
        ({"n_em_iter": 0}, r"n_em_iter >= 1, got 0"),
        ({"n_em_iter": 2.5}, "n_em_iter as an integer"),
        ({"horizon": 5}, r"horizon >= state dimension \+ 1 = 7"),
        ({"horizon": 20.0}, "horizon as an integer"),
        ({"fir_feedback": 1}, "fir_feedback as True or False"),
    ],
)
def test_bad_parameters(model, kw, msg):
    with pytest.raises(ValueError, match=msg):
        IntegratedFilter(model, **kw)


def test_bad_z(model):
    f = IntegratedFilter(model)
    with pytest.raises(ValueError, match=r"expected z with shape \(\.\.\., T, 3\), got \(7,\)"):
        f.filter(np.zeros(7))
    with pytest.raises(ValueError, match="dtype int64"):
        f.filter(np.ones((9, 3), dtype=np.int64))
    with pytest.raises(ValueError, match="object array"):
        f.filter(np.empty((9, 3), dtype=object))
    with pytest.raises(ValueError, match="all NaN"):
        f.filter(np.full((9, 3), np.nan))
    with pytest.raises(ValueError, match="IntegratedState"):
        f.step(EMKalmanFilter(model).init(), np.zeros(3))
