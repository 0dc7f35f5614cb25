"""Result tables laid out like the papers', rendered for the terminal (rich), Markdown, text, HTML.

Two layouts:

* :func:`method_table` - paper A Tables 4-5: one joint, method rows x ``East | North | Up | Mean``.
* :func:`joint_method_table` - paper B Tables 3-5 (all joints in one table): ``joint x method``
  rows x ``X | Y | Z | Mean``, plus the error at CDF 0.9, the mean outside camera outages
  ("in view") and the mean and error at CDF 0.9 inside them.

Both accept the papers' own numbers (``paper=``), shown either as extra rows marked "(paper)"
or as a column next to ours. The numbers the papers report are provided as constants
(:data:`PAPER_A_RMSE_M`, :data:`PAPER_B_RMSE_M`, :data:`PAPER_A_TIME_PER_STEP_MS`; SPEC §14).

A table is built once as a :class:`ResultTable` (plain data) and rendered by :func:`to_rich`,
:func:`to_markdown`, :func:`to_text` or :func:`to_html`.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from rich import box
from rich.markup import escape
from rich.table import Table

from kinefuse.exceptions import InputError

__all__ = [
    "PAPER_A_RMSE_M",
    "PAPER_A_TIME_PER_STEP_MS",
    "PAPER_B_RMSE_M",
    "ResultTable",
    "TableRow",
    "joint_method_table",
    "method_table",
    "timing_table",
    "to_html",
    "to_markdown",
    "to_rich",
    "to_text",
]

#: Paper A (Sun 2024) Tables 4-5, test 1, RMSE in m: ``{joint: {method: (east, north, up, mean)}}``.
PAPER_A_RMSE_M = {
    "elbow": {
        "KF": (0.178, 0.011, 0.010, 0.066),
        "FIR": (0.086, 0.014, 0.014, 0.038),
        "EM-KF/FIR": (0.086, 0.013, 0.013, 0.037),
    },
    "wrist": {
        "KF": (0.036, 0.020, 0.020, 0.025),
        "FIR": (0.069, 0.014, 0.014, 0.032),
        "EM-KF/FIR": (0.040, 0.018, 0.018, 0.025),
    },
}

#: Paper B (Xu 2023) Tables 3-5, RMSE in m: ``{joint: {method: (x, y, z, mean)}}``.
PAPER_B_RMSE_M = {
    "wrist_r": {
        "ELM/KF": (0.0959, 0.0819, 0.0292, 0.0690),
        "ELM/FIR": (0.0903, 0.0739, 0.0282, 0.0641),
    },
    "wrist_l": {
        "ELM/KF": (0.2023, 0.2103, 0.0352, 0.1493),
        "ELM/FIR": (0.0617, 0.0873, 0.0333, 0.0607),
    },
    "knee_r": {
        "ELM/KF": (0.1133, 0.2025, 0.0226, 0.1128),
        "ELM/FIR": (0.0771, 0.0880, 0.0047, 0.0566),
    },
}

#: Paper A Table 6: MATLAB run time per step, ms (mean of wrist and elbow).
PAPER_A_TIME_PER_STEP_MS = {"KF": 0.037, "FIR": 0.237, "EM-KF/FIR": 7.954}

_PAPER_MODES = ("rows", "column")


@dataclass(frozen=True)
class TableRow:
    """One table row: labels (e.g. ``(method,)`` or ``(joint, method)``) and values.

    ``None`` or NaN values render as "–". ``paper=True`` marks numbers quoted from a paper.
    """

    labels: tuple[str, ...]
    values: tuple[float | None, ...]
    paper: bool = False


@dataclass(frozen=True)
class ResultTable:
    """A renderer-independent table.

    Attributes
    ----------
    title : str
    label_headers : tuple of str
        Headers of the label columns (``("Method",)`` or ``("Joint", "Method")``).
    value_headers : tuple of str
        Headers of the numeric columns.
    rows : tuple of TableRow
    digits : int
        Decimals shown (3 like paper A, 4 like paper B).
    notes : tuple of str
        Footnotes (definitions, sample counts).
    best : bool
        Mark the smallest value of each column among a joint's rows (error and time tables);
        False where smaller is not better (angle ranges, counts, real-vs-virtual figures).
    """

    title: str
    label_headers: tuple[str, ...]
    value_headers: tuple[str, ...]
    rows: tuple[TableRow, ...]
    digits: int = 4
    notes: tuple[str, ...] = ()
    best: bool = True

    def cell(self, value) -> str:
        """Format one value."""
        if value is None:
            return "–"
        if isinstance(value, str):
            return value
        v = float(value)
        if not math.isfinite(v):
            return "–"
        text = f"{v:.{self.digits}f}"
        return text[1:] if text.startswith("-") and not text.strip("-0.") else text  # no "-0.0"


def _paper_values(paper, key, n: int) -> tuple | None:
    if paper is None or key not in paper:
        return None
    vals = tuple(paper[key])
    if len(vals) != n:
        raise InputError(
            f"paper values for {key!r}: expected {n} numbers (x, y, z, mean), got {len(vals)}"
        )
    return vals


def _check_mode(paper_mode: str) -> None:
    if paper_mode not in _PAPER_MODES:
        raise InputError(f"expected paper_mode in {_PAPER_MODES}, got {paper_mode!r}")


def method_table(
    result,
    joint: str,
    *,
    outage: bool = False,
    axis_labels: Sequence[str] = ("East", "North", "Up"),
    paper: Mapping[str, Sequence[float]] | None = None,
    paper_mode: str = "rows",
    digits: int = 3,
    include_counts: bool = False,
    title: str | None = None,
    drop_empty: bool = False,
) -> ResultTable:
    """Paper A layout (Tables 4-5): method rows x per-axis RMSE and their mean, one joint.

    Parameters
    ----------
    result : EvaluationResult
    joint : str
        Joint to tabulate.
    outage : bool
        Use only samples inside camera outages.
    axis_labels : sequence of 3 str
        Column names of the axes (paper A: East/North/Up; paper B: X/Y/Z).
    paper : mapping method -> (x, y, z, mean), optional
        The paper's numbers (m), e.g. ``PAPER_A_RMSE_M["elbow"]``.
    paper_mode : {"rows", "column"}
        ``"rows"``: a row "METHOD (paper)" after each method (methods only in the paper are
        appended); ``"column"``: one extra column "Mean (paper)".
    digits : int
        Decimals (paper A prints 3).
    include_counts : bool
        Add a column "N" with the number of samples used (methods with missing samples are
        evaluated on fewer samples).
    title : str, optional
    drop_empty : bool
        Leave out the methods with no sample here (e.g. an arm-only method at a leg joint);
        one footnote names them as not applicable.

    Returns
    -------
    ResultTable
    """
    _check_mode(paper_mode)
    headers = [f"{a} (m)" for a in axis_labels] + ["Mean (m)"]
    if paper is not None and paper_mode == "column":
        headers.append("Mean, paper (m)")
    if include_counts:
        headers.append("N")
    rows, empty = _method_rows(
        result, joint, outage, paper, paper_mode, include_counts, drop_empty, len(headers) - 4
    )
    where = "inside camera outages" if outage else "all samples"
    notes = ["Mean = arithmetic mean of the three per-axis RMSEs (as in the papers)."]
    if empty:
        notes.append(_not_applicable(empty, f"at {joint}" + (" inside outages" if outage else "")))
    return ResultTable(
        title=title or f"RMSE at {joint}, {where}",
        label_headers=("Method",),
        value_headers=tuple(headers),
        rows=tuple(rows),
        digits=digits,
        notes=tuple(notes),
    )


def _method_rows(result, joint, outage, paper, paper_mode, include_counts, drop_empty, n_pad):
    """Rows of :func:`method_table` and the methods left out for having no sample."""
    pad = (None,) * n_pad
    rows = []
    empty = []
    for method in result.methods:
        r = result.row(method, joint, outage=outage)
        if drop_empty and r["n_samples"] == 0:
            empty.append(method)
            continue
        vals = [r[a] for a in result.axes] + [r["mean"]]
        pv = _paper_values(paper, method, 4)
        if paper is not None and paper_mode == "column":
            vals.append(pv[3] if pv else None)
        if include_counts:
            vals.append(str(r["n_samples"]))
        rows.append(TableRow((method,), tuple(vals)))
        if pv and paper_mode == "rows":
            rows.append(TableRow((f"{method} (paper)",), pv + pad, paper=True))
    if paper is not None and paper_mode == "rows":
        for method in paper:
            if method not in result.methods:
                rows.append(
                    TableRow(
                        (f"{method} (paper)",), _paper_values(paper, method, 4) + pad, paper=True
                    )
                )
    return rows, empty


def _not_applicable(methods: Sequence[str], where: str) -> str:
    return f"Not applicable {where}: {', '.join(methods)} (no estimate there)."


def joint_method_table(
    result,
    *,
    joints: Sequence[str] | None = None,
    axis_labels: Sequence[str] = ("X", "Y", "Z"),
    paper: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
    paper_mode: str = "rows",
    include_cdf: bool = True,
    include_outage: bool | None = None,
    digits: int = 4,
    title: str | None = None,
    notes: Sequence[str] = (),
    drop_empty: bool = False,
) -> ResultTable:
    """Paper B layout (Tables 3-5 in one): joint x method rows, per-axis RMSE, mean, CDF 0.9.

    Parameters
    ----------
    result : EvaluationResult
    joints : sequence of str, optional
        Joints to include (default: all evaluated joints).
    axis_labels : sequence of 3 str
        Axis column names.
    paper : mapping joint -> method -> (x, y, z, mean), optional
        The paper's numbers (m), e.g. :data:`PAPER_B_RMSE_M`.
    paper_mode : {"rows", "column"}
        Extra "(paper)" rows, or one "Mean, paper" column.
    include_cdf : bool
        Add the error at CDF ``p`` column.
    include_outage : bool, optional
        Add the mean RMSE outside camera outages ("Mean in view"), and the mean RMSE and the
        error at ``p`` inside them (default: when outages exist).
    digits : int
        Decimals (paper B prints 4).
    title : str, optional
    notes : sequence of str
        Extra footnotes, after the column definitions (e.g. what the reference is).
    drop_empty : bool
        Leave out the joint-method rows with no sample (a footnote names them once as not
        applicable).

    Returns
    -------
    ResultTable
    """
    _check_mode(paper_mode)
    joints = tuple(result.joints if joints is None else joints)
    empty: dict[str, list[str]] = {}
    if include_outage is None:
        include_outage = result.has_outages
    pct = f"{result.p:g}"
    headers = [*axis_labels, "Mean"]
    if include_cdf:
        headers.append(f"@CDF {pct}")
    if include_outage:
        headers += ["Mean in view", "Mean out"] + ([f"@CDF {pct} out"] if include_cdf else [])
    if paper is not None and paper_mode == "column":
        headers.append("Mean paper")
    n_extra = len(headers) - 4
    rows = []
    for joint in joints:
        jp = paper.get(joint) if paper is not None else None
        rows += _joint_rows(
            result, joint, jp, paper is not None, paper_mode, include_cdf, include_outage,
            drop_empty, n_extra, empty,
        )  # fmt: skip
    return ResultTable(
        title=title or "RMSE per joint and method (m)",
        label_headers=("Joint", "Method"),
        value_headers=tuple(headers),
        rows=tuple(rows),
        digits=digits,
        notes=(*_joint_method_notes(result, pct, include_cdf, include_outage, empty), *notes),
    )


def _joint_rows(
    result,
    joint,
    jp,
    has_paper,
    paper_mode,
    include_cdf,
    include_outage,
    drop_empty,
    n_extra,
    empty,
) -> list[TableRow]:
    """The rows of one joint in :func:`joint_method_table` (``empty`` collects left-out methods)."""
    rows = []
    for method in result.methods:
        r = result.row(method, joint)
        if drop_empty and r["n_samples"] == 0:
            empty.setdefault(method, []).append(joint)
            continue
        vals = _joint_values(result, method, joint, r, include_cdf, include_outage)
        pv = _paper_values(jp, method, 4)
        if has_paper and paper_mode == "column":
            vals.append(pv[3] if pv else None)
        rows.append(TableRow((joint, method), tuple(vals)))
        if pv and paper_mode == "rows":
            rows.append(
                TableRow((joint, f"{method} (paper)"), tuple(pv) + (None,) * n_extra, paper=True)
            )
    if jp is not None and paper_mode == "rows":
        for method in jp:
            if method not in result.methods:
                pv = _paper_values(jp, method, 4)
                rows.append(
                    TableRow(
                        (joint, f"{method} (paper)"), tuple(pv) + (None,) * n_extra, paper=True
                    )
                )
    return rows


def _joint_values(result, method, joint, r, include_cdf, include_outage) -> list:
    """One joint-method row's values: axes, mean, then CDF and outage columns as asked."""
    vals = [r[a] for a in result.axes] + [r["mean"]]
    if include_cdf:
        vals.append(r["error_at_p"])
    if include_outage:
        vals.append(result.row(method, joint, in_view=True)["mean"])
        ro = result.row(method, joint, outage=True)
        vals.append(ro["mean"])
        if include_cdf:
            vals.append(ro["error_at_p"])
    return vals


def _joint_method_notes(result, pct, include_cdf, include_outage, empty) -> list[str]:
    """Footnotes of :func:`joint_method_table`: column definitions, methods not applicable."""
    foot = [
        "All values in m. Mean = arithmetic mean of the three per-axis RMSEs (as in the papers)."
    ]
    if include_cdf:
        foot.append(
            f"@CDF {pct} = Euclidean position error not exceeded by {result.p:.0%} of the samples."
        )
    if include_outage:
        foot.append(
            "in view = only samples outside camera outages (the camera sees the joint); "
            "out = only samples inside camera outages."
        )
    by_joints: dict[tuple[str, ...], list[str]] = {}
    for method, js in empty.items():
        by_joints.setdefault(tuple(js), []).append(method)
    for js, methods in by_joints.items():
        foot.append(_not_applicable(methods, "at " + ", ".join(js)))
    return foot


def timing_table(
    result, *, paper: Mapping[str, float] | None = None, digits: int = 3
) -> ResultTable:
    """Run time per time step like paper A Table 6 (ms), optionally next to the paper's numbers."""
    headers = ["Total (s)", "Per step (ms)"] + (
        ["Per step, paper (ms)"] if paper is not None else []
    )
    rows = []
    for method in result.methods:
        if method not in result.run_time_s:
            continue
        vals = [result.run_time_s[method], result.time_per_step_ms(method)]
        if paper is not None:
            vals.append(paper.get(method))
        rows.append(TableRow((method,), tuple(vals)))
    return ResultTable(
        title="Run time",
        label_headers=("Method",),
        value_headers=tuple(headers),
        rows=tuple(rows),
        digits=digits,
        notes=(
            "Per step = all joints of one time step; the paper's numbers are MATLAB, per joint.",
        )
        if paper is not None
        else (),
    )


# --------------------------------------------------------------------------------------------
# renderers
# --------------------------------------------------------------------------------------------


def _best_per_column(table: ResultTable) -> dict[tuple[int, int], bool]:
    """Mark the smallest value of each numeric column among our rows (per joint group)."""
    best = {}
    if not table.best:
        return best
    groups: dict[tuple, list[int]] = {}
    for i, row in enumerate(table.rows):
        if not row.paper:
            groups.setdefault(row.labels[:-1], []).append(i)
    for idx in groups.values():
        if len(idx) < 2:
            continue
        for c in range(len(table.value_headers)):
            vals = [(table.rows[i].values[c], i) for i in idx]
            vals = [
                (float(v), i)
                for v, i in vals
                if v is not None and not isinstance(v, str) and math.isfinite(float(v))
            ]
            if len(vals) >= 2:
                lo = min(v for v, _ in vals)
                for v, i in vals:
                    if v == lo:
                        best[(i, c)] = True
    return best


def to_rich(table: ResultTable):
    """Render as a :class:`rich.table.Table` (paper rows dim italic, best value per column bold).

    Titles, labels and notes are text, not rich markup: a label such as
    ``"EM-KF/FIR [calibrated on reference]"`` prints as written (unescaped, rich took the
    bracket for a style tag and printed nothing of it).
    """
    t = Table(
        title=escape(table.title),
        caption=escape("\n".join(table.notes)) or None,
        caption_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
    )
    # a narrow terminal wraps the labels (long "[calibrated on ...]" tags), never the numbers:
    # each value column keeps the width of its widest cell and header word
    for h in table.label_headers:
        t.add_column(escape(h), overflow="fold")
    for c, h in enumerate(table.value_headers):
        cells = [table.cell(r.values[c]) for r in table.rows if c < len(r.values)]
        need = max([len(x) for x in cells] + [len(w) for w in h.split()] + [1])
        t.add_column(escape(h), justify="right", no_wrap=True, min_width=need)
    best = _best_per_column(table)
    previous = None
    for i, row in enumerate(table.rows):
        labels = [escape(x) for x in row.labels]
        if len(labels) > 1 and previous is not None and labels[0] == previous:
            labels[0] = ""
        else:
            previous = labels[0] if len(labels) > 1 else None
        cells = []
        for c, v in enumerate(row.values):
            s = table.cell(v)
            s = escape(s)
            cells.append(f"[bold green]{s}[/]" if best.get((i, c)) else s)
        t.add_row(*labels, *cells, style="dim italic" if row.paper else None)
    return t


def to_markdown(table: ResultTable) -> str:
    """Render as a GitHub-flavoured Markdown table with the title as a bold caption."""
    head = [*table.label_headers, *table.value_headers]
    lines = [f"**{table.title}**", "", "| " + " | ".join(head) + " |"]
    lines.append(
        "|"
        + "|".join(["---"] * len(table.label_headers) + ["---:"] * len(table.value_headers))
        + "|"
    )
    for row in table.rows:
        cells = [*row.labels, *(table.cell(v) for v in row.values)]
        if row.paper:
            cells = [f"*{c}*" if c != "–" else c for c in cells]
        lines.append("| " + " | ".join(cells) + " |")
    if table.notes:
        lines.append("")
        lines += [f"_{n}_" for n in table.notes]
    return "\n".join(lines) + "\n"


def to_text(table: ResultTable) -> str:
    """Render as plain fixed-width text (no colour), e.g. for logs."""
    head = [*table.label_headers, *table.value_headers]
    body = [[*row.labels, *(table.cell(v) for v in row.values)] for row in table.rows]
    widths = [max(len(str(r[c])) for r in [head, *body]) for c in range(len(head))]
    nl = len(table.label_headers)

    def fmt(cells):
        return "  ".join(
            str(c).ljust(w) if i < nl else str(c).rjust(w)
            for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        )

    rule = "-" * len(fmt(head))
    out = [table.title, rule, fmt(head), rule, *(fmt(r) for r in body), rule, *table.notes]
    return "\n".join(out) + "\n"


def to_html(table: ResultTable) -> str:
    """Render as an HTML ``<table>`` (classes ``paper`` and ``best`` for styling; no scripts)."""
    e = html.escape
    best = _best_per_column(table)
    parts = ['<table class="results">', f"<caption>{e(table.title)}</caption>", "<thead><tr>"]
    parts += [f'<th scope="col">{e(h)}</th>' for h in table.label_headers]
    parts += [f'<th scope="col" class="num">{e(h)}</th>' for h in table.value_headers]
    parts.append("</tr></thead><tbody>")
    for i, row in enumerate(table.rows):
        parts.append('<tr class="paper">' if row.paper else "<tr>")
        parts += [f"<td>{e(lbl)}</td>" for lbl in row.labels]
        for c, v in enumerate(row.values):
            cls = "num best" if best.get((i, c)) else "num"
            parts.append(f'<td class="{cls}">{e(table.cell(v))}</td>')
        parts.append("</tr>")
    parts.append("</tbody></table>")
    if table.notes:
        parts.append('<p class="note">' + "<br>".join(e(n) for n in table.notes) + "</p>")
    return "".join(parts)
