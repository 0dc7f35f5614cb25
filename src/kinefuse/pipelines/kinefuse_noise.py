"""Noise model of the ``"kinefuse"`` fusion: parameters and their fit from cross-variograms.

:class:`NoiseParameters` (per axis: q, white camera and chain noise, Gauss-Markov chain and
camera errors); :func:`estimate_noise` (offline, lag-k cross-variograms of the two sensors, the
"three-cornered hat"); ``_Moments``: the same statistics accumulated as data arrive, with the
conservative prior of the causal mode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kinefuse.pipelines._kinefuse_kernels import accumulate_moments

__all__ = ["NoiseParameters", "estimate_noise"]

_VAR_FLOOR_M2 = (
    1e-6  # (1 mm)²: smallest white-noise variance (below: neither credible nor identifiable)
)
# the conservative prior of the causal noise fit (_prior_variograms)
_PRIOR_R_CAM = 1e-3  # prior camera white noise, m² (SPEC §12.2 R_V)
_PRIOR_R_IMU = 1e-4  # prior white noise of the corrected chain, m² (1 cm)²
_PRIOR_VAR_B = 2.5e-3  # prior stationary variance of the chain error b, m² (5 cm)²
_PRIOR_TAU_B_S = 1.0  # prior correlation time of b, s (b decays in an outage)
_PRIOR_Q = 0.1  # prior q (SPEC §12.2)
_TAU_GRID = np.exp(np.linspace(np.log(1.0), np.log(3.0e4), 48))  # GM correlation times, samples
#: Candidate relative motion gains γ of the offline noise fit (estimate_noise, Notes): a sensor
#: error proportional to the motion, up to ±50 % of it, in steps of 1 %.
_GAIN_GRID = np.linspace(-0.5, 0.5, 101)
_GAIN_STEP = float(_GAIN_GRID[1] - _GAIN_GRID[0])  # refined around the best point in 1/20 steps


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
        accumulate_moments(zc, zi, ok, int(t0), int(t1), self.S, self.D)
        return self

    def noise(
        self, dt_s: float, prior_pairs: float = 0.0, camera_white: bool = False
    ) -> NoiseParameters:
        """Noise parameters from the moments (:func:`estimate_noise`, Notes).

        ``prior_pairs > 0`` adds that many pseudo-pairs per lag (and pseudo-triples) of the
        conservative prior of :func:`_prior_variograms` to the data before the fit.
        ``camera_white``: no camera-error state (σ_c² = 0); the camera's white level is the
        white part of its variogram fit and the chain's variogram is the rest of the
        difference variogram (Notes of :mod:`kinefuse.pipelines.kinefuse_fusion`, causal mode).
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
