"""IMM fusion (paper B Eqs. 24-48, SPEC §8): oracles, index convention, robustness, streaming."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kinefuse.exceptions import InputError
from kinefuse.filters import IMM, IMMResult, IMMState, lag_posteriors
from kinefuse.filters._kernels import kf_predict, kf_update
from kinefuse.filters._kernels_imm import imm_probabilities
from kinefuse.models import LinearGaussianModel, constant_velocity

DT = 1.0 / 30.0
ASYM = np.array([[0.9, 0.1], [0.35, 0.65]])  # rows sum to 1, Γ ≠ Γᵀ


def _trajectory(rng, T, n_axes=3, q=0.5):
    """Noise-free constant-velocity-ish positions (T, n_axes), m."""
    acc = rng.normal(scale=np.sqrt(q) / DT, size=(T, n_axes))
    vel = np.cumsum(acc * DT, axis=0)
    return np.cumsum(vel * DT, axis=0)


def _model_1d(r, q=0.2):
    F = np.array([[1.0, DT], [0.0, 1.0]])
    H = np.array([[1.0, 0.0]])
    Q = q * np.array([[DT * DT / 4, DT / 2], [DT / 2, 1.0]])
    return LinearGaussianModel(F=F, H=H, Q=Q, R=np.array([[r]]), dt_s=DT)


# ---------------------------------------------------------------------------- oracles
def test_identical_models_equal_single_kf(rng):
    model = constant_velocity(DT, 0.5, 0.01)
    T = 80
    z = _trajectory(rng, T) + 0.1 * rng.normal(size=(T, 3))
    z[[10, 11, 40]] = np.nan  # both missing: predict only
    imm = IMM(model, model, transition=ASYM, mu0=(0.6, 0.4))
    x0 = np.r_[z[0, 0], 0.0, z[0, 1], 0.0, z[0, 2], 0.0]
    P0 = np.diag([0.01, 1.0] * 3)
    state = imm.init(mean=x0, cov=P0)
    zz = np.stack([z, z], axis=-2)  # the same measurement for both models
    _, res = imm.filter(zz[1:], state=state)

    x, P = x0.copy(), P0.copy()
    mu = np.array([0.6, 0.4])
    for t in range(1, T):
        x, P = kf_predict(x, P, model.F, model.Q)
        if np.all(np.isfinite(z[t])):
            x, P, _, _, ok = kf_update(x, P, z[t], model.H, model.R)
            assert ok
        mu = ASYM.T @ mu  # equal likelihoods: μ_t = c̄ = Γᵀ μ_{t−1}
        np.testing.assert_allclose(res.mean[t - 1], x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.cov[t - 1], P, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.model_mean[t - 1], [x, x], rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.mu[t - 1], mu, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(res.observed, np.all(np.isfinite(z[1:]), axis=-1))


def test_matches_filterpy_imm_standard_reading_multistep(rng):
    filterpy = pytest.importorskip("filterpy.kalman")
    m1 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 5.0, 0.2)
    Gam = np.array([[0.97, 0.03], [0.2, 0.8]])
    mu0 = np.array([0.3, 0.7])
    T = 60
    z = _trajectory(rng, T) + 0.1 * rng.normal(size=(T, 3))
    z[25:30] += 0.8  # a jump that moves μ towards the high-noise model
    x0 = np.r_[z[0, 0], 0.0, z[0, 1], 0.0, z[0, 2], 0.0]
    P0 = np.diag([0.05, 1.0] * 3)

    kfs = []
    for m in (m1, m2):
        kf = filterpy.KalmanFilter(dim_x=6, dim_z=3)
        kf.F, kf.H, kf.Q, kf.R = m.F.copy(), m.H.copy(), m.Q.copy(), m.R.copy()
        kf.x, kf.P = x0.reshape(6, 1).copy(), P0.copy()
        kfs.append(kf)
    oracle = filterpy.IMMEstimator(kfs, mu0.copy(), Gam)

    imm = IMM(m1, m2, transition=Gam, mu0=mu0, mu_floor=0.0, reading="R1")
    state = imm.init(mean=x0, cov=P0)
    _, res = imm.filter(np.stack([z, z], axis=-2)[1:], state=state)
    mus = []
    for t in range(1, T):
        oracle.predict()
        oracle.update(z[t].reshape(3, 1))
        mus.append(oracle.mu.copy())
        np.testing.assert_allclose(res.mu[t - 1], oracle.mu, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res.mean[t - 1], oracle.x.ravel(), rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.cov[t - 1], oracle.P, rtol=1e-9, atol=1e-12)
        for m in range(2):
            np.testing.assert_allclose(res.model_mean[t - 1, m], kfs[m].x.ravel(), atol=1e-9)
    mus = np.array(mus)
    assert mus[:, 1].max() > 0.9 and mus[:, 0].max() > 0.9  # the run exercises both regimes


def _hand_step(Gam, mu, xs, Ps, models, zs):
    """One IMM step written out with explicit indices (SPEC §8.3)."""
    M = len(mu)
    cbar = [sum(Gam[i][m] * mu[i] for i in range(M)) for m in range(M)]
    out_x, out_P, lam = [], [], []
    for m in range(M):
        w = [Gam[i][m] * mu[i] / cbar[m] for i in range(M)]
        x0 = sum(w[i] * xs[i] for i in range(M))
        P0 = sum(w[i] * (Ps[i] + np.outer(xs[i] - x0, xs[i] - x0)) for i in range(M))
        F, Q, H, R = models[m].F, models[m].Q, models[m].H, models[m].R
        xp, Pp = F @ x0, F @ P0 @ F.T + Q
        nu = zs[m] - H @ xp
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        out_x.append(xp + K @ nu)
        out_P.append((np.eye(2) - K @ H) @ Pp)
        lam.append(
            np.exp(-0.5 * nu @ np.linalg.solve(S, nu)) / np.sqrt(np.linalg.det(2 * np.pi * S))
        )
    c = sum(lam[m] * cbar[m] for m in range(M))
    mu_new = np.array([lam[m] * cbar[m] / c for m in range(M)])
    x = sum(mu_new[m] * out_x[m] for m in range(M))
    P = sum(mu_new[m] * (out_P[m] + np.outer(out_x[m] - x, out_x[m] - x)) for m in range(M))
    return mu_new, x, P, np.array(out_x)


@pytest.mark.parametrize("use_prev", [True, False])
def test_one_step_against_hand_computation_asymmetric(use_prev):
    models = (_model_1d(0.04), _model_1d(0.01, q=1.0))
    Gam = np.array([[0.9, 0.1], [0.4, 0.6]])
    mu = np.array([0.7, 0.3])
    own_x = np.array([[0.1, 0.5], [0.3, -0.2]])
    own_P = np.array([np.diag([0.02, 0.5]), [[0.01, 0.002], [0.002, 0.3]]])
    ext_x = np.array([[0.0, 1.0], [0.5, -1.0]])
    ext_P = np.array([np.diag([0.03, 0.4]), [[0.02, 0.001], [0.001, 0.2]]])
    zs = np.array([[0.2], [0.45]])
    imm = IMM(models=models, transition=Gam, mu_floor=0.0)
    state = imm.init(mean=own_x, cov=own_P, mu=mu)
    prev = (ext_x, ext_P) if use_prev else None
    _, out = imm.step(state, zs, prev=prev)
    xs, Ps = (ext_x, ext_P) if use_prev else (own_x, own_P)
    mu_h, x_h, P_h, xm_h = _hand_step(Gam, mu, xs, Ps, models, zs)
    np.testing.assert_allclose(out.mu, mu_h, rtol=1e-12)
    np.testing.assert_allclose(out.mean, x_h, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(out.cov, P_h, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(out.model_mean, xm_h, rtol=1e-12, atol=1e-14)
    if use_prev:  # external posteriors make the IMM's own (here: none yet) irrelevant
        _, out0 = imm.step(imm.init(mu=mu), zs, prev=prev)
        np.testing.assert_array_equal(out0.mean, out.mean)
        np.testing.assert_array_equal(out0.mu, out.mu)
    # the transposed convention gives a different answer, so this test pins the index order
    mu_t, _, _, _ = _hand_step(Gam.T / Gam.T.sum(1, keepdims=True), mu, xs, Ps, models, zs)
    assert np.abs(mu_t - out.mu).max() > 1e-3


def _numpy_imm(Gam, mu, xs, Ps, models, z, prev, floor):
    """Plain NumPy transcription of SPEC §8.3 (reading R2), one element, over ``z (T, M, n_z)``.

    Missing model measurement: predict only and no evidence (its log-likelihood := log-mean-exp
    of the updated models'; none updated: μ = c̄). Floor: entries below it set to exactly the
    floor, the rest rescaled (the kernel's ``apply_floor``). Non-finite ``prev`` rows: own
    posteriors.
    """
    M = len(mu)
    xs, Ps, mu = [np.array(a, dtype=float) for a in (xs, Ps, mu)]
    out = {k: [] for k in ("mean", "cov", "mu", "model_mean", "model_cov", "log_likelihood")}
    for t in range(z.shape[0]):
        xin, Pin = xs.copy(), Ps.copy()
        for i in range(M):
            if np.all(np.isfinite(prev[0][t, i])) and np.all(np.isfinite(prev[1][t, i])):
                xin[i], Pin[i] = prev[0][t, i], prev[1][t, i]
        cbar = Gam.T @ mu  # Eq. 25
        W = Gam * mu[:, None] / cbar[None, :]  # Eq. 26: W[i, m] = μ_{i|m}
        ll = np.full(M, np.nan)
        upd = np.zeros(M, bool)
        for m in range(M):
            x0 = W[:, m] @ xin  # Eq. 27
            P0 = sum(W[i, m] * (Pin[i] + np.outer(xin[i] - x0, xin[i] - x0)) for i in range(M))
            F, Q, H, R = models[m].F, models[m].Q, models[m].H, models[m].R
            xp, Pp = F @ x0, F @ P0 @ F.T + Q  # Eqs. 29-32
            xs[m], Ps[m] = xp, Pp
            if np.all(np.isfinite(z[t, m])):
                nu = z[t, m] - H @ xp  # Eqs. 33-38
                S = H @ Pp @ H.T + R
                K = np.linalg.solve(S, H @ Pp).T
                A = np.eye(len(xp)) - K @ H
                xs[m], Ps[m] = xp + K @ nu, A @ Pp @ A.T + K @ R @ K.T
                ll[m] = -0.5 * (nu @ np.linalg.solve(S, nu) + np.linalg.slogdet(2 * np.pi * S)[1])
                upd[m] = True
        lmax = ll[upd].max() if upd.any() else -np.inf
        if lmax > -np.inf:
            ll_eff = np.where(upd, ll, lmax + np.log(np.mean(np.exp(ll[upd] - lmax))))
            lw = ll_eff + np.log(cbar)  # Eqs. 45-46 in log form
            mu = np.exp(lw - lw.max())
            mu /= mu.sum()
        else:
            mu = cbar.copy()
        low = mu < floor
        if low.any():
            mu = np.where(low, floor, mu * (1 - floor * low.sum()) / mu[~low].sum())
        x = mu @ xs  # Eqs. 47-48
        P = sum(mu[m] * (Ps[m] + np.outer(xs[m] - x, xs[m] - x)) for m in range(M))
        for k, v in (("mean", x), ("cov", P), ("mu", mu), ("model_mean", xs), ("model_cov", Ps),
                     ("log_likelihood", ll)):  # fmt: skip
            out[k].append(np.array(v, copy=True))
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("n_axes", [3, 2])  # 3: the compiled (M, n_x, n_z) = (2, 6, 3) fast path
def test_kernel_matches_numpy_transcription_of_spec(rng, n_axes):
    """imm_run vs SPEC §8.3 written out in NumPy: NaN gaps, external priors with gaps, floor."""
    m1 = constant_velocity(DT, 0.5, 0.01, n_axes=n_axes)
    m2 = constant_velocity(DT, 3.0, 0.002, n_axes=n_axes)
    R2 = m2.R + 0.0005 * (np.ones((n_axes, n_axes)) - np.eye(n_axes))  # full R: dense path
    m2 = LinearGaussianModel(F=m2.F, H=m2.H, Q=m2.Q, R=R2, dt_s=DT)
    floor = 1e-3
    T, n_x = 50, 2 * n_axes
    truth = _trajectory(rng, T, n_axes)
    z = np.stack([truth + 0.1 * rng.normal(size=truth.shape),
                  truth + 0.04 * rng.normal(size=truth.shape)], axis=1)  # fmt: skip
    z[rng.random((T, 2)) < 0.15] = np.nan  # single-model gaps
    z[[12, 33]] = np.nan  # both missing
    z[20:24, 1] += 2.0  # camera glitch: μ_2 hits the floor
    x_ext = np.zeros((T, 2, n_x))
    x_ext[..., 0::2] = np.nan_to_num(z) + 0.01 * rng.normal(size=z.shape)
    x_ext[..., 1::2] = 0.2 * rng.normal(size=z.shape)
    P_ext = np.broadcast_to(np.diag([2e-3, 0.4] * n_axes), (T, 2, n_x, n_x)).copy()
    P_ext[..., 0, 1] = P_ext[..., 1, 0] = 1e-3  # correlated position/velocity
    prev = lag_posteriors(x_ext, P_ext)
    prev[0][rng.random(T) < 0.2, 1] = np.nan  # external model-2 prior missing: own posterior
    x0 = np.zeros((2, n_x))
    x0[:, 0::2] = truth[0]
    x0[1, 1::2] = 0.1  # different model means: the spread-of-means terms matter
    P0 = np.array([np.diag([0.01, 1.0] * n_axes), np.diag([0.02, 0.5] * n_axes)])
    mu0 = np.array([0.6, 0.4])
    imm = IMM(m1, m2, transition=ASYM, mu_floor=floor)
    _, res = imm.filter(z, state=imm.init(mean=x0, cov=P0, mu=mu0), prev=prev)
    ref = _numpy_imm(ASYM, mu0, x0, P0, (m1, m2), z, prev, floor)
    for k in ("mean", "cov", "mu", "model_mean", "model_cov"):
        np.testing.assert_allclose(getattr(res, k), ref[k], rtol=0, atol=1e-10, err_msg=k)
    np.testing.assert_allclose(res.log_likelihood, ref["log_likelihood"], rtol=1e-12, atol=1e-9)
    assert res.mu[:, 1].min() == pytest.approx(floor, rel=1e-12)  # the floor was exercised
    assert res.mu[:, 1].max() > 0.9


# ---------------------------------------------------------------------------- robustness
def test_huge_innovation_keeps_mu_valid_and_floor_respected(rng):
    m1 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 0.5, 0.001)
    T = 120
    truth = _trajectory(rng, T)
    z = np.stack(
        [truth + 0.05 * rng.normal(size=(T, 3)), truth + 0.01 * rng.normal(size=(T, 3))], 1
    )
    z[30:60, 1] += 1e8  # camera glitch: astronomically large innovations
    z[70, :] += 1e6  # both models: Λ = exp(−~1e15) underflows to 0 in the linear domain
    floor = 1e-6
    imm = IMM(m1, m2, mu_floor=floor)
    _, res = imm.filter(z)
    assert np.all(np.isfinite(res.mu))
    np.testing.assert_allclose(res.mu.sum(-1), 1.0, atol=1e-12)
    assert res.mu.min() >= floor * (1 - 1e-12)
    assert np.all(res.mu[31:60, 1] == pytest.approx(floor, rel=1e-9))
    assert np.all(np.isfinite(res.mean)) and np.all(np.isfinite(res.cov))
    assert np.all(res.log_likelihood[70] < -1e10)
    # no lock-in: the camera model wins again once its data are good
    assert res.mu[-1, 1] > 0.5


def test_probability_update_extremes():
    cbar = np.array([0.3, 0.7])
    both = np.array([True, True])
    # every likelihood −inf (νᵀS⁻¹ν overflowed): no evidence, μ = c̄
    mu = imm_probabilities(np.array([-np.inf, -np.inf]), both, cbar, 1e-6)
    np.testing.assert_allclose(mu, cbar, rtol=1e-12)
    # one −inf: that model goes exactly to the floor
    mu = imm_probabilities(np.array([-np.inf, -3.0]), both, cbar, 1e-6)
    np.testing.assert_allclose(mu, [1e-6, 1 - 1e-6], rtol=1e-12)
    # log-likelihoods far below the double range of exp() still give the right ratio
    mu = imm_probabilities(np.array([-1e300, -1e300]), both, cbar, 0.0)
    np.testing.assert_allclose(mu, cbar, rtol=1e-12)
    mu = imm_probabilities(np.array([-5000.0, -5000.0 + np.log(2.0)]), both, cbar, 0.0)
    np.testing.assert_allclose(mu, [0.3 / 1.7, 1.4 / 1.7], rtol=1e-10)
    # exact floor with three models: several entries below it
    mu = imm_probabilities(np.array([0.0, -800.0, -900.0]), np.ones(3, bool), np.ones(3) / 3, 1e-3)
    np.testing.assert_allclose(mu, [1 - 2e-3, 1e-3, 1e-3], rtol=1e-12)


def test_one_model_missing_leaves_mu_to_the_markov_chain(rng):
    m1 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 0.5, 0.002)
    T = 40
    truth = _trajectory(rng, T)
    z = np.stack([truth + 0.1 * rng.normal(size=(T, 3)), truth + 0.04 * rng.normal(size=(T, 3))], 1)
    z[20, 1] = np.nan  # camera missing
    z[25, 0] = np.nan  # IMU missing
    z[30] = np.nan  # both missing
    imm = IMM(m1, m2, transition=ASYM, mu_floor=0.0)
    _, res = imm.filter(z)
    for t in (20, 25, 30):
        np.testing.assert_allclose(res.mu[t], ASYM.T @ res.mu[t - 1], rtol=1e-12)
        assert res.observed[t] == (t != 30)
    np.testing.assert_array_equal(res.model_observed[20], [True, False])
    np.testing.assert_array_equal(res.model_observed[25], [False, True])
    assert np.isnan(res.log_likelihood[20, 1]) and np.isfinite(res.log_likelihood[20, 0])
    assert np.all(np.isnan(res.model_innovation[30]))
    # elsewhere μ does move (the test can fail if likelihoods were ignored)
    assert np.abs(res.mu[21] - ASYM.T @ res.mu[20]).max() > 1e-4


def test_uninitialised_start_and_all_missing(rng):
    m = constant_velocity(DT, 0.5, 0.01)
    imm = IMM(m, m)
    z = np.full((5, 2, 3), np.nan)
    z[2, 1] = [1.0, 2.0, 3.0]  # first valid sample: camera only
    z[3] = [[1.0, 2.0, 3.0], [1.01, 2.0, 3.0]]
    _, res = imm.filter(z)
    assert np.all(np.isnan(res.mean[:2])) and not res.observed[:2].any()
    np.testing.assert_allclose(res.model_mean[2], [[1, 0, 2, 0, 3, 0]] * 2)
    np.testing.assert_array_equal(res.model_observed[2], [False, True])
    np.testing.assert_allclose(res.mu[2], [0.5, 0.5])
    assert np.all(np.isfinite(res.mean[2:]))
    with pytest.raises(InputError, match="all NaN"):
        imm.filter(np.full((4, 2, 3), np.nan))


# ---------------------------------------------------------------------------- streaming
def _series(rng, batch, T):
    truth = _trajectory(rng, int(np.prod(batch)) * T).reshape(*batch, T, 3)
    z = np.stack(
        [truth + 0.05 * rng.normal(size=truth.shape), truth + 0.02 * rng.normal(size=truth.shape)],
        axis=-2,
    )
    mask = rng.random(z.shape[:-1]) < 0.1
    z[mask] = np.nan
    z[..., 20:26, 1, :] = np.nan  # camera outage
    z[..., 0, :, :] = z[..., 1, :, :]  # every element starts with a valid row
    z[..., 0, :, :] = np.where(np.isnan(z[..., 0, :, :]), 0.0, z[..., 0, :, :])
    return z


def _ext_posteriors(rng, z):
    """External per-model posteriors (stand-ins for FIR-1/FIR-2), with NaN gaps."""
    n_x = 6
    pos = np.nan_to_num(z)
    x = np.zeros((*z.shape[:-1], n_x))
    x[..., 0::2] = pos + 0.01 * rng.normal(size=pos.shape)
    x[..., 1::2] = 0.1 * rng.normal(size=pos.shape)
    P = np.broadcast_to(np.diag([1e-3, 0.5] * 3), (*z.shape[:-1], n_x, n_x)).copy()
    x_prev, P_prev = lag_posteriors(x, P)
    x_prev[..., 7, 1, :] = np.nan  # external model-2 posterior missing at one step
    return x_prev, P_prev


def _assert_results_equal(a: IMMResult, b: IMMResult, atol=0.0):
    for f in ("mean", "cov", "position", "mu", "model_mean", "model_cov", "log_likelihood",
              "model_innovation", "model_distance"):  # fmt: skip
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=0, atol=atol, err_msg=f)
    np.testing.assert_array_equal(a.observed, b.observed)
    np.testing.assert_array_equal(a.model_observed, b.model_observed)


@pytest.mark.parametrize("with_prev", [False, True])
def test_stream_equals_batch_equals_split_resume(rng, with_prev):
    m1 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 0.5, 0.001)
    imm = IMM(m1, m2, transition=ASYM)
    batch, T = (2, 3), 50
    z = _series(rng, batch, T)
    prev = _ext_posteriors(rng, z) if with_prev else None
    state_b, res = imm.filter(z, prev=prev)

    state = imm.init(batch_shape=batch)
    steps = []
    for t in range(T):
        p = None if prev is None else (prev[0][..., t, :, :], prev[1][..., t, :, :, :])
        state, out = imm.step(state, z[..., t, :, :], prev=p)
        steps.append(out)
    for f in ("mean", "cov", "mu", "model_mean", "model_distance"):
        stacked = np.stack([getattr(o, f) for o in steps], axis=len(batch))
        np.testing.assert_array_equal(stacked, getattr(res, f), err_msg=f)
    np.testing.assert_array_equal(state.mu, state_b.mu)
    assert state.k == state_b.k == T

    cut = 23
    p1 = None if prev is None else (prev[0][..., :cut, :, :], prev[1][..., :cut, :, :, :])
    p2 = None if prev is None else (prev[0][..., cut:, :, :], prev[1][..., cut:, :, :, :])
    s1, r1 = imm.filter(z[..., :cut, :, :], prev=p1)
    s2, r2 = imm.filter(z[..., cut:, :, :], state=s1, prev=p2)
    joined = IMMResult(
        **{f: np.concatenate([getattr(r1, f), getattr(r2, f)], axis=len(batch))
           for f in ("mean", "cov", "position", "observed", "mu", "model_mean", "model_cov",
                     "model_observed", "log_likelihood", "model_innovation", "model_distance")}
    )  # fmt: skip
    _assert_results_equal(joined, res)
    np.testing.assert_array_equal(s2.x, state_b.x)


def test_batched_equals_loop_over_elements(rng):
    m1 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 2.0, 0.001)
    imm = IMM(m1, m2, transition=ASYM)
    batch, T = (3, 2), 40
    z = _series(rng, batch, T)
    prev = _ext_posteriors(rng, z)
    _, res = imm.filter(z, prev=prev)
    for idx in np.ndindex(*batch):
        _, r = imm.filter(z[idx], prev=(prev[0][idx], prev[1][idx]))
        for f in ("mean", "cov", "mu", "model_mean", "log_likelihood"):
            np.testing.assert_array_equal(getattr(res, f)[idx], getattr(r, f), err_msg=f)


def test_prev_changes_the_result_only_in_reading_r2(rng):
    m1 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 0.5, 0.001)
    z = _series(rng, (), 30)
    prev = _ext_posteriors(rng, z)
    _, r_own = IMM(m1, m2).filter(z)
    _, r_ext = IMM(m1, m2).filter(z, prev=prev)
    assert np.abs(r_own.mean - r_ext.mean).max() > 1e-4
    with pytest.raises(InputError, match="R1"):
        IMM(m1, m2, reading="R1").filter(z, prev=prev)


def test_lag_posteriors_shifts_by_one():
    x = np.arange(2 * 4 * 2 * 3, dtype=float).reshape(2, 4, 2, 3)
    P = np.ones((2, 4, 2, 3, 3))
    xp, Pp = lag_posteriors(x, P)
    assert np.all(np.isnan(xp[:, 0])) and np.all(np.isnan(Pp[:, 0]))
    np.testing.assert_array_equal(xp[:, 1:], x[:, :-1])


# ---------------------------------------------------------------------------- validation
def test_construction_and_state():
    m = constant_velocity(DT, 0.5, 0.01)
    imm = IMM(m, m)
    assert imm.models == (m, m) and imm.n_models == 2 and imm.n_x == 6 and imm.n_z == 3
    imm3 = IMM(models=[m, m, m], transition=np.full((3, 3), 1 / 3))
    np.testing.assert_allclose(imm3.mu0, [1 / 3] * 3)
    st = imm.init(batch_shape=(4,), mean=np.zeros(6))
    assert isinstance(st, IMMState)
    assert st.x.shape == (4, 2, 6) and st.P.shape == (4, 2, 6, 6) and st.mu.shape == (4, 2)
    assert st.initialized.all()
    with pytest.raises(ValueError):  # read-only configuration
        imm.transition[0, 0] = 0.5
    changed = dataclasses.replace(imm, transition=ASYM)
    assert changed.models == imm.models
    np.testing.assert_array_equal(changed.transition, ASYM)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(transition=[[0.9, 0.2], [0.1, 0.9]]), "rows summing to 1"),
        (dict(transition=[[1.1, -0.1], [0.1, 0.9]]), ">= 0"),
        (dict(transition=np.eye(3)), r"shape \(2, 2\)"),
        (dict(mu0=(0.6, 0.6)), "summing to 1"),
        (dict(mu0=(1.0,)), "mu0"),
        (dict(mu_floor=0.5), "mu_floor"),
        (dict(mu_floor=-1e-3), "mu_floor"),
        (dict(reading="R3"), "reading"),
    ],
)
def test_bad_configuration(kwargs, match):
    m = constant_velocity(DT, 0.5, 0.01)
    with pytest.raises(InputError, match=match):
        IMM(m, m, **kwargs)


def test_bad_models_and_inputs():
    m3 = constant_velocity(DT, 0.5, 0.01)
    m2 = constant_velocity(DT, 0.5, 0.01, n_axes=2)
    with pytest.raises(InputError, match="n_x, n_z"):
        IMM(m3, m2)
    with pytest.raises(InputError, match="either"):
        IMM(m3, m3, models=[m3, m3, m3])
    with pytest.raises(InputError, match="two models"):
        IMM(m3)
    with pytest.raises(InputError, match="at least 2"):
        IMM(models=[m3])
    imm = IMM(m3, m3)
    with pytest.raises(InputError, match=r"\(\.\.\., T, 2, 3\)"):
        imm.filter(np.zeros((10, 3)))
    with pytest.raises(InputError, match="shape"):
        imm.step(imm.init(), np.zeros(3))
    with pytest.raises(InputError, match="x_prev"):
        imm.filter(np.zeros((10, 2, 3)), prev=(np.zeros((10, 6)), np.zeros((10, 2, 6, 6))))
    with pytest.raises(InputError, match="batch shape"):
        imm.filter(np.zeros((4, 10, 2, 3)), state=imm.init(batch_shape=(3,)))


def test_run_inplace_without_per_model_outputs_gives_the_same_combined_output():
    """``per_model=False`` (paper B's core: the per-model outputs are most of the memory) skips
    only the per-model fields: the combined output and the updated state are byte-identical."""

    rng = np.random.default_rng(8)
    imm = IMM(constant_velocity(1 / 30, q=0.5, r=1e-3), constant_velocity(1 / 30, q=0.5, r=4e-3))
    z = np.cumsum(rng.normal(0, 0.01, (3, 120, 2, 3)), axis=1)
    z[:, 30:50, 1] = np.nan
    z[1, :8] = np.nan

    def run(per_model):
        s = imm.init((3,))
        x, P, mu, init = s.x.copy(), s.P.copy(), s.mu.copy(), s.initialized.copy()
        r = imm._run_inplace(np.ascontiguousarray(z), None, x, P, mu, init, per_model=per_model)
        return r, (x, P, mu, init)

    full, s_full = run(True)
    lean, s_lean = run(False)
    for name in ("mean", "cov", "position", "observed", "mu", "model_observed"):
        assert getattr(lean, name).tobytes() == getattr(full, name).tobytes(), name
    for a, b in zip(s_lean, s_full, strict=True):
        assert a.tobytes() == b.tobytes()
    assert lean.model_cov is None and lean.log_likelihood is None
    assert full.model_cov.shape == (3, 120, 2, 6, 6)


def test_position_is_h_times_mean_for_selection_and_general_h():
    """``position`` is ``H x̂``: taken by column selection when H is a 0/1 selection matrix
    (the matrix product is the oracle), by the product otherwise."""
    from kinefuse.filters.imm import _selected_columns

    cv = constant_velocity(1 / 30, q=0.5, r=1e-3)
    np.testing.assert_array_equal(_selected_columns(cv.H), [0, 2, 4])
    for H in (2.0 * cv.H, cv.H + np.eye(3, 6, 1), 0.5 * np.ones((3, 6))):
        assert _selected_columns(H) is None
    rng = np.random.default_rng(3)
    z = np.stack([_trajectory(rng, 50), _trajectory(rng, 50)], axis=-2)  # (T, M=2, 3)
    res = IMM(cv, cv).filter(z)[1]
    np.testing.assert_array_equal(res.position, res.mean @ cv.H.T)
    # every field is set, as by the dataclass constructor (generic ones None)
    assert res.cov.shape == (50, 6, 6) and res.model_mean.shape == (50, 2, 6)
    assert res.innovation is None and res.mode is None and res.cov_blocks is None
    assert dataclasses.replace(res, mu=None).cov is res.cov
