"""Input validation helpers shared by public boundaries (never used inside kernels)."""

from __future__ import annotations

import difflib
import math
from collections.abc import Sequence

import numpy as np

from kinefuse.exceptions import InputError


def as_float_array(
    value, name: str, *, ndim_min: int = 0, last_dim: int | None = None
) -> np.ndarray:
    """Return ``value`` as a C-contiguous float64 array, refusing non-float dtypes.

    Integer, boolean and object arrays are refused rather than silently cast: an integer
    position array almost always means millimetres or a wrong column.
    """
    arr = np.asarray(value)
    if arr.dtype == object:
        raise InputError(f"expected {name} as a float array, got an object array")
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(
            f"expected {name} as a float array (float32/float64), got dtype {arr.dtype}; "
            f"convert explicitly, e.g. {name}.astype(float)"
        )
    if arr.ndim < ndim_min:
        shape = "(..., " + ", ".join(["T", "d"][-ndim_min:]) + ")" if ndim_min else "an array"
        raise InputError(
            f"expected {name} with at least {ndim_min} dimensions {shape}, got shape {arr.shape}"
        )
    if last_dim is not None and (arr.ndim == 0 or arr.shape[-1] != last_dim):
        raise InputError(f"expected {name} with shape (..., {last_dim}), got {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def as_float(value, message: str) -> float:
    """``float(value)``; an InputError with ``message`` when ``value`` is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(message) from None


def did_you_mean(name: str, choices: Sequence[str], otherwise: str | None = None) -> str:
    """The fix for an unknown ``name``: the closest of ``choices``, else a list of them.

    Parameters
    ----------
    name : str
        The unknown name as given.
    choices : sequence of str
        The names that are allowed, in the order a list of them should show.
    otherwise : str, optional
        What to say when no choice is close; default ``"expected one of <choices>"``.

    Returns
    -------
    str
        ``"did you mean 'x'?"`` or ``otherwise``.
    """
    close = difflib.get_close_matches(name, choices, n=1)
    if close:
        return f"did you mean {close[0]!r}?"
    return otherwise if otherwise is not None else f"expected one of {', '.join(choices)}"


def readonly_array(a) -> np.ndarray:
    """A float64 copy of ``a`` that cannot be written to (frozen configurations hold these)."""
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


def finite_rows(a: np.ndarray) -> np.ndarray:
    """Whether each row of ``a (..., d)`` is finite in all its ``d`` entries: ``(...)`` bool.

    The same as ``np.all(np.isfinite(a), axis=-1)``, column by column: a reduction over a short
    last axis is several times slower in numpy than ``d`` passes over strided columns.
    """
    a = np.asarray(a)
    if a.shape[-1] == 0:
        return np.ones(a.shape[:-1], bool)
    ok = np.isfinite(a[..., 0])
    for i in range(1, a.shape[-1]):
        ok &= np.isfinite(a[..., i])
    return ok


def positive_finite(value, name: str) -> float:
    """Return ``value`` as a float, requiring it to be finite and > 0 (text is refused)."""
    if isinstance(value, (str, bytes, bool, np.bool_)):
        raise InputError(f"expected {name} as a positive number, got {value!r}")
    out = as_float(value, f"expected {name} as a positive number, got {value!r}")
    if not math.isfinite(out) or out <= 0.0:
        raise InputError(f"expected {name} finite and > 0, got {value!r}")
    return out


def names_arg(value, name: str):
    """``value`` as a tuple of names, or None; a bare string (which Python would iterate letter
    by letter: "unknown joint 'e'") is refused with the fix."""
    if value is None:
        return None
    if isinstance(value, (str, bytes)):
        raise InputError(
            f"expected {name} as a sequence of names, e.g. [{value!r}], got the string {value!r}"
        )
    try:
        return tuple(value)
    except TypeError:
        raise InputError(
            f"expected {name} as a sequence of names, got {type(value).__name__}"
        ) from None


def check_psd_stack(m: np.ndarray, name: str) -> None:
    """Each ``(n, n)`` matrix of ``m (..., n, n)`` symmetric positive semi-definite, to rounding
    (relative 1e-9); matrices with a NaN are skipped (not given). Raises an InputError naming
    the first bad one."""
    n = m.shape[-1]
    a = np.asarray(m, dtype=float).reshape(-1, n, n)
    idx = np.flatnonzero(np.all(np.isfinite(a), axis=(1, 2)))
    if idx.size == 0:
        return
    a = a[idx]
    scale = np.maximum(np.abs(a).max(axis=(1, 2)), np.finfo(float).tiny)
    asym = np.abs(a - a.transpose(0, 2, 1)).max(axis=(1, 2))
    where = lambda k: np.unravel_index(int(idx[k]), m.shape[:-2]) if m.ndim > 2 else ()  # noqa: E731
    bad = np.flatnonzero(asym > 1e-9 * scale)
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"expected {name} symmetric, got max |{name} - {name}ᵀ| = {asym[k]:.3g} at "
            f"index {where(k)}"
        )
    eig = np.linalg.eigvalsh(a).min(axis=1)
    bad = np.flatnonzero(eig < -1e-9 * scale)
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"expected {name} positive semi-definite, got smallest eigenvalue {eig[k]:.3g} at "
            f"index {where(k)}"
        )


def psd_matrix(value, name: str, n: int, *, strict: bool = False) -> np.ndarray:
    """Return ``value`` as an ``(n, n)`` symmetric positive (semi-)definite float matrix."""
    m = np.asarray(value, dtype=float) if not isinstance(value, np.ndarray) else value
    if m.dtype == object or not np.issubdtype(np.asarray(m).dtype, np.number):
        raise InputError(
            f"expected {name} as a numeric ({n}, {n}) matrix, got dtype {np.asarray(m).dtype}"
        )
    m = np.asarray(m, dtype=float)
    if m.shape != (n, n):
        raise InputError(f"expected {name} with shape ({n}, {n}), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise InputError(f"expected {name} finite, got non-finite entries")
    if not np.allclose(m, m.T, rtol=1e-10, atol=1e-14 * max(1.0, float(np.abs(m).max()))):
        raise InputError(
            f"expected {name} symmetric, got max |{name} - {name}.T| = {np.abs(m - m.T).max():.3g}"
        )
    eig_min = float(np.linalg.eigvalsh(m).min())
    tol = 1e-12 * max(1.0, float(np.abs(m).max()))
    if strict and eig_min <= 0.0:
        raise InputError(
            f"expected {name} positive definite, got smallest eigenvalue {eig_min:.3g}"
        )
    if eig_min < -tol:
        raise InputError(
            f"expected {name} positive semi-definite, got smallest eigenvalue {eig_min:.3g}"
        )
    return m
