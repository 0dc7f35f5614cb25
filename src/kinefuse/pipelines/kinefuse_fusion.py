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
import scipy.linalg

from kinefuse._compile import njit
from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU
from kinefuse.exceptions import InputError
from kinefuse.pipelines.features import chain_features
from kinefuse.pipelines.offset_bridge import prequential_bridge

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
# causal mode (see kinefuse_fusion, Notes "Causal")
_N_FOLDS_CAUSAL = 10  # CV folds of the streaming ridge (bounded cost per re-solve)
_PRIOR_S = 2.0  # weight of the conservative noise prior, seconds of pseudo-data
_PRIOR_R_CAM = 1e-3  # prior camera white noise, m² (SPEC §12.2 R_V)
_PRIOR_R_IMU = 1e-4  # prior white noise of the corrected chain, m² (1 cm)²
_PRIOR_VAR_B = 2.5e-3  # prior stationary variance of the chain error b, m² (5 cm)²
_PRIOR_TAU_B_S = 1.0  # prior correlation time of b, s (b decays in an outage)
_PRIOR_Q = 0.1  # prior q (SPEC §12.2)
_MIN_FIT_S = 3.0  # camera-seen history before the correction uses more than an intercept, s
_TAU_GRID = np.exp(np.linspace(np.log(1.0), np.log(3.0e4), 48))  # GM correlation times, samples
#: Candidate relative motion gains γ of the offline noise fit (estimate_noise, Notes): a sensor
#: error proportional to the motion, up to ±50 % of it, in steps of 1 %.
_GAIN_GRID = np.linspace(-0.5, 0.5, 101)
_GAIN_STEP = float(_GAIN_GRID[1] - _GAIN_GRID[0])  # refined around the best point in 1/20 steps


# --------------------------------------------------------------------------- kernels (numba)
@njit
def _scalar_update(x, P, z, h, r):
    """Scalar measurement update in place (no allocation): ``x (n,)``, ``P (n, n)``."""
    n = x.shape[0]
    ph = np.zeros(n)
    for i in range(n):
        for j in range(n):
            ph[i] += P[i, j] * h[j]  # P Hᵀ
    s = r  # S = H P Hᵀ + R   (scalar)
    nu = z  # ν = z − H x
    for i in range(n):
        s += h[i] * ph[i]
        nu -= h[i] * x[i]
    k = ph / s  # K = P Hᵀ S⁻¹
    for i in range(n):
        x[i] += k[i] * nu  # x⁺ = x⁻ + K ν
    # Joseph form (SPEC §1 numerical hygiene), expanded for a scalar update:
    # (I − K H) P (I − K H)ᵀ + K R Kᵀ = P − K (P Hᵀ)ᵀ − (P Hᵀ) Kᵀ + S K Kᵀ   (symmetric)
    for i in range(n):
        for j in range(i, n):
            v = P[i, j] - k[i] * ph[j] - ph[i] * k[j] + s * k[i] * k[j]
            P[i, j] = v
            P[j, i] = v


@njit
def _predict(x, P, F, Q):
    """Prediction in place: ``x ← F x``, ``P ← F P Fᵀ + Q`` (symmetrised)."""
    n = x.shape[0]
    xn = F @ x  # x⁻ = F x
    FP = F @ P
    for i in range(n):
        x[i] = xn[i]
        for j in range(i, n):
            v = Q[i, j]
            for m in range(n):
                v += FP[i, m] * F[j, m]  # P⁻ = F P Fᵀ + Q
            P[i, j] = v
            P[j, i] = v


@njit
def _kf_segment(z_cam, z_imu, F, Q, r_cam, r_imu, x, P, predict_first, h_cam, h_imu, x_out, P_out):
    """Forward KF over one segment, batch (B, L), continuing from ``x (B, n)``, ``P (B, n, n)``.

    Each sample has two scalar measurements, either may be NaN (not measured). The first
    sample is predicted from ``(x, P)`` when ``predict_first`` (a continuation), else ``(x, P)``
    is the prior of the first sample. ``x`` and ``P`` are overwritten with the last posterior.
    """
    B, L = z_cam.shape
    for b in range(B):
        xb = x[b].copy()
        Pb = P[b].copy()
        for t in range(L):
            if t > 0 or predict_first:
                _predict(xb, Pb, F[b], Q[b])
            if np.isfinite(z_cam[b, t]):
                _scalar_update(xb, Pb, z_cam[b, t], h_cam, r_cam[b])
            if np.isfinite(z_imu[b, t]):
                _scalar_update(xb, Pb, z_imu[b, t], h_imu, r_imu[b])
            x_out[b, t] = xb
            P_out[b, t] = Pb
        x[b] = xb
        P[b] = Pb


@njit
def _rts_step(xf, Pf, F, Q, xs, Ps):
    """One RTS step back: filtered ``(xf, Pf)`` at t, smoothed ``(xs, Ps)`` at t+1, F, Q: t -> t+1."""
    Pp = F @ Pf @ F.T + Q  # P⁻_{t+1}
    C = np.linalg.solve(Pp + 1e-15 * np.eye(Pp.shape[0]), F @ Pf).T  # C = P̂ Fᵀ (P⁻)⁻¹
    xs = xf + C @ (xs - F @ xf)  # x̃_t = x̂_t + C (x̃_{t+1} − F x̂_t)
    Ps = Pf + C @ (Ps - Pp) @ C.T  # P̃_t = P̂_t + C (P̃_{t+1} − P⁻) Cᵀ
    return xs, 0.5 * (Ps + Ps.T)


@njit
def _smooth(xf, Pf, F, Q, lag, x_out, P_out):
    """RTS over a batch (B, T): fixed-interval (``lag < 0``) or fixed-lag with ``lag`` samples.

    ``F[b, t], Q[b, t]`` are the transition into sample t (from t − 1); time-varying, so the
    causal mode's piecewise-constant parameters are smoothed with the model that was filtered.
    """
    B, T = xf.shape[0], xf.shape[1]
    for b in range(B):
        if lag < 0:
            xs = xf[b, T - 1].copy()
            Ps = Pf[b, T - 1].copy()
            x_out[b, T - 1] = xs
            P_out[b, T - 1] = Ps
            for t in range(T - 2, -1, -1):
                xs, Ps = _rts_step(xf[b, t], Pf[b, t], F[b, t + 1], Q[b, t + 1], xs, Ps)
                x_out[b, t] = xs
                P_out[b, t] = Ps
        else:
            for t in range(T):
                e = min(t + lag, T - 1)
                xs = xf[b, e].copy()
                Ps = Pf[b, e].copy()
                for s in range(e - 1, t - 1, -1):
                    xs, Ps = _rts_step(xf[b, s], Pf[b, s], F[b, s + 1], Q[b, s + 1], xs, Ps)
                x_out[b, t] = xs
                P_out[b, t] = Ps


@njit
def _accumulate_moments(zc, zi, ok, t0, t1, S, D):
    """Add the lag-k products of the pairs ``(t − k, t)``, t in [t0, t1), to S and D (in place).

    ``S (K, 4, 3)``: per lag k = 1..K and axis: number of pairs, Σ Δzc², Σ Δzc Δzi, Σ Δzi².
    ``D (3, 3)``: per axis: number of triples, Σ Δ²zc Δ²zi, Σ Δ²zi² (second differences).
    Only samples with ``ok`` enter; ``zc, zi (T, 3)``.
    """
    K = S.shape[0]
    for t in range(t0, t1):
        if not ok[t]:
            continue
        for k in range(1, K + 1):
            if t - k < 0:
                break
            if ok[t - k]:
                for a in range(3):
                    dc = zc[t, a] - zc[t - k, a]
                    di = zi[t, a] - zi[t - k, a]
                    S[k - 1, 0, a] += 1.0
                    S[k - 1, 1, a] += dc * dc
                    S[k - 1, 2, a] += dc * di
                    S[k - 1, 3, a] += di * di
        if t >= 2 and ok[t - 1] and ok[t - 2]:
            for a in range(3):
                d2c = zc[t, a] - 2.0 * zc[t - 1, a] + zc[t - 2, a]
                d2i = zi[t, a] - 2.0 * zi[t - 1, a] + zi[t - 2, a]
                D[0, a] += 1.0
                D[1, a] += d2c * d2i
                D[2, a] += d2i * d2i


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
    motion_gain : ndarray
        Diagnostic, not a model parameter: the relative motion gain γ between the sensors'
        errors found by the offline fit (:func:`estimate_noise`, Notes), dimensionless;
        0 where not estimated.
    """

    q: np.ndarray
    r_cam: np.ndarray
    r_imu: np.ndarray
    var_b: np.ndarray
    phi_b: np.ndarray
    var_c: np.ndarray
    phi_c: np.ndarray
    motion_gain: np.ndarray

    @classmethod
    def default(cls, shape=(3,)) -> NoiseParameters:
        """Before any camera-seen history: q = 0.1 and R_V = 1e-3 m² (SPEC §12.2), R_I = 1e-4 m².

        R_I is 1 cm² rather than SPEC's 1e-2 m² [J]: without camera history the chain is the
        only sensor and should be followed, not smoothed with a 10 cm noise model.
        """
        f = lambda v: np.full(shape, float(v))  # noqa: E731
        return cls(f(0.1), f(1e-3), f(1e-4), f(0.0), f(0.0), f(0.0), f(0.0), f(0.0))


def _gm_fit(V, w, tau_max=np.inf):
    """Fit ``V(k) = 2 r + 2 σ² (1 − φ^k)`` (k = 1..K) with r, σ² >= 0; weighted least squares.

    Grid over the correlation time τ (φ = e^{−1/τ}, τ <= ``tau_max`` samples); for each τ the
    2-parameter non-negative least-squares fit in closed form (the unconstrained solution, or
    one parameter at zero); the best τ is kept. ``V, w`` of shape ``(K,)`` or ``(m, K)`` (m
    independent fits, ``tau_max`` scalar or ``(m,)``). Returns ``(r, σ², φ)``, floats or
    arrays ``(m,)``; φ = 0 where σ² = 0.
    """
    V = np.asarray(V, dtype=float)
    single = V.ndim == 1
    V = np.atleast_2d(V)
    m, K = V.shape
    if K == 0:
        z = np.zeros(m)
        return (0.0, 0.0, 0.0) if single else (z, z, z)
    k = np.arange(1, K + 1, dtype=float)
    sw = np.sqrt(np.atleast_2d(np.asarray(w, dtype=float)))  # (m, K)
    phi = np.exp(-1.0 / _TAU_GRID)  # (G,)
    allowed = _TAU_GRID[None] <= np.broadcast_to(np.asarray(tau_max, float), (m,))[:, None]
    basis = 2.0 * (1.0 - phi[:, None] ** k)  # σ² column per τ, (G, K)
    x1 = 2.0 * sw  # r column, (m, K)
    y = V * sw
    s11 = np.sum(x1 * x1, 1)[:, None]  # (m, 1)
    s12 = (x1 * sw) @ basis.T  # (m, G)
    s22 = (sw * sw) @ (basis * basis).T
    b1 = np.sum(x1 * y, 1)[:, None]
    b2 = (y * sw) @ basis.T
    yy = np.sum(y * y, 1)[:, None]
    det = s11 * s22 - s12**2
    with np.errstate(divide="ignore", invalid="ignore"):
        r_f = (s22 * b1 - s12 * b2) / det
        s_f = (s11 * b2 - s12 * b1) / det
        s_only = np.maximum(b2 / s22, 0.0)
        r_only = np.maximum(b1 / s11, 0.0)
    zero = np.zeros_like(r_f)
    cand_r = np.stack([r_f, zero, np.broadcast_to(r_only, r_f.shape)])  # (3, m, G)
    cand_s = np.stack([s_f, s_only, zero])
    valid = np.isfinite(cand_r) & np.isfinite(cand_s) & (cand_r >= 0) & (cand_s >= 0)
    valid[0] &= det > 1e-12 * s11 * s22
    valid &= allowed[None]
    sse = yy - 2 * (cand_r * b1 + cand_s * b2) + cand_r**2 * s11
    sse = sse + 2 * cand_r * cand_s * s12 + cand_s**2 * s22
    sse = np.where(valid, sse, np.inf).transpose(1, 0, 2).reshape(m, -1)  # (m, 3 G)
    best = np.argmin(sse, axis=1)
    i, g = np.unravel_index(best, (3, phi.size))
    r = cand_r[i, np.arange(m), g]
    s2 = cand_s[i, np.arange(m), g]
    ph = np.where(s2 > 0, phi[g], 0.0)
    if single:
        return float(r[0]), float(s2[0]), float(ph[0])
    return r, s2, ph


def _gm_sse(V, w, r, s2, phi):
    """Weighted squared residual of the fit of :func:`_gm_fit`; ``V, w (m, K)`` -> ``(m,)``."""
    k = np.arange(1, V.shape[1] + 1, dtype=float)
    fit = 2.0 * r[:, None] + 2.0 * s2[:, None] * (1.0 - phi[:, None] ** k)
    return np.sum(w * (V - fit) ** 2, axis=1)


class _Moments:
    """Lag-k cross moments of a camera series and a chain series, accumulated as data arrive.

    ``add(zc, zi, ok, t0, t1)`` adds the pairs ``(t − k, t)`` and the triples ending at t in
    ``[t0, t1)`` (all samples ``ok``); the arrays are read at indices ``< t1`` only.
    """

    def __init__(self, max_lag: int):
        self.S = np.zeros((max(int(max_lag), 1), 4, 3))
        self.D = np.zeros((3, 3))

    def add(self, zc, zi, ok, t0: int, t1: int) -> _Moments:
        _accumulate_moments(zc, zi, ok, int(t0), int(t1), self.S, self.D)
        return self

    def noise(
        self, dt_s: float, prior_pairs: float = 0.0, camera_white: bool = False
    ) -> NoiseParameters:
        """Noise parameters from the moments (:func:`estimate_noise`, Notes).

        ``prior_pairs > 0`` adds that many pseudo-pairs per lag (and pseudo-triples) of the
        conservative prior of :func:`_prior_variograms` to the data before the fit.
        ``camera_white``: no camera-error state (σ_c² = 0); the camera's white level is the
        white part of its variogram fit and the chain's variogram is the rest of the
        difference variogram (Notes of :func:`kinefuse_fusion`, causal mode).
        """
        n = self.S[:, 0, 0]
        K = n.size
        n0 = float(prior_pairs)
        dflt = NoiseParameters.default()
        out = {k: getattr(dflt, k).copy() for k in NoiseParameters.__dataclass_fields__}
        use = (n >= 8) | (n0 > 0)
        if n0 <= 0 and (self.D[0, 0] < 8 or not np.any(use)):
            return NoiseParameters(**out)
        Vc0, Vi0, q0 = _prior_variograms(K, dt_s)
        nn = np.maximum(n, 1.0)[:, None]
        Scc, Sci, Sii = (self.S[:, i] / nn for i in (1, 2, 3))
        w_d = (n / (n + n0))[:, None] if n0 > 0 else np.ones((K, 1))
        Vc = w_d * (Scc - Sci) + (1 - w_d) * Vc0[:, None]  # pseudo-data blend, per lag
        Vi = w_d * (Sii - Sci) + (1 - w_d) * Vi0[:, None]
        Vt = np.where(n[:, None] >= 8, Scc + Sii, Vc0[:, None] + Vi0[:, None])
        Vt = np.maximum(Vt, 1e-300)
        m3 = self.D[0].copy()
        for a in range(3):
            if m3[a] >= 8:
                cross, auto = self.D[1, a] / m3[a], self.D[2, a] / m3[a]
                q_hat = 2.0 * max(cross, 0.1 * auto, 1e-12) / dt_s**2
            else:
                q_hat, m3[a] = q0, 0.0
            out["q"][a] = (m3[a] * q_hat + n0 * q0) / (m3[a] + n0) if m3[a] + n0 > 0 else q0
        w = ((n[use] + n0)[:, None] / Vt[use] ** 2).T  # (3, K')
        if camera_white:
            # the camera's white level from its variogram; all of the correlated difference
            # between the sensors goes to the chain: V_I(k) = V_diff(k) − 2 r_V
            r, _, _ = _gm_fit(Vc[use].T, w, tau_max=np.full(3, float(K)))
            r_cam = np.maximum(r, _VAR_FLOOR_M2)
            Vd = (Vc + Vi)[use].T - 2.0 * r_cam[:, None]
            r, s2, phi = _gm_fit(Vd, w)
            out["r_cam"], out["var_c"], out["phi_c"] = r_cam, np.zeros(3), np.zeros(3)
            out["r_imu"], out["var_b"], out["phi_b"] = np.maximum(r, _VAR_FLOOR_M2), s2, phi
            return NoiseParameters(**out)
        # camera (τ <= K) and chain fitted together for candidate relative motion gains γ
        # (estimate_noise, Notes): V_V = V_V,est − γ X, V_I = V_I,est + γ X, X the
        # cross-variogram (≈ the motion's); per axis, the γ of the best total fit, from a coarse
        # grid refined around its best point
        X = (w_d * Sci)[use].T  # (3, K'): the data part of the blend only
        Vc, Vi = Vc[use].T, Vi[use].T
        coarse = np.tile(_GAIN_GRID[:, None], (1, 3))
        best = _GAIN_GRID[np.argmin(_gain_fit(Vc, Vi, X, w, K, coarse)[0], axis=0)]
        gam = best[None] + _GAIN_STEP * np.linspace(-1.0, 1.0, 41)[:, None]  # (41, 3)
        sse, cam, chn, (r, s2, phi) = _gain_fit(Vc, Vi, X, w, K, gam)
        sse0, cam0, chn0, (r0, s20, phi0) = _gain_fit(Vc, Vi, X, w, K, np.zeros((1, 3)))
        g = np.argmin(sse, axis=0)
        # γ = 0 (the plain split) unless another γ fits better beyond rounding (e.g. no
        # motion: ties)
        use_g = sse[g, range(3)] < (1.0 - 1e-9) * sse0[0]
        cam, chn = cam[g, range(3)], chn[g, range(3)]
        sel = lambda a, a0, rows, rows0: np.where(use_g, a[rows], a0[rows0[0]])  # noqa: E731
        out["r_cam"] = np.maximum(sel(r, r0, cam, cam0), _VAR_FLOOR_M2)
        out["var_c"], out["phi_c"] = sel(s2, s20, cam, cam0), sel(phi, phi0, cam, cam0)
        out["r_imu"] = np.maximum(sel(r, r0, chn, chn0), _VAR_FLOOR_M2)
        out["var_b"], out["phi_b"] = sel(s2, s20, chn, chn0), sel(phi, phi0, chn, chn0)
        out["motion_gain"] = np.where(use_g, gam[g, range(3)], 0.0)
        return NoiseParameters(**out)


def _gain_fit(Vc, Vi, X, w, K: int, gam):
    """Fits of :meth:`_Moments.noise` for candidate motion gains ``gam (G, 3)`` (per axis).

    ``Vc, Vi, X, w (3, K')``: the two sensors' error variograms, the cross-variogram and the
    weights. Returns ``(sse (G, 3), cam (G, 3), chn (G, 3), (r, s2, φ))``: the total
    weighted residual per candidate and axis, and the row indices of the camera's and the
    chain's fit in the flat arrays ``r, s2, φ`` of :func:`_gm_fit`.
    """
    G = gam.shape[0]
    g = gam[:, :, None]
    V = np.concatenate([Vc[None] - g * X[None], Vi[None] + g * X[None]], axis=1)  # (G, 6, K')
    V = V.reshape(G * 6, -1)  # rows: γ-major, then camera axes 0-2, chain axes 0-2
    W = np.tile(np.concatenate([w, w]), (G, 1))
    r, s2, phi = _gm_fit(V, W, tau_max=np.tile([float(K)] * 3 + [np.inf] * 3, G))
    sse = _gm_sse(V, W, r, s2, phi).reshape(G, 2, 3).sum(axis=1)
    rows = np.arange(G)[:, None] * 6 + np.arange(3)[None]
    return sse, rows, rows + 3, (r, s2, phi)


def _prior_variograms(K: int, dt_s: float):
    """Conservative prior of the causal noise fit: error variograms ``(K,)`` of camera and chain, q.

    Camera: white, ``R_V = 1e-3 m²`` (SPEC §12.2). Chain (after the correction): white
    ``(1 cm)²`` plus a random walk of diffusion ``1e-2 m²/s`` (SPEC's R_I per second): the
    chain is trusted at high frequency only and the camera sets the low frequencies. q = 0.1
    (SPEC §12.2).
    """
    k = np.arange(1, K + 1, dtype=float)
    Vc0 = np.full(K, 2.0 * _PRIOR_R_CAM)
    Vi0 = 2.0 * _PRIOR_R_IMU + 2.0 * _PRIOR_VAR_B * (1.0 - np.exp(-k * dt_s / _PRIOR_TAU_B_S))
    return Vc0, Vi0, _PRIOR_Q


def _ok_rows(z_cam, z_imu, available):
    return (
        np.asarray(available, dtype=bool)
        & np.all(np.isfinite(z_cam), -1)
        & np.all(np.isfinite(z_imu), -1)
    )


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
    the approximate variance of the estimate, which grows with the motion at lag k). The
    camera's correlation time is at most K samples (a slower camera error and a chain error
    would both be drifts, and p would not be observable at low frequency).

    *Errors that follow the motion.* The split above assumes both errors independent of p. An
    error of the chain that the correction cannot express (e.g. a slowly varying heading or
    gain error: the chain under- or over-reports the limb's excursion) correlates with the
    motion, ``E[Δ_k p Δ_k e_I] = −γ_I M(k)`` with ``M(k) = E[(Δ_k p)²]``, and likewise
    ``γ_V`` for the camera. Then ``V_V,est(k) = V_V(k) + γ M(k)`` and
    ``V_I,est(k) = V_I(k) − γ M(k)`` with ``γ = γ_I − γ_V``: the motion, which dwarfs the
    errors, moves chain error into the camera's variogram (or back), and the filter then
    follows a poor chain where the camera sees the joint. Only the split is biased: the sum
    ``V_V + V_I`` (the variogram of ``z_cam − z_imu``, in which p cancels) is not. So both
    error models are fitted to ``V_V,est − γ X`` and ``V_I,est + γ X``, ``X(k) = E[Δ_k z_cam
    Δ_k z_imu] ≈ M(k)``, for each γ of a grid over ±0.5 (steps 0.01, refined to 0.0005 around the best) and the γ of the smallest
    total weighted residual is kept, per axis (:attr:`NoiseParameters.motion_gain`). A motion
    term is identified by its shape: M(k) keeps growing or oscillates with the movement, while
    each error model's variogram is monotone and saturating (the camera's within K samples).
    γ = 0 is the plain split, kept on ties (e.g. without motion).

    The motion model's
    q comes from second differences: ``E[Δ² z_cam Δ² z_imu] = E[(Δ² p)²] = q dt² / 2`` for
    the constant-velocity model with ``Q = q [[dt²/4, dt/2], [dt/2, 1]]``, floored at a tenth
    of the chain's own ``E[(Δ² z_imu)²]`` (the cross moment can be near zero when the camera
    is noisy). White variances are floored at (1 mm)².

    All statistics are sums of lag-k products, so they are accumulated as data arrive in the
    causal mode (:class:`_Moments`) at O(K) per sample.
    """
    zc = np.ascontiguousarray(z_cam, dtype=float)
    zi = np.ascontiguousarray(z_imu, dtype=float)
    ok = _ok_rows(zc, zi, available)
    T = zc.shape[0]
    K = int(max(1, min(max_lag, T - 1)))
    return _Moments(K).add(zc, zi, ok, 0, T).noise(dt_s)


# --------------------------------------------------------------------------- learned correction
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
        for f in np.unique(fold):
            m = fold == f
            new = [Xa[m].T @ Xa[m], Xa[m].T @ Y[m], float(np.sum(Y[m] ** 2))]
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
    F[:, 0, 0] = F[:, 1, 1] = 1.0
    F[:, 0, 1] = dt  # p += dt v
    F[:, 2, 2] = p.phi_b  # b ← φ_b b
    F[:, 3, 3] = p.phi_c  # c ← φ_c c
    Q[:, :2, :2] = p.q[:, None, None] * np.outer(g, g)  # q [[dt²/4, dt/2], [dt/2, 1]]
    Q[:, 2, 2] = p.var_b * (1.0 - p.phi_b**2)  # σ_b² (1 − φ_b²)
    Q[:, 3, 3] = p.var_c * (1.0 - p.phi_c**2)
    return F, Q


def _prior(z0_cam, z0_imu, p: NoiseParameters):
    """Prior ``x (3, 4)``, ``P (3, 4, 4)`` at the first sample: p from the given position."""
    x = np.zeros((3, _N_X))
    P = np.zeros((3, _N_X, _N_X))
    for a in range(3):
        x[a, 0] = next((float(z[a]) for z in (z0_cam, z0_imu) if np.isfinite(z[a])), 0.0)
        P[a] = np.diag([1.0, 1.0, p.var_b[a], p.var_c[a]])
    return x, P


def _run(zc, zi, p: NoiseParameters, dt: float):
    """Offline: filter + fixed-interval RTS of one joint, ``zc, zi (T, 3)`` -> (3, T, 4), (3, T, 4, 4)."""
    T = zc.shape[0]
    F, Q = _model_matrices(p, dt)
    first = lambda z: np.array([next(iter(z[np.isfinite(z[:, a]), a]), np.nan) for a in range(3)])  # noqa: E731
    x, P = _prior(first(zc), first(zi), p)
    xf = np.empty((3, T, _N_X))
    Pf = np.empty((3, T, _N_X, _N_X))
    zc_b, zi_b = np.ascontiguousarray(zc.T), np.ascontiguousarray(zi.T)
    _kf_segment(zc_b, zi_b, F, Q, p.r_cam, p.r_imu, x, P, False, _H_CAM, _H_IMU, xf, Pf)
    xs, Ps = np.empty_like(xf), np.empty_like(Pf)
    tile = lambda A: np.ascontiguousarray(np.broadcast_to(A[:, None], (3, T, _N_X, _N_X)))  # noqa: E731
    _smooth(xf, Pf, tile(F), tile(Q), -1, xs, Ps)
    return xs, Ps


def _fit_joint(zc, zi, phi, seen, dt, alpha, max_lag):
    """Offline: fit the correction and the noise parameters of one joint on the ``seen`` samples."""
    block = max(2, int(round(1.0 / dt)))
    t = np.flatnonzero(seen)
    reg = RidgeCorrection(block=block, **({} if alpha is None else {"alphas": alpha})).fit(
        phi[seen], (zc - zi)[seen], t
    )
    corr = reg.predict(phi)
    zic = zi + corr
    params = estimate_noise(np.where(seen[:, None], zc, np.nan), zic, seen, dt, max_lag=max_lag)
    return reg, corr, params


def _refit_times(seen: np.ndarray, min_history: int, refit_every: int | None) -> list[int]:
    """Causal refit times t (fit on samples < t): outage onsets and every ``refit_every`` samples.

    Only once ``min_history`` camera samples precede t; each decision reads ``seen[: t + 1]``.
    """
    T = seen.size
    n_seen = np.cumsum(seen)
    times = set((np.flatnonzero(~seen[1:] & seen[:-1]) + 1).tolist())
    first = np.flatnonzero(n_seen >= min_history)
    if first.size:
        times.add(int(first[0]) + 1)
        if refit_every:
            times.update(range(int(first[0]) + 1, T, int(refit_every)))
    return sorted(t for t in times if 0 < t < T and n_seen[t - 1] >= min_history)


@dataclass(frozen=True)
class _CausalSettings:
    """Settings of :func:`_causal_joint` (see :func:`kinefuse_fusion`)."""

    alpha: Any
    max_lag: int
    min_history: int
    refit_every: int | None
    lag: int
    n_folds: int
    min_fit_s: float
    prior_s: float


def _causal_joint(zc, zi, phi, seen, dt, cfg: _CausalSettings):
    """Causal fusion of one joint; returns mean (3, T, 4), cov (3, T, 4, 4), correction (T, 3),
    the last (ridge, noise), the number of refits and the first refit time (T if none)."""
    T = zc.shape[0]
    block = max(2, int(round(1.0 / dt)))
    kw = {} if cfg.alpha is None else {"alphas": cfg.alpha}
    min_blocks = max(2, int(np.ceil(cfg.min_fit_s / (block * dt))))
    reg = RidgeCorrection(
        block=block, n_folds=cfg.n_folds, min_blocks=min_blocks, reselect_growth=1.5, **kw
    )
    mom = _Moments(cfg.max_lag)
    ok = seen & np.all(np.isfinite(zi), -1)
    corr = np.zeros((T, 3))  # the correction in use at t (prequential: fitted on samples < t)
    zu = np.full((T, 3), np.nan)  # corrected chain as filtered: zi + corr
    ze = np.full((T, 3), np.nan)  # the same minus the b shifts so far: continuous across refits
    shift = np.zeros(3)
    p = mom.noise(dt, cfg.prior_s / dt, camera_white=True)
    x, P = _prior(zc[0], zi[0], p)
    xf = np.empty((3, T, _N_X))
    Pf = np.empty((3, T, _N_X, _N_X))
    Fs = np.empty((3, T, _N_X, _N_X)) if cfg.lag else None
    Qs = np.empty_like(Fs) if cfg.lag else None
    times = _refit_times(seen, cfg.min_history, cfg.refit_every)
    bounds = [0, *times, T]
    done = 0  # samples [0, done) are in the ridge moments and the variograms
    for k in range(len(bounds) - 1):
        t0, t1 = bounds[k], bounds[k + 1]
        if k > 0:  # refit on [0, t0); carry the filter state
            rows = np.arange(done, t0)[ok[done:t0]]
            if rows.size:
                reg.partial_fit(phi[rows], zc[rows] - zi[rows], rows)
            mom.add(zc, ze, ok, done, t0)
            done = t0
            p = mom.noise(dt, cfg.prior_s / dt, camera_white=True)
            f = reg.predict(phi[t0 - 1 : t1])
            # the state b is the chain error left after the correction: shift it by the change
            # of the correction at the last sample, so that the corrected chain p + b is
            # continuous across the refit
            x[:, 2] += f[0] - corr[t0 - 1]
            shift += f[0] - corr[t0 - 1]
            corr[t0:t1] = f[1:]
        zu[t0:t1] = zi[t0:t1] + corr[t0:t1]
        ze[t0:t1] = zu[t0:t1] - shift
        F, Q = _model_matrices(p, dt)
        # contiguous outputs, copied in: the kernel's one (C-contiguous) specialisation, the
        # one the offline path uses (a strided slice would compile the loop a second time)
        x_seg = np.empty((3, t1 - t0, _N_X))
        P_seg = np.empty((3, t1 - t0, _N_X, _N_X))
        _kf_segment(
            np.ascontiguousarray(zc[t0:t1].T),
            np.ascontiguousarray(zu[t0:t1].T),
            F,
            Q,
            p.r_cam,
            p.r_imu,
            x,
            P,
            t0 > 0,
            _H_CAM,
            _H_IMU,
            x_seg,
            P_seg,
        )
        xf[:, t0:t1] = x_seg
        Pf[:, t0:t1] = P_seg
        if cfg.lag:
            Fs[:, t0:t1] = F[:, None]
            Qs[:, t0:t1] = Q[:, None]
    if cfg.lag:
        xs, Ps = np.empty_like(xf), np.empty_like(Pf)
        _smooth(xf, Pf, Fs, Qs, int(cfg.lag), xs, Ps)
        xf, Pf = xs, Ps
    last = {"noise": p, "correction": reg if times else None}
    return xf, Pf, corr, last, len(times), (times[0] if times else T)


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
    bridge: bool = True,
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
        correction is zero and the noise parameters are the conservative prior (Notes).
    refit_every : int or None
        Causal mode: also refit every this many samples (None: only at outage onsets).
    bridge : bool
        Causal mode: inside outages output the prequentially chosen offset bridge
        (:func:`kinefuse.pipelines.offset_bridge.prequential_bridge`, Notes "Causal outage
        bridge") instead of the filter's prediction (default True).

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
    interpolates b between its values before and after.

    **Causal** (streaming, O(T) in total): one forward filter runs over the whole series and
    its state is carried across refits. At each refit time t_k (outage onsets and every
    ``refit_every`` samples, once ``min_history`` camera samples exist) the ridge moments and
    the noise statistics are updated with the samples of ``[t_{k−1}, t_k)`` only, the
    correction and the noise parameters are re-solved, and the filter continues from its
    current state with the new parameters; the state b is shifted by the change of the
    correction at ``t_k − 1``, so that the corrected chain ``p + b`` is continuous (the past
    is not re-filtered). With ``lag > 0`` a fixed-lag RTS runs over the last ``lag`` samples
    with the (time-varying) model that was filtered. Cost per refit: O(refit_every · K) for
    the statistics, O(folds · F³) for the cross-validated ridge (the penalty is re-selected
    only when the history has grown by half since the last selection), O(1) for the noise fit.

    The causal noise fit is conservative by construction (what failed before: on a short
    history the fit said "chain error after the correction ≈ 0, camera error coloured", and
    the filter followed the chain away from the camera while the camera saw the joint):

    * the chain statistics are *prequential*: each sample's corrected chain is the one the
      filter used, ``z_imu + f̂_k(φ)`` with ``f̂_k`` fitted before it, minus the b shifts made
      so far (so it is continuous across refits and slow chain error absorbed piecewise by the
      refits stays visible): the residual error of the correction is measured out of sample.
      An in-sample residual after a regression on many features is far too small;
    * the camera error is white (no state c in causal mode) and all correlated difference
      between the sensors is attributed to the chain: ``V_I(k) = V_diff(k) − 2 R_V`` with
      ``V_diff`` the variogram of ``z_cam − z_imu`` (robust) and R_V the white part of the
      camera's cross-variogram. The split of the cross-variograms between the two sensors
      (offline) fails when the chain error correlates with the motion (e.g. a correction
      partly fitted to a drift): it moves chain error into a coloured camera error; and with
      both b and c correlated, p is only weakly observable at low frequency;
    * the variograms are blended with ``2 s`` of pseudo-data of a prior
      (:func:`_prior_variograms`): camera white with R_V = 1e-3 m² (SPEC §12.2), chain error
      a Gauss-Markov process of (5 cm)² and 1 s correlation time plus (1 cm)² white,
      q = 0.1. The prior's b is stationary, so in an outage b decays to zero (the corrected
      chain) instead of holding a noisy last offset; as history accumulates the data dominate;
    * the correction is intercept-only until 3 s of camera history (3 cross-validation
      blocks).

    Before the first refit the prior parameters are used with no correction; outputs in
    outages before any camera-seen history are the (smoothed) chain, ``SOURCE_IMU``.

    **Causal outage bridge** (``bridge=True``): inside an outage that starts after at least
    ``min_history`` camera-seen samples, the output is the chain (raw, or corrected by the
    causal f̂) plus the smoothed last camera-chain offset decaying towards that chain,
    ``z_t + exp(−h/τ_d) ē_{τ_s}``, with the chain and (τ_s, τ_d) chosen at the onset by the mean squared error of that predictor on all complete
    pairs ``(s, s + h)``, ``h <= 2 s``, of the camera-seen history (prequential selection;
    candidates include the chain alone and the held offset); the covariance is that
    predictor's historical error at the horizon h. Developed on the tuning set (issue 11):
    there the filter's own prediction decayed the chain error with a prior time constant and
    was no better than the chain alone, and a held offset carries the camera's noise.

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
    n_refits = []
    cfg = _CausalSettings(
        alpha=alpha,
        max_lag=int(max_lag),
        min_history=int(min_history),
        refit_every=refit_every,
        lag=int(lag),
        n_folds=_N_FOLDS_CAUSAL,
        min_fit_s=_MIN_FIT_S,
        prior_s=_PRIOR_S,
    )
    for j in range(J):
        seen = av[:, j]
        if not causal:
            if seen.sum() >= 2:
                reg, corr, pj = _fit_joint(zc[:, j], zi[:, j], phi[:, j], seen, dt, alpha, max_lag)
            else:
                reg, corr, pj = None, np.zeros((T, 3)), NoiseParameters.default()
                source[~seen, j] = SOURCE_IMU
            m, P = _run(zc[:, j], zi[:, j] + corr, pj, dt)
            last = {"noise": pj, "correction": reg}
        else:
            m, P, corr, last, n, t_first = _causal_joint(
                zc[:, j], zi[:, j], phi[:, j], seen, dt, cfg
            )
            source[:t_first, j][~seen[:t_first]] = SOURCE_IMU
            n_refits.append(n)
        pos[:, j] = m[..., 0].T
        cov[:, j, range(3), range(3)] = P[..., 0, 0].T
        if causal and bridge:
            bp, bv, choices = prequential_bridge(
                (zi[:, j], zi[:, j] + corr), zc[:, j], seen, min_history=min_history
            )
            rows = np.flatnonzero(np.all(np.isfinite(bp), axis=-1))
            pos[rows, j] = bp[rows]
            cov[rows, j] = 0.0
            ax = np.arange(3)
            cov[rows[:, None], j, ax, ax] = bv[rows]
            last["bridge"] = choices
        bias[:, j] = m[..., 2].T
        corr_all[:, j] = corr
        params.append(last)
    return KinefuseResult(
        position=pos,
        cov=cov,
        source=source,
        correction=corr_all,
        chain_error=bias,
        params=params,
        info={
            "causal": bool(causal),
            "lag": int(lag),
            "n_features": int(phi.shape[-1]),
            "n_refits": n_refits,
        },
    )
