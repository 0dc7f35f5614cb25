"""``"kinefuse"``: IMU-chain + camera fusion with a learned, state-dependent chain-error model.

Per joint and axis a linear-Gaussian state-space model tracks the joint position together with
the slowly varying errors of both sensors, while a regression on IMU features learns the part of
the chain error that depends on the limb's state. During a camera outage the chain, corrected by
the regression and by the tracked error, carries the joint. See :func:`kinefuse_fusion`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kinefuse._compile import njit
from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU
from kinefuse.exceptions import InputError
from kinefuse.pipelines.features import chain_features

__all__ = [
    "KinefuseResult",
    "NoiseParameters",
    "RidgeCorrection",
    "estimate_noise",
    "kinefuse_fusion",
]

_N_X = 4  # per axis: [p, v, b, c]
_H_CAM = np.array([1.0, 0.0, 0.0, 1.0])  # z_cam = p + c + n_V
_H_IMU = np.array([1.0, 0.0, 1.0, 0.0])  # z_imu + f(φ) = p + b + n_I
_VAR_FLOOR_M2 = (
    1e-6  # (1 mm)²: smallest white-noise variance (below: neither credible nor identifiable)
)
#: Default ridge penalties of :class:`RidgeCorrection` (last: intercept only).
_ALPHAS = (*np.logspace(-4, 3, 15).tolist(), float("inf"))
_TAU_GRID = np.exp(np.linspace(np.log(1.0), np.log(3.0e4), 48))  # GM correlation times, samples


# --------------------------------------------------------------------------- kernels (numba)
@njit
def _scalar_update(x, P, z, h, r):
    ph = P @ h  # P Hᵀ
    s = h @ ph + r  # S = H P Hᵀ + R   (scalar)
    k = ph / s  # K = P Hᵀ S⁻¹
    x = x + k * (z - h @ x)  # x⁺ = x⁻ + K ν
    A = np.eye(P.shape[0]) - np.outer(k, h)
    P = A @ P @ A.T + r * np.outer(k, k)  # Joseph form (SPEC §1 numerical hygiene)
    return x, 0.5 * (P + P.T)


@njit
def _kf_two_sensors(z_cam, z_imu, F, Q, r_cam, r_imu, x0, P0, h_cam, h_imu, x_out, P_out):
    """Forward KF, batch (B, T); each sample has two scalar measurements, either may be NaN."""
    B, T = z_cam.shape
    for b in range(B):
        x = x0[b].copy()
        P = P0[b].copy()
        for t in range(T):
            if t > 0:
                x = F[b] @ x  # x⁻ = F x
                P = F[b] @ P @ F[b].T + Q[b]  # P⁻ = F P Fᵀ + Q
                P = 0.5 * (P + P.T)
            if np.isfinite(z_cam[b, t]):
                x, P = _scalar_update(x, P, z_cam[b, t], h_cam, r_cam[b])
            if np.isfinite(z_imu[b, t]):
                x, P = _scalar_update(x, P, z_imu[b, t], h_imu, r_imu[b])
            x_out[b, t] = x
            P_out[b, t] = P


@njit
def _rts_backward(xf, Pf, F, Q, t_end, t_stop, xs_end, Ps_end):
    """RTS from ``t_end`` (smoothed = given) down to ``t_stop``; returns the value at t_stop."""
    xs = xs_end.copy()
    Ps = Ps_end.copy()
    for t in range(t_end - 1, t_stop - 1, -1):
        Pp = F @ Pf[t] @ F.T + Q  # P⁻_{t+1}
        C = np.linalg.solve(Pp + 1e-15 * np.eye(Pp.shape[0]), F @ Pf[t]).T  # C = P̂ Fᵀ (P⁻)⁻¹
        xs = xf[t] + C @ (xs - F @ xf[t])
        Ps = Pf[t] + C @ (Ps - Pp) @ C.T
        Ps = 0.5 * (Ps + Ps.T)
    return xs, Ps


@njit
def _smooth(xf, Pf, F, Q, lag, x_out, P_out):
    """Fixed-interval RTS (lag < 0) or fixed-lag RTS with ``lag`` samples, batch (B, T)."""
    B, T = xf.shape[0], xf.shape[1]
    for b in range(B):
        if lag < 0:
            xs = xf[b, T - 1].copy()
            Ps = Pf[b, T - 1].copy()
            x_out[b, T - 1] = xs
            P_out[b, T - 1] = Ps
            for t in range(T - 2, -1, -1):
                xs, Ps = _rts_backward(xf[b], Pf[b], F[b], Q[b], t + 1, t, xs, Ps)
                x_out[b, t] = xs
                P_out[b, t] = Ps
        else:
            for t in range(T):
                e = min(t + lag, T - 1)
                xs, Ps = _rts_backward(xf[b], Pf[b], F[b], Q[b], e, t, xf[b, e], Pf[b, e])
                x_out[b, t] = xs
                P_out[b, t] = Ps


# --------------------------------------------------------------------------- noise model
@dataclass(frozen=True)
class NoiseParameters:
    """Noise parameters of the per-axis model, arrays of shape ``(..., 3)`` (one per axis).

    Attributes
    ----------
    q : ndarray
        Variance of the velocity increment per step, (m/s)² (paper A's q, SPEC §1).
    r_cam, r_imu : ndarray
        White measurement-noise variances of the camera and of the corrected IMU chain, m².
    var_b, phi_b : ndarray
        Stationary variance (m²) and per-step autocorrelation of the chain-error state b
        (first-order Gauss-Markov; ``phi_b → 1`` is a random walk).
    var_c, phi_c : ndarray
        The same for the camera-error state c.
    """

    q: np.ndarray
    r_cam: np.ndarray
    r_imu: np.ndarray
    var_b: np.ndarray
    phi_b: np.ndarray
    var_c: np.ndarray
    phi_c: np.ndarray

    @classmethod
    def default(cls, shape=(3,)) -> NoiseParameters:
        """Before any camera-seen history: q = 0.1 and R_V = 1e-3 m² (SPEC §12.2), R_I = 1e-4 m².

        R_I is 1 cm² rather than SPEC's 1e-2 m² [J]: without camera history the chain is the
        only sensor and should be followed, not smoothed with a 10 cm noise model.
        """
        f = lambda v: np.full(shape, float(v))  # noqa: E731
        return cls(f(0.1), f(1e-3), f(1e-4), f(0.0), f(0.0), f(0.0), f(0.0))


def _gm_fit(V: np.ndarray, w: np.ndarray, tau_max: float = np.inf) -> tuple[float, float, float]:
    """Fit ``V(k) = 2 r + 2 σ² (1 − φ^k)`` (k = 1..K) with r, σ² >= 0; weighted least squares.

    Grid over the correlation time τ (φ = e^{−1/τ}); for each τ a 2-parameter non-negative
    least-squares fit; the best τ is kept. Returns ``(r, σ², φ)``.
    """
    k = np.arange(1, V.size + 1, dtype=float)
    sw = np.sqrt(w)
    best = (np.inf, max(0.5 * V[0], 0.0) if V.size else 0.0, 0.0, 0.0)
    for tau in _TAU_GRID[_TAU_GRID <= tau_max]:
        phi = np.exp(-1.0 / tau)
        A = np.stack([np.full_like(k, 2.0), 2.0 * (1.0 - phi**k)], axis=1) * sw[:, None]
        y = V * sw
        cands = []
        sol, *_ = np.linalg.lstsq(A, y, rcond=None)
        if np.all(sol >= 0):
            cands.append(sol)
        for i in range(2):  # one parameter at zero
            a = A[:, 1 - i]
            c = max(float(a @ y) / max(float(a @ a), 1e-300), 0.0)
            s = np.zeros(2)
            s[1 - i] = c
            cands.append(s)
        for s in cands:
            sse = float(np.sum((A @ s - y) ** 2))
            if sse < best[0]:
                best = (sse, float(s[0]), float(s[1]), float(phi))
    return best[1], best[2], best[3]


def estimate_noise(z_cam, z_imu, available, dt_s: float, *, max_lag: int = 60) -> NoiseParameters:
    """Estimate the noise parameters from camera-seen data (cross-variogram "three-cornered hat").

    Parameters
    ----------
    z_cam : array_like, shape (T, 3)
        Camera positions of one joint, m (NaN where not seen).
    z_imu : array_like, shape (T, 3)
        Corrected IMU-chain positions ``z_imu + f̂(φ)`` of the same joint, m.
    available : array_like of bool, shape (T,)
        Camera-seen samples; only pairs/triples of seen samples are used.
    dt_s : float
        Sampling interval, s.
    max_lag : int
        Largest lag K of the variograms, samples.

    Returns
    -------
    NoiseParameters
        Arrays of shape (3,) (per axis). Defaults (:meth:`NoiseParameters.default`) for axes with
        fewer than 8 usable pairs.

    Notes
    -----
    Both sensors see the same motion p: ``z_cam = p + e_V``, ``z_imu = p + e_I`` with errors
    independent of each other and of p. For lag-k differences ``Δ_k``::

        E[Δ_k z_cam · Δ_k z_imu] = E[(Δ_k p)²]
        V_V(k) = E[Δ_k z_cam (Δ_k z_cam − Δ_k z_imu)] = E[(Δ_k e_V)²]
        V_I(k) = E[Δ_k z_imu (Δ_k z_imu − Δ_k z_cam)] = E[(Δ_k e_I)²]

    so each sensor's error variogram is identified separately (the idea of the three-cornered
    hat, with the common motion as the third "clock"). Each error is modelled as white noise
    plus a first-order Gauss-Markov process, whose variogram is ``2 r + 2 σ² (1 − φ^k)``; it
    is fitted over k = 1..K by non-negative weighted least squares on a grid of correlation
    times, with weights ``n_k / (E[(Δ_k z_cam)²] + E[(Δ_k z_imu)²])²`` (number of pairs over
    the approximate variance of the estimate, which grows with the motion at lag k). The motion model's q comes from second differences:
    ``E[Δ² z_cam Δ² z_imu] = E[(Δ² p)²] = q dt² / 2`` for the constant-velocity model with
    ``Q = q [[dt²/4, dt/2], [dt/2, 1]]``, floored at a tenth of the chain's own
    ``E[(Δ² z_imu)²]`` (the cross moment can be near zero when the camera is noisy). White
    variances are floored at (1 mm)².
    """
    zc = np.asarray(z_cam, dtype=float)
    zi = np.asarray(z_imu, dtype=float)
    ok = (
        np.asarray(available, dtype=bool)
        & np.all(np.isfinite(zc), -1)
        & np.all(np.isfinite(zi), -1)
    )
    T = zc.shape[0]
    out = {k: np.empty(3) for k in ("q", "r_cam", "r_imu", "var_b", "phi_b", "var_c", "phi_c")}
    dflt = NoiseParameters.default()
    K = int(max(1, min(max_lag, T - 1)))
    Vc = np.zeros((K, 3))
    Vi = np.zeros((K, 3))
    Vt = np.ones((K, 3))
    n = np.zeros(K)
    for k in range(1, K + 1):
        m = ok[k:] & ok[:-k]
        n[k - 1] = m.sum()
        if n[k - 1] == 0:
            continue
        dc = zc[k:][m] - zc[:-k][m]
        di = zi[k:][m] - zi[:-k][m]
        Vc[k - 1] = np.mean(dc * (dc - di), axis=0)
        Vi[k - 1] = np.mean(di * (di - dc), axis=0)
        Vt[k - 1] = np.maximum(np.mean(dc * dc + di * di, axis=0), 1e-300)
    m3 = ok[2:] & ok[1:-1] & ok[:-2] if T >= 3 else np.zeros(0, bool)
    use = n >= 8
    for a in range(3):
        if m3.sum() < 8 or not np.any(use):
            for key in out:
                out[key][a] = getattr(dflt, key)[a]
            continue
        d2c = zc[2:, a][m3] - 2 * zc[1:-1, a][m3] + zc[:-2, a][m3]
        d2i = zi[2:, a][m3] - 2 * zi[1:-1, a][m3] + zi[:-2, a][m3]
        out["q"][a] = (
            2.0 * max(float(np.mean(d2c * d2i)), 0.1 * float(np.mean(d2i * d2i)), 1e-12) / dt_s**2
        )
        w = n[use] / Vt[use, a] ** 2
        r, s2, phi = _gm_fit(Vc[use, a], w, tau_max=float(K))
        out["r_cam"][a], out["var_c"][a], out["phi_c"][a] = max(r, _VAR_FLOOR_M2), s2, phi
        r, s2, phi = _gm_fit(Vi[use, a], w)
        out["r_imu"][a], out["var_b"][a], out["phi_b"][a] = max(r, _VAR_FLOOR_M2), s2, phi
    return NoiseParameters(**out)


# --------------------------------------------------------------------------- learned correction
class RidgeCorrection:
    """Ridge regression of the chain error on IMU features, from accumulated moments (streaming).

    Parameters
    ----------
    alphas : sequence of float
        Candidate ridge penalties on the standardised coefficients (dimensionless, per sample):
        ``β = (C + α I)⁻¹ c`` with C the feature correlation matrix and c the standardised
        feature-target covariances; ``inf`` = intercept only. The intercept is not penalised.
        The penalty is chosen by blocked leave-one-block-out cross-validation.
    block : int
        Block length of the cross-validation, samples (default 30 = 1 s at 30 Hz). Blocks are
        contiguous in time, so the serially correlated errors of a block do not leak into its
        own prediction (a plain GCV would pick a far too small penalty here).

    Attributes
    ----------
    alpha_ : float
        Selected penalty.
    coef_ : ndarray, shape (F, D)
    intercept_ : ndarray, shape (D,)
    cv_error_ : ndarray, shape (len(alphas),)
        Mean squared CV prediction error per candidate, m².

    Notes
    -----
    ``partial_fit(X, Y, t)`` adds the moments ``n, Σx̃x̃ᵀ, Σx̃yᵀ, Σyᵀy`` (``x̃ = [x, 1]``) of
    the rows to the block ``t // block`` of each row; ``fit`` = fresh moments + one
    ``partial_fit``. Each solve uses only the stored moments: for a held-out block the
    training moments are the totals minus the block's, and its squared error is
    ``Σyᵀy − 2 θᵀ Σx̃y + θᵀ Σx̃x̃ᵀ θ``. Features are standardised with the moments of all
    blocks. With fewer than 2 blocks nothing can be validated and the largest penalty of the
    grid is used (by default ``inf``: intercept only).
    """

    def __init__(self, alphas=_ALPHAS, block: int = 30):
        self.alphas = tuple(float(a) for a in alphas)
        self.block = int(block)

    def fit(self, X, Y, t=None) -> RidgeCorrection:
        """Fit on ``X (n, F)``, ``Y (n, D)`` at sample times ``t (n,)`` (default 0..n−1)."""
        self.blocks_ = {}
        return self.partial_fit(X, Y, t)

    def partial_fit(self, X, Y, t=None) -> RidgeCorrection:
        """Accumulate the moments of more rows and re-solve; returns self."""
        X = np.asarray(X, dtype=float)
        Y = np.asarray(Y, dtype=float)
        t = np.arange(X.shape[0]) if t is None else np.asarray(t)
        if not hasattr(self, "blocks_"):
            self.blocks_ = {}
        ok = np.all(np.isfinite(X), 1) & np.all(np.isfinite(Y), 1)
        X, Y, t = X[ok], Y[ok], t[ok]
        Xa = np.concatenate([X, np.ones((X.shape[0], 1))], axis=1)
        self.n_features_ = X.shape[1]
        self.n_outputs_ = Y.shape[1]
        for b in np.unique(t // self.block):
            m = t // self.block == b
            new = np.array([Xa[m].T @ Xa[m], Xa[m].T @ Y[m], np.sum(Y[m] ** 2)], dtype=object)
            self.blocks_[int(b)] = new if b not in self.blocks_ else self.blocks_[int(b)] + new
        self._solve()
        return self

    @staticmethod
    def _theta(Sxx, Sxy, scale, alpha):
        """Ridge in standardised units from raw augmented moments; θ = [β; β0] raw units."""
        n = Sxx[-1, -1]
        F = Sxx.shape[0] - 1
        if n < 1:
            return np.zeros((F + 1, Sxy.shape[1]))
        mx = Sxx[:F, -1] / n
        my = Sxy[-1] / n
        if not np.isfinite(alpha) or F == 0:
            beta = np.zeros((F, Sxy.shape[1]))
        else:
            C = (Sxx[:F, :F] / n - np.outer(mx, mx)) / np.outer(scale, scale)
            c = (Sxy[:F] / n - np.outer(mx, my)) / scale[:, None]
            beta = np.linalg.solve(C + alpha * np.eye(F), c) / scale[:, None]
        return np.concatenate([beta, (my - mx @ beta)[None]], axis=0)

    def _solve(self) -> None:
        F = self.n_features_
        tot = sum(self.blocks_.values()) if self.blocks_ else None
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
        errs = np.full(len(self.alphas), np.nan)
        if len(self.blocks_) >= 2:
            for i, a in enumerate(self.alphas):
                sse = 0.0
                for blk in self.blocks_.values():
                    th = self._theta(Sxx - blk[0], Sxy - blk[1], self.scale_, a)
                    sse += blk[2] - 2.0 * np.sum(th * blk[1]) + np.sum(th * (blk[0] @ th))
                errs[i] = sse / n
            best = int(np.nanargmin(errs))
        else:
            best = len(self.alphas) - 1  # cannot validate: the most regularised candidate
        self.cv_error_ = errs
        self.alpha_ = self.alphas[best]
        th = self._theta(Sxx, Sxy, self.scale_, self.alpha_)
        self.coef_, self.intercept_ = th[:F], th[F]

    def predict(self, X) -> np.ndarray:
        """``f̂(X) (n, D)``; rows with NaN features predict 0 (no correction)."""
        X = np.asarray(X, dtype=float)
        out = self.intercept_ + np.nan_to_num(X) @ self.coef_
        out[~np.all(np.isfinite(X), 1)] = 0.0
        return out


# --------------------------------------------------------------------------- result
@dataclass(frozen=True, eq=False)
class KinefuseResult:
    """Output of :func:`kinefuse_fusion`.

    Attributes
    ----------
    position : ndarray, shape (T, J, 3)
        Fused joint positions, m.
    cov : ndarray, shape (T, J, 3, 3)
        Their covariance (diagonal: the axes are independent problems), m².
    source : ndarray of int8, shape (T, J)
        :data:`kinefuse.conventions.SOURCE_NAMES` codes: ``SOURCE_FUSED`` where the camera saw
        the joint, ``SOURCE_BRIDGED`` in an outage bridged by the corrected chain, ``SOURCE_IMU``
        in an outage before any camera-seen history (uncorrected chain).
    correction : ndarray, shape (T, J, 3)
        The learned correction ``f̂(φ_t)`` added to the chain, m (the one in use at t).
    chain_error : ndarray, shape (T, J, 3)
        Estimated residual chain error b (state), m.
    params : list of dict
        Per joint: the fitted noise parameters and ridge model of the last refit.
    """

    position: np.ndarray
    cov: np.ndarray
    source: np.ndarray
    correction: np.ndarray
    chain_error: np.ndarray
    params: list = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- core
def _model_matrices(p: NoiseParameters, dt: float):
    """``F, Q (3, 4, 4)`` per axis for states [p, v, b, c]."""
    F = np.zeros((3, _N_X, _N_X))
    Q = np.zeros((3, _N_X, _N_X))
    g = np.array([dt / 2.0, 1.0])
    for a in range(3):
        F[a] = np.array(
            [
                [1.0, dt, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0, 0, p.phi_b[a], 0],
                [0, 0, 0, p.phi_c[a]],
            ]
        )
        Q[a, :2, :2] = p.q[a] * np.outer(g, g)
        Q[a, 2, 2] = p.var_b[a] * (1.0 - p.phi_b[a] ** 2)
        Q[a, 3, 3] = p.var_c[a] * (1.0 - p.phi_c[a] ** 2)
    return F, Q


def _run(zc, zi, p: NoiseParameters, dt: float, lag: int):
    """Filter (+ smoother) one joint: ``zc, zi (T, 3)`` -> mean (3, T, 4), cov (3, T, 4, 4)."""
    T = zc.shape[0]
    F, Q = _model_matrices(p, dt)
    x0 = np.zeros((3, _N_X))
    P0 = np.zeros((3, _N_X, _N_X))
    for a in range(3):
        first = np.concatenate(
            [zc[:, a][np.isfinite(zc[:, a])], zi[:, a][np.isfinite(zi[:, a])], [0.0]]
        )
        x0[a, 0] = first[0]
        P0[a] = np.diag([1.0, 1.0, p.var_b[a], p.var_c[a]])
    zc_b = np.ascontiguousarray(zc.T)
    zi_b = np.ascontiguousarray(zi.T)
    xf = np.empty((3, T, _N_X))
    Pf = np.empty((3, T, _N_X, _N_X))
    _kf_two_sensors(zc_b, zi_b, F, Q, p.r_cam, p.r_imu, x0, P0, _H_CAM, _H_IMU, xf, Pf)
    if lag == 0:
        return xf, Pf
    xs = np.empty_like(xf)
    Ps = np.empty_like(Pf)
    _smooth(xf, Pf, F, Q, int(lag), xs, Ps)
    return xs, Ps


def _fit_joint(zc, zi, phi, seen, dt, alpha, max_lag):
    """Refit the correction and the noise parameters of one joint on the ``seen`` samples."""
    block = max(2, int(round(1.0 / dt)))
    t = np.flatnonzero(seen)
    reg = RidgeCorrection(block=block, **({} if alpha is None else {"alphas": alpha})).fit(
        phi[seen], (zc - zi)[seen], t
    )
    corr = reg.predict(phi)
    zic = zi + corr
    params = estimate_noise(np.where(seen[:, None], zc, np.nan), zic, seen, dt, max_lag=max_lag)
    return reg, corr, params


def _check(z_imu, z_cam, available, dt_s, features):
    zi = np.asarray(z_imu)
    zc = np.asarray(z_cam)
    for name, z in (("z_imu", zi), ("z_cam", zc)):
        if not np.issubdtype(z.dtype, np.floating) or z.ndim != 3 or z.shape[-1] != 3:
            raise InputError(
                f"expected {name} as floats with shape (T, J, 3), got {z.shape} {z.dtype}"
            )
    if zc.shape != zi.shape:
        raise InputError(f"expected z_cam with the shape of z_imu {zi.shape}, got {zc.shape}")
    T, J, _ = zi.shape
    if T < 1 or J < 1:
        raise InputError(
            f"expected at least one sample and one joint, got z_imu with shape {zi.shape}"
        )
    av = np.asarray(available)
    if av.dtype != bool or av.shape != (T, J):
        raise InputError(
            f"expected available as bool with shape (T, J) = {(T, J)}, got {av.shape} {av.dtype}"
        )
    if isinstance(dt_s, bool):
        raise InputError(f"expected dt_s as a positive number of seconds, got {dt_s!r}")
    try:
        dt = float(dt_s)
    except (TypeError, ValueError):
        raise InputError(f"expected dt_s as a positive number of seconds, got {dt_s!r}") from None
    if not np.isfinite(dt) or dt <= 0:
        raise InputError(f"expected dt_s finite and > 0, got {dt_s!r}")
    if np.any(np.isinf(zi)):
        raise InputError("expected z_imu finite or NaN (missing), got ±inf")
    zc = np.where(av[..., None], zc, np.nan).astype(float)
    if np.any(~np.isfinite(zc[av])):
        raise InputError("expected z_cam finite where available is True, got NaN/inf")
    if features is not None:
        ft = np.asarray(features)
        if not np.issubdtype(ft.dtype, np.floating) or ft.ndim != 3 or ft.shape[:2] != (T, J):
            raise InputError(
                f"expected features as floats with shape (T, J, F) = ({T}, {J}, F), got {ft.shape}"
            )
        features = ft.astype(float)
    return zi.astype(float), zc, av, dt, features


def kinefuse_fusion(
    z_imu,
    z_cam,
    available,
    dt_s: float,
    *,
    causal: bool = False,
    features=None,
    lag: int = 0,
    parents=None,
    alpha=None,
    max_lag: int | None = None,
    min_history: int = 30,
    refit_every: int | None = 60,
) -> KinefuseResult:
    """Fuse an IMU chain and a camera with a learned, state-dependent chain-error model.

    Parameters
    ----------
    z_imu : array_like, shape (T, J, 3)
        IMU-chain joint positions (SPEC §2.1/§2.2), m, in the frame of ``z_cam`` (aligned,
        e.g. Kabsch, SPEC §2.2 "Kinect side"). NaN rows = IMU sample missing (not measured).
    z_cam : array_like, shape (T, J, 3)
        Camera joint positions, m; ignored where ``available`` is False.
    available : array_like of bool, shape (T, J)
        Camera availability per joint (SPEC §2.2 outage definition).
    dt_s : float
        Sampling interval of the common timeline, s (SPEC §12.2: 1/30 s).
    causal : bool
        False (offline): one fit on all camera-seen samples and a fixed-interval RTS smoother
        over the whole series. True: everything at t uses only samples up to ``t + lag``
        (refits at outage onsets and every ``refit_every`` samples; forward filter, or a
        fixed-lag smoother with ``lag > 0``).
    features : array_like, shape (T, J, F), optional
        IMU features φ per joint (:func:`kinefuse.pipelines.features.imu_features`: segment
        orientation elements, angular rates, relative rotations). Default: features from the
        chain positions alone (:func:`kinefuse.pipelines.features.chain_features`: segment
        direction and length from ``parents``, position and finite-difference velocity). The
        chain's backward-difference velocity is appended to given features (it absorbs a
        residual time offset between the streams, ``e(t) ≈ −δ ż(t)``).
    lag : int
        Causal mode only: fixed-lag smoothing delay, samples (0 = filter).
    parents : sequence of int, optional
        Parent joint index (or -1) of each joint, for the default features.
    alpha : sequence of float, optional
        Candidate ridge penalties of the correction (default: :class:`RidgeCorrection`'s grid,
        chosen by blocked cross-validation with 1 s blocks).
    max_lag : int, optional
        Largest lag of the noise variograms, samples (:func:`estimate_noise`); default 1 s.
    min_history : int
        Camera-seen samples needed before the first fit (causal mode); before it the
        correction is zero and the noise parameters are SPEC §12.2 defaults.
    refit_every : int or None
        Causal mode: also refit every this many samples (None: only at outage onsets).

    Returns
    -------
    KinefuseResult
        ``position (T, J, 3)``, ``cov (T, J, 3, 3)``, ``source (T, J)`` and diagnostics.

    Notes
    -----
    **Model** (per joint, independently per axis; state ``x = [p, v, b, c]``)::

        p_{t+1} = p_t + dt v_t + dt/2 w_t ,   v_{t+1} = v_t + w_t ,   w ~ N(0, q)
        b_{t+1} = φ_b b_t + u_t ,  u ~ N(0, σ_b² (1 − φ_b²))      chain-error residual
        c_{t+1} = φ_c c_t + s_t ,  s ~ N(0, σ_c² (1 − φ_c²))      camera coloured error
        z_cam_t               = p_t + c_t + n_V ,  n_V ~ N(0, R_V)   (when available)
        z_imu_t + f̂(φ_t)      = p_t + b_t + n_I ,  n_I ~ N(0, R_I)   (always)

    ``f̂`` is a ridge regression (:class:`RidgeCorrection`) of the chain error
    ``e_t = z_cam_t − z_imu_t`` on the IMU features ``φ_t`` over all camera-seen samples so far,
    its penalty chosen by leave-one-block-out cross-validation over 1 s blocks; it captures the
    error that follows the limb's state (soft-tissue motion, axis, length and offset
    errors). ``b`` (first-order Gauss-Markov, a random walk when ``φ_b → 1``) captures what the
    regression misses and ``c`` the camera's correlated error (e.g. bone-length variation).

    **Noise parameters** (q, R_V, R_I, σ_b², φ_b, σ_c², φ_c) are estimated per joint and axis
    from the camera-seen data by :func:`estimate_noise` (lag-k cross-variograms of the two
    sensors), after the correction; no per-trial constants.

    **Offline**: fit on all camera-seen samples, forward KF (sequential scalar updates, NaN =
    not measured), fixed-interval RTS (SPEC §9 equations). In an outage the smoother
    interpolates b between its values before and after. **Causal**: at each refit time t_k
    (outage onsets, every ``refit_every`` samples, once ``min_history`` camera samples exist)
    the regression and the noise parameters are refitted on the camera-seen history before
    t_k and the filter is re-run over the history with the new correction (the moments are
    accumulated, so this is a streaming computation); outputs in ``[t_k, t_{k+1})`` come from
    that run (fixed-lag smoothed with ``lag > 0``). In an outage b decays as ``φ_b^k``.

    Deviations from the papers
    --------------------------
    Not in paper A or B: a third method of this package. It replaces paper B's IMM of two
    position filters (SPEC §8) and ELM-1/ELM-2 (SPEC §10) by one state-space model with both
    sensors as measurements and a regression on IMU features instead of on positions.
    """
    if not isinstance(causal, (bool, np.bool_)):
        raise InputError(f"expected causal as a bool, got {causal!r}")
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
        raise InputError(f"expected lag as an int >= 0 (samples), got {lag!r}")
    if not causal and lag != 0:
        raise InputError("lag applies to causal=True only (offline mode smooths the whole series)")
    zi, zc, av, dt, phi = _check(z_imu, z_cam, available, dt_s, features)
    base = chain_features(zi, dt, parents)
    # the chain's velocity is always a feature: it absorbs a residual time offset between the
    # streams (e(t) ≈ −δ ż(t)); the rest comes from the IMU features when given
    phi = base if phi is None else np.concatenate([phi, base[..., -3:]], axis=-1)
    if max_lag is None:
        max_lag = max(2, int(round(1.0 / dt)))
    T, J, _ = zi.shape
    pos = np.empty((T, J, 3))
    cov = np.zeros((T, J, 3, 3))
    corr_all = np.zeros((T, J, 3))
    bias = np.zeros((T, J, 3))
    source = np.where(av, SOURCE_FUSED, SOURCE_BRIDGED).astype(np.int8)
    params = []
    for j in range(J):
        seen = av[:, j]
        if not causal:
            if seen.sum() >= 2:
                reg, corr, pj = _fit_joint(zc[:, j], zi[:, j], phi[:, j], seen, dt, alpha, max_lag)
            else:
                reg, corr, pj = None, np.zeros((T, 3)), NoiseParameters.default()
                source[~seen, j] = SOURCE_IMU
            m, P = _run(zc[:, j], zi[:, j] + corr, pj, dt, -1)
            pos[:, j] = m[..., 0].T
            cov[:, j, range(3), range(3)] = P[..., 0, 0].T
            bias[:, j] = m[..., 2].T
            corr_all[:, j] = corr
            params.append({"noise": pj, "correction": reg})
            continue
        # causal: epochs between refit times
        n_seen = np.cumsum(seen)  # seen samples in [0, t]
        onset = np.flatnonzero(~seen[1:] & seen[:-1]) + 1
        times = set(int(t) for t in onset)
        first = np.flatnonzero(n_seen >= min_history)
        if first.size:
            times.add(int(first[0]) + 1)
            if refit_every:
                times.update(range(int(first[0]) + 1, T, int(refit_every)))
        times = sorted(t for t in times if 0 < t < T and n_seen[t - 1] >= min(min_history, 2))
        bounds = [0, *times, T]
        last = {"noise": NoiseParameters.default(), "correction": None}
        for k in range(len(bounds) - 1):
            t0, t1 = bounds[k], bounds[k + 1]
            if t0 == t1:
                continue
            end = min(t1 + lag, T)
            hist = seen[:t0].copy()
            if k == 0 or hist.sum() < 2:
                corr = np.zeros((end, 3))
                pj = NoiseParameters.default()
                reg = None
                source[t0:t1, j][~seen[t0:t1]] = SOURCE_IMU
            else:
                reg, _, pj = _fit_joint(
                    zc[:t0, j], zi[:t0, j], phi[:t0, j], hist, dt, alpha, max_lag
                )
                corr = reg.predict(phi[:end, j])
            zc_e = zc[:end, j].copy()
            m, P = _run(zc_e, zi[:end, j] + corr, pj, dt, lag)
            pos[t0:t1, j] = m[:, t0:t1, 0].T
            cov[t0:t1, j, range(3), range(3)] = P[:, t0:t1, 0, 0].T
            bias[t0:t1, j] = m[:, t0:t1, 2].T
            corr_all[t0:t1, j] = corr[t0:t1]
            last = {"noise": pj, "correction": reg}
        params.append(last)
    return KinefuseResult(
        position=pos,
        cov=cov,
        source=source,
        correction=corr_all,
        chain_error=bias,
        params=params,
        info={"causal": bool(causal), "lag": int(lag), "n_features": int(phi.shape[-1])},
    )
