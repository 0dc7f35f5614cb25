"""ELM regressor (paper B Eqs. 49-52, SPEC §10.1) and the SPEC §13 clipping helper."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.exceptions import InputError
from kinefuse.learning import ELMRegressor, NotFittedError, clip_norm


def _smooth_data(rng, n):
    X = rng.uniform(-2.0, 2.0, size=(n, 2))
    y = np.sin(X[:, 0]) + 0.5 * X[:, 1] ** 2
    return X, y


def _r2(y, yhat):
    return 1.0 - np.sum((y - yhat) ** 2) / np.sum((y - np.mean(y)) ** 2)


def test_recovers_smooth_mapping_on_held_out_data(rng):
    X, y = _smooth_data(rng, 800)
    Xt, yt = _smooth_data(rng, 400)
    elm = ELMRegressor(n_hidden=40, random_state=0).fit(X, y)
    pred = elm.predict(Xt)
    assert pred.shape == yt.shape
    assert _r2(yt, pred) > 0.99


def test_multi_output_shapes_and_attributes(rng):
    X = rng.normal(size=(300, 3))
    Y = np.column_stack([X @ [1.0, -2.0, 0.5], np.tanh(X[:, 0])])
    elm = ELMRegressor(n_hidden=20, random_state=1).fit(X, Y)
    assert elm.predict(X).shape == (300, 2)
    assert elm.input_weights_.shape == (3, 20)
    assert elm.biases_.shape == (20,)
    assert elm.output_weights_.shape == (20, 2)
    assert elm.x_mean_.shape == (3,) and elm.y_scale_.shape == (2,)
    assert np.all(np.abs(elm.input_weights_) <= 1.0) and np.all(np.abs(elm.biases_) <= 1.0)
    skip = ELMRegressor(n_hidden=20, linear_skip=True, random_state=1).fit(X, Y)
    assert skip.output_weights_.shape == (20 + 3 + 1, 2)
    # a 2-D y with one column keeps its 2-D layout
    assert ELMRegressor(random_state=0).fit(X, Y[:, :1]).predict(X).shape == (300, 1)


def test_deterministic_for_fixed_seed_and_different_across_seeds(rng):
    X, y = _smooth_data(rng, 300)
    p1 = ELMRegressor(random_state=7).fit(X, y).predict(X)
    p2 = ELMRegressor(random_state=7).fit(X, y).predict(X)
    p3 = ELMRegressor(random_state=8).fit(X, y).predict(X)
    np.testing.assert_array_equal(p1, p2)
    assert np.max(np.abs(p1 - p3)) > 1e-6
    # a Generator is consumed: two fits from the same Generator differ, two equal seeds agree
    a = ELMRegressor(random_state=np.random.default_rng(3)).fit(X, y)
    b = ELMRegressor(random_state=np.random.default_rng(3)).fit(X, y)
    np.testing.assert_array_equal(a.input_weights_, b.input_weights_)
    w0 = a.input_weights_.copy()
    a.fit(X, y)
    assert not np.array_equal(w0, a.input_weights_)


def test_integer_seed_draws_numpys_layer_every_fit(rng):
    """Oracle: ``np.random.default_rng(seed)``'s uniform draws, W then b, at every fit of an
    integer seed (they are drawn once and reused); a fitted model's arrays are its own."""
    X, y = _smooth_data(rng, 300)
    g = np.random.default_rng(11)
    W, b = g.uniform(-1.0, 1.0, size=(2, 20)), g.uniform(-1.0, 1.0, size=20)
    m1 = ELMRegressor(random_state=11).fit(X, y)
    m1.input_weights_ += 1.0  # writable, and not the shared draws
    m2 = ELMRegressor(random_state=np.int64(11)).fit(X[:200], y[:200])
    np.testing.assert_array_equal(m2.input_weights_, W)
    np.testing.assert_array_equal(m2.biases_, b)
    m1.fit(X, y)
    np.testing.assert_array_equal(m1.input_weights_, W)
    with pytest.raises(InputError, match="random_state >= 0"):
        ELMRegressor(random_state=-1).fit(X, y)


def test_pinv_solver_equals_lstsq_on_hidden_matrix(rng):
    X = rng.normal(size=(200, 3)) * [1.0, 10.0, 0.1] + [0.0, 5.0, -1.0]
    Y = np.column_stack([np.sin(X[:, 0]) + X[:, 1], X[:, 2] ** 2])
    elm = ELMRegressor(n_hidden=15, solver="pinv", alpha=0.0, random_state=2).fit(X, Y)
    # rebuild the hidden matrix independently from the documented recipe (SPEC §10.1)
    x_mean, x_std = X.mean(axis=0), X.std(axis=0)
    y_mean, y_std = Y.mean(axis=0), Y.std(axis=0)
    Hh = 1.0 / (1.0 + np.exp(-(((X - x_mean) / x_std) @ elm.input_weights_ + elm.biases_)))
    beta = np.linalg.lstsq(Hh, (Y - y_mean) / y_std, rcond=None)[0]
    np.testing.assert_allclose(elm.output_weights_, beta, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(elm.predict(X), Hh @ beta * y_std + y_mean, rtol=1e-10, atol=1e-10)


def test_ridge_small_alpha_close_to_pinv(rng):
    X, y = _smooth_data(rng, 400)
    p_ridge = ELMRegressor(alpha=1e-10, random_state=4).fit(X, y).predict(X)
    p_pinv = ELMRegressor(solver="pinv", random_state=4).fit(X, y).predict(X)
    np.testing.assert_allclose(p_ridge, p_pinv, atol=1e-4)


def test_partial_fit_equals_fit_ridge_unstandardized(rng):
    X = rng.normal(size=(500, 3))
    Y = np.column_stack([np.sin(X[:, 0]) * X[:, 1], X[:, 2]])
    kw = dict(n_hidden=25, alpha=1e-3, standardize=False, linear_skip=True, random_state=5)
    full = ELMRegressor(**kw).fit(X, Y)
    inc = ELMRegressor(**kw)
    for chunk in np.array_split(np.arange(500), [1, 60, 61, 300]):  # includes a 1-sample chunk
        inc.partial_fit(X[chunk], Y[chunk])
    assert inc.n_samples_seen_ == 500
    scale = np.abs(full.output_weights_).max()  # A = HᵀH is ill-conditioned without scaling
    np.testing.assert_allclose(inc.output_weights_, full.output_weights_, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(inc.predict(X), full.predict(X), rtol=1e-9, atol=1e-10)
    assert inc.train_rms_ == pytest.approx(full.train_rms_, rel=1e-12)


def test_partial_fit_equals_fit_ridge_standardized_targets(rng):
    # The input scaling is frozen by the first chunk: use a second chunk with the same inputs
    # (same X statistics) but different targets, so the exact target-moment update is tested.
    X1 = rng.normal(size=(250, 2)) * [2.0, 0.5] + [1.0, -3.0]
    ya = np.sin(X1[:, 0]) + X1[:, 1]
    yb = 3.0 * np.cos(X1[:, 1]) + 10.0
    kw = dict(n_hidden=20, alpha=1e-4, random_state=6)
    full = ELMRegressor(**kw).fit(np.vstack([X1, X1]), np.concatenate([ya, yb]))
    inc = ELMRegressor(**kw).partial_fit(X1, ya).partial_fit(X1, yb)
    np.testing.assert_allclose(inc.x_mean_, full.x_mean_, rtol=1e-12)
    np.testing.assert_allclose(inc.y_mean_, full.y_mean_, rtol=1e-12)
    np.testing.assert_allclose(inc.y_scale_, full.y_scale_, rtol=1e-12)
    # The two fits solve (HᵀH + αI) β = HᵀỸ with the Gram matrix and right-hand side summed in
    # different orders. Rounding perturbs them by about sqrt(n)·eps relative (probabilistic
    # bound, Higham & Mary 2019), which the solve amplifies by at most cond(HᵀH + αI): a
    # norm-wise tolerance from the conditioning, not from one machine's BLAS (issue 12).
    A = full._A + full.alpha * np.eye(full._A.shape[0])
    n = full.n_samples_seen_
    tol = np.linalg.cond(A) * np.sqrt(n) * np.finfo(float).eps
    diff = np.linalg.norm(inc.output_weights_ - full.output_weights_)
    assert diff <= tol * np.linalg.norm(full.output_weights_), (diff, tol)


def test_partial_fit_pinv_matches_fit(rng):
    X, y = _smooth_data(rng, 400)
    kw = dict(n_hidden=10, solver="pinv", standardize=False, random_state=9)
    full = ELMRegressor(**kw).fit(X, y)
    inc = ELMRegressor(**kw).partial_fit(X[:200], y[:200]).partial_fit(X[200:], y[200:])
    np.testing.assert_allclose(inc.predict(X), full.predict(X), atol=1e-6)


def test_linear_skip_extrapolates_affine_map(rng):
    A = np.array([[1.5, -0.5], [0.3, 2.0]])
    c = np.array([0.2, -1.0])
    X = rng.uniform(-1.0, 1.0, size=(400, 2))
    Y = X @ A + c + 0.01 * rng.normal(size=(400, 2))
    Xo = rng.uniform(2.0, 3.0, size=(200, 2))  # 2-3x outside the training range
    Yo = Xo @ A + c
    # alpha 1e-3: the ridge then prefers the linear columns (at 1e-6 sigmoid and linear columns
    # are nearly collinear on the training range and share the weight; see the ELM docstring)
    err_sig = ELMRegressor(alpha=1e-3, random_state=0).fit(X, Y).predict(Xo) - Yo
    err_lin = ELMRegressor(alpha=1e-3, linear_skip=True, random_state=0).fit(X, Y).predict(Xo) - Yo
    rmse_sig = np.sqrt(np.mean(err_sig**2))
    rmse_lin = np.sqrt(np.mean(err_lin**2))
    assert rmse_lin < 0.15  # m-scale map, targets span about ±3
    assert rmse_lin < 0.2 * rmse_sig
    assert ELMRegressor(alpha=1e-3, linear_skip=True, random_state=0).fit(X, Y).predict(X) == (
        pytest.approx(X @ A + c, abs=0.05)
    )


def test_predict_before_fit_raises():
    with pytest.raises(NotFittedError, match="not fitted yet"):
        ELMRegressor().predict(np.zeros((3, 2)))
    assert issubclass(NotFittedError, ValueError) and issubclass(NotFittedError, AttributeError)


@pytest.mark.parametrize(
    ("X", "y", "match"),
    [
        (np.array([[np.nan, 1.0]] * 30), np.zeros(30), "X finite"),
        (np.ones((30, 2)), np.r_[np.zeros(29), np.nan], "y finite"),
        (np.ones((30, 2)), np.zeros(29), "same number of samples"),
        (np.ones(30), np.zeros(30), r"reshape\(-1, 1\)"),
        (np.ones((30, 2)), np.zeros((30, 2, 1)), "n_outputs"),
        (np.ones((30, 2), dtype=int), np.zeros(30), "float array"),
        (np.ones((1, 2)), np.zeros(1), "at least 2"),
    ],
)
def test_bad_input_errors(X, y, match):
    with pytest.raises(InputError, match=match):
        ELMRegressor(random_state=0).fit(X, y)


@pytest.mark.parametrize(
    ("params", "match"),
    [
        (dict(n_hidden=0), "n_hidden"),
        (dict(n_hidden=2.5), "n_hidden"),
        (dict(activation="relu"), "activation"),
        (dict(solver="svd"), "solver"),
        (dict(alpha=-1.0), "alpha"),
        (dict(random_state="seed"), "random_state"),
    ],
)
def test_bad_hyperparameters(params, match, rng):
    X, y = _smooth_data(rng, 300)
    with pytest.raises(InputError, match=match):
        ELMRegressor(**params).fit(X, y)


def test_predict_and_partial_fit_shape_checks(rng):
    X, y = _smooth_data(rng, 300)
    elm = ELMRegressor(random_state=0).fit(X, y)
    with pytest.raises(InputError, match=r"\(n_samples, 2\)"):
        elm.predict(np.zeros((5, 3)))
    with pytest.raises(InputError, match="X finite"):
        elm.predict(np.full((5, 2), np.nan))
    with pytest.raises(InputError, match="as in the first chunk"):
        elm.partial_fit(X, np.column_stack([y, y]))


def test_few_samples_warns_but_fits(rng):
    X, y = _smooth_data(rng, 50)
    with pytest.warns(UserWarning, match="recommended"):
        elm = ELMRegressor(n_hidden=20, random_state=0).fit(X, y)
    assert np.all(np.isfinite(elm.predict(X)))


def test_constant_feature_and_target_do_not_break(rng):
    X = np.column_stack([rng.normal(size=300), np.full(300, 4.0)])
    elm = ELMRegressor(random_state=0).fit(X, np.full(300, 2.5))
    np.testing.assert_allclose(elm.predict(X), 2.5, atol=1e-9)
    assert elm.x_scale_[1] == 1.0


def test_clip_norm_and_predict_clip_factor(rng):
    v = np.array([[3.0, 4.0], [0.3, 0.4], [np.nan, 1.0]])
    out = clip_norm(v, 1.0)
    np.testing.assert_allclose(out[0], [0.6, 0.8])
    np.testing.assert_array_equal(out[1], v[1])
    assert np.isnan(out[2, 0]) and out[2, 1] == 1.0  # a vector with NaN is left as is
    # per-row limits broadcast over the vector axis
    np.testing.assert_allclose(clip_norm(v[:2], np.array([10.0, 0.25]))[1], [0.15, 0.2])
    with pytest.raises(InputError, match="max_norm"):
        clip_norm(v, -1.0)

    X = rng.uniform(-1.0, 1.0, size=(300, 3))
    Y = X * 0.1
    elm = ELMRegressor(linear_skip=True, random_state=0).fit(X, Y)
    assert elm.train_rms_ == pytest.approx(np.sqrt(np.mean(np.sum(Y**2, axis=1))), rel=1e-12)
    far = np.full((4, 3), 50.0)
    raw = elm.predict(far)
    clipped = elm.predict(far, clip_factor=3.0)
    assert np.all(np.linalg.norm(raw, axis=1) > 3.0 * elm.train_rms_)
    np.testing.assert_allclose(np.linalg.norm(clipped, axis=1), 3.0 * elm.train_rms_, rtol=1e-12)
    np.testing.assert_allclose(clipped / np.linalg.norm(clipped, axis=1, keepdims=True),
                               raw / np.linalg.norm(raw, axis=1, keepdims=True), rtol=1e-12)  # fmt: skip
    # 1-D targets: each scalar is clipped on its own
    e1 = ELMRegressor(linear_skip=True, random_state=0).fit(X, Y[:, 0])
    assert np.all(np.abs(e1.predict(far, clip_factor=3.0)) <= 3.0 * e1.train_rms_ * (1 + 1e-12))


def test_get_set_params_roundtrip():
    elm = ELMRegressor(n_hidden=5, random_state=3)
    assert elm.get_params()["n_hidden"] == 5
    elm.set_params(alpha=0.1)
    assert elm.alpha == 0.1
    with pytest.raises(InputError, match="unknown parameter"):
        elm.set_params(beta=1)
    assert "n_hidden=5" in repr(elm)


def test_row_norms_equal_numpy_norm_bit_for_bit(rng):
    """The clip's row norms are numpy's ``linalg.norm(axis=-1)`` (the oracle), to the bit,
    with NaN, inf, zeros and huge and tiny values."""
    from kinefuse.learning.elm import _row_norms

    Y = rng.normal(size=(200, 3)) * 10.0 ** rng.integers(-150, 150, size=(200, 1))
    Y[3] = np.nan
    Y[4, 1] = np.inf
    Y[5] = 0.0
    np.testing.assert_array_equal(_row_norms(Y), np.linalg.norm(Y, axis=-1, keepdims=True))


@pytest.mark.parametrize("y_dims", [1, 3])
def test_predict_finite_rows_fills_the_others(rng, y_dims):
    """The fast path predicts the finite rows as ``predict`` does (the oracle) and fills the
    others; all finite, it is ``predict`` itself."""
    X = rng.normal(size=(200, 4))
    y = X[:, :y_dims] ** 2 if y_dims > 1 else X[:, 0] ** 2
    elm = ELMRegressor(20, random_state=0).fit(X, y)
    Xq = rng.normal(size=(9, 4))
    np.testing.assert_array_equal(elm._predict_finite_rows(Xq, np.nan), elm.predict(Xq))
    Xq[[2, 5], 1] = np.nan
    got = elm._predict_finite_rows(Xq, -7.0, 2.0)
    ok = np.isfinite(Xq).all(axis=1)
    np.testing.assert_array_equal(got[ok], elm.predict(Xq[ok], clip_factor=2.0))
    assert np.all(got[~ok] == -7.0) and got.shape == ((9,) if y_dims == 1 else (9, 3))
