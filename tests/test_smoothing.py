"""RTS smoothing: filterpy / pykalman / closed-form oracles, segments, fixed lag, invariants."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.exceptions import InputError
from kinefuse.filters import KalmanFilter, fixed_lag_smooth, rts_smooth, rts_smooth_segments
from kinefuse.filters._base import FilterResult, initial_covariance
from kinefuse.models import constant_velocity
from test_kalman import random_cv, simulate, with_gaps

# compiles general-route kernels that `kinefuse warm-up` does not: one worker (tests/conftest.py)
pytestmark = pytest.mark.xdist_group("oracle-kernels")

ATOL = 1e-8


def _filterpy_rts(mean, cov, model):
    from filterpy.kalman import rts_smoother

    n = len(mean)
    return rts_smoother(mean, cov, [model.F] * n, [model.Q] * n)


def _full_r_twin(model):
    """Same F, Q (all the RTS uses) but a non-diagonal R: forces the dense RTS path."""
    n = model.n_z
    R = model.R + 0.1 * np.min(np.diag(model.R)) * (np.ones((n, n)) - np.eye(n))
    twin = model.replace(R=R)
    assert not twin.axis_blocks
    return twin


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("n_axes", [2, 3])
def test_rts_matches_filterpy_with_gaps(seed, n_axes):
    rng = np.random.default_rng(300 + seed)
    model = random_cv(rng, n_axes)
    _, z = simulate(model, rng, 250)
    z = with_gaps(rng, z)
    x0 = rng.normal(size=model.n_x)
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0))
    sm = rts_smooth(model, res)
    xs_ref, Ps_ref, _, _ = _filterpy_rts(res.mean.copy(), res.cov.copy(), model)
    np.testing.assert_allclose(sm.mean, xs_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(sm.cov, Ps_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(sm.position, xs_ref @ model.H.T, atol=ATOL, rtol=0)
    np.testing.assert_array_equal(sm.observed, res.observed)
    assert sm.innovation is None and sm.distance is None


def test_rts_matches_pykalman_smoother():
    from pykalman import KalmanFilter as PKF

    rng = np.random.default_rng(8)
    model = random_cv(rng)
    _, z = simulate(model, rng, 120)
    z = with_gaps(rng, z)
    x0 = rng.normal(size=6)
    P0 = initial_covariance(model)
    pkf = PKF(
        transition_matrices=model.F,
        observation_matrices=model.H,
        transition_covariance=model.Q,
        observation_covariance=model.R,
        initial_state_mean=model.F @ x0,
        initial_state_covariance=model.F @ P0 @ model.F.T + model.Q,
    )
    m_ref, P_ref = pkf.smooth(np.ma.masked_invalid(z))
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=x0, cov=P0))
    sm = rts_smooth(model, res)
    np.testing.assert_allclose(sm.mean, m_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(sm.cov, P_ref, atol=ATOL, rtol=0)


def test_rts_equals_closed_form_joint_gaussian():
    """Condition the joint Gaussian of x_0..x_{T-1} on the observed z: exact smoothing."""
    rng = np.random.default_rng(13)
    model = constant_velocity(0.1, q=0.4, r=np.diag([0.05, 0.02]), n_axes=2)
    F, Q, H, R = model.F, model.Q, model.H, model.R
    n_x, n_z, T = 4, 2, 7
    m0 = rng.normal(size=n_x)
    A = rng.normal(size=(n_x, n_x))
    P0 = A @ A.T * 0.1 + 0.05 * np.eye(n_x)  # full (cross-axis) prior: dense path
    _, z = simulate(model, rng, T, x0=m0)
    z[3] = np.nan
    # prior of the stacked states: x_t = F^{t+1} x_{-1} + sum_l F^{t-l} w_l
    mu = np.concatenate([np.linalg.matrix_power(F, t + 1) @ m0 for t in range(T)])
    cov_t = []
    c = P0
    for _ in range(T):
        c = F @ c @ F.T + Q
        cov_t.append(c)
    Sigma = np.zeros((T * n_x, T * n_x))
    for i in range(T):
        for j in range(i + 1):
            blk = np.linalg.matrix_power(F, i - j) @ cov_t[j]
            Sigma[i * n_x : (i + 1) * n_x, j * n_x : (j + 1) * n_x] = blk
            Sigma[j * n_x : (j + 1) * n_x, i * n_x : (i + 1) * n_x] = blk.T
    obs = [t for t in range(T) if not np.any(np.isnan(z[t]))]
    Hb = np.zeros((len(obs) * n_z, T * n_x))
    for k, t in enumerate(obs):
        Hb[k * n_z : (k + 1) * n_z, t * n_x : (t + 1) * n_x] = H
    Rb = np.kron(np.eye(len(obs)), R)
    zb = np.concatenate([z[t] for t in obs])
    S = Hb @ Sigma @ Hb.T + Rb
    G = np.linalg.solve(S, Hb @ Sigma).T
    post_mean = (mu + G @ (zb - Hb @ mu)).reshape(T, n_x)
    post_cov = Sigma - G @ Hb @ Sigma
    kf = KalmanFilter(model)
    _, res = kf.filter(z, kf.init(mean=m0, cov=P0))
    sm = rts_smooth(model, res)
    np.testing.assert_allclose(sm.mean, post_mean, atol=1e-9, rtol=0)
    for t in range(T):
        np.testing.assert_allclose(
            sm.cov[t], post_cov[t * n_x : (t + 1) * n_x, t * n_x : (t + 1) * n_x], atol=1e-9
        )
    # and the filter alone is not the smoother (the test can fail)
    assert np.max(np.abs(res.mean[:-1] - post_mean[:-1])) > 1e-3


def test_smoothed_cov_below_filtered_cov(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 400, batch=(3,))
    z = with_gaps(rng, z)
    _, res = KalmanFilter(model).filter(z)
    sm = rts_smooth(model, res)
    diff = res.cov - sm.cov
    eig = np.linalg.eigvalsh(0.5 * (diff + np.swapaxes(diff, -1, -2)))
    assert np.min(eig) > -1e-12
    assert np.max(eig[:, :-1]) > 1e-6  # strictly better somewhere before the end
    np.testing.assert_array_equal(sm.cov[:, -1], res.cov[:, -1])
    np.testing.assert_array_equal(sm.cov, np.swapaxes(sm.cov, -1, -2))


def test_rts_with_uninitialised_leading_samples(rng):
    model = constant_velocity(1 / 30, q=0.5, r=0.02)
    _, z = simulate(model, rng, 100, batch=(2,))
    z = with_gaps(rng, z)
    z[0, :12] = np.nan
    z[1, :3] = np.nan
    _, res = KalmanFilter(model).filter(z)
    sm = rts_smooth(model, res)
    for b, t0 in ((0, 12), (1, 3)):
        assert np.all(np.isnan(sm.mean[b, :t0])) and np.all(np.isnan(sm.cov[b, :t0]))
        xs_ref, Ps_ref, _, _ = _filterpy_rts(res.mean[b, t0:].copy(), res.cov[b, t0:].copy(), model)
        np.testing.assert_allclose(sm.mean[b, t0:], xs_ref, atol=ATOL, rtol=0)
        np.testing.assert_allclose(sm.cov[b, t0:], Ps_ref, atol=ATOL, rtol=0)


def test_axis_rts_equals_dense_rts_and_falls_back(rng):
    model = constant_velocity(1 / 30, q=1.0, r=np.diag([0.01, 0.02, 0.005]))
    twin = _full_r_twin(model)
    _, z = simulate(model, rng, 300, batch=(4,))
    z = with_gaps(rng, z)
    _, res = KalmanFilter(model).filter(z)
    fast = rts_smooth(model, res)
    dense = rts_smooth(twin, res)
    np.testing.assert_allclose(fast.mean, dense.mean, atol=1e-10, rtol=0)
    np.testing.assert_allclose(fast.cov, dense.cov, atol=1e-10, rtol=0)
    for lag in (0, 5):
        a = fixed_lag_smooth(model, res, lag)
        d = fixed_lag_smooth(twin, res, lag)
        np.testing.assert_allclose(a.mean, d.mean, atol=1e-10, rtol=0)
        np.testing.assert_allclose(a.cov, d.cov, atol=1e-10, rtol=0)
    # filtered covariances with cross-axis terms: the axis-blocked model must not decouple
    _, res_x = KalmanFilter(twin).filter(z)
    sm_x = rts_smooth(model, res_x)
    xs_ref, Ps_ref, _, _ = _filterpy_rts(res_x.mean[0].copy(), res_x.cov[0].copy(), model)
    np.testing.assert_allclose(sm_x.mean[0], xs_ref, atol=ATOL, rtol=0)
    np.testing.assert_allclose(sm_x.cov[0], Ps_ref, atol=ATOL, rtol=0)


def test_batched_rts_equals_loop(rng):
    model = constant_velocity(1 / 30, q=0.5, r=0.02)
    _, z = simulate(model, rng, 80, batch=(2, 3))
    z = with_gaps(rng, z)
    _, res = KalmanFilter(model).filter(z)
    sm = rts_smooth(model, res)
    for i in range(2):
        for j in range(3):
            one = FilterResult(
                res.mean[i, j], res.cov[i, j], res.position[i, j], res.observed[i, j]
            )
            s1 = rts_smooth(model, one)
            np.testing.assert_array_equal(s1.mean, sm.mean[i, j])
            np.testing.assert_array_equal(s1.cov, sm.cov[i, j])


def test_segments_smooth_each_available_run_independently(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 120)
    z[40:55] = np.nan  # outage 1
    z[90:91] = np.nan  # outage 2 (one sample)
    _, res = KalmanFilter(model).filter(z)
    seg = rts_smooth_segments(model, res)  # available = observed
    available = res.observed
    np.testing.assert_array_equal(rts_smooth(model, res, mask=available).mean, seg.mean)
    for a, b in ((0, 40), (55, 90), (91, 120)):
        part = FilterResult(res.mean[a:b], res.cov[a:b], res.position[a:b], res.observed[a:b])
        ref = rts_smooth(model, part)
        np.testing.assert_allclose(seg.mean[a:b], ref.mean, atol=1e-12, rtol=0)
        np.testing.assert_allclose(seg.cov[a:b], ref.cov, atol=1e-12, rtol=0)
    # outage samples are returned as filtered; segment ends equal the filter
    np.testing.assert_array_equal(seg.mean[40:55], res.mean[40:55])
    np.testing.assert_array_equal(seg.mean[[39, 89, 119]], res.mean[[39, 89, 119]])
    # whole-series smoothing does cross the outage (differs at the end of segment 1)
    assert np.max(np.abs(rts_smooth(model, res).mean[39] - seg.mean[39])) > 1e-6


def test_fixed_lag_equals_truncated_fixed_interval(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 60, batch=(2,))
    z = with_gaps(rng, z)
    _, res = KalmanFilter(model).filter(z)
    lag = 7
    fl = fixed_lag_smooth(model, res, lag)
    for t in (0, 10, 31, 52, 59):
        e = min(t + lag, 59) + 1
        part = FilterResult(
            res.mean[:, :e], res.cov[:, :e], res.position[:, :e], res.observed[:, :e]
        )
        ref = rts_smooth(model, part)
        np.testing.assert_allclose(fl.mean[:, t], ref.mean[:, t], atol=1e-12, rtol=0)
        np.testing.assert_allclose(fl.cov[:, t], ref.cov[:, t], atol=1e-12, rtol=0)
    np.testing.assert_array_equal(fixed_lag_smooth(model, res, 0).mean, res.mean)
    np.testing.assert_allclose(
        fixed_lag_smooth(model, res, 100).mean, rts_smooth(model, res).mean, atol=1e-12
    )


def test_smoothing_bad_input(rng):
    model = constant_velocity(1 / 30, q=1.0, r=0.01)
    _, z = simulate(model, rng, 20)
    _, res = KalmanFilter(model).filter(z)
    with pytest.raises(
        ValueError, match=r"expected mask with shape \(20,\) \(\.\.\., T\), got \(19,\)"
    ):
        rts_smooth(model, res, mask=np.ones(19, dtype=bool))
    with pytest.raises(ValueError, match="bool array, got dtype int"):
        rts_smooth(model, res, mask=np.ones(20, dtype=int))
    with pytest.raises(ValueError, match="lag as an int >= 0"):
        fixed_lag_smooth(model, res, -1)
    with pytest.raises(ValueError, match="lag as an int >= 0"):
        fixed_lag_smooth(model, res, 2.5)
    with pytest.raises(ValueError, match="FilterResult"):
        rts_smooth(model, (res.mean, res.cov))
    model2 = constant_velocity(1 / 30, q=1.0, r=0.01, n_axes=2)
    with pytest.raises(
        ValueError, match=r"expected result.mean with shape \(\.\.\., T, 4\), got \(20, 6\)"
    ):
        rts_smooth(model2, res)
    with pytest.raises(ValueError, match="LinearGaussianModel"):
        rts_smooth(KalmanFilter(model), res)


def test_segments_means_only_on_full_covariances(rng):
    """``cov=False`` on cross-axis (dense) covariances: the same means, bit for bit, as the
    full smoother, which matches filterpy's; ``cov`` None."""
    model = constant_velocity(1 / 30, q=1.0, r=np.diag([0.01, 0.02, 0.005]))
    twin = _full_r_twin(model)
    _, z = simulate(model, rng, 200, batch=(3,))
    z[:, 60:75] = np.nan  # an outage: two segments
    _, res = KalmanFilter(twin).filter(z)  # covariances with cross-axis terms
    full = rts_smooth_segments(model, res)
    lean = rts_smooth_segments(model, res, cov=False)
    assert lean.cov is None and full.cov is not None
    np.testing.assert_array_equal(lean.mean, full.mean)
    np.testing.assert_array_equal(lean.position, full.position)
    xs_ref, _, _, _ = _filterpy_rts(res.mean[0, :60].copy(), res.cov[0, :60].copy(), model)
    np.testing.assert_allclose(lean.mean[0, :60], xs_ref, atol=ATOL, rtol=0)


def test_dense_rts_for_six_states_equals_the_general_loop(rng):
    """rts_dense6 (the size a compile-time constant) is rts_dense's arithmetic: equal bit for
    bit, with and without the covariances, fixed interval and fixed lag."""
    from kinefuse.filters._kernels_axis import rts_dense, rts_dense6

    model = constant_velocity(1 / 30, q=1.0, r=np.diag([0.01, 0.02, 0.005]))
    _, z = simulate(model, rng, 150, batch=(2,))
    z[:, 40:50] = np.nan
    _, res = KalmanFilter(_full_r_twin(model)).filter(z)
    args = (res.mean, res.cov, np.ones((2, 150), bool), model.F, model.Q)
    full = np.arange(6)
    for lag in (-1, 4):
        for n_cov in (2, 0):
            outs = []
            for fn in (rts_dense, rts_dense6):
                m, c = np.empty((2, 150, 6)), np.empty((n_cov, 150 if n_cov else 0, 6, 6))
                outs.append((fn(*args, lag, m, c, full), m, c))
            for a, b in zip(*outs, strict=True):
                np.testing.assert_array_equal(a, b)
        # the position rows/columns only: that block of the full output, bit for bit
        m_full, c_full = np.empty((2, 150, 6)), np.empty((2, 150, 6, 6))
        rts_dense6(*args, lag, m_full, c_full, full)
        m, c = np.empty((2, 150, 6)), np.empty((2, 150, 3, 3))
        rts_dense6(*args, lag, m, c, np.array([0, 2, 4]))
        np.testing.assert_array_equal(m, m_full)
        np.testing.assert_array_equal(c, c_full[..., 0::2, 0::2])


def test_segments_position_covariance_is_the_block_of_the_full_one(rng):
    # cov="position": H P̃ Hᵀ, the same numbers as that block of the full smoothed covariance,
    # on full (dense) covariances and on the axis-blocked layout, fixed interval and fixed lag
    model = constant_velocity(1 / 30, q=1.0, r=np.diag([0.01, 0.02, 0.005]))
    _, z = simulate(model, rng, 120, batch=(2,))
    z[:, 30:36] = np.nan
    avail = np.all(np.isfinite(z), axis=-1)
    for flt in (KalmanFilter(_full_r_twin(model)), KalmanFilter(model)):
        _, res = flt.filter(z)
        for smooth, args in ((rts_smooth_segments, (avail,)), (fixed_lag_smooth, (5, avail))):
            full, pos = smooth(model, res, *args), smooth(model, res, *args, cov="position")
            assert pos.cov.shape == (2, 120, 3, 3)
            np.testing.assert_array_equal(pos.mean, full.mean)
            np.testing.assert_array_equal(pos.cov, full.cov[..., 0::2, 0::2])
    with pytest.raises(InputError, match="cov"):
        rts_smooth_segments(model, res, avail, cov="full")
