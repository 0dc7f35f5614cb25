"""OnlineFilter: update == filter, checkpoint/restore, generic filter objects, bad input."""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pytest

from kinefuse.filters import IMM, KalmanFilter, OnlineFilter
from kinefuse.models import constant_velocity


def _data(rng, T=150, batch=(3,)):
    z = np.cumsum(rng.normal(scale=0.02, size=(*batch, T, 3)), axis=-2)
    z[..., rng.random(T) < 0.1, :] = np.nan
    z[0, :4] = np.nan  # one element starts with an outage
    return z


def test_update_equals_filter(rng):
    kf = KalmanFilter(constant_velocity(1 / 30, q=1.0, r=0.01))
    z = _data(rng)
    state, res = kf.filter(z)
    online = OnlineFilter(kf)
    assert online.state is None
    outs = [online.update(z[:, t]) for t in range(z.shape[1])]
    np.testing.assert_array_equal(np.stack([o.mean for o in outs], axis=1), res.mean)
    np.testing.assert_array_equal(np.stack([o.cov for o in outs], axis=1), res.cov)
    np.testing.assert_array_equal(np.stack([o.distance for o in outs], axis=1), res.distance)
    np.testing.assert_array_equal(np.stack([o.observed for o in outs], axis=1), res.observed)
    np.testing.assert_array_equal(online.state.x, state.x)
    assert online.n_updates == z.shape[1] and online.state.k == z.shape[1]


def test_checkpoint_restore_continues_identically(rng):
    kf = KalmanFilter(constant_velocity(1 / 30, q=0.5, r=0.02))
    z = _data(rng, T=80)
    online = OnlineFilter(kf)
    for t in range(40):
        online.update(z[:, t])
    ckpt = online.checkpoint()
    ckpt = pickle.loads(pickle.dumps(ckpt))  # survives serialisation
    first = [online.update(z[:, t]).mean for t in range(40, 80)]
    online.restore(ckpt)
    assert online.n_updates == 40 and online.state.k == 40
    second = [online.update(z[:, t]).mean for t in range(40, 80)]
    np.testing.assert_array_equal(np.stack(first), np.stack(second))
    # restoring twice works (the checkpoint is not consumed or aliased)
    online.restore(ckpt)
    third = [online.update(z[:, t]).mean for t in range(40, 80)]
    np.testing.assert_array_equal(np.stack(first), np.stack(third))
    # a fresh wrapper restored from the checkpoint agrees too
    other = OnlineFilter(kf)
    other.restore(ckpt)
    np.testing.assert_array_equal(other.update(z[:, 40]).mean, first[0])


def test_checkpoint_is_a_copy(rng):
    kf = KalmanFilter(constant_velocity(1 / 30, q=0.5, r=0.02))
    online = OnlineFilter(kf, kf.init((2,), mean=np.zeros(6)))
    ckpt = online.checkpoint()
    x_saved = ckpt["state"].x.copy()
    online.update(np.ones((2, 3)))
    np.testing.assert_array_equal(ckpt["state"].x, x_saved)
    assert ckpt["filter_type"] == "KalmanFilter" and ckpt["n_updates"] == 0


class _EmaState(NamedTuple):
    y: np.ndarray
    k: int


@dataclass(frozen=True)
class _Ema:
    """A minimal non-Kalman filter with the init/step protocol (stand-in for others' filters)."""

    alpha: float = 0.5

    def init(self, batch_shape=()):
        return _EmaState(np.zeros((*batch_shape, 3)), 0)

    def step(self, state, z):
        y = state.y + self.alpha * (np.asarray(z) - state.y)
        return _EmaState(y, state.k + 1), y


def test_works_with_any_init_step_filter():
    online = OnlineFilter(_Ema(0.5))
    out = online.update(np.full((2, 3), 4.0))
    np.testing.assert_array_equal(out, np.full((2, 3), 2.0))
    ckpt = online.checkpoint()
    a = online.update(np.zeros((2, 3)))
    online.restore(ckpt)
    np.testing.assert_array_equal(online.update(np.zeros((2, 3))), a)
    np.testing.assert_array_equal(a, np.full((2, 3), 1.0))


def test_online_bad_input():
    with pytest.raises(ValueError, match="init.*step.*got str"):
        OnlineFilter("kf")
    kf = KalmanFilter(constant_velocity(1 / 30, q=1.0, r=0.01))
    online = OnlineFilter(kf)
    online.update(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"expected z with shape \(2, 3\).*got \(3,\)"):
        online.update(np.zeros(3))
    with pytest.raises(ValueError, match="checkpoint dict"):
        online.restore({"x": 1})
    with pytest.raises(ValueError, match="checkpoint of a KalmanFilter, got one of a _Ema"):
        online.restore(OnlineFilter(_Ema()).checkpoint())
    with pytest.raises(ValueError, match="version"):
        online.restore({"version": 99, "filter_type": "KalmanFilter", "state": None})
    with pytest.raises(ValueError, match=r"expected z with shape \(\.\.\., n_z\)"):
        OnlineFilter(kf).update(1.0)


def test_imm_update_takes_one_row_per_model(rng):
    """OnlineFilter(IMM(m, m)).update(z (M, n_z)) is one element (issue #14), == IMM.filter."""
    m = constant_velocity(1 / 30, q=0.5, r=1e-3)
    imm = IMM(m, constant_velocity(1 / 30, q=0.5, r=4e-4))
    online = OnlineFilter(imm)
    out = online.update(np.zeros((2, 3)))
    assert online.state.initialized.shape == ()
    assert out.mean.shape == (6,)
    z = np.cumsum(rng.normal(scale=0.02, size=(4, 40, 2, 3)), axis=1)  # (B, T, M, n_z)
    z[1, 5:9, 0] = np.nan
    _, res = imm.filter(z)
    online = OnlineFilter(imm)
    outs = [online.update(z[:, t]) for t in range(z.shape[1])]
    assert online.state.initialized.shape == (4,)
    np.testing.assert_array_equal(np.stack([o.mean for o in outs], axis=1), res.mean)
    np.testing.assert_array_equal(np.stack([o.mu for o in outs], axis=1), res.mu)
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, 3\)"):
        OnlineFilter(imm).update(np.zeros(3))
