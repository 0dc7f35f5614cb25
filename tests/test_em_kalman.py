"""EM-adaptive KF (paper A §3.2, SPEC §5): KF limit, independent NumPy reference, option B."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from kinefuse.exceptions import NumericalWarning
from kinefuse.filters._base import initial_covariance
from kinefuse.filters._kernels import kf_predict, kf_update
from kinefuse.filters.em_kalman import EMKalmanFilter, EMKalmanState
from kinefuse.models import constant_velocity

DT = 1.0 / 30.0


@pytest.fixture
def model():
    # paper A elbow test 1 (q = 1, R = 0.01 I)
    return constant_velocity(DT, q=1.0, r=1e-2)


def track(rng, batch, T, sigma=0.02):
    tt = np.arange(T) * DT
    f = rng.uniform(0.1, 0.5, size=(*batch, 1, 3))
    ph = rng.uniform(0, 2 * np.pi, size=(*batch, 1, 3))
    truth = 0.2 * np.sin(2 * np.pi * f * tt[:, None] + ph)
    return truth + sigma * rng.normal(size=truth.shape)


def em_reference(model, z, n_iter):
    """Straightforward NumPy transcription of SPEC §5.3 option A (dense, np.linalg.solve)."""
    F, H, Q, R = model.F, model.H, model.Q, model.R
    n_x = model.n_x
    x = P = None
    means, covs, Rs = [], [], []
    for zt in z:
        valid = bool(np.all(np.isfinite(zt)))
        if x is None:
            if valid:
                x, P = np.linalg.pinv(H) @ zt, initial_covariance(model)
            means.append(np.full(n_x, np.nan) if x is None else x)
            covs.append(np.full((n_x, n_x), np.nan) if x is None else P)
            Rs.append(np.full((3, 3), np.nan))
            continue
        xm = F @ x
        Pminus = F @ P @ F.T + Q
        if not valid:
            x, P = xm, Pminus
            means.append(x)
            covs.append(P)
            Rs.append(np.full((3, 3), np.nan))
            continue
        Pm, Rj = Pminus, R
        for _ in range(n_iter):
            S = H @ Pm @ H.T + Rj
            K = np.linalg.solve(S, H @ Pm).T
            x = xm + K @ (zt - H @ xm)
            A = np.eye(n_x) - K @ H
            P = A @ Pm @ A.T + K @ Rj @ K.T
            e = zt - H @ x
            Rj = np.outer(e, e) + H @ P @ H.T
            d = x - xm
            Pm = P + np.outer(d, d)
        means.append(x)
        covs.append(P)
        Rs.append(Rj)
    return np.array(means), np.array(covs), np.array(Rs)


def kf_with_dense_kernels(model, z):
    """The plain KF through the dense reference kernels of ``_kernels.py``."""
    x = P = None
    out = []
    for zt in z:
        if x is None:
            x, P = np.linalg.pinv(model.H) @ zt, initial_covariance(model)
        else:
            x, P = kf_predict(x, P, model.F, model.Q)
            if np.all(np.isfinite(zt)):
                x, P, _nu, _S, ok = kf_update(x, P, zt, model.H, model.R)
                assert ok
        out.append((x, P))
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


def test_one_iteration_is_the_kalman_filter(model, rng):
    z = track(rng, (), 120)
    z[50] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error", NumericalWarning)
        _, r = EMKalmanFilter(model, n_iter=1).filter(z)
    m_ref, P_ref = kf_with_dense_kernels(model, z)
    np.testing.assert_allclose(r.mean, m_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(r.cov, P_ref, rtol=1e-11, atol=1e-16)
    # ... while R^{(1)} = Ω₁ differs from the nominal R (SPEC §5.2-6)
    assert not np.allclose(r.R_em[10], model.R)
    assert not r.observed[50] and np.all(np.isnan(r.R_em[50]))


@pytest.mark.parametrize("n_iter", [2, 3])
def test_matches_numpy_reference(model, rng, n_iter):
    z = track(rng, (), 200)
    z[[70, 71, 150]] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error", NumericalWarning)  # floors must not bind at N_EM <= 3
        _, r = EMKalmanFilter(model, n_iter=n_iter).filter(z)
    m_ref, P_ref, R_ref = em_reference(model, z, n_iter)
    np.testing.assert_allclose(r.mean, m_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(r.cov, P_ref, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(r.R_em, R_ref, rtol=1e-8, atol=1e-14)
    # the state adapts from 2 iterations on: it differs from the KF (SPEC §5.2-6)
    m_kf, _ = kf_with_dense_kernels(model, z)
    assert np.abs(r.mean - m_kf).max() > 1e-4


def test_ten_iterations_finite_psd(model, rng):
    z = track(rng, (2,), 400)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        _, r = EMKalmanFilter(model, n_iter=10).filter(z)
    assert (
        np.all(np.isfinite(r.mean))
        and np.all(np.isfinite(r.cov))
        and np.all(np.isfinite(r.R_em[:, 1:]))
    )
    np.testing.assert_array_equal(r.cov, np.swapaxes(r.cov, -1, -2))
    assert np.linalg.eigvalsh(r.cov).min() > -1e-15
    assert np.linalg.eigvalsh(r.R_em[:, 1:]).min() > 0


def test_floor_warns_once_per_call():
    # q large, R far too large and N_EM = 30: R_em collapses below 1e-3 x nominal, the floor binds
    rng = np.random.default_rng(5)
    m = constant_velocity(DT, q=1.0, r=1.0)
    z = track(rng, (3,), 300, sigma=1e-3)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        _, r = EMKalmanFilter(m, n_iter=30).filter(z)
    msgs = [w for w in rec if issubclass(w.category, NumericalWarning)]
    assert len(msgs) == 1 and "floor" in str(msgs[0].message)
    # floor honoured: generalised eigenvalues of R_em w.r.t. R_nom >= 1e-3 (R_nom = I)
    assert np.linalg.eigvalsh(r.R_em[:, 1:]).min() >= 1e-3 * (1 - 1e-9)


def test_option_b_runs_carries_state_and_differs(model, rng):
    z = track(rng, (2,), 150)
    fa = EMKalmanFilter(model, n_iter=3)
    fb = EMKalmanFilter(model, n_iter=3, regularized=True)
    sa, ra = fa.filter(z)
    s0 = fb.init((2,))
    np.testing.assert_allclose(s0.u, 5.0)  # û₀ = n_z + 2
    np.testing.assert_allclose(s0.U, np.broadcast_to(model.R, (2, 3, 3)))  # Û₀ = R_nom
    sb, rb = fb.filter(z)
    assert np.all(np.isfinite(rb.mean)) and np.all(np.isfinite(sb.U))
    assert np.abs(rb.mean - ra.mean).max() > 1e-5
    # û − n_z − 1 after n updates: ρⁿ + (1 − ρⁿ)/(1 − ρ)  (149 updates: the first row initialises)
    rho, n = fb.rho, 149
    np.testing.assert_allclose(sb.u - 4.0, rho**n + (1 - rho**n) / (1 - rho), rtol=1e-12)
    assert not np.allclose(sb.U, s0.U)
    np.testing.assert_array_equal(sa.u, fa.init((2,)).u)  # option A leaves (û, Û) untouched
    # option B: split-and-resume carries (û, Û)
    s1, r1 = fb.filter(z[:, :77])
    s2, r2 = fb.filter(z[:, 77:], s1)
    np.testing.assert_allclose(np.concatenate([r1.mean, r2.mean], 1), rb.mean, rtol=0, atol=1e-13)
    np.testing.assert_allclose(s2.U, sb.U, rtol=1e-13)


def test_option_b_first_step_by_hand(model):
    # one update of option B with N_EM = 1: R⁽⁰⁾ = Û⁻/(û⁻ − 4) from the forgotten prior
    f = EMKalmanFilter(model, n_iter=1, regularized=True)
    z = np.array([[0.0, 0.0, 0.0], [0.01, -0.02, 0.005]])
    s, r = f.filter(z)
    rho = f.rho
    u_pr = rho * (5.0 - 4.0) + 4.0
    R0 = rho * model.R / (u_pr - 4.0)
    P0 = initial_covariance(model)
    Pm = model.F @ P0 @ model.F.T + model.Q
    H = model.H
    K = np.linalg.solve(H @ Pm @ H.T + R0, H @ Pm).T
    np.testing.assert_allclose(r.mean[1], K @ z[1], rtol=1e-12, atol=1e-16)
    e = z[1] - H @ r.mean[1]
    om1 = np.outer(e, e) + H @ r.cov[1] @ H.T
    np.testing.assert_allclose(s.U, rho * model.R + om1, rtol=1e-10)
    np.testing.assert_allclose(s.u, u_pr + 1.0)


# --- stream == batch == split; batched == loop ----------------------------------------------


def test_stream_batch_split_equal(model, rng):
    z = track(rng, (2,), 60)
    z[0, 20] = np.nan
    f = EMKalmanFilter(model, n_iter=3)
    s_all, r_all = f.filter(z)
    s1, r1 = f.filter(z[:, :29])
    s2, r2 = f.filter(z[:, 29:], s1)
    np.testing.assert_allclose(
        np.concatenate([r1.mean, r2.mean], 1), r_all.mean, rtol=0, atol=1e-14
    )
    np.testing.assert_allclose(
        np.concatenate([r1.R_em, r2.R_em], 1), r_all.R_em, rtol=0, atol=1e-16
    )
    state = f.init((2,))
    means = []
    for t in range(60):
        state, out = f.step(state, z[:, t])
        assert out.mean.shape == (2, 6) and out.R_em.shape == (2, 3, 3)
        means.append(out.mean)
    np.testing.assert_allclose(np.stack(means, 1), r_all.mean, rtol=0, atol=1e-14)
    assert isinstance(state, EMKalmanState) and state.k == s_all.k == 60
    np.testing.assert_allclose(state.P, s_all.P, rtol=0, atol=1e-16)


def test_batched_equals_loop(model, rng):
    z = track(rng, (3, 2), 40)
    f = EMKalmanFilter(model, n_iter=2)
    _, r = f.filter(z)
    assert r.mean.shape == (3, 2, 40, 6) and r.R_em.shape == (3, 2, 40, 3, 3)
    for i in range(3):
        for j in range(2):
            _, rij = f.filter(z[i, j])
            np.testing.assert_allclose(r.mean[i, j], rij.mean, rtol=0, atol=1e-15)
            np.testing.assert_allclose(r.distance[i, j], rij.distance, rtol=1e-14)


def test_covariance_psd_long_run(model):
    rng = np.random.default_rng(11)
    f = EMKalmanFilter(model, n_iter=3)
    state = f.init((2,))
    for _ in range(3):  # 3 x 2 x 40,000 joint-steps
        z = track(rng, (2,), 40_000)
        z[rng.random(z.shape[:-1]) < 0.02] = np.nan
        state, r = f.filter(z, state)
        C = r.cov[:, ::5]
        np.testing.assert_array_equal(C, np.swapaxes(C, -1, -2))
        assert np.linalg.eigvalsh(C).min() > -1e-15
        assert np.all(np.isfinite(r.mean))


# --- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize("n_iter", [0, -1])
def test_n_iter_below_one(model, n_iter):
    with pytest.raises(ValueError, match=rf"expected n_iter >= 1, got {n_iter}"):
        EMKalmanFilter(model, n_iter=n_iter)


@pytest.mark.parametrize("n_iter", [2.0, "3", True])
def test_n_iter_not_integer(model, n_iter):
    with pytest.raises(ValueError, match="expected n_iter as an integer"):
        EMKalmanFilter(model, n_iter=n_iter)


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        ({"tau": 0.0}, "tau > 0"),
        ({"tau": math.nan}, "tau finite"),
        ({"rho": 1.5}, r"rho > 0.0 and <= 1.0"),
        ({"rho": 0.0}, r"rho > 0.0"),
        ({"regularized": "yes"}, "regularized as True or False"),
    ],
)
def test_bad_parameters(model, kw, msg):
    with pytest.raises(ValueError, match=msg):
        EMKalmanFilter(model, **kw)


def test_bad_z(model, rng):
    f = EMKalmanFilter(model)
    with pytest.raises(ValueError, match=r"expected z with shape \(\.\.\., T, 3\), got \(5, 4\)"):
        f.filter(np.zeros((5, 4)))
    with pytest.raises(ValueError, match="dtype int32"):
        f.filter(np.zeros((5, 3), dtype=np.int32))
    with pytest.raises(ValueError, match="object array"):
        f.filter(np.array([[1.0, 2.0, None]] * 4, dtype=object))
    with pytest.raises(ValueError, match=r"batch element \(1,\)\) is all NaN"):
        z = track(rng, (2,), 10)
        z[1] = np.nan
        f.filter(z)
    with pytest.raises(ValueError, match="±inf"):
        f.filter(np.full((4, 3), np.inf))
    with pytest.raises(ValueError, match=r"expected z with shape \(3,\)"):
        f.step(f.init(), np.zeros((1, 3)))
    with pytest.raises(TypeError, match="LinearGaussianModel"):
        EMKalmanFilter("model")
