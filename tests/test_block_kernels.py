"""Fast kernels against their references: KF/RTS on covariance blocks, O(1) UFIR, floor clip.

The references are the dense kernels (``method="dense"``), the iterative UFIR (``fast=False``),
filterpy's ``rts_smoother`` and LAPACK's ``eigh`` (``floor_clip_lapack``).
"""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.exceptions import InputError
from kinefuse.filters import KalmanFilter, UFIRFilter, rts_smooth
from kinefuse.filters._base import expand_cov_blocks
from kinefuse.filters._kernels_linalg import floor_clip, floor_clip_lapack
from kinefuse.models import constant_velocity
from test_kalman import random_cv, simulate, with_gaps

# compiles general-route kernels that `kinefuse warm-up` does not: one worker (tests/conftest.py)
pytestmark = pytest.mark.xdist_group("oracle-kernels")

ALL = ("mean", "cov", "position", "observed", "innovation", "distance")


def _data(seed, model, B=4, T=160):
    rng = np.random.default_rng(seed)
    _, z = simulate(model, rng, T, batch=(B,))
    return with_gaps(rng, z)


@pytest.mark.parametrize("isotropic", [True, False])
def test_kf_blocks_equal_dense_reference(isotropic):
    rng = np.random.default_rng(1)
    model = (
        constant_velocity(1 / 30, q=0.7, r=0.004) if isotropic else random_cv(rng)
    )  # shared block / one block per axis
    z = _data(2, model)
    _, fast = KalmanFilter(model).filter(z)
    _, ref = KalmanFilter(model, method="dense").filter(z)
    assert fast.cov_blocks is not None and ref.cov_blocks is None
    assert (fast.cov_blocks.strides[-2] == 0) == isotropic  # one stored block when shared
    for name in ALL:
        np.testing.assert_allclose(
            getattr(fast, name), getattr(ref, name), rtol=1e-12, atol=1e-12, err_msg=name
        )


def test_kf_outputs_subset_and_blocks_layout():
    model = constant_velocity(1 / 30, q=0.7, r=0.004)
    z = _data(3, model)
    kf = KalmanFilter(model)
    s_all, r_all = kf.filter(z)
    s_sub, r_sub = kf.filter(z, outputs=("position", "cov"))
    assert r_sub.mean is None and r_sub.innovation is None and r_sub.observed is None
    np.testing.assert_array_equal(r_sub.position, r_all.position)
    np.testing.assert_array_equal(r_sub.cov_blocks, r_all.cov_blocks)
    np.testing.assert_array_equal(s_sub.P, s_all.P)
    cb = r_all.cov_blocks
    full = r_all.cov
    assert full.shape == (*z.shape[:-1], 6, 6)
    np.testing.assert_array_equal(full[..., 2, 3], cb[..., 1, 1])  # documented layout
    np.testing.assert_array_equal(expand_cov_blocks(cb), full)
    with pytest.raises(InputError, match="outputs"):
        kf.filter(z, outputs=("speed",))


@pytest.mark.parametrize(
    ("isotropic", "batch"), [(False, (8,)), (True, (8,)), (True, (2, 4)), (False, ())]
)
def test_kf_step_fast_path_equals_filter_and_split(isotropic, batch):
    """Both kernels of the step (one shared recursion for isotropic models, per axis
    otherwise) and the flat / reshaped batch layouts give the batch filter's numbers."""
    rng = np.random.default_rng(4)
    model = constant_velocity(1 / 30, q=0.7, r=0.004) if isotropic else random_cv(rng)
    z = _data(5, model, B=8, T=60).reshape(*batch, 60, 3) if batch else _data(5, model, 1, 60)[0]
    kf = KalmanFilter(model)
    s_all, r_all = kf.filter(z)
    st = kf.init(batch)
    means, covs, dists, pos = [], [], [], []
    for t in range(z.shape[-2]):
        st, out = kf.step(st, np.ascontiguousarray(z[..., t, :]))
        means.append(out.mean)
        covs.append(out.cov)
        dists.append(out.distance)
        pos.append(out.position)
    ax = len(batch)
    np.testing.assert_array_equal(np.stack(means, ax), r_all.mean)
    np.testing.assert_array_equal(np.stack(covs, ax), r_all.cov)
    np.testing.assert_array_equal(np.stack(dists, ax), r_all.distance)
    np.testing.assert_array_equal(np.stack(pos, ax), r_all.position)
    np.testing.assert_array_equal(st.P, s_all.P)
    if batch != (8,):
        return
    s1, r1 = kf.filter(z[:, :25])
    s2, r2 = kf.filter(z[:, 25:], state=s1)
    np.testing.assert_array_equal(np.concatenate([r1.mean, r2.mean], 1), r_all.mean)
    np.testing.assert_array_equal(s2.x, s_all.x)
    bad = np.ascontiguousarray(z[:, 0])
    bad[0, 0] = np.inf
    with pytest.raises(InputError, match="inf"):
        kf.step(st, bad)
    with pytest.raises(InputError, match="inf"):
        kf.filter(np.where(np.isnan(z), np.inf, z))


@pytest.mark.parametrize("isotropic", [True, False])
def test_rts_blocks_equal_filterpy_and_dense(isotropic):
    from filterpy.kalman import rts_smoother

    rng = np.random.default_rng(6)
    model = constant_velocity(1 / 30, q=0.7, r=0.004) if isotropic else random_cv(rng)
    z = _data(7, model, B=2, T=120)
    z[:, 0] = np.where(np.isnan(z[:, 0]), 0.0, z[:, 0])  # initialised from sample 0
    _, res = KalmanFilter(model).filter(z)
    sm = rts_smooth(model, res)
    assert sm.cov_blocks is not None
    # dense path: the same filtered result with full covariances only
    dense_in = type(res)(mean=res.mean, cov=res.cov, position=res.position, observed=res.observed)
    sm_dense = rts_smooth(model, dense_in)
    np.testing.assert_allclose(sm.mean, sm_dense.mean, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(sm.cov, sm_dense.cov, rtol=1e-11, atol=1e-15)
    np.testing.assert_allclose(sm.position, sm_dense.position, rtol=1e-12, atol=1e-13)
    for b in range(z.shape[0]):
        n = z.shape[1]
        xs, Ps, _, _ = rts_smoother(res.mean[b], res.cov[b], [model.F] * n, [model.Q] * n)
        np.testing.assert_allclose(sm.mean[b], xs, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sm.cov[b], Ps, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize(("N", "missing"), [(10, 0.05), (40, 0.02), (200, 0.02), (60, 0.3)])
def test_ufir_cv_covariance_closed_form_equals_iterative(N, missing):
    """Scattered missing samples: nearly every horizon has a gap, so the covariance comes from
    the O(1) closed form (``_kernels_ufir_cov``) almost everywhere; the literal 6x6 iterative
    UFIR is the oracle. Tolerance: the iterative Joseph recursion runs up to N steps, each
    rounding at ~1e-16 relative on a well-conditioned 2x2 block."""
    rng = np.random.default_rng(N)
    model = constant_velocity(1 / 30, q=0.7, r=0.004)
    z = _data(N, model, B=2, T=2 * N + 90)
    z[:, rng.random(z.shape[1]) < missing] = np.nan  # frame-wide dropouts
    z[1, rng.random(z.shape[1]) < missing] = np.nan  # and element-specific ones
    z[:, 0] = np.where(np.isnan(z[:, 0]), 0.0, z[:, 0])
    f = UFIRFilter(model, horizon=N)
    _, fast = f.filter(z)
    _, ref = f._run(z, f.init(z.shape[:1]), fast=False)
    incomplete = ~np.isfinite(z).all(-1)
    horizon_gap = np.array([[incomplete[b, max(0, k - N + 1) : k + 1].any() for k in range(z.shape[1])] for b in range(2)])  # fmt: skip
    assert (fast.fir_ready & horizon_gap).sum() > z.shape[1] // 2  # the closed form is exercised
    np.testing.assert_array_equal(fast.fir_ready, ref.fir_ready)
    np.testing.assert_allclose(fast.cov, ref.cov, rtol=1e-9, atol=1e-14)
    # split mid-block: the same covariance (to rounding: the last step of a call is iterative)
    s1, r1 = f.filter(z[:, : N + 7])
    _, r2 = f.filter(z[:, N + 7 :], state=s1)
    np.testing.assert_allclose(np.concatenate([r1.cov, r2.cov], 1), fast.cov, rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("N", [10, 40])
def test_ufir_constant_velocity_o1_equals_iterative(N):
    model = constant_velocity(1 / 30, q=0.7, r=0.004)
    z = _data(8 + N, model, B=3, T=4 * N + 30)
    z[1, N + 5 : 2 * N + 2] = np.nan  # outage longer than N - K: KF fallback inside the series
    f = UFIRFilter(model, horizon=N)
    assert "cv" in f._arrays
    state, fast = f.filter(z)
    s_ref, ref = f._run(z, f.init(z.shape[:1]), fast=False)  # dense iterative reference
    np.testing.assert_array_equal(fast.fir_ready, ref.fir_ready)
    np.testing.assert_allclose(fast.mean, ref.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.cov, ref.cov, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(state.P, s_ref.P, rtol=1e-9, atol=1e-14)
    # no covariance wanted: same estimates and state, bit for bit
    s_nc, r_nc = f.filter(z, outputs=("mean",))
    assert r_nc.cov_blocks is None and r_nc.position is None
    np.testing.assert_array_equal(r_nc.mean, fast.mean)
    np.testing.assert_array_equal(s_nc.P, state.P)
    # split anywhere (mid block of N samples) == one run, bit for bit
    cut = N + N // 2 + 1
    s1, r1 = f.filter(z[:, :cut])
    s2, r2 = f.filter(z[:, cut:], state=s1)
    np.testing.assert_array_equal(np.concatenate([r1.mean, r2.mean], 1), fast.mean)
    np.testing.assert_array_equal(s2.x, state.x)


def test_floor_clip_equals_lapack_reference():
    rng = np.random.default_rng(9)
    for n in (3, 6):
        for k in range(200):
            X = rng.normal(size=(n, n))
            nom = X @ X.T + 0.1 * np.eye(n)
            Y = rng.normal(size=(n, n))
            if k % 3 == 0:  # near the floor and nearly isotropic (close eigenvalues)
                A = nom * rng.uniform(1e-4, 2e-3) + 10 ** rng.uniform(-12, -3) * (Y @ Y.T)
            else:
                A = Y @ Y.T * rng.uniform(1e-6, 1)
            a1, a2 = A.copy(), A.copy()
            assert floor_clip(a1, nom, 1e-3, n) and floor_clip_lapack(a2, nom, 1e-3, n)
            np.testing.assert_allclose(a1, a2, rtol=0, atol=1e-10 * np.abs(a2).max())


@pytest.mark.parametrize("shared", [True, False])
def test_expand_cov_blocks_equals_explicit_blocks(shared):
    """Oracle: the full matrix written block by block with Python loops; a NaN block (an
    element without a state) makes its whole matrix NaN; off-block zeros are +0.0."""
    rng = np.random.default_rng(11)
    n_a, lead = 3, (4, 5)
    own = rng.normal(size=(*lead, 1 if shared else n_a, 3))
    own[1, 2] = np.nan
    cb = np.broadcast_to(own, (*lead, n_a, 3)) if shared else own
    want = np.zeros((*lead, 2 * n_a, 2 * n_a))
    for idx in np.ndindex(*lead):
        for a in range(n_a):
            p00, p01, p11 = cb[idx][a]
            want[idx][2 * a : 2 * a + 2, 2 * a : 2 * a + 2] = [[p00, p01], [p01, p11]]
        if np.isnan(cb[idx]).any():
            want[idx] = np.nan
    got = expand_cov_blocks(cb)
    np.testing.assert_array_equal(got, want)
    finite = np.isfinite(got)
    assert not np.signbit(got[finite & (want == 0)]).any()


@pytest.mark.parametrize("q", [0.7, 30.0])
def test_kf_three_axis_pass_equals_the_general_pass_bit_for_bit(q):
    """The 3-D shared-covariance pass (state in registers, element by element) against the
    general per-axis pass on the same inputs: every output and the state, byte for byte
    (missing rows, an element that starts late, negative positions)."""
    from kinefuse.filters._kernels_blocks import _kf_pass, kf_filter_blocks

    model = constant_velocity(1 / 30, q=q, r=0.004)
    z = _data(3, model, B=5, T=300)
    z[1, :40] = np.nan
    z[2] *= -1.0
    kf = KalmanFilter(model)
    par, p0, shared = kf._packed
    assert shared and par.shape[0] == 3  # the case the 3-axis pass serves
    st = kf.init((5,))
    B, T, _ = z.shape

    def run(general):
        x, P, init = st.x.copy(), st.P.copy(), st.initialized.copy()
        outs = [np.empty((B, T, 6)), np.empty((B, T, 1, 3)), np.empty((B, T, 3)),
                np.empty((B, T), bool), np.empty((B, T, 3)), np.empty((B, T))]  # fmt: skip
        if general:
            _kf_pass(
                z, x.copy(), P.copy(), init.copy(), x, P, init, 0, 3, 0, *par[0], *p0[0], *outs
            )
        else:
            kf_filter_blocks(z, x, P, init, par, p0[:1], *outs)
        return [*outs, x, P, init]

    for got, want in zip(run(False), run(True), strict=True):
        assert got.tobytes() == want.tobytes()


def test_rts_three_axis_pass_equals_the_general_pass_bit_for_bit():
    """The 3-D shared-block RTS pass against the general pass run on the same block repeated
    per axis (which the module documents as the same arithmetic): smoothed means, blocks and
    positions byte for byte, with mask gaps, a sample without a state and a step whose
    P⁻ is not positive definite (the restart)."""
    from kinefuse.filters._kernels_blocks import rts_blocks

    model = constant_velocity(1 / 30, q=0.7, r=0.004)
    z = _data(5, model, B=4, T=250)
    kf = KalmanFilter(model)
    _, res = kf.filter(z, outputs=("mean", "cov"))
    par = kf._packed[0]
    mean = np.array(res.mean)
    cb1 = np.array(res.cov_blocks[:, :, :1])  # the shared block (a writable copy)
    cb1[2, 120] = [-1.0, 0.0, 1.0]  # not positive definite: the pass restarts there
    mean[3, 60] = np.nan
    mask = np.ones(mean.shape[:2], bool)
    mask[1, 100:110] = False

    def run(cb):
        B, T, n_c = cb.shape[:3]
        out = (np.empty_like(mean), np.empty((B, T, n_c, 3)), np.empty((B, T, 3)))
        rts_blocks(mean, cb, mask, par, *out)
        return out

    m1, c1, p1 = run(cb1)
    m3, c3, p3 = run(np.ascontiguousarray(np.repeat(cb1, 3, axis=2)))
    assert m1.tobytes() == m3.tobytes() and p1.tobytes() == p3.tobytes()
    assert c1[:, :, 0].tobytes() == np.ascontiguousarray(c3[:, :, 0]).tobytes()


def test_ufir_cv_shared_missing_pattern_equals_one_element_at_a_time():
    """Elements with the previous element's missing pattern copy its covariance blocks; the
    oracle is each element filtered alone (nothing to share), resumed from its own state.
    Element 2 differs from element 1 by one missing sample after the split, element 4 from
    element 3 by the samples before it (in its ring), element 1 from element 0 by its starting
    covariance only (the closed form does not depend on it): 2 and 4 must compute their own."""
    from kinefuse.filters.ufir import UFIRState

    N = 40
    rng = np.random.default_rng(5)
    model = constant_velocity(1 / 30, q=0.7, r=0.004)
    _, z_all = simulate(model, rng, 4 * N, batch=(5,))
    z = z_all.copy()
    z[:, rng.random(z.shape[1]) < 0.05] = np.nan  # frame-wide dropouts: one pattern
    z[:, 0] = np.where(np.isnan(z[:, 0]), 0.0, z[:, 0])
    cut = N + 9
    z[2, cut + N // 2, 1] = np.nan  # one element-specific sample after the split
    z[4, : cut - 1] = np.nan  # element 4: another ring at the split
    z[4, cut - 1] = z_all[4, cut - 1]
    f = UFIRFilter(model, horizon=N)
    s1, _ = f.filter(z[:, :cut])
    s1.P[1] *= 3.0  # the fallback KF's start, not the closed form's
    state, res = f.filter(z[:, cut:], state=s1)
    assert np.isfinite(res.cov[2, N // 2]).all() and np.isfinite(res.cov[4, N // 2]).all()
    for b in range(5):
        sb = UFIRState(*(a if np.isscalar(a) else a[b : b + 1] for a in s1))
        st_b, r_b = f.filter(z[b : b + 1, cut:], state=sb)
        np.testing.assert_array_equal(res.cov[b], r_b.cov[0])
        np.testing.assert_array_equal(res.mean[b], r_b.mean[0])
        np.testing.assert_array_equal(state.P[b], st_b.P[0])
    assert not np.array_equal(res.cov[2], res.cov[1]) and not np.array_equal(res.cov[4], res.cov[3])
    np.testing.assert_array_equal(res.cov[1], res.cov[0])  # same pattern: the same blocks
