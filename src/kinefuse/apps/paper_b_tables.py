"""The tables of ``kinefuse experiment paper-b`` beyond paper B's own layout.

Paper B's CDF-0.9 claims (ELM/FIR vs ELM/KF), a 3-D RMSE summary per data set next to the
simple baselines, kinefuse vs camera only per joint in view, and issue 11's targets (kinefuse vs
the best simple baseline inside outages). Each ``*_table`` returns ``(ResultTable, numbers)``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from kinefuse.apps._common import finite_or_none, result_table
from kinefuse.apps.splits import DataSplit
from kinefuse.pipelines._outages import outage_intervals

__all__ = [
    "PAPER_B_CDF_CLAIMS",
    "cdf_table",
    "in_view_table",
    "relative_pct",
    "rmse3_pooled",
    "summary_table",
    "targets_table",
]

#: Paper B's CDF-0.9 improvement claims (ELM/FIR vs ELM/KF), SPEC §14.
PAPER_B_CDF_CLAIMS = {
    "elbow_r": 0.1271,
    "wrist_r": 0.1640,
    "wrist_l": 0.5671,
    "knee_r": 0.4832,
}


def cdf_table(ev, title: str):
    """Paper B's CDF-0.9 claims: ELM/FIR vs ELM/KF per joint, overall and in outages."""
    rows = []
    res = {}
    for j in ev.joints:
        if "ELM/FIR" not in ev.methods or "ELM/KF" not in ev.methods:
            break
        a = ev.row("ELM/FIR", j)["error_at_p"]
        b = ev.row("ELM/KF", j)["error_at_p"]
        ao = ev.row("ELM/FIR", j, outage=True)["error_at_p"]
        bo = ev.row("ELM/KF", j, outage=True)["error_at_p"]
        imp = (b - a) / b if b > 0 else float("nan")
        impo = (bo - ao) / bo if bo > 0 else float("nan")
        claim = PAPER_B_CDF_CLAIMS.get(j)
        rows.append(
            (
                (j,),
                (b, a, 100 * imp, bo, ao, 100 * impo, None if claim is None else 100 * claim),
                False,
            )
        )
        res[j] = {
            "elm_kf_m": finite_or_none(b),
            "elm_fir_m": finite_or_none(a),
            "improvement": finite_or_none(imp),
            "improvement_outage": finite_or_none(impo),
            "paper": claim,
        }
    t = result_table(
        title,
        ("Joint",),
        (
            "ELM/KF @0.9",
            "ELM/FIR @0.9",
            "Impr. %",
            "ELM/KF out",
            "ELM/FIR out",
            "Impr. out %",
            "Paper impr. %",
        ),
        rows,
        (
            "Error at CDF 0.9 (m) and its relative reduction by ELM/FIR vs ELM/KF; 'out' = inside "
            "camera outages. Paper B claims (SPEC §14): right elbow 12.71 % (its numbers give "
            "21.7 %), right wrist 16.40 %, left wrist 56.71 %, right knee 48.32 %.",
        ),
        digits=4,
    )
    return t, res


def rmse3_pooled(ev, method: str, outage: bool) -> tuple[float, int]:
    """3-D RMSE (m) pooled over joints inside (or outside) the outages, and its sample count."""
    m = ev.methods.index(method)
    e = ev.errors[m]  # (J, T)
    sel = (ev.outage_mask.T == outage) & np.isfinite(e)
    n = int(sel.sum())
    return (float(np.sqrt(np.mean(e[sel] ** 2))) if n else float("nan")), n


def oracle_linear_offset(parts, base: str = "offset interp") -> float | None:
    """A bound, not a method: 3-D RMSE (m) inside the outages of the IMU chain plus, per outage
    of each joint, the linear-in-time offset that best fits the hidden reference there (least
    squares on the samples every method is denied). No bridge of the form chain + a linear
    offset does better; offset interp is one. Computed as ``base`` (offset interp: the chain
    plus an offset linear in time inside each outage) plus the best linear correction, which is
    the same family. Pooled over joints and parts, over the samples where ``base`` and the
    reference are finite; None without any."""
    return _oracle_offset(parts, base, 1)


def oracle_constant_offset(parts, base: str = "offset hold") -> float | None:
    """A bound, not a method: as :func:`oracle_linear_offset` with the best *constant* offset
    per outage added to the IMU chain, i.e. the chain plus the mean hidden chain error of the
    outage. No bridge of the form chain + one offset per outage (offset hold, any held or
    learned constant) does better. Computed as ``base`` (offset hold: the chain plus a constant
    inside each outage) plus the best constant correction, the same family."""
    return _oracle_offset(parts, base, 0)


def _oracle_offset(parts, base: str, degree: int) -> float | None:
    """RMS residual of ``reference − base`` after a least-squares polynomial in time of
    ``degree`` per outage interval of each joint (see the two oracles above)."""
    errs = []
    for p in parts:
        e_all = p["reference"] - p["estimates"][base]  # (T, J, 3)
        for j in range(e_all.shape[1]):
            for a, b in outage_intervals(~p["outage"][:, j]):
                ok = np.all(np.isfinite(e_all[a:b, j]), axis=-1)
                if ok.sum() < degree + 1:
                    continue
                e = e_all[a:b, j][ok]
                k = np.flatnonzero(ok).astype(float)
                A = np.stack([k**d for d in range(degree + 1)], axis=1)
                errs.append(e - A @ np.linalg.lstsq(A, e, rcond=None)[0])
    if not errs:
        return None
    return finite_or_none(np.sqrt(np.mean(np.sum(np.concatenate(errs) ** 2, axis=-1))))


def relative_pct(a: float, b: float) -> float | None:
    """Relative difference ``100 (a − b) / b`` (%; negative: a is lower)."""
    return finite_or_none(100.0 * (a - b) / b) if b > 0 and np.isfinite(a) else None


def summary_table(ev, title: str, notes=()):
    """Every method, 3-D RMSE pooled over joints in view and in outages, next to the baselines."""
    n_all = max(rmse3_pooled(ev, m, True)[1] for m in ev.methods)
    ref = {b: rmse3_pooled(ev, b, True)[0] for b in ("offset interp", "offset hold")}
    rows, res = [], {}
    for m in ev.methods:
        out, n = rmse3_pooled(ev, m, True)
        inv, _ = rmse3_pooled(ev, m, False)
        cover = 100.0 * n / n_all if n_all else float("nan")
        vs = [relative_pct(out, ref[b]) if b in ev.methods else None for b in ref]
        rows.append(((m,), (1e3 * inv, 1e3 * out, cover, *vs), False))
        res[m] = {
            "rmse_3d_in_view_m": finite_or_none(inv),
            "rmse_3d_outage_m": finite_or_none(out),
            "outage_coverage": finite_or_none(cover / 100.0),
            "vs_offset_interp_pct": vs[0],
            "vs_offset_hold_pct": vs[1],
        }
    t = result_table(
        title,
        ("Method",),
        (
            "3-D in view",
            "3-D out",
            "covered out %",
            "out vs offset interp %",
            "out vs offset hold %",
        ),
        rows,
        (
            "3-D RMSE in mm, pooled over joints and trials; 'out' = inside camera outages, "
            "'covered out %' = share of outage samples with an estimate (camera gap-fill "
            "bridges gaps of <= 20 frames only: its 'out' figure is over those); 'vs' = "
            "relative difference of the 3-D outage RMSE to the baseline (negative = lower). "
            "offset interp is offline (reads the camera after the outage), offset hold causal.",
            *notes,
        ),
        digits=1,
    )
    return t, res


def in_view_table(ev, title: str, notes=()):
    """Per joint in view: kinefuse (offline, causal) vs camera only, 3-D RMSE (mm)."""
    rows, res = [], {}
    ours = [m for m in ("kinefuse", "kinefuse causal") if m in ev.methods]
    if "camera only" not in ev.methods or not ours:
        return None, res
    for j in ev.joints:
        cam = ev.row("camera only", j, in_view=True)["rmse_3d"]
        vals = [1e3 * cam]
        for m in ours:
            r = ev.row(m, j, in_view=True)["rmse_3d"]
            vals += [1e3 * r, relative_pct(r, cam)]
            res.setdefault(m, {})[j] = relative_pct(r, cam)
        rows.append(((j,), tuple(vals), False))
    heads = ["camera only"]
    for m in ours:
        heads += [m, f"{m} vs camera %"]
    return result_table(title, ("Joint",), heads, rows, notes, digits=1), res


def targets_table(
    summaries: Mapping[str, dict],
    split: DataSplit,
    in_view: Mapping[str, dict],
    oracles: Mapping[str, Mapping[str, float | None]] | None = None,
):
    """Issue 11's targets: kinefuse vs the best simple baseline inside outages, per data set,
    with what the best constant and the best linear offset per outage
    (:func:`oracle_constant_offset`, :func:`oracle_linear_offset`: bounds computed from the
    hidden reference; ``oracles[data set]["constant" | "linear"]``, m) reach against offset
    interp."""
    rows, res = [], {}
    oracles = oracles or {}
    for ds, sm in summaries.items():
        vals = []
        for ours, base in (("kinefuse", "offset interp"), ("kinefuse causal", "offset hold")):
            a, b = ((sm.get(m) or {}).get("rmse_3d_outage_m") for m in (ours, base))
            vals += [
                None if a is None else 1e3 * a,
                None if b is None else 1e3 * b,
                None if a is None or b is None else relative_pct(a, b),
            ]
        for ours in ("kinefuse", "kinefuse causal"):
            worst = [v for v in (in_view.get(ds, {}).get(ours) or {}).values() if v is not None]
            vals.append(max(worst) if worst else None)
        interp = (sm.get("offset interp") or {}).get("rmse_3d_outage_m")
        for kind in ("constant", "linear"):
            bound = (oracles.get(ds) or {}).get(kind)
            vals.append(None if bound is None or interp is None else relative_pct(bound, interp))
        rows.append(((ds,), tuple(vals), False))
        res[ds] = dict(
            zip(
                (
                    "kinefuse_out_mm",
                    "offset_interp_out_mm",
                    "offline_vs_offset_interp_pct",
                    "kinefuse_causal_out_mm",
                    "offset_hold_out_mm",
                    "causal_vs_offset_hold_pct",
                    "worst_joint_in_view_vs_camera_pct",
                    "causal_worst_joint_in_view_vs_camera_pct",
                    "oracle_constant_offset_vs_offset_interp_pct",
                    "oracle_linear_offset_vs_offset_interp_pct",
                ),
                vals,
                strict=True,
            )
        )
    t = result_table(
        f"Fusion vs the simple baselines inside outages (3-D RMSE, mm) — {split.name} set",
        ("Data",),
        (
            "kinefuse",
            "offset interp",
            "Δ %",
            "causal",
            "offset hold",
            "Δ % c",
            "view %",
            "view % c",
            "const. oracle Δ %",
            "lin. oracle Δ %",
        ),
        rows,
        (
            "kinefuse = offline, causal = kinefuse causal; Δ % = kinefuse vs offset interp, "
            "Δ % c = causal vs offset hold (target, issue 11: <= -25 %); view % (c) = the worst "
            "joint's in-view 3-D RMSE of kinefuse (causal) relative to camera only (target: "
            "<= +5 %; UTD-MHAD: none, the in-view reference is the camera input itself). "
            "oracle Δ % = bounds, not methods, vs offset interp: the IMU chain plus the constant "
            "(const.) or the linear-in-time (lin.) offset that best fits the hidden reference "
            "in each outage. No bridge that adds one offset per outage to the chain (a held or "
            "learned constant) beats the const. bound; none of offset interp's form beats the "
            "lin. bound (beating it takes following the offset's change inside the outage).",
            split.describe(),
        ),
        digits=1,
    )
    return t, res
