"""Upper-limb posture capture, paper A (Sun 2024): IMU chain -> per-joint EM-KF/FIR (SPEC §11).

:func:`upper_limb` filters given elbow/wrist chain positions (all joints in one batch call);
:func:`upper_limb_from_recording` builds the chain from a recording with
:mod:`kinefuse.kinematics` first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kinefuse._validation import names_arg, positive_finite
from kinefuse.conventions import MODE_EM, MODE_FIR, MODE_KF, MODE_PREDICT
from kinefuse.exceptions import InputError
from kinefuse.filters import KalmanFilter
from kinefuse.filters.em_kalman import EMKalmanFilter
from kinefuse.filters.integrated import IntegratedFilter
from kinefuse.filters.ufir import UFIRFilter
from kinefuse.io.recording import JointStream, Recording
from kinefuse.kinematics import chain_positions, lengths_from_joints
from kinefuse.kinematics import upper_limb as upper_limb_skeleton
from kinefuse.models import constant_velocity

__all__ = [
    "UPPER_LIMB_METHODS",
    "UpperLimbResult",
    "paper_a_filter",
    "upper_limb",
    "upper_limb_from_recording",
]

#: Filters of paper A: the integrated filter and its three baselines.
UPPER_LIMB_METHODS = ("em-kf-fir", "kf", "fir", "em-kf")


@dataclass(frozen=True, eq=False)
class UpperLimbResult:
    """Output of :func:`upper_limb` (time-major).

    Attributes
    ----------
    position : ndarray, shape (T, J, 3)
        Filtered joint positions, m (frame of the input chain; ENU for paper A).
    cov : ndarray, shape (T, J, 3, 3)
        Position covariance, m².
    mode : ndarray of int8, shape (T, J)
        Branch per sample (:data:`kinefuse.conventions.MODE_NAMES`): "em-kf-fir" its own trace;
        "kf" KF/predict; "em-kf" EM-KF/predict; "fir" FIR, KF in the dead zone, predict.
    distance : ndarray, shape (T, J)
        Paper A's D₁ ``νᵀR⁻¹ν`` ("em-kf-fir", "fir") or the NIS ``νᵀS⁻¹ν`` ("kf",
        "em-kf"); NaN where not observed.
    distance2 : ndarray, shape (T, J) or None
        D₂ ``νᵀR_em⁻¹ν`` of the integrated filter ("em-kf-fir" only).
    observed : ndarray of bool, shape (T, J)
        True where the measurement was used.
    joints : tuple of str
    method : str
    dt_s : float
    t_s : ndarray, shape (T,) or None
        Sample times, s (from :func:`upper_limb_from_recording`).
    """

    position: np.ndarray
    cov: np.ndarray
    mode: np.ndarray
    distance: np.ndarray
    distance2: np.ndarray | None
    observed: np.ndarray
    joints: tuple[str, ...]
    method: str
    dt_s: float
    t_s: np.ndarray | None = None


def _per_joint(value, name: str, J: int) -> list[float]:
    if np.ndim(value) == 0:
        vals = [value] * J
    else:
        vals = list(value)
        if len(vals) != J:
            raise InputError(
                f"expected {name} as a scalar or one value per joint ({J}), got {len(vals)}"
            )
    out = []
    for v in vals:
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise InputError(f"expected {name} as numbers, got {v!r}") from None
        if not math.isfinite(f) or f < 0 or (name == "r" and f == 0):
            raise InputError(
                f"expected {name} finite and {'> 0' if name == 'r' else '>= 0'}, got {v!r}"
            )
        out.append(f)
    return out


def _chain_arrays(z_elbow, z_wrist, joints):
    if isinstance(z_elbow, JointStream):
        if z_wrist is not None:
            raise InputError("expected z_wrist=None when a chain JointStream is given")
        st = z_elbow
        names = (
            tuple(joints)
            if joints is not None
            else tuple(j for j in st.joints if j.startswith(("elbow", "wrist")))
        )
        if not names:
            raise InputError(
                f"expected elbow/wrist joints in the chain stream, got {list(st.joints)}"
            )
        z = np.stack([st.position(j) for j in names], axis=1)
        dt = float(np.median(np.diff(st.t_s))) if st.t_s.size > 1 else None
        if dt is not None and np.max(np.diff(st.t_s)) > 1.5 * dt:
            k = int(np.argmax(np.diff(st.t_s)))
            raise InputError(
                f"expected the chain stream on a regular timeline (the filter steps dt = {dt:.4g} "
                f"s), got a {np.diff(st.t_s)[k]:.4g}-s step at t = {st.t_s[k]:.4g} s; resample it "
                "(kinefuse.io.resample_positions) or mark missing samples NaN on a regular grid"
            )
        return z, names, dt, st.t_s
    arrs = []
    for name, v in (("z_elbow", z_elbow), ("z_wrist", z_wrist)):
        if v is None:
            continue
        a = np.asarray(v)
        if not np.issubdtype(a.dtype, np.floating):
            raise InputError(f"expected {name} as a float array (T, 3), got dtype {a.dtype}")
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"expected {name} with shape (T, 3), got {a.shape}")
        arrs.append(a.astype(np.float64))
    if len(arrs) == 2 and arrs[0].shape != arrs[1].shape:
        raise InputError(
            f"expected z_wrist with the shape of z_elbow {arrs[0].shape}, got {arrs[1].shape}"
        )
    default = ("elbow", "wrist")[: len(arrs)]
    names = names_arg(joints, "joints") or default
    if len(names) != len(arrs):
        raise InputError(f"expected {len(arrs)} joint names, got {len(names)}")
    return np.stack(arrs, axis=1), names, None, None


def paper_a_filter(dt_s: float, q: float, r: float, **filter_kwargs) -> IntegratedFilter:
    """Paper A's integrated EM-KF/FIR filter (SPEC §7) on the constant-velocity model.

    The one construction of both forms of paper A: the batch :func:`upper_limb` runs its
    ``filter``, the online :class:`~kinefuse.streaming.processors.IntegratedProcessor` its
    ``step`` (stream = batch is the filter's own contract, tested in the filter layer).

    Parameters
    ----------
    dt_s, q, r : float
        Sample interval (s), process-noise scale ((m/s)² per step) and measurement-noise
        variance ``R = r I`` (m²) of :func:`kinefuse.models.constant_velocity`.
    **filter_kwargs
        :class:`~kinefuse.filters.integrated.IntegratedFilter` settings (``horizon``,
        ``threshold1``, ``threshold2``, ``n_em_iter``, ``gate``, ``fir_feedback``).
    """
    return IntegratedFilter(constant_velocity(dt_s, q=q, r=r), **filter_kwargs)


def _filter(method, dt, q, r, z, horizon, threshold1, threshold2, n_em_iter):
    """Paper A's filter (or a baseline) on ``z (J, T, 3)``: its FilterResult."""
    model = constant_velocity(dt, q, r)
    if method == "em-kf-fir":
        flt = paper_a_filter(dt, q, r, horizon=horizon, threshold1=threshold1,
                             threshold2=threshold2, n_em_iter=n_em_iter)  # fmt: skip
    elif method == "kf":
        flt = KalmanFilter(model)
    elif method == "fir":
        flt = UFIRFilter(model, horizon=horizon)
    else:
        flt = EMKalmanFilter(model, n_iter=n_em_iter)
    return flt.filter(z)[1]


def _mode_and_distance(method, res, r: float):
    """Per sample: the branch (MODE_*) and the distance of :class:`UpperLimbResult`."""
    if method == "em-kf-fir":
        return res.mode, res.distance
    if method in ("kf", "em-kf"):
        mode = np.where(res.observed, MODE_KF if method == "kf" else MODE_EM, MODE_PREDICT)
        return mode, res.distance
    nu = res.innovation
    dist = np.einsum("...i,...i->...", nu, nu) / r  # D₁ = νᵀ R⁻¹ ν, R = r I
    mode = np.where(res.observed, np.where(res.fir_ready, MODE_FIR, MODE_KF), MODE_PREDICT)
    return mode, dist


def upper_limb(
    z_elbow,
    z_wrist=None,
    dt_s: float | None = None,
    method: str = "em-kf-fir",
    *,
    q=0.1,
    r=0.01,
    horizon: int = 20,
    threshold1: float = 2.0,
    threshold2: float = 2.0,
    n_em_iter: int = 3,
    joints: Sequence[str] | None = None,
) -> UpperLimbResult:
    r"""Paper A (Sun 2024) per-joint filtering of IMU-chain positions (SPEC §11).

    Parameters
    ----------
    z_elbow : array_like of float, shape (T, 3), or JointStream
        Elbow chain positions ``p1_k`` (SPEC §2.1), m, NaN rows missing; or a chain
        :class:`~kinefuse.io.recording.JointStream` (e.g. from
        :func:`kinefuse.kinematics.chain_positions`) whose ``elbow*``/``wrist*`` joints are
        filtered (or ``joints``).
    z_wrist : array_like of float, shape (T, 3), optional
        Wrist chain positions ``p2_k``, m (None with a JointStream).
    dt_s : float, optional
        Sample interval, s (> 0). Default: the stream's median interval, else 1/30 (paper A).
    method : {"em-kf-fir", "kf", "fir", "em-kf"}
        Integrated EM-KF/FIR filter (paper A, SPEC §7) or a baseline: KF (SPEC §4), UFIR with
        KF dead zone (SPEC §6), EM-KF (SPEC §5).
    q : float or sequence of float
        Process-noise scale, (m/s)² per step, one for all joints or one per joint (paper A
        elbow test 1: 1, wrist test 1: 0.1).
    r : float or sequence of float
        Measurement-noise variance ``R = r I``, m² (paper A: 0.01-0.1).
    horizon : int
        UFIR horizon N, samples (default 20 at 30 Hz).
    threshold1, threshold2 : float
        Integrated-filter gates (SPEC §7.2; defaults 2, 2).
    n_em_iter : int
        EM iterations N_EM (default 3).
    joints : sequence of str, optional
        Joint names (arrays: default ``("elbow", "wrist")``) or joints to pick from the stream.

    Returns
    -------
    UpperLimbResult

    Raises
    ------
    ValueError
        Shapes other than ``(T, 3)``, mismatching elbow/wrist shapes, unknown method,
        ``dt_s <= 0``, a joint without any valid sample.

    Notes
    -----
    The joints are filtered **independently** (paper A's design: the wrist filter does not use
    the elbow estimate), as one batch ``(J, T, 3)`` call per distinct ``(q, r)``.

    Deviations from the paper
    -------------------------
    The filters carry the corrections of SPEC §4-§7 (see their docstrings); missing samples
    (NaN) predict only; q and r are inputs, since the paper tunes them per test.
    """
    if not isinstance(method, str) or method not in UPPER_LIMB_METHODS:
        raise InputError(f"unknown method {method!r}; expected one of {UPPER_LIMB_METHODS}")
    z, names, dt_stream, t_s = _chain_arrays(z_elbow, z_wrist, joints)
    if dt_s is None:
        dt_s = dt_stream if dt_stream is not None else 1.0 / 30.0
    dt = positive_finite(dt_s, "dt_s")
    if dt_stream is not None and abs(dt - dt_stream) > 0.05 * dt_stream:
        raise InputError(
            f"dt_s = {dt:g} s differs from the chain stream's sample step {dt_stream:.4g} s; leave "
            "dt_s unset (the stream's), or resample the stream"
        )
    T, J, _ = z.shape
    if T < 1:
        raise InputError(f"expected at least one sample, got shape {z.shape}")
    qs, rs = _per_joint(q, "q", J), _per_joint(r, "r", J)
    return _filter_joints(z, dt, method, qs, rs, (horizon, threshold1, threshold2, n_em_iter),
                          names, t_s)  # fmt: skip


def _filter_joints(z, dt, method, qs, rs, settings, names, t_s) -> UpperLimbResult:
    """:func:`upper_limb` on validated ``z (T, J, 3)``: one batch call per distinct ``(q, r)``;
    ``settings = (horizon, threshold1, threshold2, n_em_iter)``."""
    T, J, _ = z.shape
    zj = np.ascontiguousarray(z.transpose(1, 0, 2))
    pos = np.empty((J, T, 3))
    cov = np.empty((J, T, 3, 3))
    mode = np.empty((J, T), dtype=np.int8)
    dist = np.full((J, T), np.nan)
    dist2 = np.full((J, T), np.nan) if method == "em-kf-fir" else None
    obs = np.empty((J, T), dtype=bool)
    groups: dict[tuple[float, float], list[int]] = {}
    for j in range(J):
        groups.setdefault((qs[j], rs[j]), []).append(j)
    for (qv, rv), idx in groups.items():
        res = _filter(method, dt, qv, rv, zj[idx], *settings)
        pos[idx] = res.position
        cov[idx] = res.cov[..., 0::2, 0::2]
        obs[idx] = res.observed
        mode[idx], dist[idx] = _mode_and_distance(method, res, rv)
        if dist2 is not None:
            dist2[idx] = res.distance2
    return UpperLimbResult(
        position=np.ascontiguousarray(pos.transpose(1, 0, 2)),
        cov=np.ascontiguousarray(cov.transpose(1, 0, 2, 3)),
        mode=np.ascontiguousarray(mode.T),
        distance=np.ascontiguousarray(dist.T),
        distance2=None if dist2 is None else np.ascontiguousarray(dist2.T),
        observed=np.ascontiguousarray(obs.T),
        joints=names,
        method=method,
        dt_s=dt,
        t_s=t_s,
    )


def _fill(t_src: np.ndarray, p: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``p (T, 3)`` (NaN = missing) onto ``t_dst``, ends held."""
    ok = np.all(np.isfinite(p), axis=1)
    if not np.any(ok):
        return np.full((t_dst.size, 3), np.nan)
    return np.stack([np.interp(t_dst, t_src[ok], p[ok, k]) for k in range(3)], axis=-1)


def _check_recording_args(recording, side, source, shoulder, rate_hz):
    """Validated ``(joint stream, side letter, rate Hz)`` of :func:`upper_limb_from_recording`."""
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    if source not in ("vision", "reference"):
        raise InputError(f"expected source in ('vision', 'reference'), got {source!r}")
    if shoulder not in ("stream", "constant"):
        raise InputError(f"expected shoulder in ('stream', 'constant'), got {shoulder!r}")
    stream = getattr(recording, source)
    if stream is None:
        raise InputError(f"expected a {source} joint stream in the recording, got None")
    s = str(side).lower()[:1]
    if s not in ("l", "r"):
        raise InputError(f"expected side in ('l', 'r'), got {side!r}")
    return stream, s, positive_finite(rate_hz, "rate_hz")


def _timeline(t_src: np.ndarray, rate: float) -> np.ndarray:
    """The stream's timeline when its median rate is within 5 % of ``rate``, else a uniform
    grid at ``rate`` over its span."""
    src_rate = 1.0 / float(np.median(np.diff(t_src))) if t_src.size > 1 else rate
    if abs(src_rate - rate) <= 0.05 * rate:
        return t_src
    return t_src[0] + np.arange(int(np.floor((t_src[-1] - t_src[0]) * rate)) + 1) / rate


def _shoulder_root(stream, sh: str, t: np.ndarray, shoulder: str, source: str) -> np.ndarray:
    """Chain root ``(T, 3)`` on ``t``: the stream's shoulder (gaps interpolated) or paper A's
    constant one (mean over the first second of available samples)."""
    t_src = stream.t_s
    p_sh = stream.position(sh)
    if shoulder == "constant":
        ok = np.all(np.isfinite(p_sh), axis=1)
        first = t_src[ok][:1]
        if first.size == 0:
            raise InputError(f"no available {sh!r} sample in the {source} stream")
        sel = ok & (t_src < first[0] + 1.0)
        return np.broadcast_to(p_sh[sel].mean(axis=0), (t.size, 3)).copy()
    return _fill(t_src, p_sh, t)


def upper_limb_from_recording(
    recording,
    side: str = "r",
    calibration=None,
    skeleton=None,
    *,
    source: str = "vision",
    shoulder: str = "stream",
    rate_hz: float = 30.0,
    method: str = "em-kf-fir",
    **filter_kwargs,
) -> UpperLimbResult:
    """Paper A end to end: IMU orientations -> elbow/wrist chain (SPEC §2.1) -> :func:`upper_limb`.

    Parameters
    ----------
    recording : Recording
        IMU orientations for ``upper_arm_<side>`` and ``forearm_<side>``; the ``source`` joint
        stream with ``shoulder_<side>`` (and elbow/wrist for default lengths).
    side : {"r", "l"}
    calibration : Calibration, optional
        Segment axes, lengths and camera alignment (:func:`kinefuse.kinematics.calibrate`).
    skeleton : Skeleton, optional
        Default :func:`kinefuse.kinematics.upper_limb` with the median bone lengths of the
        ``source`` stream and axes ``e2`` (or the calibration's).
    source : {"vision", "reference"}
        Joint stream giving the shoulder root; the output is in its frame.
    shoulder : {"stream", "constant"}
        ``"stream"`` (default): the stream's shoulder trajectory, linearly interpolated across
        its gaps and resampled to the filter rate. ``"constant"``: paper A's fixed shoulder,
        the mean over the first second of available samples (SPEC §2.1).
    rate_hz : float
        Filter rate (default 30 Hz, SPEC §12.2); the stream's timeline is used when its
        median rate is within 5 %, else a uniform grid at ``rate_hz`` over its span.
    method : str
        As in :func:`upper_limb`.
    **filter_kwargs
        ``q, r, horizon, threshold1, threshold2, n_em_iter`` of :func:`upper_limb`.

    Returns
    -------
    UpperLimbResult
        Joints ``elbow_<side>``, ``wrist_<side>``; ``t_s`` the filter timeline.

    Deviations from the paper
    -------------------------
    Paper A measures the shoulder once (constant ``p0``); the default here follows the
    stream's shoulder, which is what a camera or reference provides (``shoulder="constant"``
    for the paper's form). IMU orientations are SLERP-resampled to the filter timeline.
    """
    stream, s, rate = _check_recording_args(recording, side, source, shoulder, rate_hz)
    t = _timeline(stream.t_s, rate)
    sh = f"shoulder_{s}"
    root = _shoulder_root(stream, sh, t, shoulder, source)
    sk = skeleton
    if sk is None:
        sk = upper_limb_skeleton(s, lengths={f"upper_arm_{s}": 0.3, f"forearm_{s}": 0.25})
        if calibration is None or not calibration.lengths_m:
            segs = [(sk.segments[i], sk.proximal[i], sk.distal[i]) for i in range(len(sk.segments))]
            sk = sk.with_lengths(lengths_from_joints(stream, segs))
    chain = chain_positions(recording, sk, calibration, root={sh: root}, source=source, t_s=t)
    names = (f"elbow_{s}", f"wrist_{s}")
    z = np.stack([chain.position(j) for j in names], axis=1)
    res = upper_limb(z[:, 0], z[:, 1], 1.0 / rate, method, joints=names, **filter_kwargs)
    return UpperLimbResult(**{**res.__dict__, "t_s": t})
