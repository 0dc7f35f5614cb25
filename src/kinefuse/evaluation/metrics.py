"""Accuracy metrics of joint-position estimates, defined as papers A and B use them (SPEC §14).

All functions take positions ``est`` and ``ref`` with shape ``(..., T, 3)`` in metres (time on
axis -2, leading batch axes, see :mod:`kinefuse.conventions`) and an optional boolean ``mask``
``(..., T)`` that restricts the metric to some samples (e.g. camera outages). A sample is used
only where the mask is True *and* every coordinate of both ``est`` and ``ref`` is finite; other
samples are excluded (and counted by :func:`valid_samples` / :class:`EvaluationResult`).
A batch element with no usable sample yields NaN, never an error and never a warning.

Definitions (SPEC §14, checked against the papers' arithmetic):

* per-axis RMSE ``RMSE_a = sqrt(mean_k (est_ka - ref_ka)²)``;
* **"mean" RMSE** (both papers' "Mean" column) = arithmetic mean of the three per-axis RMSEs,
  *not* the 3-D RMSE;
* 3-D RMSE ``sqrt(mean_k ||est_k - ref_k||²)``;
* error CDF: empirical CDF of the Euclidean error magnitude ``||est_k - ref_k||``;
* error at CDF ``p``: the smallest error ``e`` with ``F(e) >= p`` (inverse of the empirical CDF);
* "improvement at 0.9" = relative reduction of the 90th-percentile error.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from kinefuse._validation import names_arg
from kinefuse.conventions import AXES_ENU
from kinefuse.exceptions import InputError

__all__ = [
    "EvaluationResult",
    "error_at",
    "error_cdf",
    "evaluate",
    "mean_rmse",
    "position_error",
    "relative_improvement",
    "rmse_3d",
    "rmse_per_axis",
    "valid_samples",
]


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------


def _positions(value, name: str, *, estimate: bool = False) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise InputError(
            f"expected {name} as a numeric array with shape (..., T, 3), got dtype {arr.dtype}"
        )
    if arr.ndim < 2 or arr.shape[-1] != 3:
        raise InputError(f"expected {name} with shape (..., T, 3), got {arr.shape}")
    out = np.asarray(arr, dtype=np.float64)
    n_inf = int(np.count_nonzero(np.isinf(out)))
    if n_inf and not estimate:  # NaN marks a missing sample, ±inf nothing a reference holds
        raise InputError(f"expected {name} finite or NaN (missing), got ±inf in {n_inf} entries")
    return out


def _pair(est, ref, mask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and broadcast; return ``(est, ref, valid)`` with ``valid`` shaped ``(..., T)``."""
    e = _positions(est, "est", estimate=True)
    r = _positions(ref, "ref")
    try:
        shape = np.broadcast_shapes(e.shape, r.shape)
    except ValueError:
        raise InputError(
            f"expected est and ref with the same shape (..., T, 3), got {e.shape} and {r.shape}"
        ) from None
    e = np.broadcast_to(e, shape)
    r = np.broadcast_to(r, shape)
    # an estimate's NaN is a missing sample; its ±inf (a diverged filter) is an infinite error
    valid = ~np.any(np.isnan(e), axis=-1) & np.all(np.isfinite(r), axis=-1)
    if mask is not None:
        m = np.asarray(mask)
        if m.dtype != bool:
            raise InputError(
                f"expected mask as a boolean array with shape (..., T) = {shape[:-1]}, got dtype {m.dtype}"
            )
        try:
            m = np.broadcast_to(m, shape[:-1])
        except ValueError:
            raise InputError(
                f"expected mask with shape (..., T) = {shape[:-1]}, got {m.shape}"
            ) from None
        valid = valid & m
    return e, r, valid


def valid_samples(est, ref, mask=None) -> np.ndarray:
    """Samples that the metrics use.

    Parameters
    ----------
    est, ref : array_like, shape (..., T, 3)
        Estimated and reference positions, m. NaN marks a missing sample.
    mask : array_like of bool, shape (..., T), optional
        Restrict to samples where True (e.g. inside camera outages).

    Returns
    -------
    ndarray of bool, shape (..., T)
        True where the mask is True and all coordinates of both ``est`` and ``ref`` are finite.
        ``(~valid_samples(est, ref)).sum(-1)`` counts the samples excluded because of NaN.
    """
    return _pair(est, ref, mask)[2].copy()


def _sq_error(est, ref, mask) -> tuple[np.ndarray, np.ndarray]:
    """Squared per-axis errors with invalid samples zeroed, and the valid count ``(...,)``."""
    e, r, valid = _pair(est, ref, mask)
    with np.errstate(invalid="ignore"):
        d2 = np.where(valid[..., None], (e - r) ** 2, 0.0)
    return d2, valid.sum(axis=-1)


def _divide(num: np.ndarray, n: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, num / np.maximum(n, 1), np.nan)


# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------


def rmse_per_axis(est, ref, mask=None) -> np.ndarray:
    """Root-mean-square error per axis.

    Parameters
    ----------
    est, ref : array_like, shape (..., T, 3)
        Estimated and reference positions, m (``ref`` may broadcast against ``est``).
    mask : array_like of bool, shape (..., T), optional
        Use only samples where True.

    Returns
    -------
    ndarray, shape (..., 3)
        ``sqrt(mean_k (est_ka - ref_ka)²)`` for each axis ``a``, m; NaN where no sample is valid.

    Notes
    -----
    A sample is excluded from *all* axes when any coordinate of ``est`` or ``ref`` is NaN, so
    the three axes and :func:`rmse_3d` are always computed on the same samples.
    """
    d2, n = _sq_error(est, ref, mask)
    return np.sqrt(_divide(d2.sum(axis=-2), n[..., None]))


def mean_rmse(est, ref, mask=None) -> np.ndarray:
    """The papers' "Mean" RMSE: the arithmetic mean of the three per-axis RMSEs (SPEC §14).

    ``est``, ``ref`` (``(..., T, 3)``, m) and ``mask`` (``(..., T)``) as in
    :func:`rmse_per_axis`. Returns ``(RMSE_x + RMSE_y + RMSE_z) / 3``, shape ``(...)``, m; NaN
    where no sample is valid.

    Notes
    -----
    This is what paper A (Tables 4-5, "Mean (m)") and paper B (Tables 3-5) report: every row of
    their tables checks to ±0.0005 against this definition and not against :func:`rmse_3d`.
    """
    return rmse_per_axis(est, ref, mask).mean(axis=-1)


def rmse_3d(est, ref, mask=None) -> np.ndarray:
    """3-D RMSE: ``sqrt(mean_k ||est_k - ref_k||²)``, shape ``(...)``, m.

    ``est``, ``ref`` and ``mask`` as in :func:`rmse_per_axis`; NaN where no sample is valid.
    Equals ``sqrt(sum_a RMSE_a²)``.
    """
    d2, n = _sq_error(est, ref, mask)
    return np.sqrt(_divide(d2.sum(axis=(-2, -1)), n))


def position_error(est, ref, mask=None) -> np.ndarray:
    """Euclidean position error per sample.

    Parameters
    ----------
    est, ref : array_like, shape (..., T, 3)
        Estimated and reference positions, m.
    mask : array_like of bool, shape (..., T), optional
        Samples where False are returned as NaN.

    Returns
    -------
    ndarray, shape (..., T)
        ``||est_k - ref_k||``, m; NaN where the sample is not valid.
    """
    e, r, valid = _pair(est, ref, mask)
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(e - r, axis=-1)
    return np.where(valid, err, np.nan)


def error_cdf(est, ref, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """Empirical CDF of the Euclidean position error of one series.

    Parameters
    ----------
    est, ref : array_like, shape (T, 3)
        Estimated and reference positions of one joint, m. (Batches are refused: the number
        of valid samples differs between batch elements; loop over them.)
    mask : array_like of bool, shape (T,), optional
        Use only samples where True.

    Returns
    -------
    sorted_errors : ndarray, shape (n,)
        Valid errors in ascending order, m (``n`` = number of valid samples, possibly 0).
    probabilities : ndarray, shape (n,)
        ``F(sorted_errors[i]) = (i + 1) / n``, the empirical CDF (a right-continuous step
        function; plot it with ``drawstyle="steps-post"``).
    """
    e = _positions(est, "est", estimate=True)
    if e.ndim != 2:
        raise InputError(
            f"expected est with shape (T, 3) (one joint; loop over batches), got {e.shape}"
        )
    err = position_error(e, ref, mask)
    x = np.sort(err[~np.isnan(err)])  # an infinite error (a diverged estimate) counts
    n = x.size
    return x, np.arange(1, n + 1, dtype=float) / max(n, 1)


def error_at(est, ref, *, p: float = 0.9, mask=None) -> np.ndarray:
    """Position error at CDF level ``p`` (paper B's "error at 0.9").

    Parameters
    ----------
    est, ref, mask
        As in :func:`rmse_per_axis`: positions ``(..., T, 3)`` in m, samples used ``(..., T)``.
    p : float in (0, 1]
        CDF level; 0.9 is the level both papers read off their CDF figures.

    Returns
    -------
    ndarray, shape (...)
        The smallest valid error ``e`` with ``F(e) >= p``, i.e. ``sorted_errors[ceil(p n) - 1]``
        of :func:`error_cdf` (no interpolation), m; NaN where no sample is valid.
    """
    p = float(p)
    if not (0.0 < p <= 1.0):
        raise InputError(f"expected p in (0, 1], got {p!r}")
    err = position_error(est, ref, mask)
    if err.shape[-1] == 0:
        return np.full(err.shape[:-1], np.nan)
    x = np.sort(err, axis=-1)  # inf (a diverged estimate) sorts before NaN (not valid), last
    n = (~np.isnan(err)).sum(axis=-1)
    # 1e-9 guards p * n against round-off just above an integer (0.9 * 10 = 9.000000000000002)
    idx = np.clip(np.ceil(p * n - 1e-9).astype(np.int64) - 1, 0, err.shape[-1] - 1)
    out = np.take_along_axis(x, idx[..., None], axis=-1)[..., 0]
    return np.where(n > 0, out, np.nan)


def relative_improvement(a, b) -> np.ndarray | float:
    """Relative reduction of an error ``a`` with respect to a baseline error ``b``.

    Parameters
    ----------
    a : float or array_like
        Error of the method under test (e.g. ELM/FIR error at CDF 0.9), m.
    b : float or array_like
        Error of the baseline (e.g. ELM/KF), m.

    Returns
    -------
    float or ndarray
        ``(b - a) / b``: 0.25 means ``a`` is 25 % smaller than ``b``; negative means worse.
        NaN where ``b`` is 0 or either is NaN.

    Examples
    --------
    Paper B's right elbow, error at 0.9 from 0.0866 m (ELM/KF) to 0.0678 m (ELM/FIR):

    >>> round(float(relative_improvement(0.0678, 0.0866)), 3)
    0.217
    """
    a_arr = np.asarray(a, dtype=float)
    b_arr = np.asarray(b, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(b_arr != 0, (b_arr - a_arr) / np.where(b_arr != 0, b_arr, 1.0), np.nan)
    return float(out) if out.ndim == 0 else out


# --------------------------------------------------------------------------------------------
# evaluation of several methods on several joints
# --------------------------------------------------------------------------------------------


def _json_number(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """Per-method, per-joint accuracy tables: overall, inside and outside camera outages.

    Arrays are indexed ``[method, joint(, axis)]`` in the order of ``methods`` and ``joints``.
    ``*_outage`` arrays are NaN when no outage mask was given or a joint has no outage sample;
    ``*_in_view`` arrays (the complement: samples outside outages, the camera sees the joint)
    are NaN when no outage mask was given or a joint has no sample in view.

    Attributes
    ----------
    methods, joints, axes : tuple of str
        Names; ``axes`` defaults to ENU (``east, north, up``).
    rmse : ndarray, shape (M, J, 3)
        Per-axis RMSE, m.
    mean_rmse : ndarray, shape (M, J)
        Mean of the per-axis RMSEs (the papers' "Mean"), m.
    rmse_3d : ndarray, shape (M, J)
        3-D RMSE, m.
    error_at_p : ndarray, shape (M, J)
        Euclidean error at CDF level ``p``, m.
    n_samples : ndarray of int, shape (M, J)
        Samples used (both finite).
    n_excluded : ndarray of int, shape (M, J)
        Samples excluded because the estimate or the reference was NaN.
    rmse_outage, mean_rmse_outage, rmse_3d_outage, error_at_p_outage, n_samples_outage
        The same restricted to outage samples.
    rmse_in_view, mean_rmse_in_view, rmse_3d_in_view, error_at_p_in_view, n_samples_in_view
        The same restricted to samples outside outages (``~outage_mask``).
    errors : ndarray, shape (M, J, T)
        Euclidean error per sample, m (NaN where excluded); used for CDFs.
    outage_mask : ndarray of bool, shape (T, J) or None
        True inside camera outages.
    p : float
        CDF level of ``error_at_p`` (0.9).
    run_time_s : dict of str -> float
        Wall-clock run time of each method over the whole recording, s (if given).
    n_steps : int
        Number of time steps ``T``.
    """

    methods: tuple[str, ...]
    joints: tuple[str, ...]
    axes: tuple[str, ...]
    rmse: np.ndarray
    mean_rmse: np.ndarray
    rmse_3d: np.ndarray
    error_at_p: np.ndarray
    n_samples: np.ndarray
    n_excluded: np.ndarray
    rmse_outage: np.ndarray
    mean_rmse_outage: np.ndarray
    rmse_3d_outage: np.ndarray
    error_at_p_outage: np.ndarray
    n_samples_outage: np.ndarray
    rmse_in_view: np.ndarray
    mean_rmse_in_view: np.ndarray
    rmse_3d_in_view: np.ndarray
    error_at_p_in_view: np.ndarray
    n_samples_in_view: np.ndarray
    errors: np.ndarray
    outage_mask: np.ndarray | None
    p: float = 0.9
    run_time_s: dict = field(default_factory=dict)
    n_steps: int = 0

    # ---- lookup ------------------------------------------------------------------------
    def _idx(self, method: str, joint: str) -> tuple[int, int]:
        try:
            m = self.methods.index(method)
        except ValueError:
            raise InputError(
                f"unknown method {method!r}; evaluated: {list(self.methods)}"
            ) from None
        try:
            j = self.joints.index(joint)
        except ValueError:
            raise InputError(f"unknown joint {joint!r}; evaluated: {list(self.joints)}") from None
        return m, j

    @property
    def has_outages(self) -> bool:
        """True when an outage mask with at least one outage sample was given."""
        return self.outage_mask is not None and bool(np.any(self.outage_mask))

    @staticmethod
    def _subset(outage: bool, in_view: bool) -> str:
        if outage and in_view:
            raise InputError("expected at most one of outage=True and in_view=True, got both")
        return "_outage" if outage else "_in_view" if in_view else ""

    def row(self, method: str, joint: str, *, outage: bool = False, in_view: bool = False) -> dict:
        """Metrics of one method at one joint as a flat dict (m; NaN where undefined).

        Keys: one per axis name, ``mean``, ``rmse_3d``, ``error_at_p``, ``n_samples``.
        ``outage``: only samples inside camera outages; ``in_view``: only samples outside them.
        """
        m, j = self._idx(method, joint)
        sfx = self._subset(outage, in_view)
        rmse = getattr(self, "rmse" + sfx)
        out = {ax: float(rmse[m, j, a]) for a, ax in enumerate(self.axes)}
        out["mean"] = float(getattr(self, "mean_rmse" + sfx)[m, j])
        out["rmse_3d"] = float(getattr(self, "rmse_3d" + sfx)[m, j])
        out["error_at_p"] = float(getattr(self, "error_at_p" + sfx)[m, j])
        out["n_samples"] = int(getattr(self, "n_samples" + sfx)[m, j])
        return out

    def cdf(
        self, method: str, joint: str, *, outage: bool = False, in_view: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Empirical error CDF ``(sorted_errors, probabilities)`` of one method at one joint."""
        m, j = self._idx(method, joint)
        err = self.errors[m, j]
        if self._subset(outage, in_view):
            if self.outage_mask is None:
                err = err[:0]
            else:
                err = err[self.outage_mask[:, j] == bool(outage)]
        x = np.sort(err[~np.isnan(err)])  # an infinite error counts (the plot clips it)
        return x, np.arange(1, x.size + 1, dtype=float) / max(x.size, 1)

    def improvement(
        self,
        method: str,
        baseline: str,
        joint: str,
        *,
        metric: str = "error_at_p",
        outage: bool = False,
        in_view: bool = False,
    ) -> float:
        """Relative reduction of ``metric`` of ``method`` vs ``baseline`` (see :func:`relative_improvement`).

        ``metric`` is a key of :meth:`row` (``"error_at_p"``, ``"mean"``, ``"rmse_3d"``, an axis).
        """
        a = self.row(method, joint, outage=outage, in_view=in_view)
        b = self.row(baseline, joint, outage=outage, in_view=in_view)
        if metric not in a:
            raise InputError(f"unknown metric {metric!r}; expected one of {list(a)}")
        return float(relative_improvement(a[metric], b[metric]))

    def time_per_step_ms(self, method: str) -> float:
        """Run time per time step (all joints together), ms; NaN if no run time was given."""
        t = self.run_time_s.get(method)
        if t is None or self.n_steps == 0:
            return float("nan")
        return 1e3 * float(t) / self.n_steps

    def to_dict(self) -> dict:
        """JSON-ready nested dict (NaN -> ``None``); raw per-sample errors are left out."""
        results: dict = {}
        for method in self.methods:
            per_joint = {}
            for joint in self.joints:
                overall = {
                    k: (_json_number(v) if k != "n_samples" else v)
                    for k, v in self.row(method, joint).items()
                }
                m, j = self._idx(method, joint)
                overall["n_excluded"] = int(self.n_excluded[m, j])
                entry = {"overall": overall, "outage": None, "in_view": None}
                if self.outage_mask is not None:
                    for key, kw in (("outage", {"outage": True}), ("in_view", {"in_view": True})):
                        entry[key] = {
                            k: (_json_number(v) if k != "n_samples" else v)
                            for k, v in self.row(method, joint, **kw).items()
                        }
                per_joint[joint] = entry
            results[method] = per_joint
        return {
            "methods": list(self.methods),
            "joints": list(self.joints),
            "axes": list(self.axes),
            "units": "m",
            "p": self.p,
            "mean_definition": "arithmetic mean of the per-axis RMSEs (SPEC §14)",
            "n_steps": self.n_steps,
            "results": results,
            "run_time_s": {k: _json_number(v) for k, v in self.run_time_s.items()},
            "time_per_step_ms": {
                k: _json_number(self.time_per_step_ms(k)) for k in self.run_time_s
            },
        }


def _reference_arrays(reference, joints) -> tuple[np.ndarray, tuple[str, ...]]:
    if hasattr(reference, "position_m"):
        pos = np.array(reference.position_m, dtype=float, copy=True)
        names = tuple(getattr(reference, "joints", ()) or ())
        avail = getattr(reference, "available", None)
        if avail is not None:
            pos[~np.asarray(avail, dtype=bool)] = np.nan
        if joints is not None and tuple(joints) != names:
            raise InputError(
                f"joints {tuple(joints)} differ from the reference's joints {names}; pass one of them"
            )
    else:
        pos = _positions(reference, "reference").copy()
        names = (
            tuple(joints)
            if joints is not None
            else tuple(f"joint_{j}" for j in range(pos.shape[-2]))
        )
    if pos.ndim != 3:
        raise InputError(f"expected reference positions with shape (T, J, 3), got {pos.shape}")
    if len(names) != pos.shape[1]:
        raise InputError(f"expected {pos.shape[1]} joint names for the reference, got {len(names)}")
    return pos, names


def evaluate(
    estimates: Mapping[str, np.ndarray],
    reference,
    outage_mask=None,
    run_time_s: Mapping[str, float] | None = None,
    *,
    joints: Sequence[str] | None = None,
    axes: Sequence[str] = AXES_ENU,
    p: float = 0.9,
) -> EvaluationResult:
    """Evaluate several methods against one reference, per joint, overall and in outages.

    Parameters
    ----------
    estimates : mapping of str -> array_like, shape (T, J, 3)
        Estimated joint positions of each method, m, in the reference's joint order.
    reference : JointStream or array_like, shape (T, J, 3)
        Reference positions, m. For a :class:`~kinefuse.io.recording.JointStream` the joint
        names come from it and samples with ``available == False`` are excluded.
    outage_mask : array_like of bool, shape (T, J), optional
        True where the camera was unavailable (the "outage" columns of the tables).
    run_time_s : mapping of str -> float, optional
        Wall-clock time each method took for the whole recording, s.
    joints : sequence of str, optional
        Joint names when ``reference`` is a plain array (default ``joint_0, joint_1 ...``).
    axes : sequence of 3 str
        Axis names for tables (ENU by default; paper B uses ``X, Y, Z``).
    p : float
        CDF level of the "error at" column (0.9 in both papers).

    Returns
    -------
    EvaluationResult
    """
    if not isinstance(estimates, Mapping) or not estimates:
        raise InputError("expected estimates as a non-empty mapping method name -> (T, J, 3) array")
    ref, names = _reference_arrays(reference, names_arg(joints, "joints"))
    T, J, _ = ref.shape
    axes = tuple(axes)
    if len(axes) != 3:
        raise InputError(f"expected 3 axis names, got {axes}")
    E = _stacked_estimates(estimates, ref)  # (M, J, T, 3)
    R = np.moveaxis(ref, 0, 1)[None]  # (1, J, T, 3)
    om = _outage_mask(outage_mask, T, J)
    rt = _run_times(run_time_s, estimates)
    both = ~np.isnan(E).any(-1) & np.isfinite(R).all(-1)  # (M, J, T): samples scored
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rmse = rmse_per_axis(E, R)
        mean = rmse.mean(-1)
        r3 = rmse_3d(E, R)
        e_at = error_at(E, R, p=p)
        errors = position_error(E, R)
        subsets = _subset_metrics(E, R, om, both, p, (rmse, mean, r3, e_at))
    names_s = ("rmse", "mean_rmse", "rmse_3d", "error_at_p", "n_samples")
    per_subset = {
        n + sfx: v for sfx, vals in subsets.items() for n, v in zip(names_s, vals, strict=True)
    }
    return EvaluationResult(
        methods=tuple(estimates),
        joints=names,
        axes=axes,
        rmse=rmse,
        mean_rmse=mean,
        rmse_3d=r3,
        error_at_p=e_at,
        n_samples=both.sum(-1),
        n_excluded=(~both).sum(-1),
        **per_subset,
        errors=errors,
        outage_mask=om,
        p=float(p),
        run_time_s=rt,
        n_steps=int(T),
    )


def _stacked_estimates(estimates: Mapping, ref: np.ndarray) -> np.ndarray:
    """The methods' positions, validated against ``ref`` (T, J, 3), as (M, J, T, 3)."""
    est = []
    for name, value in estimates.items():
        e = _positions(value, f"estimates[{name!r}]", estimate=True)
        if e.shape != ref.shape:
            raise InputError(
                f"expected estimates[{name!r}] with shape (T, J, 3) = {ref.shape}, got {e.shape}"
            )
        est.append(e)
    E = np.stack(est)  # (M, T, J, 3)
    return np.moveaxis(E, 1, 2)  # (M, J, T, 3)


def _run_times(run_time_s, estimates) -> dict[str, float]:
    """Run time per method, s, for methods among the estimates."""
    rt = {}
    for k, v in (run_time_s or {}).items():
        if k not in estimates:
            raise InputError(
                f"run_time_s has method {k!r} that is not in estimates {list(estimates)}"
            )
        rt[k] = float(v)
    return rt


def _outage_mask(outage_mask, T: int, J: int) -> np.ndarray | None:
    """A copy of the (T, J) boolean outage mask, validated; None when not given."""
    if outage_mask is None:
        return None
    om = np.asarray(outage_mask)
    if om.dtype != bool or om.shape != (T, J):
        raise InputError(
            f"expected outage_mask as bool with shape (T, J) = {(T, J)}, got {om.shape} {om.dtype}"
        )
    return om.copy()


def _subset_metrics(E, R, om, both, p, overall) -> dict[str, tuple]:
    """Metrics inside (``"_outage"``) and outside (``"_in_view"``) camera outages (NaN without)."""
    rmse, mean, r3, e_at = overall
    subsets = {}
    for sfx, inside in (("_outage", True), ("_in_view", False)):
        if om is not None:
            sel = np.moveaxis(om == inside, 0, 1)[None]  # (1, J, T)
            r_s = rmse_per_axis(E, R, sel)
            subsets[sfx] = (
                r_s,
                r_s.mean(-1),
                rmse_3d(E, R, sel),
                error_at(E, R, p=p, mask=sel),
                (both & sel).sum(-1),
            )
        else:
            subsets[sfx] = (
                np.full_like(rmse, np.nan),
                np.full_like(mean, np.nan),
                np.full_like(r3, np.nan),
                np.full_like(e_at, np.nan),
                np.zeros(mean.shape, dtype=np.int64),
            )
    return subsets
