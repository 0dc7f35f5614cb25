"""The study report: ``out_dir/study_report.html`` (self-contained, figures embedded).

Box plots of the per-recording errors for every estimate and joint (3-D RMSE and the error at
CDF 0.9, overall and, when the sessions have camera outages, inside them), a summary table
(recordings, median, quartiles, mean), run times per method, and the failed tasks with their
one-line errors. Same look and embedding as the single-recording report
(:mod:`kinefuse.evaluation.report`): inline CSS, base64 PNG, no scripts, no URLs; the figures
also as PNG files in ``out_dir/figures/``.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from kinefuse import __version__
from kinefuse.evaluation import plots, tables
from kinefuse.evaluation.report import REPORT_CSS
from kinefuse.evaluation.tables import ResultTable, TableRow

__all__ = ["NO_SCORES", "STUDY_REPORT_NAME", "collect", "summary_table", "write_study_report"]

STUDY_REPORT_NAME = "study_report.html"


def collect(results: Sequence[Mapping], metric: str, subset: str = "all") -> dict:
    """``{(estimate, joint): values over recordings}`` of one metric (one value per recording).

    Baselines that several methods evaluate (the IMU chain, the camera) count once per recording.
    """
    out: dict[tuple[str, str], dict[str, float]] = {}
    for res in results:
        for r in res.get("rows") or ():
            if r["metric"] != metric or r["subset"] != subset or r["value"] is None:
                continue
            out.setdefault((r["estimate"], r["joint"]), {}).setdefault(
                res["recording"], float(r["value"])
            )
    return {k: np.array(list(v.values())) for k, v in out.items()}


def _box_figure(data: Mapping[tuple[str, str], np.ndarray], title: str, ylabel: str):
    joints = list(dict.fromkeys(j for _, j in data))
    estimates = list(dict.fromkeys(e for e, _ in data))
    colors = plots.method_colors(estimates)
    short, common = plots.short_method_labels(estimates, wrap=24)
    lines = max(s.count("\n") + 1 for s in short.values())
    fig = Figure(
        figsize=(max(4.0, 1.2 + 1.1 * len(estimates)) * len(joints), 3.4 + 0.35 * lines),
        layout="constrained",
    )
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(joints), squeeze=False)[0]
    for ax, joint in zip(axes, joints, strict=True):
        labels = [e for e in estimates if (e, joint) in data]
        vals = [data[(e, joint)] for e in labels]
        box = ax.boxplot(vals, patch_artist=True, showfliers=True)
        ax.set_xticks(range(1, len(labels) + 1), [short[e] for e in labels], rotation=30,
                      ha="right", rotation_mode="anchor", fontsize=8)  # fmt: skip
        for patch, e in zip(box["boxes"], labels, strict=True):
            patch.set_facecolor(colors[e])
            patch.set_alpha(0.55)
        ax.set_title(f"{joint} (n = {', '.join(str(v.size) for v in vals)})", fontsize=10)
        ax.set_ylabel(ylabel)
        ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle(plots.with_caption(fig, title, common), fontsize=10 if common else 11)
    return fig


#: Said instead of an empty error table when no recording of a study has a reference.
NO_SCORES = (
    "none: no recording has a [reference] to score against (IMU-only sessions give joint "
    "positions and angles, not errors); each recording's outputs and report are in "
    "recordings/<recording>/<method>/"
)


def summary_table(results: Sequence[Mapping], subset: str, title: str):
    metrics = ("rmse_3d", "rmse_mean", "error_cdf_0.9")
    cols = {m: collect(results, m, subset) for m in metrics}
    keys = list(cols["rmse_3d"])
    rows = []
    for est, joint in keys:
        v = cols["rmse_3d"][(est, joint)]
        q1, med, q3 = np.percentile(v, [25, 50, 75]) if v.size else (math.nan,) * 3
        others = [cols[m].get((est, joint), np.array([])) for m in metrics[1:]]
        rows.append(
            TableRow(
                labels=(est, joint, str(v.size)),
                values=(
                    float(med),
                    float(q1),
                    float(q3),
                    float(np.mean(v)) if v.size else None,
                    *(float(np.median(o)) if o.size else None for o in others),
                ),
            )
        )
    return ResultTable(
        title=title,
        label_headers=("Estimate", "Joint", "Recordings"),
        value_headers=(
            "3-D RMSE median",
            "Q1",
            "Q3",
            "mean",
            "Mean-axis RMSE median",
            "CDF 0.9 median",
        ),
        rows=tuple(rows),
        digits=4,
        notes=_zero_note(cols["rmse_3d"]),
    )


def _zero_note(rmse_3d: Mapping) -> tuple[str, ...]:
    """A note for estimates that equal the reference on every recording (their rows say nothing)."""
    zero = sorted({est for (est, _), v in rmse_3d.items() if v.size and not np.any(v)})
    if not zero:
        return ()
    return (
        f"{', '.join(zero)}: exactly 0 on every recording: the reference is the input these "
        "follow (e.g. the camera used as the reference, with no outage), so these rows say "
        "nothing about accuracy.",
    )


def _timing_rows(results: Sequence[Mapping]) -> str:
    per: dict[str, list[float]] = {}
    for res in results:
        if res["status"] == "failed":
            continue
        for r in res.get("rows") or ():
            if r["metric"] == "task_wall_s" and r["value"] is not None:
                per.setdefault(res["method"], []).append(float(r["value"]))
    e = html.escape
    lines = [
        '<table class="results"><caption>Task wall time per recording (s): run_session '
        "including the per-recording report</caption><tr><th>Method</th>"
        '<th class="num">Tasks</th><th class="num">Median</th><th class="num">Total</th></tr>'
    ]
    for m, v in per.items():
        lines.append(
            f'<tr><td>{e(m)}</td><td class="num">{len(v)}</td>'
            f'<td class="num">{np.median(v):.2f}</td><td class="num">{np.sum(v):.1f}</td></tr>'
        )
    lines.append("</table>")
    return "".join(lines)


def write_study_report(out_dir: str | Path, study, results: Sequence[Mapping]) -> Path:
    """Write ``study_report.html`` (and ``figures/*.png``) for a finished study.

    Parameters
    ----------
    out_dir : str or Path
        The study's output folder.
    study : Study
    results : sequence of mapping
        Task results in study order (:func:`kinefuse.batch.tasks.run_task`).

    Returns
    -------
    Path
        The report (written atomically: temporary sibling + rename).
    """
    out = Path(out_dir)
    has_outage = any(
        r["subset"] == "outage" and r["metric"] == "n_samples" and (r["value"] or 0) > 0
        for res in results
        for r in res.get("rows") or ()
    )
    figures = _distribution_figures(out / "figures", results, has_outage)
    e = html.escape
    ok = [r for r in results if r["status"] != "failed"]
    failed = [r for r in results if r["status"] == "failed"]
    calibrated = sorted({r.get("calibrated_on") or "" for r in ok} - {""})
    n_rec = len({r["recording"] for r in results})
    meta = (
        f"generated {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} by kinefuse {e(__version__)} · "
        f"{n_rec} recordings · {len(results)} tasks: {len(ok)} finished, {len(failed)} failed · "
        f"methods: {e(', '.join(study.methods))}"
    )
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>kinefuse study: {e(study.name)}</title><style>{REPORT_CSS}</style></head><body>",
        f'<header><h1>kinefuse study: {e(study.name)}</h1><div class="meta">{meta}</div></header>',
        '<nav><a href="#summary">Summary</a><a href="#distributions">Distributions</a>'
        + ('<a href="#warnings">Warnings</a>' if any(r.get("warnings") for r in ok) else "")
        + '<a href="#failed">Failed</a></nav><main>',
        '<section id="summary"><h2>Summary</h2>',
        f'<p class="note">Calibrated on: {e(", ".join(calibrated) or "n/a")}. Errors against '
        "each session's [reference]; the IMU chain and camera rows are the baselines each "
        "method's evaluation includes. Full table: <code>study_results.parquet</code> / "
        "<code>study_results.csv</code>; per recording: <code>recordings/&lt;recording&gt;/"
        "&lt;method&gt;/report.html</code>.</p>",
    ]
    scores = summary_table(ok, "all", "Over recordings, all samples (m)")
    parts.append(tables.to_html(scores) if scores.rows else f'<p class="note">{e(NO_SCORES)}.</p>')
    if has_outage:
        parts.append(tables.to_html(summary_table(ok, "outage", "Inside camera outages (m)")))
    parts.append(_timing_rows(ok))
    parts.append("</section>")
    parts.append('<section id="distributions"><h2>Distributions over recordings</h2>')
    parts += figures
    parts.append("</section>")
    parts.append(_warnings_section(ok))
    parts.append(_failed_section(failed) + "</main></body></html>")
    path = out / STUDY_REPORT_NAME
    tmp = path.with_name(STUDY_REPORT_NAME + ".part")
    tmp.write_text("\n".join(parts), encoding="utf-8")
    tmp.replace(path)
    return path


def _distribution_figures(fig_dir: Path, results, has_outage: bool) -> list[str]:
    """Box plots over recordings, written as PNGs and returned as inline ``<figure>`` HTML."""
    fig_dir.mkdir(parents=True, exist_ok=True)
    e = html.escape
    figures: list[str] = []

    def emit(key: str, fig, alt: str, caption: str) -> None:
        data = plots.figure_to_png(fig, fig_dir / f"{key}.png")
        b64 = base64.b64encode(data).decode("ascii")
        figures.append(
            f'<figure><img alt="{e(alt)}" src="data:image/png;base64,{b64}">'
            f"<figcaption>{e(caption)} (also <code>figures/{e(key)}.png</code>)</figcaption></figure>"
        )

    panels = [("rmse_3d", "all", "3-D RMSE per recording, all samples")]
    panels.append(("error_cdf_0.9", "all", "Error at CDF 0.9 per recording, all samples"))
    if has_outage:
        panels.append(("rmse_3d", "outage", "3-D RMSE per recording, inside camera outages"))
    for metric, subset, title in panels:
        data = collect(results, metric, subset)
        if data:
            emit(
                f"study_{metric.replace('.', '_')}_{subset}",
                _box_figure(data, title, "m"),
                title,
                f"{title}: box = quartiles, line = median, whiskers 1.5 IQR; one value per "
                "recording.",
            )
    return figures


def _warnings_section(ok) -> str:
    """The finished tasks' run warnings (highlighted, per recording and method); empty if none."""
    e = html.escape
    warned = [r for r in ok if r.get("warnings")]
    if not warned:
        return ""
    items = "".join(
        f"<li><b>{e(r['recording'])} / {e(r['method'])}</b><ul>"
        + "".join(f"<li>{e(w)}</li>" for w in r["warnings"])
        + "</ul></li>"
        for r in warned
    )
    return (
        f'<section class="warnings" id="warnings"><h2>Warnings ({len(warned)} of {len(ok)} '
        f"tasks)</h2><ul>{items}</ul></section>"
    )


def _failed_section(failed) -> str:
    """The failed tasks as an HTML section (recording, method, error)."""
    e = html.escape
    parts = [f'<section id="failed"><h2>Failed tasks ({len(failed)})</h2>']
    if failed:
        parts.append(
            '<table class="results"><tr><th>Recording</th><th>Method</th><th>Error</th></tr>'
        )
        for r in failed:
            parts.append(
                f"<tr><td>{e(r['recording'])}</td><td>{e(r['method'] or '-')}</td>"
                f"<td>{e(r.get('error') or '')}</td></tr>"
            )
        parts.append("</table>")
    else:
        parts.append("<p>None.</p>")
    parts.append("</section>")
    return "\n".join(parts)
