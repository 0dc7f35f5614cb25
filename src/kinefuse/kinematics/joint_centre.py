"""One joint centre from the two IMUs beside it: the rigid-body model and its least-squares fit.

Seel, Schauer & Raisch 2012 (two sensors, world frames up to a heading), Crabolu et al. 2017
(one sensor, still proximal segment), the hinge axis of the relative rotation (Ehrig et al.
2007) and the fit's excitation and uncertainty; :mod:`kinefuse.kinematics.functional` combines
the joints into a calibration (the model's equations are in its docstring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from kinefuse.exceptions import InputError
from kinefuse.io.recording import ImuStream
from kinefuse.kinematics.forward import as_rotation_matrices, rotation_z
from kinefuse.orientation.resample import slerp_resample

__all__ = ["GRAVITY_M_S2", "JointFit", "Signals", "fit_joint", "joint_signals"]


@dataclass(frozen=True, eq=False)
class JointFit:
    """One joint's functional estimate.

    Attributes
    ----------
    joint : str
        Joint name.
    proximal, distal : str or None
        The IMU segments on either side (``proximal`` None: one-sensor fixed-centre model).
    r_proximal_m, r_distal_m : ndarray, shape (3,), or None
        Vector from each sensor to the joint centre in that sensor's frame, m.
    heading_deg : float
        Heading (rotation about the vertical) taking the proximal sensor's world frame onto the
        distal sensor's, deg (0 for the one-sensor model).
    heading_sd_deg : float
        Its standard deviation from the fit (Gauss-Newton covariance), deg. It only counts the
        noise: where the rigid model is violated (soft tissue), ``heading_deg`` also absorbs
        model error and can be far off while ``heading_sd_deg`` is small.
    r_sd_m : float
        Largest standard deviation of the sensor-to-joint vector components, m (same caveat).
    axis_proximal, axis_distal : ndarray, shape (3,)
        Dominant axis of the relative angular velocity (the hinge axis for a hinge joint) in each
        sensor frame, signs matched in the world frame (``axis_proximal`` None without proximal).
    hinge_rate_rad_s : ndarray, shape (3,)
        RMS relative angular rate along the principal axes, largest first, rad/s (a hinge has
        one large value).
    excitation_s2 : float
        The excitation measure (Notes of :func:`functional_calibration`), s⁻².
    axial_excitation_s2 : float
        Excitation along the hinge axis (the centre moved along it in both frames), s⁻²: below
        the threshold the centre's position along the axis is not observable.
    residual_m_s2 : float
        RMS of the joint-acceleration mismatch after the fit, m/s².
    n_samples : int
        Samples used.
    """

    joint: str
    proximal: str | None
    distal: str
    r_proximal_m: np.ndarray | None
    r_distal_m: np.ndarray
    heading_deg: float
    heading_sd_deg: float
    r_sd_m: float
    axis_proximal: np.ndarray | None
    axis_distal: np.ndarray
    hinge_rate_rad_s: np.ndarray
    excitation_s2: float
    axial_excitation_s2: float
    residual_m_s2: float
    n_samples: int


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]×`` for ``v`` (K, 3) -> (K, 3, 3)."""
    z = np.zeros(v.shape[0])
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], -1),
            np.stack([v[:, 2], z, -v[:, 0]], -1),
            np.stack([-v[:, 1], v[:, 0], z], -1),
        ],
        axis=1,
    )


def _fill(x: np.ndarray) -> np.ndarray:
    """NaN rows linearly interpolated (for the filter only; those samples are not fitted)."""
    ok = np.all(np.isfinite(x), axis=1)
    if np.all(ok):
        return x
    i = np.arange(x.shape[0])
    return np.stack([np.interp(i, i[ok], x[ok, k]) for k in range(x.shape[1])], -1)


def _fill_rotations(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-from-sensor (K, 3, 3) with rows missing in ``q (K, 4)`` slerped between their
    valid neighbours (held at the ends), for the low-pass only: those samples are not fitted,
    but an arbitrary rotation there (e.g. the identity) would be smeared by the filter into the
    valid samples around them (and turn the heading of a joint fit)."""
    ok = np.all(np.isfinite(q), axis=1)
    if np.all(ok) or not np.any(ok):
        return np.where(ok[:, None, None], as_rotation_matrices(q, "orientation"), np.eye(3))
    filled = slerp_resample(t[ok], q[ok], t, max_gap_s=np.inf) if ok.sum() > 1 else q.copy()
    idx = np.flatnonzero(ok)
    filled[: idx[0]], filled[idx[-1] + 1 :] = q[idx[0]], q[idx[-1]]
    return as_rotation_matrices(filled, "orientation")


#: Gravity used by the one-sensor (fixed-centre) model, m/s².
GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class Signals:
    R: np.ndarray  # (K, 3, 3) world_from_sensor
    K: np.ndarray  # (K, 3, 3) LP([ω̇]× + [ω]×²), sensor frame
    acc: np.ndarray  # (K, 3) LP(a), sensor frame
    Kw: np.ndarray  # (K, 3, 3) LP(R K), world frame
    accw: np.ndarray  # (K, 3) LP(R a), world frame
    gyr: np.ndarray  # (K, 3) LP(ω)
    ok: np.ndarray  # (K,)


def joint_signals(st: ImuStream, segment: str, t: np.ndarray, cutoff_hz: float) -> Signals:
    """One sensor's low-passed model terms on the timeline ``t`` (see :func:`fit_joint`)."""
    for name, v in (("acc_m_s2", st.acc_m_s2), ("gyr_rad_s", st.gyr_rad_s)):
        if v is None:
            raise InputError(
                f"IMU {segment!r}: functional calibration needs {name} (accelerometer and gyroscope), "
                "got none"
            )
    same = st.t_s.shape == t.shape and np.allclose(st.t_s, t)
    if same:
        acc, gyr, q = st.acc_m_s2, st.gyr_rad_s, st.q_world_from_sensor
    else:
        acc = np.stack([np.interp(t, st.t_s, st.acc_m_s2[:, k]) for k in range(3)], -1)
        gyr = np.stack([np.interp(t, st.t_s, st.gyr_rad_s[:, k]) for k in range(3)], -1)
        q = slerp_resample(st.t_s, st.q_world_from_sensor, t)
    R = as_rotation_matrices(q, f"IMU {segment!r} orientation")
    ok = (
        np.all(np.isfinite(acc), axis=1)
        & np.all(np.isfinite(gyr), axis=1)
        & np.all(np.isfinite(R), axis=(1, 2))
    )
    if np.count_nonzero(ok) < 10:
        raise InputError(
            f"IMU {segment!r}: expected at least 10 samples with orientation, acc and gyro in the "
            f"calibration window, got {int(np.count_nonzero(ok))}"
        )
    R = _fill_rotations(q, t)
    acc, gyr = _fill(acc), _fill(gyr)
    fs = 1.0 / float(np.median(np.diff(t)))
    if cutoff_hz is not None and cutoff_hz < 0.45 * fs and t.size > 15:
        sos = butter(2, cutoff_hz, fs=fs, output="sos")

        def lp(x):
            return sosfiltfilt(sos, x, axis=0)
    else:

        def lp(x):
            return x

    # the model a + K r is linear in r: filtering both sides keeps it exact (the same linear
    # filter on the measured acceleration and on the regressor K, not on K's inputs)
    W = _skew(gyr)
    K_raw = W @ W + _skew(np.gradient(gyr, t, axis=0))
    return Signals(
        R=R,
        K=lp(K_raw),
        acc=lp(acc),
        Kw=lp(R @ K_raw),
        accw=lp(np.einsum("kij,kj->ki", R, acc)),
        gyr=lp(gyr),
        ok=ok,
    )


def _excitation(sig: Signals) -> float:
    """``sqrt`` of the middle eigenvalue of ``mean_k K(k)ᵀ K(k)``, s⁻²."""
    M = np.einsum("kji,kjl->il", sig.K[sig.ok], sig.K[sig.ok]) / max(int(np.sum(sig.ok)), 1)
    return float(np.sqrt(max(np.linalg.eigvalsh(M)[1], 0.0)))


def _hinge_axes(A: Signals | None, B: Signals, ok: np.ndarray):
    """Hinge axis in A's and B's frame and the RMS relative rates about the principal axes.

    Axis: the invariant direction of the relative rotation ``R_Aᵀ R_B`` (the direction part of
    Ehrig et al. 2007's SARA): the top singular vectors of ``mean_k R_A(k)ᵀ R_B(k)``. Rates: the
    principal RMS values of the relative angular velocity ``R_Bᵀ(R_B ω_B − R_A ω_A)``.
    """
    wB = np.einsum("kij,kj->ki", B.R, B.gyr)
    wrel = wB if A is None else wB - np.einsum("kij,kj->ki", A.R, A.gyr)
    inB = np.einsum("kji,kj->ki", B.R[ok], wrel[ok])
    ev, vec = np.linalg.eigh(inB.T @ inB / max(inB.shape[0], 1))
    rates = np.sqrt(np.clip(ev[::-1], 0.0, None))
    if A is None:
        return None, vec[:, -1], rates
    M = np.einsum("kji,kjl->il", A.R[ok], B.R[ok]) / max(int(np.sum(ok)), 1)
    U, _, Vt = np.linalg.svd(M)
    jA, jB = U[:, 0], Vt[0]
    if np.dot(np.einsum("ij,j->i", M, jB), jA) < 0:
        jB = -jB
    return jA, jB, rates


def fit_joint(
    joint, prox, dist, A: Signals | None, B: Signals, min_excitation, n_eff_ratio, constraint
):
    """Fit one joint centre (and heading) from the signals of its two sensors ``A``, ``B``.

    ``A`` None: the one-sensor fixed-centre model. Returns the :class:`JointFit` and the
    excitation of each sensor (the model and its terms: :mod:`kinefuse.kinematics.functional`).
    """
    ok = B.ok if A is None else A.ok & B.ok
    n = int(np.count_nonzero(ok))
    # ---- excitation
    exc = [_excitation(B)] if A is None else [_excitation(A), _excitation(B)]
    exc_joint = min(exc)
    if exc_joint < min_excitation:
        raise InputError(
            f"functional calibration: joint {joint!r} ({prox or 'fixed'} / {dist}) lacked excitation: "
            f"{exc_joint:.3g} s^-2 < {min_excitation:g} s^-2 required; record movement of that joint "
            "(several cycles, in more than one direction for a ball joint) or use a static calibration"
        )
    fun, x0, Amat = _joint_model(A, B, ok, constraint)
    sol = least_squares(fun, x0, method="trf", x_scale="jac")
    resid = float(np.sqrt(np.mean(sol.fun**2)))
    jA, jB, rates = _hinge_axes(A, B, ok)
    axial = _axial_excitation(A, B, ok, jA, jB, Amat, n)
    sd = _standard_deviations(sol, n_eff_ratio)
    if A is None:
        rA, rB, psi = None, sol.x[:3], 0.0
    else:
        rA, rB = sol.x[:3], sol.x[3:6]
        psi = float(np.arctan2(np.sin(sol.x[6]), np.cos(sol.x[6]))) if sol.x.size > 6 else np.nan
    return JointFit(
        joint=joint,
        proximal=prox,
        distal=dist,
        r_proximal_m=rA,
        r_distal_m=rB,
        heading_deg=float(np.degrees(psi)),
        heading_sd_deg=0.0 if A is None else float(np.degrees(sd[6])) if sd.size > 6 else np.nan,
        r_sd_m=float(np.max(sd[:6] if A is not None else sd[:3])),
        axis_proximal=jA,
        axis_distal=jB,
        hinge_rate_rad_s=rates,
        excitation_s2=exc_joint,
        axial_excitation_s2=axial,
        residual_m_s2=resid,
        n_samples=n,
    ), exc


def _joint_model(A: Signals | None, B: Signals, ok: np.ndarray, constraint: str):
    """The residual function of the joint constraint, its linear start and design matrix."""
    KB, aB = B.K[ok], B.acc[ok]
    wB0, GB = B.accw[ok], B.Kw[ok]
    if A is None:
        # Crabolu et al. 2017: the centre is still, its specific force is gravity: R_B (a_B + K_B r) = g
        g = np.array([0.0, 0.0, GRAVITY_M_S2])

        def fun(x):
            return (wB0 + GB @ x - g).ravel()

        Amat = GB.reshape(-1, 3)
        b = (g - wB0).reshape(-1)
        x0 = np.linalg.lstsq(Amat, b, rcond=None)[0]
    else:
        KA, aA = A.K[ok], A.acc[ok]
        wA0, GA = A.accw[ok], A.Kw[ok]

        # Seel et al. 2012 Eq. (8) in vector form, with the world frames allowed to differ by a
        # heading psi: Rz(psi) R_A (a_A + K_A r_A) = R_B (a_B + K_B r_B)
        def fun(x):
            pa = wA0 + GA @ x[:3]
            pb = wB0 + GB @ x[3:6]
            return (pa @ rotation_z(x[6]).T - pb).ravel()

        Amat = np.concatenate([GA, -GB], axis=2).reshape(-1, 6)
        b = (wB0 - wA0).reshape(-1)
        x0 = np.r_[np.linalg.lstsq(Amat, b, rcond=None)[0], 0.0]
        if constraint == "norm":
            # Seel et al. 2012 Eq. (8) as published: orientation-free, immune to heading drift
            def fun(x):
                return np.linalg.norm(
                    aA + np.einsum("kij,j->ki", KA, x[:3]), axis=1
                ) - np.linalg.norm(aB + np.einsum("kij,j->ki", KB, x[3:6]), axis=1)

            x0 = x0[:6]
    return fun, x0, Amat


def _axial_excitation(A, B, ok, jA, jB, Amat, n: int) -> float:
    """Excitation of the centre moving along the hinge axis (in both frames at once), s⁻²."""
    KB = B.K[ok]
    if A is None:
        M = np.einsum("kji,kjl->il", KB, KB) / n
        return float(np.sqrt(max(jB @ M @ jB, 0.0)))
    else:
        # the centre moved along the hinge in both frames at once: (j_A, j_B)/√2
        v = np.r_[jA, jB] / np.sqrt(2.0)
        Gv = Amat.reshape(n, 3, 6) @ v
        return float(np.sqrt(np.mean(np.sum(Gv**2, axis=1))))


def _standard_deviations(sol, n_eff_ratio: float) -> np.ndarray:
    """Standard deviations of the fitted parameters (Gauss-Newton covariance)."""
    # standard deviations from the Gauss-Newton covariance, residuals taken as white over the
    # effective samples (the low-pass leaves about 2 f_c / f_s independent samples per sample)
    J = sol.jac
    dof = max(n_eff_ratio * sol.fun.size - J.shape[1], 1.0)
    s2 = float(np.sum(sol.fun**2)) * n_eff_ratio / dof
    cov = s2 * np.linalg.pinv(J.T @ J) / n_eff_ratio
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return sd
