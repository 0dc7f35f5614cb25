"""The filters' trusted fast path (``_filter_unchecked``, KF's own-state ``step``) equals the
checked public path bit for bit, and the checked path still refuses foreign or broken states."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from kinefuse.exceptions import InputError
from kinefuse.filters import (
    IMM,
    EMKalmanFilter,
    GaussianState,
    IntegratedFilter,
    KalmanFilter,
    UFIRFilter,
    UFIRState,
)
from kinefuse.filters._kernels_axis import state_blocks_shared
from kinefuse.models import constant_velocity
from kinefuse.pipelines.paper_b import PaperBCore
from kinefuse.pipelines.vision_params import VisionParams
from kinefuse.streaming.paper_b import VisionAssistedProcessor

DT = 1.0 / 30.0
MODEL = constant_velocity(DT, q=1.0, r=1e-2)
MODEL_CAM = constant_velocity(DT, q=1.0, r=4e-4)


def _data(seed=0, B=3, T=90):
    rng = np.random.default_rng(seed)
    z = np.cumsum(rng.normal(scale=0.02, size=(B, T, 3)), axis=1)
    z[:, rng.random(T) < 0.1] = np.nan
    z[1, :5] = np.nan  # starts late
    z[2, 40:60] = np.nan  # a gap longer than the UFIR horizon
    return z


FILTERS = {
    "kf": lambda: KalmanFilter(MODEL),
    "kf-dense": lambda: KalmanFilter(MODEL, method="dense"),
    "ufir": lambda: UFIRFilter(MODEL, horizon=12),
    "ufir-stored": lambda: UFIRFilter(MODEL, horizon=12, init="stored"),
    "em-kf": lambda: EMKalmanFilter(MODEL, n_iter=3),
    "integrated": lambda: IntegratedFilter(MODEL, horizon=12),
}

FIELDS = ("mean", "cov", "position", "observed", "innovation", "distance", "fir_ready", "mode")


def _assert_same(a, b):
    for name in FIELDS:
        va, vb = getattr(a, name, None), getattr(b, name, None)
        if va is None and vb is None:
            continue
        np.testing.assert_array_equal(va, vb, err_msg=name)


def _assert_same_state(a, b):
    assert type(a) is type(b)
    for va, vb in zip(a, b, strict=True):
        np.testing.assert_array_equal(va, vb)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_unchecked_filter_equals_checked_filter_in_blocks(name):
    flt = FILTERS[name]()
    z = _data()
    s_chk = s_fast = flt.init((3,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for a, b in ((0, 8), (8, 9), (9, 30), (30, 31), (31, 90)):
            s_chk, r_chk = flt.filter(z[:, a:b], s_chk)
            s_fast, r_fast = flt._filter_unchecked(z[:, a:b], s_fast)
            _assert_same(r_chk, r_fast)
    _assert_same_state(s_chk, s_fast)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_unchecked_frames_equal_checked_steps(name):
    flt = FILTERS[name]()
    z = _data(seed=1)
    s_chk = s_fast = flt.init((3,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t in range(z.shape[1]):
            s_chk, r_chk = flt.step(s_chk, z[:, t])
            s_fast, r_fast = flt._filter_unchecked(z[:, t : t + 1], s_fast)
            for f in ("mean", "cov", "position", "observed", "innovation"):
                np.testing.assert_array_equal(getattr(r_chk, f), getattr(r_fast, f)[:, 0])
    for va, vb in zip(s_chk, s_fast, strict=True):
        np.testing.assert_array_equal(va, vb)


def test_imm_unchecked_equals_checked_with_prev():
    imm = IMM(MODEL, MODEL_CAM)
    z = np.stack([_data(seed=2), _data(seed=3)], axis=-2)  # (B, T, M, n_z)
    kf = KalmanFilter(MODEL)
    _, r = kf.filter(np.nan_to_num(z[..., 0, :], nan=0.0))
    xp = np.stack([r.mean, r.mean], axis=-2)
    Pp = np.stack([r.cov, r.cov], axis=-3)
    xp[:, ::7] = np.nan
    s_chk = s_fast = imm.init((3,))
    for a, b in ((0, 1), (1, 40), (40, 90)):
        prev = (xp[:, a:b], Pp[:, a:b])
        s_chk, r_chk = imm.filter(z[:, a:b], s_chk, prev=prev)
        s_fast, r_fast = imm._filter_unchecked(z[:, a:b], s_fast, prev=prev)
        for f in ("mean", "cov", "position", "observed", "mu", "model_mean", "log_likelihood"):
            np.testing.assert_array_equal(getattr(r_chk, f), getattr(r_fast, f), err_msg=f)
    _assert_same_state(s_chk, s_fast)


def test_kf_own_state_step_equals_validated_step():
    """KF.step skips the state checks for a state it produced: the same numbers as a step from
    the same state passed as a plain (validated) GaussianState."""
    kf = KalmanFilter(MODEL)
    z = _data(seed=4)
    st = kf.init((3,))
    for t in range(z.shape[1]):
        own, r_own = kf.step(st, np.ascontiguousarray(z[:, t]))
        plain, r_plain = kf.step(GaussianState(*st), z[:, t].tolist())
        for f in ("mean", "cov", "position", "observed", "innovation", "distance"):
            np.testing.assert_array_equal(getattr(r_own, f), getattr(r_plain, f), err_msg=f)
        for va, vb in zip(own, plain, strict=True):
            np.testing.assert_array_equal(va, vb)
        st = own


# ------------------------------------------------------------------ the checked path refuses
@pytest.mark.parametrize("name", ["ufir", "em-kf", "integrated"])
def test_checked_path_refuses_a_foreign_state(name):
    flt = FILTERS[name]()
    z = _data()
    foreign = KalmanFilter(MODEL).init((3,))
    with pytest.raises(InputError, match=r"expected state as a \w+State"):
        flt.step(foreign, z[:, 0])
    with pytest.raises(InputError, match=r"expected state as a \w+State"):
        flt.filter(z, foreign)
    with pytest.raises(InputError, match="expected state as a"):
        flt.step(("not", "a", "state"), z[:, 0])


@pytest.mark.parametrize("name", ["ufir", "em-kf", "integrated"])
def test_checked_path_refuses_a_broken_state(name):
    flt = FILTERS[name]()
    z = _data()
    st = flt.init((3,))
    broken = st._replace(x=np.zeros((3, 4)))
    with pytest.raises(InputError, match=r"state\.x with shape"):
        flt.step(broken, z[:, 0])
    with pytest.raises(InputError, match="batch shape"):
        flt.filter(z[:2], st)


def test_kf_checked_path_refuses_garbage():
    kf = KalmanFilter(MODEL)
    z = _data()
    st, _ = kf.step(kf.init((3,)), np.ascontiguousarray(z[:, 0]))
    with pytest.raises(InputError, match="expected state as a GaussianState"):
        kf.step(tuple(st), z[:, 1])
    bad = GaussianState(st.x, np.full_like(st.P, np.nan), np.ones(3, bool), 1)
    with pytest.raises(InputError, match="finite state"):
        kf.step(bad, z[:, 1])
    with pytest.raises(InputError, match=r"state\.P with shape"):
        kf.step(GaussianState(st.x, st.P[:, :4, :4], st.initialized, 1), z[:, 1])
    # the filter's own state with an unusual z still goes through the checks
    with pytest.raises(InputError, match="shape"):
        kf.step(st, z[:2, 1])
    with pytest.raises(InputError, match="±inf"):
        kf.step(st, np.full((3, 3), np.inf))


def test_imm_checked_path_refuses_garbage():
    imm = IMM(MODEL, MODEL_CAM)
    z = np.zeros((3, 2, 3))
    with pytest.raises(InputError, match="IMMState"):
        imm.step(KalmanFilter(MODEL).init((3,)), z)
    st = imm.init((3,))
    with pytest.raises(InputError, match="state arrays with shapes"):
        imm.step(st._replace(mu=np.ones((3, 3)) / 3), z)


def test_paper_b_core_and_processor_refuse_inf():
    core = PaperBCore("elm-fir", VisionParams(), DT)
    state = core.init(2)
    zi = np.zeros((2, 1, 3))
    zi[1, 0, 2] = np.inf
    with pytest.raises(InputError, match="finite or NaN"):
        core.advance(state, zi, np.zeros((2, 1, 3)), np.ones((2, 1), bool))
    proc = VisionAssistedProcessor("elm-fir")
    with pytest.raises(InputError, match="finite or NaN"):
        proc.step(0.0, zi[:, 0], np.zeros((2, 3)), np.ones(2, bool))


def test_own_state_marks_are_dropped_by_replace():
    """UFIR's constant-velocity route and the KF's per-axis path mark the states they return
    (trusted on the next call); ``_replace`` gives a plain state, which is checked again."""
    z = _data(seed=5)
    ufir = UFIRFilter(MODEL, horizon=12)
    st, _ = ufir.filter(z[:, :50])
    assert type(st) is not UFIRState and isinstance(st, UFIRState)  # marked
    n_x = MODEL.n_x
    assert state_blocks_shared(st.P.reshape(-1, n_x, n_x), st.initialized.reshape(-1))
    plain = st._replace(k=st.k)
    assert type(plain) is UFIRState
    _, r_marked = ufir.filter(z[:, 50:], st)
    _, r_plain = ufir.filter(z[:, 50:], plain)
    _assert_same(r_marked, r_plain)
    kf = KalmanFilter(MODEL)
    st, _ = kf.filter(z[:, :50])
    assert type(st) is not GaussianState and isinstance(st, GaussianState)
    assert type(st._replace(k=0)) is GaussianState
