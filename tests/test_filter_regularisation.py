"""Every filter says when it had to regularise a covariance (SPEC §13), once per call.

One Cholesky routine (``_kernels_linalg.chol_status``) returns a status; the dense KF, the RTS
smoother, the IMM and the EM-KF turn a regularised factorisation into ONE NumericalWarning per
call. The inputs below make the predicted covariance indefinite by a hair (eigenvalue −1e-13
next to O(1) ones), which the ε·tr/n·I ladder repairs.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from kinefuse.exceptions import NumericalWarning
from kinefuse.filters import IMM, EMKalmanFilter, FilterResult, KalmanFilter, fixed_lag_smooth
from kinefuse.filters._kernels_linalg import (
    CHOL_FAILED,
    CHOL_OK,
    CHOL_REGULARISED,
    chol_regularised,
)
from kinefuse.models import constant_velocity

DT = 1.0 / 30.0


def _cov_giving(model, Pp):
    """``P`` with ``F P Fᵀ + Q = Pp``."""
    Finv = np.linalg.inv(model.F)
    return Finv @ (Pp - model.Q) @ Finv.T


def _indefinite_S_state(model):
    """A posterior whose next innovation covariance ``S = H P⁻ Hᵀ + R`` is diag(1, 1, −1e-13)."""
    Pp = np.eye(6)
    S = np.diag([1.0, 1.0, -1e-13])
    Pp[np.ix_([0, 2, 4], [0, 2, 4])] = S - model.R
    return _cov_giving(model, Pp)


def _with_cov(state, P):
    """``state`` holding the covariance ``P`` in every element: a posterior no ``init`` gives
    (``init`` refuses a covariance that is not positive semi-definite)."""
    return state._replace(P=np.broadcast_to(P, state.P.shape).copy())


def _regularisation_warnings(record):
    return [
        w
        for w in record
        if issubclass(w.category, NumericalWarning) and "regularised" in str(w.message)
    ]


def test_chol_status_values():
    L = np.zeros((3, 3))
    assert chol_regularised(np.eye(3), L, 3) == CHOL_OK
    assert chol_regularised(np.diag([1.0, 1.0, -1e-13]), L, 3) == CHOL_REGULARISED
    assert chol_regularised(-np.eye(3), L, 3) == CHOL_FAILED


def test_dense_kalman_warns_once_per_call():
    m = constant_velocity(DT, q=1.0, r=1e-2)
    kf = KalmanFilter(m, method="dense")
    state = _with_cov(kf.init((2,), mean=np.zeros(6)), _indefinite_S_state(m))
    z = np.zeros((2, 3, 3))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        kf.filter(z, state)
    hits = _regularisation_warnings(rec)
    assert len(hits) == 1 and "KalmanFilter" in str(hits[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NumericalWarning)
        kf.filter(z)  # a well-posed call says nothing


def test_rts_warns_once_per_call():
    m = constant_velocity(DT, q=1.0, r=1e-2)
    Pp = np.eye(6)
    Pp[np.ix_([0, 2, 4], [0, 2, 4])] = np.array(
        [[1.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, -1e-13]]
    )
    cov = np.broadcast_to(_cov_giving(m, Pp), (4, 6, 6)).copy()  # not axis-blocked: dense RTS
    res = FilterResult(
        mean=np.zeros((4, 6)), cov=cov, position=np.zeros((4, 3)), observed=np.ones(4, bool),
        innovation=None, distance=None,
    )  # fmt: skip
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        fixed_lag_smooth(m, res, 2)
    hits = _regularisation_warnings(rec)
    assert len(hits) == 1 and "RTS" in str(hits[0].message)


def test_imm_warns_once_per_call():
    m = constant_velocity(DT, q=1.0, r=1e-2)
    imm = IMM(m, m)
    state = _with_cov(imm.init((2,), mean=np.zeros(6)), _indefinite_S_state(m))
    z = np.zeros((2, 3, 2, 3))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        imm.filter(z, state)
    hits = _regularisation_warnings(rec)
    assert len(hits) == 1 and "IMM" in str(hits[0].message)


@pytest.mark.parametrize("n_iter", [1, 3])
def test_em_kf_regularisation_warns_once_per_call(n_iter):
    m = constant_velocity(DT, q=1.0, r=1e-2)
    f = EMKalmanFilter(m, n_iter=n_iter)
    st = _with_cov(f.init((2,), mean=np.zeros(6)), _indefinite_S_state(m))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        f.filter(np.zeros((2, 3, 3)), st)
    hits = _regularisation_warnings(rec)
    assert len(hits) == 1 and "EMKalmanFilter" in str(hits[0].message)
