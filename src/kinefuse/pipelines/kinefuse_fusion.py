"""``"kinefuse"``: IMU-chain + camera fusion with a learned, state-dependent chain-error model.

Per joint and axis a linear-Gaussian state-space model tracks the joint position together with
the slowly varying errors of both sensors, while a regression on IMU features learns the part of
the chain error that depends on the limb's state. During a camera outage the chain, corrected by
the regression and by the tracked error, carries the joint. See :func:`kinefuse_fusion`.

The parts, one module each: the compiled KF/RTS of the per-axis model
(:mod:`._kinefuse_kernels`), the noise model and its fit (:mod:`.kinefuse_noise`), the learned
correction (:mod:`.kinefuse_ridge`); this module holds the model matrices, the offline and the
causal (refit-scheduled) runs and :func:`kinefuse_fusion`.

Notes
-----
**Model** (per joint, independently per axis; state ``x = [p, v, b, c]``)::

    p_{t+1} = p_t + dt v_t + dt/2 w_t ,   v_{t+1} = v_t + w_t ,   w ~ N(0, q)
    b_{t+1} = φ_b b_t + u_t ,  u ~ N(0, σ_b² (1 − φ_b²))      chain-error residual
    c_{t+1} = φ_c c_t + s_t ,  s ~ N(0, σ_c² (1 − φ_c²))      camera coloured error
    z_cam_t               = p_t + c_t + n_V ,  n_V ~ N(0, R_V)   (when available)
    z_imu_t + f̂(φ_t)      = p_t + b_t + n_I ,  n_I ~ N(0, R_I)   (always)

``f̂`` is a ridge regression (:class:`~kinefuse.pipelines.kinefuse_ridge.RidgeCorrection`) of the chain error
``e_t = z_cam_t − z_imu_t`` on the IMU features ``φ_t`` over all camera-seen samples so far,
its penalty chosen by leave-one-block-out cross-validation over 2 s blocks (offline; beyond
20 blocks, 20 folds of interleaved blocks; 1 s blocks and 10 folds in causal mode); it
captures the error that follows the limb's state (soft-tissue motion, axis, length and offset
errors). The blocks must be longer than the error's correlation (a gait
cycle is about 1 s): with 1 s blocks a held-out block resembles its neighbours, the
validation is optimistic and picks too small a penalty, and the correction then extrapolates
badly in outages (on virtual walks the corrected chain was worse than the raw chain at an
ankle, 70 vs 50 mm). 2 s was chosen on the tuning set and on virtual walks outside both sets
(issue 11): outage 3-D RMSE, offline, tuning CMU 29.7 → 28.3 mm, UTD-MHAD 66.3 → 64.7 mm, 24
further recordings of the tuning motions 34.4 → 32.9 mm, 36 virtual walks and runs (CMU
02_01-02_03 and BVH 131_01-03, six seeds each, 8 occlusions a minute) 48.8 → 44.7 mm; 1.5-3 s
gave similar gains. In causal mode 2 s was slightly worse on the tuning set (49.2 → 49.7
mm), so it keeps 1 s.

**Segment-frame terms** (``segment_rotations``, issue 11). A mis-estimated sensor axis, length
or offset is a constant vector ``δ_s`` in its segment's sensor frame and moves the joint by
``R_s(t) δ_s`` in the world; a regression on world-frame features can only follow that
through the pose. Given the orientations of the segments that move a joint, the regression
also gets, per world axis ``i``, the regressors ``R_s(t)[i, :]`` with coefficients shared by
the three axes (:func:`~kinefuse.pipelines.features.segment_frame_design`,
:class:`~kinefuse.pipelines.kinefuse_ridge.AxisRidgeCorrection`); the features above keep their
own coefficient per axis. Chosen on the tuning set and on the virtual walks above (four seeds
each), outage 3-D RMSE offline: tuning CMU 30.5 → 26.3 mm (causal 48.7 → 45.0), virtual walks
47.3 → 44.2 mm; on the real UTD-MHAD tuning trials (one forearm IMU, about 2.6 s of camera
history) 64.7 → 65.3 mm (causal 71.7 → 69.6). Tried and not adopted: products of ``R_s`` with
the relative rotations of neighbouring segments (soft-tissue motion linear in the joint
angles, Dumas et al., J. Biomech. 47, 2014, the simulator's own model): tuning 26.7 mm,
walks 42.5 mm, with four times the columns (15 times the run time on a one-hour recording);
the segment-frame columns without the features: tuning 22.4 mm (best there), walks 46.8 mm,
UTD-MHAD 69.1 mm (worst there), and with the products but without the features 25.2 and
43.3 mm; nested with the features, the UTD-MHAD trials lose 0.6 mm and the walks gain. The
constant terms model calibration error, which any chain has; they do not rest on the
simulator's soft-tissue model. The paper-B rig
(:func:`~kinefuse.pipelines.vision_recording.vision_assisted_from_recording`) and
``kinefuse run`` pass the chain's orientations.

``b`` (first-order Gauss-Markov, a random walk when ``φ_b → 1``) captures what the
regression misses and ``c`` the camera's correlated error (e.g. bone-length variation).

**Noise parameters** (q, R_V, R_I, σ_b², φ_b, σ_c², φ_c) are estimated per joint and axis
from the camera-seen data by :func:`~kinefuse.pipelines.kinefuse_noise.estimate_noise` (lag-k cross-variograms of the two
sensors), after the correction; no per-trial constants.

**Offline**: fit on all camera-seen samples, forward KF (sequential scalar updates, NaN =
not measured), fixed-interval RTS (SPEC §9 equations). In an outage the smoother
interpolates b between its values before and after. With ``bridge=True`` (default), inside
an outage with camera history on both sides the output is the equal-weight mean of three
estimates: the smoother's, the causal outage bridge below run forward, and the same bridge
run backward in time (each chosen on its own side's camera-seen samples). Their errors
differ in kind (the smoother trusts the fitted noise split between chain and camera, the
bridges the offset's recent history), so their mean is the safer estimate; the variance is
that of the mean of fully correlated estimates, ``(mean of the three standard
deviations)²``, an upper bound. Chosen on the tuning set (issue 11) and on 24 further virtual
recordings of its motions (other seeds): outage 3-D RMSE 30.9 → 29.7 mm and 34.9 → 34.4 mm,
UTD-MHAD unchanged (66.3 mm).

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
  (``kinefuse_noise._prior_variograms``): camera white with R_V = 1e-3 m² (SPEC §12.2), chain error
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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kinefuse._validation import positive_finite
from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU
from kinefuse.exceptions import InputError
from kinefuse.pipelines._kinefuse_kernels import N_X, kf_segment, rts_smooth
from kinefuse.pipelines.features import chain_features, segment_frame_design
from kinefuse.pipelines.kinefuse_noise import NoiseParameters, _Moments, estimate_noise
from kinefuse.pipelines.kinefuse_ridge import AxisRidgeCorrection, RidgeCorrection
from kinefuse.pipelines.offset_bridge import prequential_bridge

__all__ = [
    "KinefuseResult",
    "NoiseParameters",
    "RidgeCorrection",
    "estimate_noise",
    "kinefuse_fusion",
]

_H_CAM = np.array([1.0, 0.0, 0.0, 1.0])  # z_cam = p + c + n_V
_H_IMU = np.array([1.0, 0.0, 1.0, 0.0])  # z_imu + f(φ) = p + b + n_I
# causal mode (see the module Notes, "Causal")
_N_FOLDS_CAUSAL = 10  # CV folds of the streaming ridge (bounded cost per re-solve)
# offline CV folds at most (block i in fold i mod 20): leave-one-block-out up to 40 s of camera
# history, which covers every recording of the experiments; beyond, the cost stays bounded (an
# hour had 1800 folds, one eigendecomposition each)
_N_FOLDS_OFFLINE = 20
_PRIOR_S = 2.0  # weight of the conservative noise prior, seconds of pseudo-data
_MIN_FIT_S = 3.0  # camera-seen history before the correction uses more than an intercept, s
_CV_BLOCK_S = 2.0  # block length of the correction's cross-validation, offline, s (Notes)
_CV_BLOCK_CAUSAL_S = 1.0  # the same, causal (on the tuning set 2 s was no better there)


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
        Per joint: the fitted noise parameters (``"noise"``) and ridge model (``"correction"``)
        of the last refit and, with ``bridge=True``, the outage bridge's choices
        (``"bridge"``: causal, :func:`~kinefuse.pipelines.offset_bridge.prequential_bridge`'s
        list; offline, ``{"forward": ..., "backward": ...}``).
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
    F = np.zeros((3, N_X, N_X))
    Q = np.zeros((3, N_X, N_X))
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
    x = np.zeros((3, N_X))
    P = np.zeros((3, N_X, N_X))
    for a in range(3):
        x[a, 0] = next((float(z[a]) for z in (z0_cam, z0_imu) if np.isfinite(z[a])), 0.0)
        P[a] = np.diag([1.0, 1.0, p.var_b[a], p.var_c[a]])
    return x, P


def _run(zc, zi, p: NoiseParameters, dt: float):
    """Offline: filter + fixed-interval RTS of one joint, ``zc, zi (T, 3)`` -> the smoothed
    states (3, T, 4) and position variances (3, T, 1, 1) (the rest is not read)."""
    T = zc.shape[0]
    F, Q = _model_matrices(p, dt)
    first = lambda z: np.array([next(iter(z[np.isfinite(z[:, a]), a]), np.nan) for a in range(3)])  # noqa: E731
    x, P = _prior(first(zc), first(zi), p)
    xf = np.empty((3, T, N_X))
    Pf = np.empty((3, T, N_X, N_X))
    zc_b, zi_b = np.ascontiguousarray(zc.T), np.ascontiguousarray(zi.T)
    kf_segment(zc_b, zi_b, F, Q, p.r_cam, p.r_imu, x, P, False, _H_CAM, _H_IMU, xf, Pf)
    xs, Ps = np.empty_like(xf), np.empty((3, T, 1, 1))
    # F, Q as (3, 1, 4, 4): the kernel reads the same model at every t (no (3, T, 4, 4) copy)
    rts_smooth(xf, Pf, F[:, None], Q[:, None], -1, xs, Ps)
    return xs, Ps


def _ridge(phi, **kwargs):
    """The correction's regression for one joint's ``phi``: features ``(T, F)`` shared by the
    axes (:class:`RidgeCorrection`) or a per-axis design ``(T, 3, K)``
    (:class:`AxisRidgeCorrection`)."""
    return (AxisRidgeCorrection if phi.ndim == 3 else RidgeCorrection)(**kwargs)


def _fit_joint(zc, zi, phi, seen, dt, alpha, max_lag):
    """Offline: fit the correction and the noise parameters of one joint on the ``seen`` samples."""
    block = max(2, int(round(_CV_BLOCK_S / dt)))
    t = np.flatnonzero(seen)
    n_blocks = len(np.unique(t // block))
    folds = None if n_blocks <= _N_FOLDS_OFFLINE else _N_FOLDS_OFFLINE
    kw = {} if alpha is None else {"alphas": alpha}
    reg = _ridge(phi, block=block, n_folds=folds, **kw).fit(phi[seen], (zc - zi)[seen], t)
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
    block = max(2, int(round(_CV_BLOCK_CAUSAL_S / dt)))
    kw = {} if cfg.alpha is None else {"alphas": cfg.alpha}
    min_blocks = max(2, int(np.ceil(cfg.min_fit_s / (block * dt))))
    reg = _ridge(
        phi, block=block, n_folds=cfg.n_folds, min_blocks=min_blocks, reselect_growth=1.5, **kw
    )
    mom = _Moments(cfg.max_lag)
    ok = seen & np.all(np.isfinite(zi), -1)
    corr = np.zeros((T, 3))  # the correction in use at t (prequential: fitted on samples < t)
    zu = np.full((T, 3), np.nan)  # corrected chain as filtered: zi + corr
    ze = np.full((T, 3), np.nan)  # the same minus the b shifts so far: continuous across refits
    shift = np.zeros(3)
    p = mom.noise(dt, cfg.prior_s / dt, camera_white=True)
    x, P = _prior(zc[0], zi[0], p)
    xf = np.empty((3, T, N_X))
    Pf = np.empty((3, T, N_X, N_X))
    Fs = np.empty((3, T, N_X, N_X)) if cfg.lag else None
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
        x_seg = np.empty((3, t1 - t0, N_X))
        P_seg = np.empty((3, t1 - t0, N_X, N_X))
        kf_segment(
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
        rts_smooth(xf, Pf, Fs, Qs, int(cfg.lag), xs, Ps)
        xf, Pf = xs, Ps
    last = {"noise": p, "correction": reg if times else None}
    return xf, Pf, corr, last, len(times), (times[0] if times else T)


def _check_options(causal, lag) -> None:
    if not isinstance(causal, (bool, np.bool_)):
        raise InputError(f"expected causal as a bool, got {causal!r}")
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
        raise InputError(f"expected lag as an int >= 0 (samples), got {lag!r}")
    if not causal and lag != 0:
        raise InputError("lag applies to causal=True only (offline mode smooths the whole series)")


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
    dt = positive_finite(dt_s, "dt_s")
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


def _rotations_by_joint(rotations, shape) -> list[list[np.ndarray]]:
    """Per joint the ``(T, 3, 3)`` rotations of ``rotations (T, J, S, 3, 3)``, padding dropped."""
    R = np.asarray(rotations)
    T, J = shape
    if (
        not np.issubdtype(R.dtype, np.floating)
        or R.ndim != 5
        or R.shape[:2] != (T, J)
        or R.shape[3:] != (3, 3)
    ):
        raise InputError(
            f"expected segment_rotations as floats with shape (T, J, S, 3, 3) = ({T}, {J}, S, 3, 3), "
            f"got {R.shape}"
        )
    out = []
    for j in range(J):
        # padding: no finite non-zero entry (all zero, or zero with the missing rows' NaN)
        segs = [R[:, j, k] for k in range(R.shape[2]) if np.any(np.nan_to_num(R[:, j, k]) != 0)]
        if not segs:
            raise InputError(f"segment_rotations: joint {j} has only padding (all-zero) segments")
        for k, Rk in enumerate(segs):
            _check_rotations(Rk, j, k)
        out.append(segs)
    return out


def _check_rotations(R: np.ndarray, j: int, k: int) -> None:
    """The finite rows of ``R (T, 3, 3)`` are rotation matrices (orthonormal, det +1, to 1e-6);
    NaN rows are missing orientations."""
    ok = np.all(np.isfinite(R), axis=(1, 2))
    Rf = R[ok]
    err = np.abs(np.einsum("tji,tjk->tik", Rf, Rf) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(Rf)
    bad = np.flatnonzero((err > 1e-6) | (det < 0))
    if bad.size:
        t = int(np.flatnonzero(ok)[bad[0]])
        raise InputError(
            f"segment_rotations: joint {j}, segment {k}, sample {t} is not a rotation matrix "
            f"(max |RᵀR − I| = {err[bad[0]]:.3g}, det {det[bad[0]]:.3g})"
        )


def kinefuse_fusion(
    z_imu, z_cam, available, dt_s: float, *, causal: bool = False, features=None, lag: int = 0,
    parents=None, alpha=None, max_lag: int | None = None, min_history: int = 30,
    refit_every: int | None = 60, bridge: bool = True, segment_rotations=None,
) -> KinefuseResult:  # fmt: skip
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
        chosen by blocked cross-validation with 2 s blocks offline, 1 s causal: module Notes).
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
        bridge") instead of the filter's prediction. Offline: inside outages with camera
        history on both sides, the mean of the smoother's output and the bridges run forward
        and backward (module Notes, "Offline"). Default True; False: the filter or smoother
        alone.
    segment_rotations : array_like, shape (T, J, S, 3, 3), optional
        Per joint, ``R_frame_from_sensor`` of the S segments whose pose moves it (e.g.
        :func:`kinefuse.pipelines.features.joint_rotations`), in the frame of the positions;
        all-zero matrices pad joints with fewer segments, NaN where an orientation is missing. When given, the correction also regresses on the segment-frame
        model (:func:`kinefuse.pipelines.features.segment_frame_design`: a constant error in
        each sensor's frame; module Notes).

    Returns
    -------
    KinefuseResult
        ``position (T, J, 3)``, ``cov (T, J, 3, 3)``, ``source (T, J)`` and diagnostics.

    Notes
    -----
    Model, noise fit, offline and causal runs, bridge: the Notes of this module's docstring.

    Deviations from the papers
    --------------------------
    Not in paper A or B: a third method of this package. It replaces paper B's IMM of two
    position filters (SPEC §8) and ELM-1/ELM-2 (SPEC §10) by one state-space model with both
    sensors as measurements and a regression on IMU features instead of on positions.
    """
    _check_options(causal, lag)
    zi, zc, av, dt, phi = _check(z_imu, z_cam, available, dt_s, features)
    base = chain_features(zi, dt, parents)
    # the chain's velocity is always a feature: it absorbs a residual time offset between the
    # streams (e(t) ≈ −δ ż(t)); the rest comes from the IMU features when given
    phi = base if phi is None else np.concatenate([phi, base[..., -3:]], axis=-1)
    rots = None
    if segment_rotations is not None:
        rots = _rotations_by_joint(segment_rotations, zi.shape[:2])
    cfg = _CausalSettings(
        alpha=alpha, max_lag=int(max(2, int(round(1.0 / dt))) if max_lag is None else max_lag),
        min_history=int(min_history), refit_every=refit_every, lag=int(lag),
        n_folds=_N_FOLDS_CAUSAL, min_fit_s=_MIN_FIT_S, prior_s=_PRIOR_S,
    )  # fmt: skip
    return _fuse(zi, zc, av, (phi, rots), dt, cfg, bool(causal), bridge)


def _joint_phi(phi, rots, j) -> np.ndarray:
    """Joint ``j``'s regressors: its features ``(T, F)``, or with segment rotations the per-axis
    design ``(T, 3, K + 3 F)``: the segment-frame columns, then the features with a coefficient
    per axis (as without rotations). Built per joint: a long recording's design for all joints
    at once would not fit in memory."""
    if rots is None:
        return phi[:, j]
    design = segment_frame_design([rots[j]])[:, 0]
    per_axis = np.einsum("tf,ad->tadf", phi[:, j], np.eye(3)).reshape(phi.shape[0], 3, -1)
    return np.concatenate([design, per_axis], axis=-1)


def _fuse(zi, zc, av, inputs, dt, cfg: _CausalSettings, causal: bool, bridge) -> KinefuseResult:
    """:func:`kinefuse_fusion` on validated inputs, joint by joint (``inputs``: the features
    and the segment rotations by joint or None)."""
    phi_all, rots = inputs
    T, J, _ = zi.shape
    pos = np.empty((T, J, 3))
    cov = np.zeros((T, J, 3, 3))
    corr_all = np.zeros((T, J, 3))
    bias = np.zeros((T, J, 3))
    source = np.where(av, SOURCE_FUSED, SOURCE_BRIDGED).astype(np.int8)
    params = []
    n_refits = []
    for j in range(J):
        seen = av[:, j]
        phi = _joint_phi(phi_all, rots, j)
        if not causal:
            if seen.sum() >= 2:
                reg, corr, pj = _fit_joint(zc[:, j], zi[:, j], phi, seen, dt, cfg.alpha,
                                           cfg.max_lag)  # fmt: skip
            else:
                reg, corr, pj = None, np.zeros((T, 3)), NoiseParameters.default()
                source[~seen, j] = SOURCE_IMU
            m, P = _run(zc[:, j], zi[:, j] + corr, pj, dt)
            last = {"noise": pj, "correction": reg}
        else:
            m, P, corr, last, n, t_first = _causal_joint(zc[:, j], zi[:, j], phi, seen, dt, cfg)
            source[:t_first, j][~seen[:t_first]] = SOURCE_IMU
            n_refits.append(n)
        pos[:, j] = m[..., 0].T
        cov[:, j, range(3), range(3)] = P[..., 0, 0].T
        if bridge:
            fill = _bridge if causal else _two_sided_bridge
            last["bridge"] = fill(pos[:, j], cov[:, j], zi[:, j], corr, zc[:, j], seen,
                                  cfg.min_history)  # fmt: skip
        bias[:, j] = m[..., 2].T
        corr_all[:, j] = corr
        params.append(last)
    info = {"causal": bool(causal), "lag": int(cfg.lag), "n_features": int(phi.shape[-1]),
            "n_refits": n_refits}  # fmt: skip
    return KinefuseResult(position=pos, cov=cov, source=source, correction=corr_all,
                          chain_error=bias, params=params, info=info)  # fmt: skip


def _bridge(pos, cov, zi, corr, zc, seen, min_history):
    """Inside outages: the prequentially chosen offset bridge replaces the filter's output
    (``pos (T, 3)``, ``cov (T, 3, 3)`` of one joint, in place); returns the choices made."""
    bp, bv, choices = prequential_bridge((zi, zi + corr), zc, seen, min_history=min_history)
    rows = np.flatnonzero(np.all(np.isfinite(bp), axis=-1))
    _put_rows(pos, cov, rows, bp[rows], bv[rows])
    return choices


def _put_rows(pos, cov, rows, p, var):
    """``pos[rows] = p`` and ``cov[rows]`` = the diagonal ``var (n, 3)`` (the axes independent)."""
    pos[rows] = p
    cov[rows] = 0.0
    ax = np.arange(3)
    cov[rows[:, None], ax, ax] = var


def _two_sided_bridge(pos, cov, zi, corr, zc, seen, min_history):
    """Offline, inside outages with camera history on both sides: the equal-weight mean of the
    smoother's output and the forward and the backward (time-reversed) prequential bridges
    (``pos (T, 3)``, ``cov (T, 3, 3)`` of one joint, in place; Notes of the module,
    "Offline"); returns both sides' choices, the backward onsets as the outages' last frames."""
    bases = (zi, zi + corr)
    fp, fv, fwd = prequential_bridge(bases, zc, seen, min_history=min_history)
    r = slice(None, None, -1)
    bp, bv, bwd = prequential_bridge(tuple(b[r] for b in bases), zc[r], seen[r],
                                     min_history=min_history)  # fmt: skip
    bp, bv = bp[r], bv[r]
    both = ~seen & np.all(np.isfinite(fp), axis=-1) & np.all(np.isfinite(bp), axis=-1)
    rows = np.flatnonzero(both)
    ax = np.arange(3)
    # the three estimates' correlation is unknown: the standard deviation of their mean is at
    # most the mean of their standard deviations (equality when fully correlated)
    sd = (np.sqrt(cov[rows][:, ax, ax]) + np.sqrt(fv[rows]) + np.sqrt(bv[rows])) / 3.0
    _put_rows(pos, cov, rows, (pos[rows] + fp[rows] + bp[rows]) / 3.0, sd**2)
    T = seen.size
    return {"forward": fwd, "backward": [(T - 1 - a, *rest) for a, *rest in bwd]}
