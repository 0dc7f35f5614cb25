"""Closed forms on 2x2 blocks (numba, inlined): the per-axis arithmetic of every filter.

An axis-blocked model (SPEC §1 "Per-axis decoupling") splits into one ``(position, velocity)``
pair per axis with a scalar measurement, so every covariance, information matrix and gain is a
symmetric 2x2 block ``[a00, a01, a11]`` or a general one ``[a00, a01, a10, a11]``. These steps
are written once here and used by the Kalman filter, the RTS smoother and the UFIR kernels
(:mod:`._kernels_blocks`, :mod:`._kernels_axis`, :mod:`._kernels_ufir`). They take and return
scalars (kept in registers) and are inlined at numba IR level, so a kernel built from them is
the same machine code as one written out; the expression order is fixed here, so every caller
gets the same rounding.
"""

from __future__ import annotations

from kinefuse._compile import njit_inline

__all__ = ["cov2_predict", "info2_back", "joseph2", "mat2_finv"]


@njit_inline
def cov2_predict(p00, p01, p11, f00, f01, f10, f11, q00, q01, q11):
    """``P⁻ = F P Fᵀ + Q`` of a symmetric block (paper A Eqs. 6 and 25).

    Returns ``(pp00, pp01, pp11, m00, m01, m10, m11)``: ``P⁻`` and ``M = F P`` (the RTS gain
    needs it).
    """
    m00 = f00 * p00 + f01 * p01
    m01 = f00 * p01 + f01 * p11
    m10 = f10 * p00 + f11 * p01
    m11 = f10 * p01 + f11 * p11
    pp00 = m00 * f00 + m01 * f01 + q00
    pp01 = m00 * f10 + m01 * f11 + q01
    pp11 = m10 * f10 + m11 * f11 + q11
    return pp00, pp01, pp11, m00, m01, m10, m11


@njit_inline
def joseph2(p00, p01, p11, k0, k1, h0, h1, r):
    """Joseph update ``A P Aᵀ + k r kᵀ`` with ``A = I − k h`` (paper A Eqs. 9 and 28).

    ``k = [k0, k1]`` any gain (the UFIR gain is not the Kalman gain, SPEC §6.2-4), ``h = [h0,
    h1]`` the measurement row, ``r`` its variance. Returns ``(n00, n01, n11)``.
    """
    a00 = 1.0 - k0 * h0
    a01 = -k0 * h1
    a10 = -k1 * h0
    a11 = 1.0 - k1 * h1
    ap00 = a00 * p00 + a01 * p01
    ap01 = a00 * p01 + a01 * p11
    ap10 = a10 * p00 + a11 * p01
    ap11 = a10 * p01 + a11 * p11
    n00 = ap00 * a00 + ap01 * a01 + r * k0 * k0
    n01 = ap00 * a10 + ap01 * a11 + r * k0 * k1
    n11 = ap10 * a10 + ap11 * a11 + r * k1 * k1
    return n00, n01, n11


@njit_inline
def info2_back(o00, o01, o11, i00, i01, i10, i11):
    """``F⁻ᵀ Ω F⁻¹`` of a symmetric block ``Ω`` (the UFIR's ``inv(F G Fᵀ)``, SPEC §6.3).

    ``i`` is ``F⁻¹``. Returns ``(n00, n01, n11)``.
    """
    b00 = i00 * o00 + i10 * o01
    b01 = i00 * o01 + i10 * o11
    b10 = i01 * o00 + i11 * o01
    b11 = i01 * o01 + i11 * o11
    return b00 * i00 + b01 * i10, b00 * i01 + b01 * i11, b10 * i01 + b11 * i11


@njit_inline
def mat2_finv(p00, p01, p10, p11, i00, i01, i10, i11):
    """``Φ F⁻¹`` of general blocks (one more power of ``F⁻¹``). Returns ``(n00, n01, n10, n11)``."""
    return (
        p00 * i00 + p01 * i10,
        p00 * i01 + p01 * i11,
        p10 * i00 + p11 * i10,
        p10 * i01 + p11 * i11,
    )
