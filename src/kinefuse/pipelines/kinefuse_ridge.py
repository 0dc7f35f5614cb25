"""The learned chain-error correction of the ``"kinefuse"`` fusion: a streaming ridge regression.

:class:`RidgeCorrection` accumulates per-fold moments, so that ``partial_fit`` as data arrive
and ``fit`` on a whole series give the same solve, and selects its penalty by blocked
cross-validation from the stored moments alone. :class:`AxisRidgeCorrection` is the same
regression on a design with one row per world axis (the segment-frame model,
:func:`kinefuse.pipelines.features.segment_frame_design`).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["AxisRidgeCorrection", "RidgeCorrection"]

#: Default ridge penalties of :class:`RidgeCorrection` (last: intercept only).
_ALPHAS = (*np.logspace(-4, 3, 15).tolist(), float("inf"))


class RidgeCorrection:
    """Ridge regression of the chain error on IMU features, from accumulated moments (streaming).

    Parameters
    ----------
    alphas : sequence of float
        Candidate ridge penalties on the standardised coefficients (dimensionless, per sample):
        ``β = (C + α I)⁻¹ c`` with C the feature correlation matrix and c the standardised
        feature-target covariances; ``inf`` = intercept only. The intercept is not penalised.
        The penalty is chosen by blocked cross-validation.
    block : int
        Block length of the cross-validation, samples (default 30 = 1 s at 30 Hz). Blocks are
        contiguous in time, so the serially correlated errors of a block do not leak into its
        own prediction (a plain GCV would pick a far too small penalty here).
    n_folds : int, optional
        Number of cross-validation folds; block ``i`` belongs to fold ``i mod n_folds``.
        Default None: one fold per block (leave-one-block-out). A bounded number keeps the
        cost of a re-solve independent of the history length (causal mode).
    min_blocks : int
        Blocks of data needed before anything but the intercept is fitted (default 2, the
        fewest that can be cross-validated).
    reselect_growth : float, optional
        Streaming: re-run the cross-validation only once the number of rows has grown by this
        factor since the last selection (e.g. 1.5: O(log n) selections); in between, the
        coefficients are re-solved at the selected penalty. Default None: select at every
        solve (``fit`` and ``partial_fit`` then agree exactly).

    Attributes
    ----------
    alpha_ : float
        Selected penalty.
    coef_ : ndarray, shape (F, D)
    intercept_ : ndarray, shape (D,)
    cv_error_ : ndarray, shape (len(alphas),)
        Mean squared CV prediction error per candidate, m² (NaN when not validated).
    n_samples_ : int
        Rows accumulated so far.

    Notes
    -----
    ``partial_fit(X, Y, t)`` adds the moments ``n, Σx̃x̃ᵀ, Σx̃yᵀ, Σyᵀy`` (``x̃ = [x, 1]``) of
    the rows to the fold of the block ``t // block`` of each row; ``fit`` = fresh moments +
    one ``partial_fit``. Each solve uses only the stored moments: for a held-out fold the
    training moments are the totals minus the fold's, and its squared error is
    ``Σyᵀy − 2 θᵀ Σx̃y + θᵀ Σx̃x̃ᵀ θ``. Features are standardised with the moments of all
    folds. One eigendecomposition per fold gives the solutions for all penalties, so a
    re-solve costs O(folds · F³) whatever the number of rows. With fewer than ``min_blocks``
    blocks (or fewer than 2 folds) nothing can be validated and the largest penalty of the
    grid is used (by default ``inf``: intercept only).
    """

    def __init__(
        self,
        alphas=_ALPHAS,
        block: int = 30,
        n_folds: int | None = None,
        min_blocks: int = 2,
        reselect_growth: float | None = None,
    ):
        self.alphas = tuple(float(a) for a in alphas)
        self.block = int(block)
        self.n_folds = n_folds
        self.min_blocks = int(min_blocks)
        self.reselect_growth = reselect_growth

    def fit(self, X, Y, t=None) -> RidgeCorrection:
        """Fit on ``X (n, F)``, ``Y (n, D)`` at sample times ``t (n,)`` (default 0..n−1)."""
        for name in ("folds_", "blocks_seen_", "n_selected_"):
            self.__dict__.pop(name, None)
        return self.partial_fit(X, Y, t)

    def partial_fit(self, X, Y, t=None) -> RidgeCorrection:
        """Accumulate the moments of more rows and re-solve; returns self."""
        X = np.asarray(X, dtype=float)
        Y = np.asarray(Y, dtype=float)
        t = np.arange(X.shape[0]) if t is None else np.asarray(t)
        if not hasattr(self, "folds_"):
            self.folds_ = {}
            self.blocks_seen_ = set()
        ok = np.all(np.isfinite(X), 1) & np.all(np.isfinite(Y), 1)
        X, Y, t = X[ok], Y[ok], t[ok]
        Xa = np.concatenate([X, np.ones((X.shape[0], 1))], axis=1)
        self.n_features_ = X.shape[1]
        self.n_outputs_ = Y.shape[1]
        blk = t // self.block
        fold = blk if self.n_folds is None else blk % int(self.n_folds)
        self.blocks_seen_.update(int(b) for b in np.unique(blk))
        # rows grouped by fold in one stable sort (each fold's rows in their order: the same
        # sums as selecting them with a mask, without a pass over all rows per fold)
        order = np.argsort(fold, kind="stable")
        folds, starts = np.unique(fold[order], return_index=True)
        ends = np.append(starts[1:], order.size)
        for f, a, b in zip(folds, starts, ends, strict=True):
            Xf, Yf = Xa[order[a:b]], Y[order[a:b]]
            new = [Xf.T @ Xf, Xf.T @ Yf, float(np.sum(Yf**2))]
            old = self.folds_.get(int(f))
            self.folds_[int(f)] = (
                new if old is None else [a + b for a, b in zip(old, new, strict=True)]
            )
        self._solve()
        return self

    @staticmethod
    def _thetas(Sxx, Sxy, scale, alphas):
        """Ridge solutions for all penalties, raw units: θ = [β; β0], shape (A, F + 1, D)."""
        n = Sxx[-1, -1]
        F = Sxx.shape[0] - 1
        A = len(alphas)
        if n < 1:
            return np.zeros((A, F + 1, Sxy.shape[1]))
        mx = Sxx[:F, -1] / n
        my = Sxy[-1] / n
        beta = np.zeros((A, F, Sxy.shape[1]))
        fin = np.isfinite(alphas)
        if F > 0 and np.any(fin):
            C = (Sxx[:F, :F] / n - np.outer(mx, mx)) / np.outer(scale, scale)
            c = (Sxy[:F] / n - np.outer(mx, my)) / scale[:, None]
            a = np.asarray(alphas, dtype=float)[fin]
            if a.size == 1:  # β = (C + α I)⁻¹ c
                beta[fin] = np.linalg.solve(C + a[0] * np.eye(F), c)[None]
            else:  # β(α) = U (Λ + α I)⁻¹ Uᵀ c for all α from one eigendecomposition C = U Λ Uᵀ
                lam, U = scipy.linalg.eigh(0.5 * (C + C.T), driver="evr", check_finite=False)
                Uc = (U.T @ c)[None] / (np.clip(lam, 0.0, None)[None, :, None] + a[:, None, None])
                beta[fin] = U @ Uc
            beta[fin] /= scale[None, :, None]
        icpt = my[None] - np.einsum("f,afd->ad", mx, beta)
        return np.concatenate([beta, icpt[:, None]], axis=1)

    def _solve(self) -> None:
        F = self.n_features_
        tot = None
        for v in self.folds_.values():
            tot = list(v) if tot is None else [a + b for a, b in zip(tot, v, strict=True)]
        self.n_samples_ = 0 if tot is None else int(round(tot[0][-1, -1]))
        if tot is None or tot[0][-1, -1] < 1:
            self.alpha_ = self.alphas[0]
            self.coef_ = np.zeros((F, self.n_outputs_))
            self.intercept_ = np.zeros(self.n_outputs_)
            self.cv_error_ = np.full(len(self.alphas), np.nan)
            return
        Sxx, Sxy, _ = tot
        n = Sxx[-1, -1]
        var = np.diag(Sxx)[:F] / n - (Sxx[:F, -1] / n) ** 2
        sd = np.sqrt(np.clip(var, 0.0, None))
        self.scale_ = np.where(sd > 1e-12 * max(1.0, float(sd.max(initial=0.0))), sd, np.inf)
        can = len(self.folds_) >= 2 and len(self.blocks_seen_) >= max(self.min_blocks, 2)
        g = self.reselect_growth
        n_sel = getattr(self, "n_selected_", 0)
        if can and g is not None and n_sel > 0 and n < g * n_sel:
            # keep the penalty chosen at n_sel rows; re-solve the coefficients only
            th = self._thetas(Sxx, Sxy, self.scale_, [self.alpha_])[0]
            self.coef_, self.intercept_ = th[:F], th[F]
            return
        errs = np.full(len(self.alphas), np.nan)
        if can:
            self.n_selected_ = n
            sse = np.zeros(len(self.alphas))
            for fx, fy, fyy in self.folds_.values():
                th = self._thetas(Sxx - fx, Sxy - fy, self.scale_, self.alphas)
                sse += fyy - 2.0 * np.sum(th * fy, axis=(1, 2))
                sse += np.sum(th * (fx @ th), axis=(1, 2))
            errs = sse / n
            best = int(np.nanargmin(errs))
        else:
            best = len(self.alphas) - 1  # cannot validate: the most regularised candidate
        self.cv_error_ = errs
        self.alpha_ = self.alphas[best]
        th = self._thetas(Sxx, Sxy, self.scale_, [self.alpha_])[0]
        self.coef_, self.intercept_ = th[:F], th[F]

    def predict(self, X) -> np.ndarray:
        """``f̂(X) (n, D)``; rows with NaN features predict 0 (no correction)."""
        X = np.asarray(X, dtype=float)
        out = X @ self.coef_  # non-finite where a feature is (NaN · 0 is NaN): no copy of X
        out += self.intercept_
        out[~np.all(np.isfinite(out), 1)] = 0.0
        return out


class AxisRidgeCorrection:
    """:class:`RidgeCorrection` on per-axis designs: ``X (n, D, K)`` -> ``Y (n, D)``.

    Each sample contributes D rows (one per output axis, ``Y[:, d] ≈ X[:, d] θ``) with one
    coefficient vector θ shared by the axes, as the segment-frame model needs
    (:func:`kinefuse.pipelines.features.segment_frame_design`); the D rows of a sample fall in
    the same cross-validation block. Parameters as :class:`RidgeCorrection` (``block`` in
    samples); the intercept is shared by the axes (the design's axis indicators carry the
    per-axis constants).
    """

    def __init__(self, **kwargs):
        self.ridge = RidgeCorrection(**kwargs)

    def fit(self, X, Y, t=None) -> AxisRidgeCorrection:
        """Fit on ``X (n, D, K)``, ``Y (n, D)`` at sample times ``t (n,)`` (default 0..n−1)."""
        self.ridge.fit(*self._rows(X, Y, t))
        return self

    def partial_fit(self, X, Y, t=None) -> AxisRidgeCorrection:
        """Accumulate the rows of more samples and re-solve; returns self."""
        self.ridge.partial_fit(*self._rows(X, Y, t))
        return self

    def predict(self, X) -> np.ndarray:
        """``f̂(X) (n, D)``; rows with NaN regressors predict 0 (no correction)."""
        X = np.asarray(X, dtype=float)
        n, D, K = X.shape
        return self.ridge.predict(X.reshape(n * D, K)).reshape(n, D)

    def __getattr__(self, name):
        # the fitted state and settings (alpha_, coef_, block...) are the inner regression's
        if name == "ridge":
            raise AttributeError(name)
        return getattr(self.ridge, name)

    @staticmethod
    def _rows(X, Y, t):
        X = np.asarray(X, dtype=float)
        Y = np.asarray(Y, dtype=float)
        n, D, K = X.shape
        t = np.arange(n) if t is None else np.asarray(t)
        return X.reshape(n * D, K), Y.reshape(n * D, 1), np.repeat(t, D)
