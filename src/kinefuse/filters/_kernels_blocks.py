"""Compiled Kalman filter and RTS smoother on per-axis covariance blocks (numba).

The fast form behind :class:`~kinefuse.filters.KalmanFilter` and
:func:`~kinefuse.filters.rts_smooth` for axis-blocked models (SPEC §1 decoupling): the
``n_x``-state problem splits into ``n_a`` independent 2-state problems with a scalar
measurement, and only what the model has is stored.

Covariance layout ("blocks")
----------------------------
``covb (B, T, n_c, 3)`` holds, for each axis block ``c``, ``[p00, p01, p11]`` of the symmetric
2x2 covariance of that axis' ``(position, velocity)`` pair (state components ``2c, 2c+1``).
``n_c = n_a`` in general; ``n_c = 1`` when every axis has the same model block and the same
initial covariance ("shared"): the per-axis recursions are then the same arithmetic on the same
numbers, so one block is computed and stored for all axes (bit-identical to computing each).
:func:`kinefuse.filters._base.expand_cov_blocks` expands the layout to ``(..., n_x, n_x)``.

Model parameters are packed per axis into ``par (n_a, 10)`` = ``[f00, f01, f10, f11, q00, q01,
q11, h0, h1, r]`` and ``p0 (n_a, 3)`` (the initial covariance block). An output array with a
zero-length first axis is not wanted and not written (``outputs=`` of the filter objects).

Loop order: joints in chunks of :data:`CHUNK`, time, joints within the chunk. Interleaving a few
independent joints per time step hides the latency of each joint's serial recursion while the
writes stay a few sequential streams (a vectorisation across the batch axis by the CPU's
out-of-order engine; the output layout ``(B, T, ...)`` rules out SIMD lanes over joints).
The common case, three axes sharing one covariance block (3-D positions), has its own pass
(:func:`_kf_pass3`): element by element, the state in local variables, which the compiler keeps
in registers (the general pass keeps it in arrays that any output store could alias); the same
arithmetic through the same helpers, about 2.5x faster, byte-identical (tested); the RTS has
the same (:func:`_rts_pass3`, which also loads each sample once and branches once per
sample: about 2.7x faster than the general pass).

The 2x2 block arithmetic (:func:`_cov_step` forward, :func:`rts2_step` backward) is written
once here and shared with :mod:`._kernels_axis` (the full-matrix layout, which the tests compare
against, together with the dense :func:`._kernels_axis.kf_filter_dense` and filterpy).
"""

from __future__ import annotations

import numpy as np

from kinefuse._compile import njit, njit_inline
from kinefuse.filters._kernels_block2 import cov2_predict, joseph2

__all__ = ["CHUNK", "kf_filter_blocks", "rts2_step", "rts_blocks"]

#: Joints interleaved per time step.
CHUNK = 8


@njit_inline
def _cov_step(p00, p01, p11, valid, cv, f00, f01, f10, f11, q00, q01, q11, h0, h1, ra):
    """Covariance block of one KF step: predict, then (if ``valid``) the Joseph update.

    Returns ``(p00, p01, p11, k0, k1, 1/S, updated)``. ``cv``: the model block is the constant
    velocity one (``F = [[1, f01], [0, 1]]``, ``H = [1, 0]``); the general formulas are then
    evaluated with the exact zero and unit terms dropped (``x·1 = x``, ``x + 0·y = x`` for the
    finite values here): the same rounding, about half the arithmetic.
    """
    if cv:
        fp00 = p00 + f01 * p01  # M = F P
        fp01 = p01 + f01 * p11
        pp00 = fp00 + fp01 * f01 + q00  # paper A Eq. 6 with P_{k-1}: P⁻ = F P Fᵀ + Q
        pp01 = fp01 + q01
        pp11 = p11 + q11
    else:
        pp00, pp01, pp11, _, _, _, _ = cov2_predict(
            p00, p01, p11, f00, f01, f10, f11, q00, q01, q11
        )
    if not valid:
        return pp00, pp01, pp11, 0.0, 0.0, 0.0, False
    if cv:
        S = pp00 + ra  # Eq. 7: S = H P⁻ Hᵀ + R (scalar)
        if not (S > 0.0 and np.isfinite(S)):
            return pp00, pp01, pp11, 0.0, 0.0, 0.0, False  # SPEC §13: predict only
        iS = 1.0 / S
        k0 = pp00 * iS  # Eq. 7: K = P⁻ Hᵀ S⁻¹
        k1 = pp01 * iS
        a00 = 1.0 - k0  # A = I − K H = [[a00, 0], [−k1, 1]]
        ap00 = a00 * pp00
        ap01 = a00 * pp01
        ap10 = -k1 * pp00 + pp01
        ap11 = -k1 * pp01 + pp11
        # Eq. 9 (Joseph): P = A P⁻ Aᵀ + K R Kᵀ
        n00 = ap00 * a00 + ra * k0 * k0
        n01 = ap00 * -k1 + ap01 + ra * k0 * k1
        n11 = ap10 * -k1 + ap11 + ra * k1 * k1
        return n00, n01, n11, k0, k1, iS, True
    ph0 = pp00 * h0 + pp01 * h1  # P⁻ Hᵀ
    ph1 = pp01 * h0 + pp11 * h1
    S = h0 * ph0 + h1 * ph1 + ra  # Eq. 7: S = H P⁻ Hᵀ + R (scalar)
    if not (S > 0.0 and np.isfinite(S)):
        return pp00, pp01, pp11, 0.0, 0.0, 0.0, False  # SPEC §13: predict only
    iS = 1.0 / S  # scalar S: its inverse is exact, no solve needed
    k0 = ph0 * iS  # Eq. 7: K = P⁻ Hᵀ S⁻¹
    k1 = ph1 * iS
    n00, n01, n11 = joseph2(pp00, pp01, pp11, k0, k1, h0, h1, ra)  # Eq. 9 (Joseph)
    return n00, n01, n11, k0, k1, iS, True


@njit_inline
def _axis_step(x0, x1, zv, upd, k0, k1, iS, f00, f01, f10, f11, h0, h1):
    """The mean of one axis in a KF step: ``x⁻ = F x`` (paper A Eq. 5, no noise term), then, if
    ``upd``, ``ν = z − H x⁻`` and ``x = x⁻ + K ν`` (Eq. 8). Returns ``(x0, x1, ν, ν²/S)``
    (``ν`` NaN and ``ν²/S`` 0 without an update)."""
    xp0 = f00 * x0 + f01 * x1
    xp1 = f10 * x0 + f11 * x1
    if upd:
        v = zv - (h0 * xp0 + h1 * xp1)
        return xp0 + k0 * v, xp1 + k1 * v, v, v * v * iS
    return xp0, xp1, np.nan, 0.0


@njit_inline
def rts2_step(p00, p01, p11, s00, s01, s11, cv, f00, f01, f10, f11, q00, q01, q11):
    """One backward RTS step of a 2x2 covariance block (SPEC §9).

    ``p``: the filtered ``P̂_t``; ``s``: the smoothed ``P̃_{t+1}``; ``cv`` as in
    :func:`_cov_step`. Returns ``(ok, c00, c01, c10, c11, n00, n01, n11)``: the gain ``C_t``
    and ``P̃_t``; ``ok`` False when ``P⁻_{t+1}`` is not positive definite (``n`` is then ``p``:
    the caller restarts the pass from the filtered estimate at ``t``).
    """
    # P⁻_{t+1} = F P̂_t Fᵀ + Q (the filter's own prediction, recomputed), M = F P̂_t;
    # constant-velocity blocks with the exact 0/1 terms dropped
    if cv:
        fp00 = p00 + f01 * p01
        fp01 = p01 + f01 * p11
        fp10 = p01
        fp11 = p11
        pp00 = fp00 + fp01 * f01 + q00
        pp01 = fp01 + q01
        pp11 = p11 + q11
    else:
        pp00, pp01, pp11, fp00, fp01, fp10, fp11 = cov2_predict(
            p00, p01, p11, f00, f01, f10, f11, q00, q01, q11
        )
    # C_t = P̂_t Fᵀ (P⁻)⁻¹ = Mᵀ adj(P⁻) / det(P⁻): one division (the 2x2 inverse in closed
    # form; det = pp00 d1 of the LDLᵀ factors, so P⁻ is positive definite iff pp00, det > 0)
    det = pp00 * pp11 - pp01 * pp01
    if not (pp00 > 0.0 and det > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, p00, p01, p11
    idt = 1.0 / det
    c00 = (fp00 * pp11 - fp10 * pp01) * idt
    c01 = (fp10 * pp00 - fp00 * pp01) * idt
    c10 = (fp01 * pp11 - fp11 * pp01) * idt
    c11 = (fp11 * pp00 - fp01 * pp01) * idt
    # P̃_t = P̂_t + C (P̃_{t+1} − P⁻_{t+1}) Cᵀ
    d00 = s00 - pp00
    d01 = s01 - pp01
    d11 = s11 - pp11
    cd00 = c00 * d00 + c01 * d01
    cd01 = c00 * d01 + c01 * d11
    cd10 = c10 * d00 + c11 * d01
    cd11 = c10 * d01 + c11 * d11
    n00 = p00 + cd00 * c00 + cd01 * c01
    n01 = p01 + cd00 * c10 + cd01 * c11
    n11 = p11 + cd10 * c10 + cd11 * c11
    return True, c00, c01, c10, c11, n00, n01, n11


@njit_inline
def _rts_axis(s0, s1, m0, m1, ok, c00, c01, c10, c11, cv, f00, f01, f10, f11):
    """``x̃_t = x̂_t + C (x̃_{t+1} − F x̂_t)`` of one axis: ``s`` is ``x̃_{t+1}``, ``m`` is
    ``x̂_t``; ``ok`` False restarts at ``x̂_t``. Returns ``x̃_t``."""
    if not ok:
        return m0, m1
    return _rts_axis_gain(s0, s1, m0, m1, c00, c01, c10, c11, cv, f00, f01, f10, f11)


@njit_inline
def _rts_axis_gain(s0, s1, m0, m1, c00, c01, c10, c11, cv, f00, f01, f10, f11):
    """:func:`_rts_axis` of a step that has a gain (no restart)."""
    if cv:
        e0 = s0 - (m0 + f01 * m1)
        e1 = s1 - m1
    else:
        e0 = s0 - (f00 * m0 + f01 * m1)
        e1 = s1 - (f10 * m0 + f11 * m1)
    return m0 + c00 * e0 + c01 * e1, m1 + c10 * e0 + c11 * e1


@njit_inline
def _rts_mean_step(mean, b, t, par, cv, C, n_c, sx):
    """:func:`_rts_axis` of every axis, in ``sx``; ``C[c, 4] == 0``: restart."""
    for a in range(par.shape[0]):
        c = 0 if n_c == 1 else a
        sx[a, 0], sx[a, 1] = _rts_axis(
            sx[a, 0], sx[a, 1], mean[b, t, 2 * a], mean[b, t, 2 * a + 1], C[c, 4] != 0.0,
            C[c, 0], C[c, 1], C[c, 2], C[c, 3], cv[a], par[a, 0], par[a, 1], par[a, 2], par[a, 3],
        )  # fmt: skip


@njit
def kf_filter_blocks(z, x, P, init, par, p0, mean, covb, pos, obs, nu, dist):
    """Per-axis KF over ``z (B, T, n_z)``; ``x (B, n_x)``, ``P (B, n_x, n_x)``, ``init (B,)``
    updated in place (full-matrix state; only the axis blocks of ``P`` are read).

    ``par (n_a, 10)``, ``p0 (n_c, 3)``: ``n_c = 1`` runs one covariance recursion for all axes
    (shared: the caller checked that the model rows and the state blocks coincide), else one
    per axis. Outputs (any may have a zero-length first axis = not wanted): ``mean (B, T, n_x)``,
    ``covb (B, T, n_c, 3)`` (module layout), ``pos (B, T, n_z)``, ``obs (B, T)``,
    ``nu (B, T, n_z)``, ``dist (B, T)``.

    Returns 0, or 1 if ``z`` holds ±inf (outputs and state are then incomplete).
    """
    n_a = par.shape[0]
    n_c = p0.shape[0]
    x_in = x.copy()
    P_in = P.copy()
    init_in = init.copy()
    if n_c == 1 and n_a == 3:  # 3-D positions, one shared covariance: the common case
        return _kf_pass3(
            z, x_in, P_in, init_in, x, P, init,
            par[0, 0], par[0, 1], par[0, 2], par[0, 3], par[0, 4], par[0, 5], par[0, 6],
            par[0, 7], par[0, 8], par[0, 9], p0[0, 0], p0[0, 1], p0[0, 2],
            mean, covb, pos, obs, nu, dist,
        )  # fmt: skip
    for c in range(n_c):
        a0, a1 = (0, n_a) if n_c == 1 else (c, c + 1)
        err = _kf_pass(
            z, x_in, P_in, init_in, x, P, init, a0, a1, c,
            par[c, 0], par[c, 1], par[c, 2], par[c, 3], par[c, 4], par[c, 5], par[c, 6],
            par[c, 7], par[c, 8], par[c, 9], p0[c, 0], p0[c, 1], p0[c, 2],
            mean, covb, pos, obs, nu, dist,
        )  # fmt: skip
        if err:
            return err
    return 0


@njit
def _kf_pass(
    z, x_in, P_in, init_in, x, P, init, a0, a1, c,
    f00, f01, f10, f11, q00, q01, q11, h0, h1, ra, p000, p001, p011,
    mean, covb, pos, obs, nu, dist,
):  # fmt: skip
    """Axes ``a0..a1-1`` of :func:`kf_filter_blocks`, sharing one covariance (block ``c``).

    The model block is passed as scalars (kept in registers: loads from arrays could alias the
    output stores). The first pass (``c == 0``) writes the per-row outputs ``obs`` and
    ``dist``, later passes combine theirs (``and``, ``+``).
    """
    B, T, n_z = z.shape
    first = c == 0
    w_mean = mean.shape[0] > 0
    w_cov = covb.shape[0] > 0
    w_pos = pos.shape[0] > 0
    w_obs = obs.shape[0] > 0
    w_nu = nu.shape[0] > 0
    w_dist = dist.shape[0] > 0
    hh = h0 * h0 + h1 * h1
    cv = f00 == 1.0 and f10 == 0.0 and f11 == 1.0 and h0 == 1.0 and h1 == 0.0
    xs = np.empty((CHUNK, a1 - a0, 2))  # per-axis state [position, velocity]
    Ps = np.empty((CHUNK, 3))  # the shared covariance block [p00, p01, p11]
    ini = np.empty(CHUNK, dtype=np.bool_)
    for c0 in range(0, B, CHUNK):
        c1 = min(B, c0 + CHUNK)
        for b in range(c0, c1):
            j = b - c0
            ini[j] = init_in[b]
            for a in range(a0, a1):
                xs[j, a - a0, 0] = x_in[b, 2 * a]
                xs[j, a - a0, 1] = x_in[b, 2 * a + 1]
            i = 2 * a0
            Ps[j, 0] = P_in[b, i, i]
            Ps[j, 1] = 0.5 * (P_in[b, i, i + 1] + P_in[b, i + 1, i])
            Ps[j, 2] = P_in[b, i + 1, i + 1]
        for t in range(T):
            for b in range(c0, c1):
                j = b - c0
                valid = True
                for a in range(n_z):
                    v = z[b, t, a]
                    if np.isnan(v):
                        valid = False
                    elif np.isinf(v):
                        return 1
                if not ini[j]:
                    if not valid:  # no state yet: NaN outputs
                        _no_state_outputs(mean, covb, pos, obs, nu, dist, b, t, a0, a1, c, first)
                        continue
                    # SPEC §4.2 initialisation [J]: x₀ = H⁺ z (positions = z, velocities = 0), P₀
                    for a in range(a0, a1):
                        xs[j, a - a0, 0] = h0 * z[b, t, a] / hh
                        xs[j, a - a0, 1] = h1 * z[b, t, a] / hh
                        if w_nu:
                            nu[b, t, a] = np.nan
                    p00 = p000
                    p01 = p001
                    p11 = p011
                    ini[j] = True
                    if w_obs and first:
                        obs[b, t] = True
                    if w_dist and first:
                        dist[b, t] = np.nan
                else:
                    p00, p01, p11, k0, k1, iS, updated = _cov_step(
                        Ps[j, 0], Ps[j, 1], Ps[j, 2], valid, cv,
                        f00, f01, f10, f11, q00, q01, q11, h0, h1, ra,
                    )  # fmt: skip
                    d = 0.0  # NIS νᵀS⁻¹ν, S diagonal across axes
                    for a in range(a0, a1):
                        xs[j, a - a0, 0], xs[j, a - a0, 1], v, dv = _axis_step(
                            xs[j, a - a0, 0], xs[j, a - a0, 1], z[b, t, a], updated, k0, k1, iS,
                            f00, f01, f10, f11, h0, h1,
                        )  # fmt: skip
                        d += dv
                        if w_nu:
                            nu[b, t, a] = v
                    if w_obs:
                        obs[b, t] = updated if first else (obs[b, t] and updated)
                    if w_dist:
                        dd = d if updated else np.nan
                        dist[b, t] = dd if first else dist[b, t] + dd
                Ps[j, 0] = p00
                Ps[j, 1] = p01
                Ps[j, 2] = p11
                if w_mean:
                    for a in range(a0, a1):
                        mean[b, t, 2 * a] = xs[j, a - a0, 0]
                        mean[b, t, 2 * a + 1] = xs[j, a - a0, 1]
                if w_cov:
                    covb[b, t, c, 0] = p00
                    covb[b, t, c, 1] = p01
                    covb[b, t, c, 2] = p11
                if w_pos:
                    for a in range(a0, a1):
                        pos[b, t, a] = h0 * xs[j, a - a0, 0] + h1 * xs[j, a - a0, 1]
        for b in range(c0, c1):
            j = b - c0
            init[b] = ini[j]
            if ini[j]:
                if first:
                    P[b, :, :] = 0.0
                for a in range(a0, a1):
                    i = 2 * a
                    x[b, i] = xs[j, a - a0, 0]
                    x[b, i + 1] = xs[j, a - a0, 1]
                    P[b, i, i] = Ps[j, 0]
                    P[b, i, i + 1] = Ps[j, 1]
                    P[b, i + 1, i] = Ps[j, 1]
                    P[b, i + 1, i + 1] = Ps[j, 2]
    return 0


@njit_inline
def _no_state_outputs(mean, covb, pos, obs, nu, dist, b, t, a0, a1, c, first):
    """The outputs of row ``(b, t)`` for axes ``a0..a1-1`` before the element's first
    measurement: NaN (``obs`` False); ``obs`` and ``dist`` are written by the first pass only."""
    if mean.shape[0] > 0:
        for a in range(a0, a1):
            mean[b, t, 2 * a] = np.nan
            mean[b, t, 2 * a + 1] = np.nan
    if covb.shape[0] > 0:
        covb[b, t, c, :] = np.nan
    if pos.shape[0] > 0:
        pos[b, t, a0:a1] = np.nan
    if obs.shape[0] > 0 and first:
        obs[b, t] = False
    if nu.shape[0] > 0:
        nu[b, t, a0:a1] = np.nan
    if dist.shape[0] > 0 and first:
        dist[b, t] = np.nan


@njit
def _kf_pass3(
    z, x_in, P_in, init_in, x, P, init,
    f00, f01, f10, f11, q00, q01, q11, h0, h1, ra, p000, p001, p011,
    mean, covb, pos, obs, nu, dist,
):  # fmt: skip
    """:func:`_kf_pass` for three axes sharing one covariance block (3-D positions).

    The same arithmetic (byte-identical outputs, tested), element by element: one element's
    state lives in local variables (registers) over its whole series, where the general pass
    keeps it in arrays that every output store could alias; about 2.5x faster.
    """
    B, T, n_z = z.shape
    w_mean, w_cov, w_pos = mean.shape[0] > 0, covb.shape[0] > 0, pos.shape[0] > 0
    w_obs, w_nu, w_dist = obs.shape[0] > 0, nu.shape[0] > 0, dist.shape[0] > 0
    hh = h0 * h0 + h1 * h1
    cv = f00 == 1.0 and f10 == 0.0 and f11 == 1.0 and h0 == 1.0 and h1 == 0.0
    for b in range(B):
        ini = init_in[b]
        xa0, xa1, xb0, xb1, xc0, xc1 = x_in[b, 0], x_in[b, 1], x_in[b, 2], x_in[b, 3], x_in[b, 4], x_in[b, 5]  # fmt: skip
        p00, p01, p11 = P_in[b, 0, 0], 0.5 * (P_in[b, 0, 1] + P_in[b, 1, 0]), P_in[b, 1, 1]
        for t in range(T):
            za, zb, zc = z[b, t, 0], z[b, t, 1], z[b, t, 2]
            if np.isinf(za) or np.isinf(zb) or np.isinf(zc):
                return 1
            valid = not (np.isnan(za) or np.isnan(zb) or np.isnan(zc))
            if not ini:
                if not valid:
                    _no_state_outputs(mean, covb, pos, obs, nu, dist, b, t, 0, 3, 0, True)
                    continue
                # SPEC §4.2 initialisation [J]: x₀ = H⁺ z (positions = z, velocities = 0), P₀
                xa0, xa1 = h0 * za / hh, h1 * za / hh
                xb0, xb1 = h0 * zb / hh, h1 * zb / hh
                xc0, xc1 = h0 * zc / hh, h1 * zc / hh
                p00, p01, p11 = p000, p001, p011
                ini = True
                va = vb = vc = dd = np.nan
                upd = True  # (obs: the first measurement counts as observed)
            else:
                p00, p01, p11, k0, k1, iS, upd = _cov_step(
                    p00, p01, p11, valid, cv, f00, f01, f10, f11, q00, q01, q11, h0, h1, ra
                )
                xa0, xa1, va, da = _axis_step(
                    xa0, xa1, za, upd, k0, k1, iS, f00, f01, f10, f11, h0, h1
                )
                xb0, xb1, vb, db = _axis_step(
                    xb0, xb1, zb, upd, k0, k1, iS, f00, f01, f10, f11, h0, h1
                )
                xc0, xc1, vc, dc = _axis_step(
                    xc0, xc1, zc, upd, k0, k1, iS, f00, f01, f10, f11, h0, h1
                )
                dd = ((0.0 + da) + db) + dc if upd else np.nan
            if w_nu:
                nu[b, t, 0], nu[b, t, 1], nu[b, t, 2] = va, vb, vc
            if w_obs:
                obs[b, t] = upd
            if w_dist:
                dist[b, t] = dd
            if w_mean:
                mean[b, t, 0], mean[b, t, 1], mean[b, t, 2] = xa0, xa1, xb0
                mean[b, t, 3], mean[b, t, 4], mean[b, t, 5] = xb1, xc0, xc1
            if w_cov:
                covb[b, t, 0, 0], covb[b, t, 0, 1], covb[b, t, 0, 2] = p00, p01, p11
            if w_pos:
                pos[b, t, 0] = h0 * xa0 + h1 * xa1
                pos[b, t, 1] = h0 * xb0 + h1 * xb1
                pos[b, t, 2] = h0 * xc0 + h1 * xc1
        init[b] = ini
        if ini:
            P[b, :, :] = 0.0
            x[b, 0], x[b, 1], x[b, 2], x[b, 3], x[b, 4], x[b, 5] = xa0, xa1, xb0, xb1, xc0, xc1
            for i in range(0, 6, 2):
                P[b, i, i], P[b, i, i + 1], P[b, i + 1, i], P[b, i + 1, i + 1] = p00, p01, p01, p11
    return 0


@njit
def rts_blocks(mean, covb, mask, par, sm_mean, sm_covb, sm_pos):
    """Fixed-interval per-axis RTS (SPEC §9) on the block layout, each run smoothed on its own.

    ``mean (B, T, n_x)``, ``covb (B, T, n_c, 3)`` filtered; ``mask (B, T)``: smoothing runs
    over each maximal run of samples where the mask is True and the filtered mean is finite;
    other samples are copied. Outputs ``sm_mean``, ``sm_covb`` (same shapes) and ``sm_pos
    (B, T, n_a)`` (``H x̃``; zero-length first axis = not wanted). A step whose ``P⁻`` is not
    positive definite restarts the pass from the filtered estimate at that sample (as
    :func:`._kernels_axis.rts_axis`; both step with :func:`rts2_step`).
    """
    B, T, n_x = mean.shape
    n_a = par.shape[0]
    n_c = covb.shape[2]
    if n_c == 1 and n_a == 3:  # 3-D positions, one shared covariance: the common case
        _rts_pass3(mean, covb, mask, par, sm_mean, sm_covb, sm_pos)
        return
    w_pos = sm_pos.shape[0] > 0
    sx = np.empty((n_a, 2))
    sP = np.empty((n_c, 3))
    C = np.empty((n_c, 5))  # per block [c00, c01, c10, c11, ok] of this step
    cv = np.empty(n_a, dtype=np.bool_)  # constant-velocity block (see _cov_step)
    for a in range(n_a):
        cv[a] = par[a, 0] == 1.0 and par[a, 2] == 0.0 and par[a, 3] == 1.0
    for b in range(B):
        nxt_ok = False  # is t + 1 in the same run as t (and usable)?
        for t in range(T - 1, -1, -1):
            usable = mask[b, t] and np.isfinite(mean[b, t, 0])
            if not usable:
                for i in range(n_x):
                    sm_mean[b, t, i] = mean[b, t, i]
                for c in range(n_c):
                    for k in range(3):
                        sm_covb[b, t, c, k] = covb[b, t, c, k]
                nxt_ok = False
            elif not nxt_ok:  # x̃_end = x̂_end, P̃_end = P̂_end
                for a in range(n_a):
                    sx[a, 0] = mean[b, t, 2 * a]
                    sx[a, 1] = mean[b, t, 2 * a + 1]
                for c in range(n_c):
                    for k in range(3):
                        sP[c, k] = covb[b, t, c, k]
                nxt_ok = True
            else:
                for c in range(n_c):
                    ok, c00, c01, c10, c11, n00, n01, n11 = rts2_step(
                        covb[b, t, c, 0], covb[b, t, c, 1], covb[b, t, c, 2],
                        sP[c, 0], sP[c, 1], sP[c, 2], cv[c],
                        par[c, 0], par[c, 1], par[c, 2], par[c, 3], par[c, 4], par[c, 5], par[c, 6],
                    )  # fmt: skip
                    C[c, 0] = c00
                    C[c, 1] = c01
                    C[c, 2] = c10
                    C[c, 3] = c11
                    C[c, 4] = 1.0 if ok else 0.0  # not ok: restart from the filtered estimate
                    sP[c, 0] = n00
                    sP[c, 1] = n01
                    sP[c, 2] = n11
                _rts_mean_step(mean, b, t, par, cv, C, n_c, sx)
            if usable:
                for a in range(n_a):
                    sm_mean[b, t, 2 * a] = sx[a, 0]
                    sm_mean[b, t, 2 * a + 1] = sx[a, 1]
                for c in range(n_c):
                    for k in range(3):
                        sm_covb[b, t, c, k] = sP[c, k]
            if w_pos:
                for a in range(n_a):
                    sm_pos[b, t, a] = (
                        par[a, 7] * sm_mean[b, t, 2 * a] + par[a, 8] * sm_mean[b, t, 2 * a + 1]
                    )


@njit
def _rts_pass3(mean, covb, mask, par, sm_mean, sm_covb, sm_pos):
    """:func:`rts_blocks` for three axes sharing one covariance block (3-D positions), with the
    smoothed state in local variables (as :func:`_kf_pass3`): the same arithmetic through the
    same helpers, byte-identical (tested).

    Each sample's inputs are loaded once, up front, and one branch decides between a step and
    a (re)start from the filtered estimate: about 1.7x faster than branching per axis.
    """
    B, T, n_x = mean.shape
    w_pos = sm_pos.shape[0] > 0
    f00, f01, f10, f11, q00, q01, q11 = par[0, 0], par[0, 1], par[0, 2], par[0, 3], par[0, 4], par[0, 5], par[0, 6]  # fmt: skip
    h0, h1 = par[0, 7], par[0, 8]
    cv = f00 == 1.0 and f10 == 0.0 and f11 == 1.0
    for b in range(B):
        nxt_ok = False  # is t + 1 in the same run as t (and usable)?
        xa0 = xa1 = xb0 = xb1 = xc0 = xc1 = s00 = s01 = s11 = 0.0
        for t in range(T - 1, -1, -1):
            m0, m1, m2 = mean[b, t, 0], mean[b, t, 1], mean[b, t, 2]
            m3, m4, m5 = mean[b, t, 3], mean[b, t, 4], mean[b, t, 5]
            p00, p01, p11 = covb[b, t, 0, 0], covb[b, t, 0, 1], covb[b, t, 0, 2]
            ok = False
            if mask[b, t] and np.isfinite(m0):
                if nxt_ok:
                    ok, c00, c01, c10, c11, n00, n01, n11 = rts2_step(
                        p00, p01, p11, s00, s01, s11,
                        cv, f00, f01, f10, f11, q00, q01, q11,
                    )  # fmt: skip
                nxt_ok = True
            else:
                nxt_ok = False
            if ok:
                s00, s01, s11 = n00, n01, n11
                xa0, xa1 = _rts_axis_gain(
                    xa0, xa1, m0, m1, c00, c01, c10, c11, cv, f00, f01, f10, f11
                )
                xb0, xb1 = _rts_axis_gain(
                    xb0, xb1, m2, m3, c00, c01, c10, c11, cv, f00, f01, f10, f11
                )
                xc0, xc1 = _rts_axis_gain(
                    xc0, xc1, m4, m5, c00, c01, c10, c11, cv, f00, f01, f10, f11
                )
            else:  # not usable (copied), the end of a run, or P⁻ not PD: the filtered estimate
                xa0, xa1, xb0, xb1, xc0, xc1 = m0, m1, m2, m3, m4, m5
                s00, s01, s11 = p00, p01, p11
            sm_mean[b, t, 0], sm_mean[b, t, 1], sm_mean[b, t, 2] = xa0, xa1, xb0
            sm_mean[b, t, 3], sm_mean[b, t, 4], sm_mean[b, t, 5] = xb1, xc0, xc1
            sm_covb[b, t, 0, 0], sm_covb[b, t, 0, 1], sm_covb[b, t, 0, 2] = s00, s01, s11
            if w_pos:
                sm_pos[b, t, 0] = h0 * xa0 + h1 * xa1
                sm_pos[b, t, 1] = h0 * xb0 + h1 * xb1
                sm_pos[b, t, 2] = h0 * xc0 + h1 * xc1


@njit
def kf_step_blocks(
    par, p0, shared, z, x, P, init, x_new, P_new, init_new, mean, covb, pos, obs, nu, dist
):  # fmt: skip
    """One time slice of :func:`kf_filter_blocks`: ``z (B, n_z)``, outputs without the T axis
    (``covb (B, n_a, 3)``); the state ``x, P, init`` is copied into ``x_new, P_new, init_new``
    and advanced there (the input state is not modified). One compiled call per online step.

    ``shared``: the model rows coincide; if the state blocks do too, one covariance recursion
    serves all axes (the same arithmetic as per axis, bit for bit) and is copied to each axis.
    """
    B, n_z = z.shape
    n_a = par.shape[0]
    x_new[:, :] = x
    P_new[:, :, :] = P
    init_new[:] = init
    if shared:
        for b in range(B):
            if init[b]:
                for a in range(1, n_a):
                    i = 2 * a
                    if (P[b, i, i] != P[b, 0, 0] or P[b, i + 1, i + 1] != P[b, 1, 1]
                            or P[b, i, i + 1] + P[b, i + 1, i] != P[b, 0, 1] + P[b, 1, 0]):  # fmt: skip
                        shared = False
    if shared and n_a == 3:  # 3-D positions, one recursion: the register-resident pass
        # T = 1 views: ``[:, None]`` costs nothing per call (``reshape`` ~0.05 µs each)
        err = _kf_pass3(
            z[:, None, :], x, P, init, x_new, P_new, init_new,
            par[0, 0], par[0, 1], par[0, 2], par[0, 3], par[0, 4], par[0, 5], par[0, 6],
            par[0, 7], par[0, 8], par[0, 9], p0[0, 0], p0[0, 1], p0[0, 2],
            mean[:, None, :], covb[:, None, :, :], pos[:, None, :], obs[:, None], nu[:, None, :],
            dist[:, None],
        )  # fmt: skip
        _copy_axis0_block(covb)
        return err
    n_x = x.shape[1]
    z3 = z.reshape(B, 1, n_z)  # (C-contiguous views: the kernels' batch specialisations)
    mean3 = mean.reshape(B, 1, n_x)
    pos3 = pos.reshape(B, 1, n_z)
    obs2 = obs.reshape(B, 1)
    nu3 = nu.reshape(B, 1, n_z)
    dist2 = dist.reshape(B, 1)
    cb = covb.reshape(B, 1, n_a, 3)
    if not shared:
        return kf_filter_blocks(
            z3, x_new, P_new, init_new, par, p0, mean3, cb, pos3, obs2, nu3, dist2
        )
    err = _kf_pass(
        z3, x, P, init, x_new, P_new, init_new, 0, n_a, 0,
        par[0, 0], par[0, 1], par[0, 2], par[0, 3], par[0, 4], par[0, 5], par[0, 6],
        par[0, 7], par[0, 8], par[0, 9], p0[0, 0], p0[0, 1], p0[0, 2],
        mean3, cb, pos3, obs2, nu3, dist2,
    )  # fmt: skip
    _copy_axis0_block(covb)
    return err


@njit_inline
def _copy_axis0_block(covb):
    """``covb (B, n_a, 3)``: the shared recursion wrote axis 0; copy it to the other axes."""
    for b in range(covb.shape[0]):
        for a in range(1, covb.shape[1]):
            for k in range(3):
                covb[b, a, k] = covb[b, 0, k]
