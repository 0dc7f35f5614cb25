"""Extreme learning machine (ELM) regressor, paper B (Xu 2023) §3.4, Eqs. 49-52 (SPEC §10.1).

Single hidden layer with random, fixed input weights and biases; only the output weights are
learned, in closed form. scikit-learn conventions: hyperparameters in ``__init__``, ``fit``
returns ``self``, learned attributes end in ``_``.
"""

from __future__ import annotations

import functools
import numbers
import warnings

import numpy as np
import scipy.linalg

from kinefuse._validation import as_float_array
from kinefuse.exceptions import InputError, KinefuseError

__all__ = ["ELMRegressor", "NotFittedError", "clip_norm"]

_ACTIVATIONS = ("sigmoid", "tanh")
_SOLVERS = ("ridge", "pinv")
#: Recommended minimum number of training samples per hidden column (SPEC §10.1: n_s >= 10 d).
SAMPLES_PER_HIDDEN = 10


class NotFittedError(KinefuseError, ValueError, AttributeError):
    """An estimator was used before ``fit`` (same bases as scikit-learn's ``NotFittedError``)."""


def _sigmoid(a: np.ndarray) -> np.ndarray:
    # logistic σ(a) = 1 / (1 + e^{−a}), overflow-free via tanh: 0.5 (1 + tanh(a / 2)), in place
    t = np.tanh(0.5 * a)
    t += 1.0
    t *= 0.5
    return t


def _rng(random_state) -> np.random.Generator:
    if random_state is None or isinstance(random_state, (numbers.Integral, np.integer)):
        if random_state is not None and int(random_state) < 0:
            raise InputError(f"expected random_state >= 0, got {random_state!r}")
        return np.random.default_rng(random_state)
    if isinstance(random_state, np.random.Generator):
        return random_state
    raise InputError(
        f"expected random_state as None, an int or a numpy Generator, got {type(random_state).__name__}"
    )


def _draw_layer(rng: np.random.Generator, n_in: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    """The random layer ``W (n_in, d) ~ U[−1, 1]``, then ``b (d,) ~ U[−1, 1]``, from ``rng``."""
    return rng.uniform(-1.0, 1.0, size=(n_in, d)), rng.uniform(-1.0, 1.0, size=d)


@functools.lru_cache(maxsize=64)
def _seeded_layer(seed: int, n_in: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_draw_layer` from ``np.random.default_rng(seed)`` (read-only; ``fit`` copies it).
    Paper B refits its ELMs with the same seed at every outage onset: the draws, not the data,
    are the same each time (about 40 µs a fit)."""
    W, b = _draw_layer(np.random.default_rng(seed), n_in, d)
    W.setflags(write=False)
    b.setflags(write=False)
    return W, b


class ELMRegressor:
    """Extreme learning machine regressor (paper B Eqs. 49-52, SPEC §10.1).

    Parameters
    ----------
    n_hidden : int
        Number of random hidden nodes ``d`` (default 20, SPEC §12.2).
    activation : {"sigmoid", "tanh"}
        Hidden activation χ; "sigmoid" is the logistic function (default, SPEC §10.1).
    alpha : float
        Ridge penalty λ >= 0 on the output weights (solver "ridge"; default 1e-6). Ignored by
        solver "pinv".
    solver : {"ridge", "pinv"}
        "ridge": ``β = (HᵀH + λI)⁻¹ HᵀY`` (default). "pinv": ``β = H⁺ Y``, the paper-literal
        Eq. 52 (minimum-norm least squares, ``np.linalg.lstsq``).
    linear_skip : bool
        Append the standardised inputs and a bias column to the hidden matrix (hpelm's
        "lin + sigm"; SPEC §10.1), so affine maps extrapolate outside the training range.
        Default False (paper-literal). Combine it with ``alpha`` around 1e-3: near λ = 0 the
        sigmoid columns (almost linear on the training range) and the linear columns are
        nearly collinear and share the weight, which largely cancels the benefit (measured on
        a 2-D affine map, 2-3x outside the training range: RMSE 0.50 with λ = 1e-6 vs 0.07
        with λ = 1e-3; pure sigmoid 0.58 and 1.1).
    standardize : bool
        Standardise X and y with the training mean and (population) standard deviation;
        predictions are de-standardised. Constant columns get scale 1. Default True.
    random_state : None, int or numpy.random.Generator
        Source of the input weights and biases (drawn at ``fit``, or at the first
        ``partial_fit``). An int gives identical weights at every ``fit``.

    Attributes
    ----------
    input_weights_ : ndarray, shape (n_features_in_, n_hidden)
        W ~ U[−1, 1] (paper B's β_q in Eq. 49).
    biases_ : ndarray, shape (n_hidden,)
        b ~ U[−1, 1].
    output_weights_ : ndarray, shape (n_hidden_out, n_outputs_)
        β of Eq. 52 (paper B's α_q in Eq. 49), in standardised units;
        ``n_hidden_out = n_hidden (+ n_features_in_ + 1 with linear_skip)``.
    x_mean_, x_scale_ : ndarray, shape (n_features_in_,)
        Input standardisation (zeros / ones when ``standardize=False``).
    y_mean_, y_scale_ : ndarray, shape (n_outputs_,)
        Target standardisation.
    train_rms_ : float
        Training RMS of the target vectors in original units,
        ``sqrt(mean_i ‖y_i‖²)``; the reference of ``predict(..., clip_factor=...)``.
    n_features_in_ : int
    n_outputs_ : int
    n_samples_seen_ : int
        Number of training samples accumulated (``fit`` resets, ``partial_fit`` adds).

    Notes
    -----
    Training (SPEC §10.1)::

        X̃ = (X − x_mean) / x_scale ,  Ỹ = (Y − y_mean) / y_scale
        H = χ(X̃ W + b)                      (n_s, d)        Eqs. 49-51 (F^E)
        [H | X̃ | 1]                         with linear_skip
        β = (HᵀH + λI)⁻¹ HᵀỸ  or  H⁺ Ỹ      (d, n_out)      Eq. 52
        predict(X) = y_mean + y_scale · (H(X) β)

    ``partial_fit`` accumulates ``A = HᵀH``, ``Hᵀ1``, ``HᵀY`` and the target moments, and
    re-solves after each chunk, so for the ridge solver a sequence of ``partial_fit`` calls
    equals one ``fit`` on the concatenated data, provided the input scaling is the same: the
    input standardisation is frozen at the first ``partial_fit`` (it shapes the hidden
    features), while the target standardisation is updated exactly. With ``solver="pinv"``,
    ``partial_fit`` solves the normal equations with a pseudo-inverse (``A⁺ HᵀỸ``, the same
    minimum-norm solution in exact arithmetic, with the squared condition number).

    Deviations from the paper
    -------------------------
    * Eqs. 49-51 swap the roles of α and β: here ``input_weights_``/``biases_`` are the random
      hidden parameters and ``output_weights_`` the learned β of Eqs. 51-52 (SPEC §10.1).
    * Eq. 51 shows β as an (s−1)-vector; it is ``(d, n_out)`` (``output_weights_``).
    * Hidden width, activation, weight distribution and normalisation are not given by the
      paper; defaults d = 20, logistic sigmoid, U[−1, 1] (Huang et al. 2006), standardised X
      and y (SPEC §12.2).
    * Default solver is ridge with λ = 1e-6 for conditioning; ``solver="pinv"`` is the
      paper-literal Eq. 52.
    * Optional ``linear_skip`` (off by default) against sigmoid saturation during long outages;
      ``clip_factor`` in :meth:`predict` / :func:`clip_norm` implement SPEC §13's clipping of
      the ELM-2 correction.
    """

    def __init__(
        self,
        n_hidden: int = 20,
        activation: str = "sigmoid",
        alpha: float = 1e-6,
        solver: str = "ridge",
        linear_skip: bool = False,
        standardize: bool = True,
        random_state=None,
    ):
        self.n_hidden = n_hidden
        self.activation = activation
        self.alpha = alpha
        self.solver = solver
        self.linear_skip = linear_skip
        self.standardize = standardize
        self.random_state = random_state

    # ------------------------------------------------------------------ sklearn protocol
    def get_params(self, deep: bool = True) -> dict:
        """Hyperparameters as a dict (scikit-learn protocol)."""
        names = ("n_hidden", "activation", "alpha", "solver", "linear_skip", "standardize")
        return {n: getattr(self, n) for n in (*names, "random_state")}

    def set_params(self, **params) -> ELMRegressor:
        """Set hyperparameters (scikit-learn protocol); returns ``self``."""
        valid = self.get_params()
        for k, v in params.items():
            if k not in valid:
                raise InputError(f"unknown parameter {k!r}; expected one of {sorted(valid)}")
            setattr(self, k, v)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"ELMRegressor({args})"

    # ------------------------------------------------------------------ public API
    def fit(self, X, y) -> ELMRegressor:
        """Fit the output weights on ``(X, y)``, drawing fresh hidden weights.

        Parameters
        ----------
        X : array_like of float, shape (n_samples, n_features)
            Inputs (paper B, ELM 1: IMU-chain positions, m).
        y : array_like of float, shape (n_samples,) or (n_samples, n_outputs)
            Targets (ELM 1: camera positions, m). The shape of ``predict``'s output follows.

        Returns
        -------
        self

        Warns
        -----
        UserWarning
            When ``n_samples < 10 · n_hidden_out`` (SPEC §10.1 recommends ``n_s >= 10 d``).
        """
        self._validate_params()
        X, Y, y_1d = self._check_xy(X, y, first=True)
        n_s = X.shape[0]
        if n_s < 2:
            raise InputError(f"expected at least 2 training samples, got {n_s}")
        self._reset(X, Y, y_1d)
        d_out = self._n_hidden_out()
        if n_s < SAMPLES_PER_HIDDEN * d_out:
            warnings.warn(
                f"ELM fitted on {n_s} samples for {d_out} hidden columns; at least "
                f"{SAMPLES_PER_HIDDEN * d_out} (10 per column) are recommended (SPEC §10.1)",
                UserWarning,
                stacklevel=2,
            )
        Hh = self._hidden(X)
        self._accumulate(Hh, Y)
        if self.solver == "pinv":
            Ys = (Y - self.y_mean_) / self.y_scale_
            self.output_weights_ = np.linalg.lstsq(Hh, Ys, rcond=None)[0]  # Eq. 52: β = H⁺ Ỹ
        else:
            self._solve()
        return self

    def partial_fit(self, X, y) -> ELMRegressor:
        """Add a chunk of training data and re-solve the output weights.

        The first call (or the first after construction) draws the hidden weights and freezes
        the input standardisation from this chunk; later calls accumulate the normal equations
        exactly. For the ridge solver, ``partial_fit`` over chunks equals ``fit`` on all data
        when the input scaling agrees (always with ``standardize=False``).

        Parameters
        ----------
        X : array_like of float, shape (n_samples, n_features)
        y : array_like of float, shape (n_samples,) or (n_samples, n_outputs)

        Returns
        -------
        self
        """
        self._validate_params()
        first = not hasattr(self, "_A")
        X, Y, y_1d = self._check_xy(X, y, first=first)
        if first:
            if self.standardize and X.shape[0] < 2:
                raise InputError(
                    f"expected at least 2 samples in the first partial_fit chunk, got {X.shape[0]}"
                )
            self._reset(X, Y, y_1d)
        Hh = self._hidden(X)
        self._accumulate(Hh, Y)
        self._solve()
        return self

    def predict(self, X, clip_factor: float | None = None) -> np.ndarray:
        """Predict targets for ``X``.

        Parameters
        ----------
        X : array_like of float, shape (n_samples, n_features)
        clip_factor : float, optional
            If given, each predicted target vector is scaled down to norm
            ``<= clip_factor · train_rms_`` (SPEC §13: ELM-2 correction clipped at 3× its
            training RMS; use ``clip_factor=3``).

        Returns
        -------
        ndarray, shape (n_samples,) or (n_samples, n_outputs)
            Same layout as the ``y`` given to ``fit``.
        """
        self._check_fitted()
        X = as_float_array(X, "X")
        if X.ndim != 2 or X.shape[1] != self.n_features_in_:
            raise InputError(
                f"expected X with shape (n_samples, {self.n_features_in_}), got {X.shape}"
            )
        if not np.all(np.isfinite(X)):
            raise InputError("expected X finite, got NaN or ±inf")
        c = None
        if clip_factor is not None:
            c = float(clip_factor)
            if not (np.isfinite(c) and c > 0):
                raise InputError(f"expected clip_factor finite and > 0, got {clip_factor!r}")
        return self._predict_unchecked(X, c)

    def _predict_unchecked(self, X: np.ndarray, clip_factor: float | None = None) -> np.ndarray:
        """:meth:`predict` on the trusted fast path (the same arithmetic, no checks): the
        model is fitted, ``X`` is a finite float64 ``(n_samples, n_features_in_)`` array and
        ``clip_factor`` None or finite > 0. For kinefuse's per-frame callers that validated
        their data (:class:`kinefuse.pipelines.paper_b.PaperBCore`)."""
        Y = self._hidden(X) @ self.output_weights_ * self.y_scale_ + self.y_mean_
        if clip_factor is not None:
            Y = _scale_to_norm(Y, _row_norms(Y), clip_factor * self.train_rms_)
        return Y[:, 0] if self._y_1d else Y

    def _predict_finite_rows(self, X: np.ndarray, fill: float, clip_factor=None) -> np.ndarray:
        """:meth:`_predict_unchecked` on the rows of ``X`` that are finite, ``fill`` on the others
        (the trusted fast path otherwise). When every row is finite (the common case, and every
        online frame that has one) ``X`` is passed whole: the same rows and numbers, no copies."""
        if np.isfinite(X).all():
            return self._predict_unchecked(X, clip_factor)
        ok = np.isfinite(X).all(axis=-1)
        n_out = self.output_weights_.shape[1]
        out = np.full((X.shape[0],) if self._y_1d else (X.shape[0], n_out), fill)
        if ok.any():
            out[ok] = self._predict_unchecked(X[ok], clip_factor)  # rows checked finite here
        return out

    # ------------------------------------------------------------------ internals
    def _validate_params(self) -> None:
        n = self.n_hidden
        if isinstance(n, bool) or not isinstance(n, (numbers.Integral, np.integer)) or n < 1:
            raise InputError(f"expected n_hidden as an int >= 1, got {n!r}")
        if self.activation not in _ACTIVATIONS:
            raise InputError(f"expected activation in {_ACTIVATIONS}, got {self.activation!r}")
        if self.solver not in _SOLVERS:
            raise InputError(f"expected solver in {_SOLVERS}, got {self.solver!r}")
        try:
            a = float(self.alpha)
        except (TypeError, ValueError):
            raise InputError(f"expected alpha as a number >= 0, got {self.alpha!r}") from None
        if not (np.isfinite(a) and a >= 0):
            raise InputError(f"expected alpha finite and >= 0, got {self.alpha!r}")

    def _check_xy(self, X, y, *, first: bool):
        X = as_float_array(X, "X")
        y = as_float_array(y, "y")
        if X.ndim != 2:
            hint = " (use X.reshape(-1, 1) for one feature)" if X.ndim == 1 else ""
            raise InputError(f"expected X with shape (n_samples, n_features){hint}, got {X.shape}")
        if y.ndim not in (1, 2):
            raise InputError(
                f"expected y with shape (n_samples,) or (n_samples, n_outputs), got {y.shape}"
            )
        if y.shape[0] != X.shape[0]:
            raise InputError(
                f"expected X and y with the same number of samples, got {X.shape[0]} and {y.shape[0]}"
            )
        if X.shape[0] == 0:
            raise InputError("expected at least one sample, got 0")
        if not np.all(np.isfinite(X)):
            raise InputError("expected X finite, got NaN or ±inf (drop missing rows first)")
        if not np.all(np.isfinite(y)):
            raise InputError("expected y finite, got NaN or ±inf (drop missing rows first)")
        y_1d = y.ndim == 1
        Y = y[:, None] if y_1d else y
        if not first:
            if X.shape[1] != self.n_features_in_:
                raise InputError(
                    f"expected X with {self.n_features_in_} features, got {X.shape[1]}"
                )
            if y_1d != self._y_1d or Y.shape[1] != self.n_outputs_:
                want = "(n_samples,)" if self._y_1d else f"(n_samples, {self.n_outputs_})"
                raise InputError(
                    f"expected y with shape {want} as in the first chunk, got {y.shape}"
                )
        return X, Y, y_1d

    def _reset(self, X: np.ndarray, Y: np.ndarray, y_1d: bool) -> None:
        n_in, n_out = X.shape[1], Y.shape[1]
        d = int(self.n_hidden)
        rs = self.random_state
        if isinstance(rs, (numbers.Integral, np.integer)) and int(rs) >= 0:  # the same draws
            W, b = _seeded_layer(int(rs), n_in, d)
            self.input_weights_, self.biases_ = W.copy(), b.copy()
        else:
            self.input_weights_, self.biases_ = _draw_layer(_rng(rs), n_in, d)
        if self.standardize:
            self.x_mean_ = X.mean(axis=0)
            sx = X.std(axis=0)
            self.x_scale_ = np.where(sx > 0, sx, 1.0)
        else:
            self.x_mean_ = np.zeros(n_in)
            self.x_scale_ = np.ones(n_in)
        self.n_features_in_ = n_in
        self.n_outputs_ = n_out
        self._y_1d = y_1d
        d_out = self._n_hidden_out()
        self._A = np.zeros((d_out, d_out))  # Σ HᵀH
        self._h_sum = np.zeros(d_out)  # Σ Hᵀ1
        self._HtY = np.zeros((d_out, n_out))  # Σ HᵀY (raw targets)
        self._y_n = 0
        self._y_mean = np.zeros(n_out)  # running target mean
        self._y_m2 = np.zeros(n_out)  # running Σ (y − mean)²
        self._y_sq = 0.0  # Σ ‖y‖²
        self.n_samples_seen_ = 0

    def _n_hidden_out(self) -> int:
        d = int(self.n_hidden)
        return d + self.n_features_in_ + 1 if self.linear_skip else d

    def _hidden(self, X: np.ndarray) -> np.ndarray:
        Xs = (X - self.x_mean_) / self.x_scale_
        a = Xs @ self.input_weights_ + self.biases_  # Eq. 49: β_q I_e + b_q
        Hh = _sigmoid(a) if self.activation == "sigmoid" else np.tanh(a)  # χ(·), F^E of Eq. 51
        if self.linear_skip:
            Hh = np.hstack([Hh, Xs, np.ones((X.shape[0], 1))])
        return Hh

    def _accumulate(self, Hh: np.ndarray, Y: np.ndarray) -> None:
        n_b = Y.shape[0]
        self._A += Hh.T @ Hh
        self._h_sum += Hh.sum(axis=0)
        self._HtY += Hh.T @ Y
        # Chan et al. pairwise update of the target mean and sum of squared deviations
        mean_b = Y.mean(axis=0)
        m2_b = ((Y - mean_b) ** 2).sum(axis=0)
        n_a = self._y_n
        n = n_a + n_b
        delta = mean_b - self._y_mean
        self._y_mean = self._y_mean + delta * (n_b / n)
        self._y_m2 = self._y_m2 + m2_b + delta**2 * (n_a * n_b / n)
        self._y_n = n
        self._y_sq += float((Y**2).sum())
        self.n_samples_seen_ = n
        self.train_rms_ = float(np.sqrt(self._y_sq / n))
        if self.standardize:
            self.y_mean_ = self._y_mean.copy()
            sy = np.sqrt(self._y_m2 / n)
            self.y_scale_ = np.where(sy > 0, sy, 1.0)
        else:
            self.y_mean_ = np.zeros(self.n_outputs_)
            self.y_scale_ = np.ones(self.n_outputs_)

    def _solve(self) -> None:
        # HᵀỸ = (HᵀY − (Hᵀ1) y_meanᵀ) / y_scale, exact for the accumulated data
        b = (self._HtY - np.outer(self._h_sum, self.y_mean_)) / self.y_scale_
        A = self._A
        if self.solver == "pinv":
            self.output_weights_ = np.linalg.pinv(A, hermitian=True) @ b  # A⁺ HᵀỸ = H⁺ Ỹ
            return
        lam = float(self.alpha)
        Areg = A + lam * np.eye(A.shape[0])  # ridge: (HᵀH + λI) β = HᵀỸ
        try:
            c = scipy.linalg.cho_factor(Areg, lower=True, check_finite=False)
            beta = scipy.linalg.cho_solve(c, b, check_finite=False)
        except np.linalg.LinAlgError:
            beta = None
        if beta is None or not np.all(np.isfinite(beta)):
            warnings.warn(
                f"ELM normal equations not positive definite (alpha={lam:g}); used the "
                "minimum-norm least-squares solution instead. Increase alpha or reduce n_hidden.",
                UserWarning,
                stacklevel=3,
            )
            beta = np.linalg.pinv(Areg, hermitian=True) @ b
        self.output_weights_ = beta

    def _check_fitted(self) -> None:
        if not hasattr(self, "output_weights_"):
            raise NotFittedError(
                f"This {type(self).__name__} instance is not fitted yet. Call 'fit' with "
                "appropriate arguments before using this estimator."
            )


def clip_norm(v, max_norm, axis: int = -1) -> np.ndarray:
    """Scale vectors down so that their Euclidean norm is at most ``max_norm`` (SPEC §13).

    Parameters
    ----------
    v : array_like of float, shape (..., n)
        Vectors along ``axis`` (e.g. ELM-2 position corrections, m). A 1-D array of shape
        (n_samples,) with ``axis=-1`` is one vector; pass ``v[:, None]`` to clip each scalar.
    max_norm : float or array_like
        Largest allowed norm, >= 0, broadcastable against ``v`` with ``axis`` removed (e.g.
        ``3 * elm.train_rms_``).
    axis : int
        Axis holding the vector components.

    Returns
    -------
    ndarray
        ``v * min(1, max_norm / ‖v‖)``; direction kept; vectors containing NaN are returned
        unchanged.
    """
    v = as_float_array(v, "v")
    if v.ndim == 0:
        raise InputError("expected v with at least one dimension (..., n), got a scalar")
    m = np.asarray(max_norm, dtype=float)
    if np.any(~np.isfinite(m)) or np.any(m < 0):
        raise InputError(f"expected max_norm finite and >= 0, got {max_norm!r}")
    norm = np.linalg.norm(v, axis=axis, keepdims=True)
    return _scale_to_norm(v, norm, np.expand_dims(m, axis) if m.ndim > 0 else m)


def _row_norms(Y: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(Y, axis=-1, keepdims=True)`` for real ``Y``: numpy's own arithmetic for
    that case (``sqrt(add.reduce(Y * Y))``) without its dispatch (a few µs per online frame)."""
    return np.sqrt(np.add.reduce(Y * Y, axis=-1, keepdims=True))


def _scale_to_norm(v: np.ndarray, norm: np.ndarray, m) -> np.ndarray:
    """``v * min(1, m / norm)`` (``norm`` the vectors' norms, broadcast; NaN norms keep v)."""
    over = norm > m
    if over.shape == norm.shape and not over.any():  # v * 1.0 is v: nothing to scale
        return v.copy()
    scale = np.divide(m, norm, out=np.ones(over.shape), where=over)  # (no 0/0: only where over)
    return v * scale
