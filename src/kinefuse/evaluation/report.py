"""A self-contained HTML report of an evaluation (figures embedded, no external resources).

:func:`write_report` writes ``out_dir/report.html`` (inline CSS, figures as base64 PNG, the
interactive 3-D viewer of :mod:`kinefuse.evaluation.viewer` with its vendored three.js inlined;
nothing is loaded from a network), the same figures as PNG files in ``out_dir/figures/`` and
the metrics as ``out_dir/metrics.json``. It refuses to overwrite an existing report unless
``force=True``.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kinefuse import __version__
from kinefuse.conventions import MODE_NAMES, SOURCE_NAMES
from kinefuse.evaluation import plots, tables, viewer
from kinefuse.evaluation._names import REPORT_NAME
from kinefuse.evaluation.metrics import EvaluationResult
from kinefuse.exceptions import InputError

__all__ = ["REPORT_NAME", "ReportOptions", "write_report"]

#: The report page's style sheet (also used by :mod:`kinefuse.evaluation.angles`).
REPORT_CSS = """
:root { --fg:#1d2330; --muted:#5b6475; --line:#d9dee7; --accent:#1f5fbf; --paper:#7a6a3a; }
* { box-sizing: border-box; }
body { font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color: var(--fg); margin: 0; background: #f6f7f9; }
header { background: #fff; border-bottom: 1px solid var(--line); padding: 18px 32px; }
header h1 { margin: 0 0 4px; font-size: 24px; }
header .meta { color: var(--muted); font-size: 13px; }
nav { padding: 8px 32px; background: #fff; border-bottom: 1px solid var(--line); font-size: 14px; }
nav a { margin-right: 14px; color: var(--accent); text-decoration: none; }
main { max-width: 1180px; margin: 0 auto; padding: 8px 32px 48px; }
section { background: #fff; border: 1px solid var(--line); border-radius: 6px; padding: 16px 20px;
          margin: 18px 0; }
h2 { margin: 0 0 10px; font-size: 19px; }
h3 { margin: 16px 0 8px; font-size: 16px; }
figure { margin: 10px 0; }
figure img { max-width: 100%; height: auto; display: block; border: 1px solid #eef0f4; }
figcaption { color: var(--muted); font-size: 13px; margin-top: 4px; }
table.results { border-collapse: collapse; margin: 6px 0; font-size: 13.5px; }
table.results caption { text-align: left; font-weight: 600; padding-bottom: 4px; }
table.results th, table.results td { padding: 3px 10px; border-bottom: 1px solid var(--line); }
table.results th { background: #f0f2f6; text-align: left; }
table.results td.num, table.results th.num { text-align: right; font-variant-numeric: tabular-nums; }
table.results td.best { font-weight: 700; color: #166534; }
table.results tr.paper td { color: var(--paper); font-style: italic; }
.tables { display: flex; flex-wrap: wrap; gap: 28px; }
p.note { color: var(--muted); font-size: 12.5px; margin: 2px 0 8px; }
.notes { white-space: pre-wrap; }
section.warnings { background: #fff8e6; border-color: #e8b64c; border-left: 5px solid #d98e04; }
section.warnings ul { margin: 0; padding-left: 20px; }
section.warnings li { margin: 3px 0; }
"""


def notes_html(notes: str | Sequence[str] | None, warnings: Sequence[str] = ()) -> str:
    """The report's warnings box (each warning once, highlighted) and its notes section.

    A note that only repeats a warning (``"warning: …"``, ``"WARNING: …"`` or
    ``"calibration: …"`` followed by the warning's text) is left out of the notes: the box
    shows it.
    """
    e = html.escape
    lines = notes.splitlines() if isinstance(notes, str) else list(notes or ())
    said = set(warnings)
    kept = [
        n
        for n in lines
        if n not in said
        and not any(n.startswith(p) and n[len(p) :] in said for p in _WARNING_PREFIXES)
    ]
    parts = []
    if warnings:
        items = "".join(f"<li>{e(w)}</li>" for w in dict.fromkeys(warnings))
        parts.append(
            f'<section class="warnings" id="warnings"><h2>Warnings ({len(said)})</h2>'
            f"<ul>{items}</ul></section>"
        )
    if kept:
        parts.append(
            f'<section><h2>Notes</h2><div class="notes">{e(chr(10).join(kept))}</div></section>'
        )
    return "".join(parts)


_WARNING_PREFIXES = ("warning: ", "WARNING: ", "calibration: ")


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "x"


def _as_positions(value, name: str, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(getattr(value, "position_m", value), dtype=float)
    if arr.shape != shape:
        raise InputError(f"expected {name} with shape (T, J, 3) = {shape}, got {arr.shape}")
    return arr


def _codes(
    value: Mapping | None, name: str, shape: tuple[int, int]
) -> dict[str, np.ndarray] | None:
    if not value:
        return None
    out = {}
    for m, c in value.items():
        arr = np.asarray(c)
        if arr.shape != shape or not np.issubdtype(arr.dtype, np.integer):
            raise InputError(
                f"expected {name}[{m!r}] as integer codes with shape (T, J) = {shape}, got {arr.shape} {arr.dtype}"
            )
        out[m] = arr
    return out


def _default_instants(T: int, outage: np.ndarray | None) -> list[int]:
    if T == 0:
        return []
    picks = [int(T * 0.25), int(T * 0.75)]
    if outage is not None and np.any(outage):
        runs = plots.outage_runs(np.any(outage, axis=1))
        a, b = max(runs, key=lambda r: r[1] - r[0])
        picks.insert(1, (a + b - 1) // 2)
    else:
        picks.insert(1, T // 2)
    return sorted({min(max(k, 0), T - 1) for k in picks})


@dataclass(frozen=True)
class ReportOptions:
    """How :func:`write_report` draws and labels an evaluation (every field has a default).

    Attributes
    ----------
    title : str
        The page's title.
    notes : str or sequence of str, optional
        Free text shown under the title (settings, data source, caveats).
    warnings : sequence of str
        Shown above the notes, highlighted (:func:`notes_html`).
    axis_labels : sequence of 3 str
        Axis names in tables and figures (paper B: ``("X", "Y", "Z")``).
    dotted : sequence of str
        Methods drawn as dots in the trajectory figures (raw, noisy inputs such as the camera).
    paper : mapping joint -> method -> (x, y, z, mean), optional
        The papers' RMSE numbers to show next to ours (e.g. ``tables.PAPER_B_RMSE_M``).
    mode_names : mapping int -> str
        Names of the ``modes`` codes (default :data:`kinefuse.conventions.MODE_NAMES`).
    source_names : mapping int -> str
        Names of the ``sources`` codes (default :data:`kinefuse.conventions.SOURCE_NAMES`).
    skeleton_edges : sequence of (str, str), optional
        Bones as joint-name pairs; enables the 3-D skeleton snapshots.
    snapshot_instants : sequence of int, optional
        Sample indices of the snapshots (default: 25 %, the middle of the longest outage or
        50 %, and 75 % of the recording).
    viewer_methods : sequence of str, optional
        Methods ticked when the viewer opens (default: the first); all can be toggled.
    interactive : bool
        Include the interactive 3-D viewer (about 0.6 MB of inlined three.js plus the
        positions, thinned to at most 30 Hz and 1.5 MB).
    dpi : int
        Resolution of the figures.
    sections : sequence of str
        Extra HTML fragments shown after the notes (e.g.
        :func:`kinefuse.evaluation.angles.angle_section`).
    extra_metrics : mapping, optional
        Merged into ``metrics.json`` (e.g. ``provenance``: which data calibrated what).
    """

    title: str = "kinefuse report"
    notes: str | Sequence[str] | None = None
    warnings: Sequence[str] = ()
    axis_labels: Sequence[str] = ("East", "North", "Up")
    dotted: Sequence[str] = ()
    paper: Mapping[str, Mapping[str, Sequence[float]]] | None = None
    mode_names: Mapping[int, str] = field(default_factory=lambda: MODE_NAMES)
    source_names: Mapping[int, str] = field(default_factory=lambda: SOURCE_NAMES)
    skeleton_edges: Sequence[tuple[str, str]] | None = None
    snapshot_instants: Sequence[int] | None = None
    viewer_methods: Sequence[str] | None = None
    interactive: bool = True
    dpi: int = 100
    sections: Sequence[str] = ()
    extra_metrics: Mapping | None = None


def write_report(
    out_dir: str | Path,
    evaluation: EvaluationResult,
    trajectories: Mapping[str, np.ndarray],
    reference,
    t_s=None,
    outage_mask=None,
    *,
    measurement=None,
    modes: Mapping[str, np.ndarray] | None = None,
    sources: Mapping[str, np.ndarray] | None = None,
    body=None,
    options: ReportOptions | None = None,
    force: bool = False,
) -> Path:
    """Write a self-contained HTML report with figures and tables of an evaluation.

    Parameters
    ----------
    out_dir : str or Path
        Output folder (created if needed).
    evaluation : EvaluationResult
        From :func:`kinefuse.evaluation.metrics.evaluate`; gives methods, joints and tables.
    trajectories : mapping method -> array_like, shape (T, J, 3)
        Estimated positions per method, m, in ``evaluation.joints`` order.
    reference : JointStream or array_like, shape (T, J, 3)
        Reference positions, m.
    t_s : array_like, shape (T,), optional
        Time, s (default: ``reference.t_s`` for a JointStream, else sample index).
    outage_mask : array_like of bool, shape (T, J), optional
        Camera outages, shaded in the figures (default: ``evaluation.outage_mask``).
    measurement : array_like, shape (T, J, 3), optional
        The raw input positions (e.g. camera), drawn as grey dots.
    modes : mapping method -> int array, shape (T, J), optional
        Active filter branch per sample (:data:`kinefuse.conventions.MODE_NAMES` codes).
    sources : mapping method -> int array, shape (T, J), optional
        Data source per sample (:data:`kinefuse.conventions.SOURCE_NAMES` codes).
    body : (names, positions, edges), optional
        A whole-body context skeleton in the same frame: joint names (K,), positions
        (T, K, 3) in m and bones as name pairs; drawn light grey under the evaluated joints
        in the snapshots and the viewer (e.g. every joint of the reference).
    options : ReportOptions, optional
        Title, notes, labels, figure and viewer settings (default: ``ReportOptions()``).
    force : bool
        Overwrite an existing ``report.html`` in ``out_dir``.

    Returns
    -------
    Path
        ``out_dir/report.html``.

    Raises
    ------
    FileExistsError
        ``out_dir/report.html`` exists and ``force`` is False (the message names the file).
    InputError
        Shapes do not match the evaluation, or ``options.viewer_methods`` names a method that
        was not evaluated.
    """
    opts = ReportOptions() if options is None else options
    out = Path(out_dir)
    report_path = out / REPORT_NAME
    if report_path.exists() and not force:
        raise FileExistsError(
            f"{report_path} already exists; pass force=True (CLI: --force) to overwrite it, or choose another output folder"
        )
    d = _checked_inputs(
        evaluation, trajectories, reference, t_s, outage_mask, measurement, modes, sources, body
    )
    unknown = [m for m in opts.viewer_methods or () if m not in evaluation.methods]
    if unknown:
        raise InputError(
            f"viewer_methods {unknown} are not evaluated methods {list(evaluation.methods)}"
        )
    style = _Style(
        plots.method_colors(evaluation.methods),
        plots.method_linestyles(evaluation.methods),
        tuple(opts.axis_labels),
        tuple(opts.dotted),
    )
    figures = _write_figures(out / "figures", evaluation, d, style, opts)
    viewer_html = (
        _viewer_html(evaluation, d, style, opts) if opts.interactive and d.t.size else None
    )
    doc = _html(
        evaluation,
        figures,
        title=opts.title,
        notes=opts.notes,
        warnings=opts.warnings,
        t=d.t,
        axis_labels=opts.axis_labels,
        paper=opts.paper,
        viewer_html=viewer_html,
    )
    if opts.sections:
        anchor = '<section id="summary">'
        doc = doc.replace(anchor, "".join(opts.sections) + anchor, 1)
    tmp = report_path.with_name(REPORT_NAME + ".part")
    tmp.write_text(doc, encoding="utf-8")
    tmp.replace(report_path)
    metrics = {**evaluation.to_dict(), **dict(opts.extra_metrics or {})}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2), encoding="utf-8")
    return report_path


def _viewer_html(evaluation: EvaluationResult, d: _Inputs, style: _Style, opts: ReportOptions):
    """The interactive 3-D viewer's HTML fragment (:mod:`kinefuse.evaluation.viewer`)."""
    return viewer.report_viewer_html(
        d.t,
        evaluation.joints,
        reference=d.ref,
        estimates=d.traj,
        colors=style.colors,
        edges=opts.skeleton_edges,
        dashed=[m for m, ls in style.linestyles.items() if ls != "-"],
        sources=d.source_codes,
        camera=d.meas,
        body=d.body,
        shown=None
        if opts.viewer_methods is None
        else ["whole body (reference)", "reference", "camera", *opts.viewer_methods],
        source_names=opts.source_names,
    )


class _Inputs(NamedTuple):
    """The validated arrays of :func:`write_report` (positions (T, J, 3), codes (T, J))."""

    ref: np.ndarray
    traj: dict[str, np.ndarray]
    t: np.ndarray
    outage: np.ndarray | None
    meas: np.ndarray | None
    mode_codes: dict[str, np.ndarray] | None
    source_codes: dict[str, np.ndarray] | None
    body: tuple | None


class _Style(NamedTuple):
    """How methods are drawn: colours, line styles, axis names, methods drawn as dots."""

    colors: dict[str, str]
    linestyles: dict[str, str]
    axis_labels: tuple[str, ...]
    dotted: tuple[str, ...]


def _checked_inputs(
    evaluation, trajectories, reference, t_s, outage_mask, measurement, modes, sources, body
) -> _Inputs:
    """Validate :func:`write_report`'s arrays against the evaluation's shape (InputError)."""
    if not isinstance(evaluation, EvaluationResult):
        raise InputError(
            f"expected evaluation as an EvaluationResult, got {type(evaluation).__name__}"
        )
    joints = evaluation.joints
    ref = _as_positions(reference, "reference", (evaluation.n_steps, len(joints), 3))
    if getattr(reference, "available", None) is not None:
        ref = ref.copy()
        ref[~np.asarray(reference.available, dtype=bool)] = np.nan
    T, J, _ = ref.shape
    missing = [m for m in evaluation.methods if m not in trajectories]
    if missing:
        raise InputError(
            f"trajectories lack the evaluated methods {missing}; got {list(trajectories)}"
        )
    traj = {
        m: _as_positions(trajectories[m], f"trajectories[{m!r}]", ref.shape)
        for m in evaluation.methods
    }
    if t_s is None:
        t_s = getattr(reference, "t_s", None)
    t = np.arange(T, dtype=float) if t_s is None else np.asarray(t_s, dtype=float)
    if t.shape != (T,):
        raise InputError(f"expected t_s with shape (T,) = ({T},), got {t.shape}")
    outage = evaluation.outage_mask if outage_mask is None else np.asarray(outage_mask, dtype=bool)
    if outage is not None and outage.shape != (T, J):
        raise InputError(f"expected outage_mask with shape (T, J) = {(T, J)}, got {outage.shape}")
    meas = None if measurement is None else _as_positions(measurement, "measurement", ref.shape)
    mode_codes = _codes(modes, "modes", (T, J))
    source_codes = _codes(sources, "sources", (T, J))
    if body is not None:
        try:
            b_names, b_pos, b_edges = body
        except (TypeError, ValueError):
            raise InputError("expected body as (names, positions (T, K, 3), edges)") from None
        b_names = [str(n) for n in b_names]
        body = (
            b_names,
            _as_positions(b_pos, "body positions", (T, len(b_names), 3)),
            list(b_edges),
        )
    return _Inputs(ref, traj, t, outage, meas, mode_codes, source_codes, body)


def _write_figures(
    fig_dir: Path, evaluation: EvaluationResult, d: _Inputs, style: _Style, opts: ReportOptions
) -> dict[str, str]:
    """Every figure as a PNG in ``fig_dir``; returns key -> base64 PNG for inlining."""
    mode_names, source_names = opts.mode_names, opts.source_names
    skeleton_edges, snapshot_instants, dpi = opts.skeleton_edges, opts.snapshot_instants, opts.dpi
    fig_dir.mkdir(parents=True, exist_ok=True)
    figures: dict[str, str] = {}  # key -> base64

    def emit(key: str, fig) -> None:
        data = plots.figure_to_png(fig, fig_dir / f"{key}.png", dpi=dpi)
        figures[key] = base64.b64encode(data).decode("ascii")

    emit("summary_rmse", plots.rmse_bar_figure(evaluation, colors=style.colors))
    for j, joint in enumerate(evaluation.joints):
        _joint_figures(emit, evaluation, d, style, j, joint)
    joints, t, outage = evaluation.joints, d.t, d.outage
    if d.mode_codes:
        emit(
            "timeline_modes",
            plots.timeline_figure(
                t, d.mode_codes, mode_names, joints, outage=outage, title="Filter branch per sample"
            ),
        )
    if d.source_codes:
        emit(
            "timeline_sources",
            plots.timeline_figure(
                t,
                d.source_codes,
                source_names,
                joints,
                outage=outage,
                title="Data source per sample",
            ),
        )
    if skeleton_edges:
        T = t.size
        instants = (
            _default_instants(T, outage)
            if snapshot_instants is None
            else [int(k) for k in snapshot_instants]
        )
        bad = [k for k in instants if not 0 <= k < T]
        if bad:
            raise InputError(f"snapshot_instants must lie in [0, {T}), got {bad}")
        if instants:
            emit(
                "skeleton",
                plots.skeleton_figure(
                    d.ref,
                    d.traj,
                    joints,
                    skeleton_edges,
                    instants,
                    t_s=t,
                    colors=style.colors,
                    linestyles=style.linestyles,
                    body=d.body,
                ),
            )
    return figures


def _joint_figures(emit, evaluation: EvaluationResult, d: _Inputs, style: _Style, j, joint):
    """The trajectory and error-CDF figures of one joint."""
    slug = _slug(joint)
    emit(
        f"trajectory_{slug}",
        plots.trajectory_figure(
            d.t,
            d.ref[:, j],
            {m: d.traj[m][:, j] for m in evaluation.methods},
            outage=None if d.outage is None else d.outage[:, j],
            measurement=None if d.meas is None else d.meas[:, j],
            joint=joint,
            axis_labels=style.axis_labels,
            colors=style.colors,
            dotted=style.dotted,
            linestyles=style.linestyles,
        ),
    )
    cdfs = {m: evaluation.cdf(m, joint) for m in evaluation.methods}
    out_cdfs = (
        {m: evaluation.cdf(m, joint, outage=True) for m in evaluation.methods}
        if evaluation.has_outages
        else None
    )
    emit(
        f"cdf_{slug}",
        plots.cdf_figure(
            cdfs,
            outage_cdfs=out_cdfs,
            p=evaluation.p,
            joint=joint,
            colors=style.colors,
            linestyles=style.linestyles,
        ),
    )


def _img(figures: Mapping[str, str], key: str, alt: str, caption: str) -> str:
    if key not in figures:
        return ""
    e = html.escape
    return (
        f'<figure><img alt="{e(alt)}" src="data:image/png;base64,{figures[key]}">'
        f"<figcaption>{e(caption)} (also <code>figures/{e(key)}.png</code>)</figcaption></figure>"
    )


def _html(
    ev: EvaluationResult, figures, *, title, notes, t, axis_labels, paper, viewer_html=None,
    warnings=(),
) -> str:  # fmt: skip
    e = html.escape
    duration = float(t[-1] - t[0]) if t.size > 1 else 0.0
    meta = (
        f"generated {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} by kinefuse {e(__version__)} · "
        f"{ev.n_steps} samples ({duration:.1f} s) · joints: {e(', '.join(ev.joints))} · "
        f"methods: {e(', '.join(ev.methods))}"
    )
    if ev.has_outages:
        frac = float(np.mean(ev.outage_mask))
        meta += f" · camera outage: {frac:.0%} of joint-samples"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{e(title)}</title><style>{REPORT_CSS}{viewer.VIEWER_CSS if viewer_html else ''}</style>"
        "</head><body>",
        f'<header><h1>{e(title)}</h1><div class="meta">{meta}</div></header>',
    ]
    nav = (
        ['<a href="#summary">Summary</a>']
        + (['<a href="#viewer">3-D viewer</a>'] if viewer_html else [])
        + [f'<a href="#joint-{_slug(j)}">{e(j)}</a>' for j in ev.joints]
    )
    if "timeline_modes" in figures or "timeline_sources" in figures:
        nav.append('<a href="#timelines">Timelines</a>')
    if "skeleton" in figures:
        nav.append('<a href="#skeleton">Skeleton</a>')
    parts.append("<nav>" + "".join(nav) + "</nav><main>")
    parts.append(notes_html(notes, warnings))

    summary = tables.joint_method_table(
        ev,
        axis_labels=axis_labels,
        paper=paper,
        title="RMSE per joint and method (m)",
        drop_empty=True,
    )
    parts.append('<section id="summary"><h2>Summary</h2>')
    parts.append(tables.to_html(summary))
    parts.append(
        _img(
            figures,
            "summary_rmse",
            "bar chart of mean RMSE per joint and method",
            "Mean RMSE per joint.",
        )
    )
    if ev.run_time_s:
        parts.append(tables.to_html(tables.timing_table(ev)))
    excluded = int(ev.n_excluded.sum())
    if excluded:
        parts.append(
            f'<p class="note">{excluded} method-joint-samples were excluded because the estimate or the '
            "reference was missing (NaN); see metrics.json for the counts.</p>"
        )
    parts.append("</section>")
    if viewer_html:
        parts.append(viewer_html)

    for joint in ev.joints:
        slug = _slug(joint)
        parts.append(f'<section id="joint-{slug}"><h2>{e(joint)}</h2><div class="tables">')
        parts.append(
            tables.to_html(
                tables.method_table(
                    ev,
                    joint,
                    axis_labels=axis_labels,
                    digits=4,
                    include_counts=True,
                    title="All samples",
                    drop_empty=True,
                )
            )
        )
        j_out = ev.has_outages and bool(np.any(ev.outage_mask[:, ev.joints.index(joint)]))
        if j_out:
            parts.append(
                tables.to_html(
                    tables.method_table(
                        ev,
                        joint,
                        outage=True,
                        axis_labels=axis_labels,
                        digits=4,
                        include_counts=True,
                        title="Inside camera outages",
                        drop_empty=True,
                    )
                )
            )
        elif ev.has_outages:
            parts.append('<p class="note">No camera outage at this joint.</p>')
        parts.append("</div>")
        parts.append(
            _img(
                figures,
                f"trajectory_{slug}",
                f"{joint} position per axis",
                "Positions per axis (reference black, camera outages shaded) and Euclidean error over time.",
            )
        )
        parts.append(
            _img(
                figures,
                f"cdf_{slug}",
                f"{joint} error CDF",
                f"Empirical CDF of the Euclidean position error; the dashed line marks CDF {ev.p:g}.",
            )
        )
        parts.append("</section>")

    if "timeline_modes" in figures or "timeline_sources" in figures:
        parts.append('<section id="timelines"><h2>Branch and source timelines</h2>')
        parts.append(
            _img(
                figures,
                "timeline_modes",
                "filter branch timeline",
                "Active filter branch per sample and joint.",
            )
        )
        parts.append(
            _img(
                figures,
                "timeline_sources",
                "data source timeline",
                "Data source per sample and joint.",
            )
        )
        parts.append("</section>")
    if "skeleton" in figures:
        parts.append('<section id="skeleton"><h2>3-D skeleton snapshots</h2>')
        parts.append(
            _img(
                figures,
                "skeleton",
                "3-D skeleton snapshots",
                "Reference (black), estimates (legend) and, when given, the whole body (grey) at a "
                "few instants; the 3-D viewer above plays the whole recording.",
            )
        )
        parts.append("</section>")
    parts.append(
        '<p class="note">RMSE per axis and "Mean" = arithmetic mean of the three per-axis RMSEs, as in '
        "Sun et al. 2024 and Xu et al. 2023; error CDFs use the Euclidean error. Samples where the "
        "estimate or the reference is missing are excluded.</p>"
    )
    parts.append("</main></body></html>")
    return "\n".join(p for p in parts if p)
