"""Iterative UFIR filter (paper A §3.3, SPEC §6): exactness, least squares, dead zone, missing data."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.filters._base import initial_covariance
from kinefuse.filters.ufir import UFIRFilter, UFIRState
from kinefuse.models import constant_velocity

DT = 1.0 / 30.0
N = 20


@pytest.fixture
def model():
    return constant_velocity(DT, q=0.1, r=1e-3)


def noisy_track(rng, shape_batch, T, sigma=0.02):
    tt = np.arange(T) * DT
    f = rng.uniform(0.1, 0.5, size=(*shape_batch, 1, 3))
    ph = rng.uniform(0, 2 * np.pi, size=(*shape_batch, 1, 3))
    truth = 0.2 * np.sin(2 * np.pi * f * tt[:, None] + ph)
    return truth + sigma * rng.normal(size=truth.shape)


def kf_reference(model, z):
    """Independent NumPy KF (SPEC §4.2: init at first valid row, Joseph update)."""
    F, H, Q, R = model.F, model.H, model.Q, model.R
    x = P = None
    means, covs = [], []
    for zt in z:
        valid = bool(np.all(np.isfinite(zt)))
        if x is None:
            if valid:
                x, P = np.linalg.pinv(H) @ zt, initial_covariance(model)
            means.append(np.full(model.n_x, np.nan) if x is None else x)
            covs.append(np.full((model.n_x,) * 2, np.nan) if x is None else P)
            continue
        x, P = F @ x, F @ P @ F.T + Q
        if valid:
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ (zt - H @ x)
            A = np.eye(model.n_x) - K @ H
            P = A @ P @ A.T + K @ R @ K.T
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


def ls_line(z, k, n, dt=DT):
    """Least-squares straight line through the valid points of the horizon ending at k, per axis."""
    tt = np.arange(k - n + 1, k + 1)
    zz = z[tt]
    ok = np.all(np.isfinite(zz), axis=1)
    A = np.stack([np.ones(ok.sum()), (tt[ok] - k) * dt], axis=1)
    coef = np.linalg.lstsq(A, zz[ok], rcond=None)[0]  # rows: position at k, slope
    return coef[0], coef[1]


# --- stream == batch == split-and-resume; batched == loop -----------------------------------


@pytest.mark.parametrize("init", ["batch", "stored"])
def test_stream_batch_split_equal(model, rng, init):
    z = noisy_track(rng, (2,), 70)
    z[0, 30] = np.nan
    z[1, 40:43] = np.nan
    f = UFIRFilter(model, horizon=N, init=init)
    s_all, r_all = f.filter(z)

    s1, r1 = f.filter(z[:, :33])
    s2, r2 = f.filter(z[:, 33:], s1)
    np.testing.assert_allclose(
        np.concatenate([r1.mean, r2.mean], axis=1), r_all.mean, rtol=0, atol=1e-13
    )
    np.testing.assert_allclose(
        np.concatenate([r1.cov, r2.cov], axis=1), r_all.cov, rtol=0, atol=1e-13
    )
    np.testing.assert_array_equal(
        np.concatenate([r1.fir_ready, r2.fir_ready], axis=1), r_all.fir_ready
    )

    state = f.init((2,))
    means = []
    for t in range(z.shape[1]):
        state, out = f.step(state, z[:, t])
        assert (
            out.mean.shape == (2, 6) and out.cov.shape == (2, 6, 6) and out.fir_ready.shape == (2,)
        )
        means.append(out.mean)
    np.testing.assert_allclose(np.stack(means, axis=1), r_all.mean, rtol=0, atol=1e-13)
    assert isinstance(state, UFIRState) and state.k == s_all.k == 70
    np.testing.assert_allclose(state.x, s_all.x, atol=1e-13)
    np.testing.assert_array_equal(state.z_buf, s_all.z_buf)


def test_batched_equals_loop(model, rng):
    z = noisy_track(rng, (2, 3), 50)
    z[1, 2, 25:27] = np.nan
    f = UFIRFilter(model, horizon=N)
    _, r = f.filter(z)
    assert r.mean.shape == (2, 3, 50, 6) and r.fir_ready.shape == (2, 3, 50)
    for i in range(2):
        for j in range(3):
            _, rij = f.filter(z[i, j])
            np.testing.assert_allclose(r.mean[i, j], rij.mean, rtol=0, atol=1e-14)
            np.testing.assert_allclose(r.cov[i, j], rij.cov, rtol=0, atol=1e-14)


@pytest.mark.parametrize("init", ["batch", "stored"])
def test_fast_path_equals_dense_reference(model, rng, init):
    z = noisy_track(rng, (3,), 90)
    z[0, 30] = np.nan
    z[1, 45:49] = np.nan
    z[2, 60:75] = np.nan  # horizons with fewer than K valid samples -> KF fallback
    f = UFIRFilter(model, horizon=N, init=init)
    _, fast = f.filter(z)
    _, dense = f._run(z, f.init((3,)), fast=False)  # literal 6x6 iterative form
    np.testing.assert_allclose(fast.mean, dense.mean, rtol=0, atol=1e-11)
    np.testing.assert_allclose(fast.cov, dense.cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(fast.fir_ready, dense.fir_ready)
    assert not fast.fir_ready[2, 75]  # 5 valid samples (< K = 6) in the horizon
    assert fast.fir_ready[2, 81]


# --- exactness and least squares (SPEC §6.2) --------------------------------------------------


def test_noise_free_constant_velocity_exact(model, rng):
    T = 60
    p0 = rng.normal(size=3)
    v = rng.normal(size=3)
    tt = np.arange(T)[:, None] * DT
    z = p0 + v * tt
    _, r = UFIRFilter(model, horizon=N).filter(z)
    np.testing.assert_allclose(r.mean[N - 1 :, 0::2], z[N - 1 :], rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        r.mean[N - 1 :, 1::2], np.broadcast_to(v, (T - N + 1, 3)), rtol=0, atol=1e-9
    )
    assert not r.fir_ready[: N - 1].any() and r.fir_ready[N - 1 :].all()


def test_batch_init_equals_least_squares(model, rng):
    z = noisy_track(rng, (), 80)
    _, r = UFIRFilter(model, horizon=N).filter(z)
    for k in (N - 1, 33, 79):
        pos, slope = ls_line(z, k, N)
        np.testing.assert_allclose(r.mean[k, 0::2], pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r.mean[k, 1::2], slope, rtol=0, atol=1e-10)


def test_missing_samples_inside_horizon_least_squares(model, rng):
    z = noisy_track(rng, (), 80)
    z[[30, 31, 35, 44]] = np.nan
    f = UFIRFilter(model, horizon=N)
    _, r = f.filter(z)
    for k in (35, 40, 44, 50):  # horizons containing missing samples (k=35, 44: newest missing)
        pos, slope = ls_line(z, k, N)
        np.testing.assert_allclose(r.mean[k, 0::2], pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r.mean[k, 1::2], slope, rtol=0, atol=1e-10)
        assert r.fir_ready[k]
    assert not r.observed[35] and not r.observed[44] and r.observed[40]
    assert np.all(np.isnan(r.innovation[35]))


def test_dead_zone_equals_kalman(model, rng):
    z = noisy_track(rng, (), 40)
    z[5] = np.nan
    _, r = UFIRFilter(model, horizon=N).filter(z)
    m_ref, P_ref = kf_reference(model, z)
    np.testing.assert_allclose(r.mean[: N - 1], m_ref[: N - 1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.cov[: N - 1], P_ref[: N - 1], rtol=1e-10, atol=1e-15)
    assert not np.allclose(r.mean[N:], m_ref[N:], atol=1e-6)  # FIR differs from the KF afterwards


def test_leading_nan_rows_then_fallback(model, rng):
    z = noisy_track(rng, (), 60)
    z[:25] = np.nan  # no data until k = 25: KF init there, FIR ready once 6 valid in horizon
    _, r = UFIRFilter(model, horizon=N).filter(z)
    assert np.all(np.isnan(r.mean[:25])) and not r.observed[:25].any()
    np.testing.assert_allclose(r.mean[25, 0::2], z[25], atol=0)
    assert not r.fir_ready[:30].any() and r.fir_ready[30:].all()


def test_stored_init_runs_and_differs(model, rng):
    z = noisy_track(rng, (), 80)
    _, rb = UFIRFilter(model, horizon=N, init="batch").filter(z)
    fs = UFIRFilter(model, horizon=N, init="stored")
    s, rs = fs.filter(z)
    assert fs.init_mode == "stored" and s.x_buf.shape == (N, 6) and s.P_buf.shape == (N, 6, 6)
    assert np.all(np.isfinite(rs.mean))
    np.testing.assert_allclose(rs.mean[: N - 1], rb.mean[: N - 1], atol=0)  # same dead zone
    assert np.abs(rs.mean[N:] - rb.mean[N:]).max() > 1e-4


def test_joseph_covariance_matches_monte_carlo():
    # SPEC §6.2-4: the Joseph recursion predicts the actual error variance of the UFIR estimate
    rng = np.random.default_rng(7)
    q, r, n, M = 0.05, 4e-4, 25, 3000
    model = constant_velocity(DT, q=q, r=r)
    g = np.array([DT / 2.0, 1.0])
    x = np.zeros((M, 3, 2))
    states = []
    for _ in range(n):
        x = x @ np.array([[1.0, 0.0], [DT, 1.0]])  # x ← F x per axis (row-vector form)
        x = x + np.sqrt(q) * rng.normal(size=(M, 3, 1)) * g
        states.append(x.copy())
    truth = np.stack(states, axis=1)  # (M, n, 3, 2)
    z = truth[..., 0] + np.sqrt(r) * rng.normal(size=(M, n, 3))
    _, res = UFIRFilter(model, horizon=n).filter(z)
    err = res.mean[:, -1, 0::2] - truth[:, -1, :, 0]
    emp = np.mean(err**2)
    pred = np.mean(res.cov[0, -1].diagonal()[0::2])
    assert 0.9 < emp / pred < 1.1, (emp, pred)
    # the short form (I − KH)P⁻ would predict several times more (SPEC table): not what we return
    assert res.fir_ready[:, -1].all()


# --- covariance hygiene ---------------------------------------------------------------------


def test_covariance_symmetric_psd_long_run(model):
    rng = np.random.default_rng(3)
    f = UFIRFilter(model, horizon=N)
    state = f.init((2,))
    for _ in range(4):  # 2 x 4 x 50,000 = 4e5 joint-steps, chunked to bound memory
        z = noisy_track(rng, (2,), 50_000)
        z[rng.random(z.shape[:-1]) < 0.03] = np.nan
        state, r = f.filter(z, state)
        C = r.cov[:, ::7]
        assert np.all(np.isfinite(C))
        np.testing.assert_array_equal(C, np.swapaxes(C, -1, -2))
        assert np.linalg.eigvalsh(C).min() > -1e-15


# --- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize("horizon", [6, 0, -3])
def test_horizon_too_short(model, horizon):
    with pytest.raises(ValueError, match=r"horizon >= state dimension \+ 1 = 7.*got"):
        UFIRFilter(model, horizon=horizon)


@pytest.mark.parametrize("horizon", [20.0, 20.5, "20", None, True])
def test_horizon_not_integer(model, horizon):
    with pytest.raises(ValueError, match="expected horizon as an integer"):
        UFIRFilter(model, horizon=horizon)


def test_replace_keeps_configuration(model):
    import dataclasses

    f = dataclasses.replace(UFIRFilter(model, horizon=15, init="stored"), horizon=25)
    assert (f.horizon, f.init_mode) == (25, "stored") and f.init((2,)).z_buf.shape == (2, 25, 3)


def test_bad_init_string(model):
    with pytest.raises(
        ValueError, match=r"expected init one of \('batch', 'stored'\), got 'recursive'"
    ):
        UFIRFilter(model, init="recursive")


def test_bad_model_type():
    with pytest.raises(TypeError, match="LinearGaussianModel"):
        UFIRFilter(np.eye(6))


def test_wrong_z_shapes_and_dtypes(model, rng):
    f = UFIRFilter(model, horizon=N)
    with pytest.raises(ValueError, match=r"expected z with shape \(\.\.\., T, 3\), got \(10, 2\)"):
        f.filter(rng.normal(size=(10, 2)))
    with pytest.raises(ValueError, match=r"expected z with shape \(\.\.\., T, 3\), got \(3,\)"):
        f.filter(np.zeros(3))
    with pytest.raises(ValueError, match="dtype int64"):
        f.filter(np.zeros((10, 3), dtype=np.int64))
    with pytest.raises(ValueError, match="object array"):
        f.filter(np.empty((10, 3), dtype=object))
    with pytest.raises(ValueError, match="all NaN"):
        f.filter(np.full((2, 30, 3), np.nan))
    state = f.init((2,))
    with pytest.raises(ValueError, match=r"expected z with shape \(2, 3\)"):
        f.step(state, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="batch shape"):
        f.filter(np.zeros((3, 5, 3)), state)
    with pytest.raises(ValueError, match="UFIRState"):
        f.filter(np.zeros((5, 3)), state=(1, 2))
    # a state from a filter with another horizon is refused
    with pytest.raises(ValueError, match=r"state.z_buf with shape"):
        UFIRFilter(model, horizon=25).filter(np.zeros((2, 5, 3)), state)


def test_initial_mean_given(model, rng):
    f = UFIRFilter(model, horizon=N)
    z = noisy_track(rng, (), 30)
    z[:3] = np.nan
    state = f.init((), mean=np.zeros(6))
    _, r = f.filter(z, state)
    assert np.all(np.isfinite(r.mean))  # predicts from the given mean through the leading NaNs
    _ = f.filter(np.full((30, 3), np.nan), state)  # all-NaN is fine with an initialised state


# issue 12 case 10: a mistyped horizon is refused at the boundary (it used to end in a
# MemoryError of 134 GiB, or run for minutes on 300 samples)
@pytest.mark.parametrize("horizon", [10**6, 10**9, 2001])
def test_horizon_too_long_is_refused_before_any_work(model, horizon):
    from kinefuse.exceptions import InputError
    from kinefuse.filters.integrated import IntegratedFilter

    with pytest.raises(InputError, match=rf"expected horizon <= 2000 samples.*got {horizon}"):
        UFIRFilter(model, horizon=horizon)
    with pytest.raises(InputError, match="expected horizon <= 2000"):
        IntegratedFilter(model, horizon=horizon)


def test_horizon_longer_than_series_warns(model):
    z = np.zeros((30, 3))
    with pytest.warns(UserWarning, match="longer than the series"):
        _, r = UFIRFilter(model, horizon=40).filter(z)
    assert not np.any(r.fir_ready)


def test_state_memory_checked_against_the_machine(model):
    from kinefuse.exceptions import InputError
    from kinefuse.filters.integrated import IntegratedFilter

    with pytest.raises(InputError, match="GiB"):
        UFIRFilter(model, horizon=2000).init((10**6, 10**3))
    with pytest.raises(InputError, match="integrated filter horizon 2000: .* GiB"):
        IntegratedFilter(model, horizon=2000).init((10**6, 10**3))
