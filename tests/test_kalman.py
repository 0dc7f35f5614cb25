"""KalmanFilter: oracles (filterpy, pykalman), layer invariants, consistency, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.filters import FilterResult, GaussianState, KalmanFilter
from kinefuse.filters._base import initial_covariance
from kinefuse.models import LinearGaussianModel, constant_velocity

ATOL = 1e-8


def random_cv(rng, n_axes=3, full_r=False):
    dt = float(rng.uniform(0.005, 0.05))
    q = float(rng.uniform(0.05, 2.0))
    if full_r:
        A = rng.normal(size=(n_axes, n_axes)) * 0.05
        r = A @ A.T + 0.01 * np.eye(n_axes)
    else:
        r = np.diag(rng.uniform(1e-4, 0.05, size=n_axes))
    return constant_velocity(dt, q, r, n_axes=n_axes)


def simulate(model, rng, T, x0=None, batch=()):
    """Draw a trajectory and measurements from the model (w ~ N(0, Q) via its rank-1 factor)."""
    n_x, n_z = model.n_x, model.n_z
    x = np.zeros((*batch, n_x)) if x0 is None else np.broadcast_to(x0, (*batch, n_x)).copy()
    w_fac = _psd_factor(model.Q)
    Lr = np.linalg.cholesky(model.R)
    xs = np.empty((*batch, T, n_x))
    zs = np.empty((*batch, T, n_z))
    for t in range(T):
        x = x @ model.F.T + rng.normal(size=(*batch, n_x)) @ w_fac.T
        xs[..., t, :] = x
        zs[..., t, :] = x @ model.H.T + rng.normal(size=(*batch, n_z)) @ Lr.T
    return xs, zs


def _psd_factor(M):
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.clip(w, 0.0, None))


def with_gaps(rng, z, frac=0.15, runs=3):
    z = z.copy()
    T = z.shape[-2]
    idx = rng.random(T) < frac
    z[..., idx, :] = np.nan
    for _ in range(runs):
        s = int(rng.integers(1, T - 10))
        z[..., s : s + int(rng.integers(2, 8)), :] = np.nan
    return z


def filterpy_run(model, z, x0, P0):
    """Reference: filterpy predict/update loop; NaN rows predict only."""
    from filterpy.kalman import KalmanFilter as FKF

    kf = FKF(dim_x=model.n_x, dim_z=model.n_z)
    kf.F = model.F.copy()
    kf.H = model.H.copy()
    kf.Q = model.Q.copy()
    kf.R = model.R.copy()
    kf.x = x0.reshape(-1, 1).copy()
    kf.P = P0.copy()
    means, covs, nis = [], [], []
    for zt in z:
        kf.predict()
        if np.any(np.isnan(zt)):
            nis.append(np.nan)
        else:
            kf.update(zt.reshape(-1, 1))
            nis.append((kf.y.T @ np.linalg.solve(kf.S, kf.y)).item())
        means.append(kf.x.ravel().copy())
        covs.append(kf.P.copy())
    return np.array(means), np.array(covs), np.array(nis)


# ------------------------------------------------------------------------------------------
# Oracles
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n_axes", [2, 3])
def test_matches_filterpy_with_gaps_given_initial_state(seed, n_axes):
    rng = np.random.default_rng(100 + seed)
    model = random_cv(rng, n_axes)
    _, z = simulate(model, rng, 300)
    z = with_gaps(rng, z)
    x0 = rng.normal(size=model.n_x)
    P0 = initial_covariance(model) * rng.uniform(0.5, 3.0)
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0, cov=P0))
    m_ref, P_ref, nis_ref = filterpy_run(model, z, x0, P0)
    np.testing.assert_allclose(res.mean, m_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.cov, P_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.distance, nis_ref, atol=1e-7, rtol=1e-9)
    observed = ~np.any(np.isnan(z), axis=-1)
    np.testing.assert_array_equal(res.observed, observed)
    np.testing.assert_allclose(res.position, m_ref @ model.H.T, atol=ATOL, rtol=0)
    assert np.all(np.isnan(res.innovation[~observed]))


def test_matches_filterpy_automatic_initialisation():
    rng = np.random.default_rng(7)
    model = random_cv(rng)
    _, z = simulate(model, rng, 200, x0=np.array([1.0, 0.0, 2.0, 0.0, -1.0, 0.0]))
    z = with_gaps(rng, z)
    z[:5] = np.nan  # leading outage: uninitialised until t0 = 5
    t0 = 5
    _, res = KalmanFilter(model).filter(z)
    assert np.all(np.isnan(res.mean[:t0])) and np.all(np.isnan(res.cov[:t0]))
    assert not res.observed[:t0].any()
    x_init = np.zeros(6)
    x_init[0::2] = z[t0]
    np.testing.assert_array_equal(res.mean[t0], x_init)
    np.testing.assert_array_equal(res.cov[t0], initial_covariance(model))
    assert res.observed[t0] and np.isnan(res.distance[t0])
    m_ref, P_ref, _ = filterpy_run(model, z[t0 + 1 :], x_init, initial_covariance(model))
    np.testing.assert_allclose(res.mean[t0 + 1 :], m_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.cov[t0 + 1 :], P_ref, atol=ATOL, rtol=0)


def test_full_r_model_uses_dense_path_and_matches_filterpy():
    rng = np.random.default_rng(11)
    model = random_cv(rng, full_r=True)
    assert not model.axis_blocks
    _, z = simulate(model, rng, 250)
    z = with_gaps(rng, z)
    x0 = rng.normal(size=6)
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0))
    m_ref, P_ref, nis_ref = filterpy_run(model, z, x0, initial_covariance(model))
    np.testing.assert_allclose(res.mean, m_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.cov, P_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.distance, nis_ref, atol=1e-7, rtol=1e-9)


def test_matches_pykalman_filter():
    from pykalman import KalmanFilter as PKF

    rng = np.random.default_rng(5)
    model = random_cv(rng)
    _, z = simulate(model, rng, 150)
    z = with_gaps(rng, z)
    x0 = rng.normal(size=6)
    P0 = initial_covariance(model)
    # pykalman's initial state is the prior of x_0 (no prediction at t = 0): one step ahead
    pkf = PKF(
        transition_matrices=model.F,
        observation_matrices=model.H,
        transition_covariance=model.Q,
        observation_covariance=model.R,
        initial_state_mean=model.F @ x0,
        initial_state_covariance=model.F @ P0 @ model.F.T + model.Q,
    )
    m_ref, P_ref = pkf.filter(np.ma.masked_invalid(z))
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0, cov=P0))
    np.testing.assert_allclose(res.mean, m_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.cov, P_ref, atol=ATOL, rtol=0)


# ------------------------------------------------------------------------------------------
# Layer invariants: stream == batch == split-and-resume, batched == loop, axis == dense
# ------------------------------------------------------------------------------------------


def _assert_results_equal(a, b, atol=0.0):
    for name in ("mean", "cov", "position", "innovation", "distance"):
        np.testing.assert_allclose(
            getattr(a, name), getattr(b, name), atol=atol, rtol=0, err_msg=name
        )
    np.testing.assert_array_equal(a.observed, b.observed)


@pytest.mark.parametrize("method", ["axis", "dense"])
def test_filter_equals_repeated_step(rng, method):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 120, batch=(4,))
    z = with_gaps(rng, z)
    z[1, :10] = np.nan
    kf = KalmanFilter(model, method=method)
    state_b, res = kf.filter(z)
    state = kf.init((4,))
    outs = []
    for t in range(z.shape[1]):
        state, out = kf.step(state, z[:, t])
        assert (
            isinstance(out, FilterResult)
            and out.mean.shape == (4, 6)
            and out.cov.shape == (4, 6, 6)
        )
        outs.append(out)
    stacked = FilterResult(
        **{
            k: np.stack([getattr(o, k) for o in outs], axis=1)
            for k in ("mean", "cov", "position", "observed", "innovation", "distance")
        }
    )
    _assert_results_equal(res, stacked)
    np.testing.assert_array_equal(state.x, state_b.x)
    np.testing.assert_array_equal(state.P, state_b.P)
    assert state.k == state_b.k == z.shape[1]


@pytest.mark.parametrize("method", ["auto", "dense"])
def test_split_and_resume_equals_one_run(rng, method):
    model = constant_velocity(0.02, q=0.3, r=0.005)
    _, z = simulate(model, rng, 400, batch=(3,))
    z = with_gaps(rng, z)
    kf = KalmanFilter(model, method=method)
    s_full, full = kf.filter(z)
    s1, first = kf.filter(z[:, :173])
    s2, second = kf.filter(z[:, 173:], s1)
    for name in ("mean", "cov", "distance"):
        joined = np.concatenate([getattr(first, name), getattr(second, name)], axis=1)
        np.testing.assert_array_equal(joined, getattr(full, name))
    np.testing.assert_array_equal(s2.x, s_full.x)
    assert s2.k == s_full.k == 400


def test_batched_equals_loop_over_elements(rng):
    model = constant_velocity(1 / 30, q=0.5, r=0.02)
    _, z = simulate(model, rng, 90, batch=(2, 3))
    z = with_gaps(rng, z)
    z[1, 2, :40] = np.nan
    kf = KalmanFilter(model)
    state, res = kf.filter(z)
    assert res.mean.shape == (2, 3, 90, 6) and res.cov.shape == (2, 3, 90, 6, 6)
    assert res.observed.shape == (2, 3, 90) and state.x.shape == (2, 3, 6)
    for i in range(2):
        for j in range(3):
            s_ij, r_ij = kf.filter(z[i, j])
            _assert_results_equal(
                FilterResult(
                    **{
                        k: getattr(res, k)[i, j]
                        for k in ("mean", "cov", "position", "observed", "innovation", "distance")
                    }
                ),
                r_ij,
            )
            np.testing.assert_array_equal(s_ij.P, state.P[i, j])


def test_axis_path_equals_dense_path(rng):
    r = np.diag([0.01, 0.03, 0.002])  # full-R argument with diagonal values
    model = constant_velocity(1 / 30, q=1.0, r=r)
    assert model.axis_blocks
    _, z = simulate(model, rng, 500, batch=(5,))
    z = with_gaps(rng, z)
    z[2, :30] = np.nan
    _, fast = KalmanFilter(model, method="axis").filter(z)
    _, dense = KalmanFilter(model, method="dense").filter(z)
    _assert_results_equal(fast, dense, atol=1e-10)


def test_non_block_initial_cov_falls_back_to_dense(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    P0 = initial_covariance(model)
    P0[0, 2] = P0[2, 0] = 0.5 * P0[0, 0]  # cross-axis correlation: decoupling not exact
    _, z = simulate(model, rng, 50)
    x0 = np.zeros(6)
    _, auto = KalmanFilter(model).filter(z, KalmanFilter(model).init(mean=x0, cov=P0))
    _, dense = KalmanFilter(model, method="dense").filter(
        z, KalmanFilter(model).init(mean=x0, cov=P0)
    )
    _assert_results_equal(auto, dense)
    assert abs(auto.cov[-1, 0, 2]) > 0
    with pytest.raises(ValueError, match="block-diagonal"):
        KalmanFilter(model, method="axis").filter(z, KalmanFilter(model).init(mean=x0, cov=P0))


def test_partial_nan_row_is_missing_and_input_not_mutated(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 20)
    z[7, 1] = np.nan
    kf = KalmanFilter(model)
    state0 = kf.init(mean=np.zeros(6))
    x_before = state0.x.copy()
    _, res = kf.filter(z, state0)
    assert not res.observed[7] and res.observed[6] and res.observed[8]
    np.testing.assert_array_equal(res.mean[7], model.F @ res.mean[6])
    np.testing.assert_array_equal(state0.x, x_before)


def test_float32_and_empty_batch(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 30)
    _, r64 = KalmanFilter(model).filter(z.astype(np.float32).astype(np.float64))
    _, r32 = KalmanFilter(model).filter(z.astype(np.float32))
    np.testing.assert_array_equal(r32.mean, r64.mean)
    st, empty = KalmanFilter(model).filter(np.zeros((0, 30, 3)))
    assert empty.mean.shape == (0, 30, 6) and st.x.shape == (0, 6)


# ------------------------------------------------------------------------------------------
# Numerical invariants and statistical consistency
# ------------------------------------------------------------------------------------------


def test_covariance_symmetric_psd_over_a_million_steps():
    rng = np.random.default_rng(42)
    model = constant_velocity(1 / 100, q=5.0, r=1e-4)
    kf = KalmanFilter(model)
    state = kf.init(mean=np.zeros(6))
    pos = np.zeros(3)
    worst = np.inf
    for _chunk in range(10):
        pos = pos + np.cumsum(rng.normal(scale=0.05, size=(100_000, 3)), axis=0)
        z = pos + rng.normal(scale=0.01, size=pos.shape)
        z[rng.random(len(z)) < 0.05] = np.nan
        pos = pos[-1]
        state, res = kf.filter(z, state)
        P = res.cov
        assert np.array_equal(P, np.swapaxes(P, -1, -2))
        for a in range(3):
            p00, p01, p11 = P[:, 2 * a, 2 * a], P[:, 2 * a, 2 * a + 1], P[:, 2 * a + 1, 2 * a + 1]
            tr = p00 + p11
            lam_min = 0.5 * (tr - np.sqrt((p00 - p11) ** 2 + 4 * p01**2))
            worst = min(worst, float(np.min(lam_min / tr)))
        assert np.all(np.isfinite(res.mean))
    assert state.k == 1_000_000
    assert worst > 0.0


def test_mean_nis_matches_measurement_dimension():
    rng = np.random.default_rng(2024)
    model = constant_velocity(1 / 30, q=0.5, r=np.diag([0.01, 0.004, 0.02]))
    x0 = np.array([0.0, 0.1, 1.0, 0.0, 0.5, -0.1])
    P0 = initial_covariance(model)
    x_start = x0 + _psd_factor(P0) @ rng.normal(size=6)
    _, z = simulate(model, rng, 6000, x0=x_start)
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0, cov=P0))
    # NIS ~ chi2(3): mean 3, sd of the mean over 6000 independent innovations ~ 0.032
    assert abs(np.mean(res.distance) - 3.0) < 0.15
    # a 4x mis-specified R must be detected by the same statistic
    kf_bad = KalmanFilter(model.replace(R=4.0 * model.R))
    _, res_bad = kf_bad.filter(z, kf_bad.init(mean=x0, cov=P0))
    assert np.mean(res_bad.distance) < 2.0


# ------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------


@pytest.fixture
def kf3():
    return KalmanFilter(constant_velocity(1 / 30, q=1.0, r=0.01))


@pytest.mark.parametrize(
    ("z", "match"),
    [
        (np.zeros((10, 2)), r"expected z with shape \(\.\.\., T, 3\), got \(10, 2\)"),
        (np.zeros(3), r"expected z with shape \(\.\.\., T, 3\), got \(3,\)"),
        (np.zeros((0, 3)), "at least one time step"),
        (np.zeros((10, 3), dtype=int), "float array.*got dtype int"),
        (np.zeros((10, 3), dtype=object), "object array"),
        (np.array([[0.0, 0.0, np.inf]] * 4), "±inf"),
        (np.array([[0.0, 0.0, -np.inf]] * 4), "±inf"),
        (np.full((10, 3), np.nan), "all NaN"),
    ],
)
def test_filter_bad_input(kf3, z, match):
    with pytest.raises(ValueError, match=match):
        kf3.filter(z)


def test_all_nan_element_named(kf3):
    z = np.zeros((2, 3, 10, 3))
    z[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"batch element \(1, 2\)"):
        kf3.filter(z)
    # with an initial state an all-NaN series is fine: predict only
    _, res = kf3.filter(z, kf3.init((2, 3), mean=np.zeros(6)))
    assert not res.observed[1, 2].any() and np.all(np.isfinite(res.mean[1, 2]))


def test_step_bad_input(kf3):
    state = kf3.init((4,))
    with pytest.raises(ValueError, match=r"expected z with shape \(4, 3\).*got \(3,\)"):
        kf3.step(state, np.zeros(3))
    with pytest.raises(ValueError, match=r"expected z with shape \(4, 3\).*got \(4, 2\)"):
        kf3.step(state, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="float array"):
        kf3.step(state, np.zeros((4, 3), dtype=np.int64))
    with pytest.raises(ValueError, match="±inf"):
        kf3.step(state, np.full((4, 3), np.inf))
    with pytest.raises(ValueError, match="GaussianState"):
        kf3.step((state.x, state.P), np.zeros((4, 3)))
    bad = GaussianState(state.x[:, :4], state.P, state.initialized, 0)
    with pytest.raises(ValueError, match=r"expected state.x with shape \(4, 6\), got \(4, 4\)"):
        kf3.step(bad, np.zeros((4, 3)))
    # a leading missing row before initialisation is fine in step: NaN outputs
    state, out = kf3.step(state, np.full((4, 3), np.nan))
    assert np.all(np.isnan(out.mean)) and not out.observed.any() and not state.initialized.any()


def test_filter_state_batch_mismatch(kf3):
    with pytest.raises(ValueError, match=r"expected state with batch shape \(2,\).*got \(3,\)"):
        kf3.filter(np.zeros((2, 5, 3)), kf3.init((3,)))


def test_constructor_validation():
    with pytest.raises(ValueError, match="LinearGaussianModel"):
        KalmanFilter("cv")
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    with pytest.raises(ValueError, match="expected method in"):
        KalmanFilter(model, method="fast")
    full = constant_velocity(
        1 / 30, q=1.0, r=np.array([[0.02, 0.01, 0], [0.01, 0.02, 0], [0, 0, 0.02]])
    )
    with pytest.raises(ValueError, match="axis-blocked"):
        KalmanFilter(full, method="axis")
    with pytest.raises(ValueError, match=r"expected mean with shape \(\.\.\., 6\), got \(4,\)"):
        KalmanFilter(model).init((2,), mean=np.zeros(4))
    with pytest.raises(ValueError, match=r"broadcastable to \(2, 6\), got \(3, 6\)"):
        KalmanFilter(model).init((2,), mean=np.zeros((3, 6)))
    with pytest.raises(AttributeError):
        KalmanFilter(model).method = "dense"


def test_generic_linear_model_dense():
    """A non-CV model (1-D position + velocity + bias) runs on the dense path."""
    F = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    H = np.array([[1.0, 0.0, 1.0]])
    model = LinearGaussianModel(
        F=F, H=H, Q=np.diag([1e-4, 1e-2, 1e-6]), R=np.array([[0.01]]), dt_s=0.1
    )
    rng = np.random.default_rng(3)
    z = rng.normal(size=(50, 1)).cumsum(axis=0) * 0.1
    x0 = np.zeros(3)
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0))
    m_ref, P_ref, _ = filterpy_run(model, z, x0, initial_covariance(model))
    np.testing.assert_allclose(res.mean, m_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(res.cov, P_ref, atol=ATOL, rtol=0)


@pytest.mark.parametrize("which", ["kf", "ufir", "em", "integrated", "imm"])
def test_an_initial_covariance_that_is_not_a_covariance_is_refused(which):
    """A negative or non-symmetric initial covariance was stored as given: the KF then gave
    positions hundreds of metres off with negative variances, and no warning."""
    from kinefuse.exceptions import InputError
    from kinefuse.filters import IMM, EMKalmanFilter, IntegratedFilter, UFIRFilter

    m = constant_velocity(1 / 30, q=0.1, r=0.01)
    flt = {
        "kf": lambda: KalmanFilter(m),
        "ufir": lambda: UFIRFilter(m, horizon=10),
        "em": lambda: EMKalmanFilter(m),
        "integrated": lambda: IntegratedFilter(m, horizon=10),
        "imm": lambda: IMM(m, m),
    }[which]()
    with pytest.raises(InputError, match="expected cov positive semi-definite, got smallest"):
        flt.init((2,), mean=np.zeros(6), cov=-np.eye(6))
    skew = np.eye(6)
    skew[0, 1] = 0.5
    with pytest.raises(InputError, match="expected cov symmetric"):
        flt.init((2,), mean=np.zeros(6), cov=skew)
    flt.init((2,), mean=np.zeros(6), cov=2.0 * np.eye(6))  # a covariance is taken


def test_imm_refuses_external_posterior_covariances_that_are_not_covariances():
    from kinefuse.exceptions import InputError
    from kinefuse.filters import IMM

    m = constant_velocity(1 / 30, q=0.1, r=0.01)
    imm = IMM(m, m, reading="R2")
    z = np.zeros((5, 2, 3))
    x = np.zeros((5, 2, 6))
    with pytest.raises(InputError, match="expected P_prev positive semi-definite"):
        imm.filter(z, prev=(x, np.broadcast_to(-np.eye(6), (5, 2, 6, 6))))
    P = np.full((5, 2, 6, 6), np.nan)  # NaN: not given, the IMM's own posterior is used
    imm.filter(z, prev=(x, P))


def test_imm_refuses_a_series_without_time_steps():
    """(B, 0, M, n_z) failed with an IndexError in the all-missing check."""
    from kinefuse.exceptions import InputError
    from kinefuse.filters import IMM

    m = constant_velocity(1 / 30, q=0.1, r=0.01)
    with pytest.raises(InputError, match="at least one time step"):
        IMM(m, m).filter(np.zeros((4, 0, 2, 3)))
