"""Joint angles in reports: a range-of-motion table and a time-series figure per joint.

:func:`range_of_motion_table` (minimum, maximum, range, mean per joint and angle, deg),
:func:`angle_extremes_table` (the same extremes, one row per joint, for the terminal),
:func:`angle_figure` (the angles over time, one panel per joint), :func:`angle_section` (both
as an HTML fragment for :func:`kinefuse.evaluation.write_report`) and
:func:`write_angle_report` (a self-contained ``report.html`` for recordings without a
reference, where there is nothing to score).
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from kinefuse import __version__
from kinefuse.evaluation import plots, tables
from kinefuse.evaluation.report import REPORT_CSS, REPORT_NAME, notes_html
from kinefuse.exceptions import InputError
from kinefuse.kinematics.angles import angle_words

__all__ = [
    "angle_extremes_table",
    "angle_figure",
    "angle_section",
    "range_of_motion_table",
    "write_angle_report",
]


#: The note of a table with a trunk row, whose three angles are not a limb joint's.
_TRUNK_NOTE = (
    "trunk (chest in pelvis; ISB spine, Wu et al. 2002): flexion = bending forward, then lateral "
    "bending (to the right positive) and axial rotation (to the left positive)"
)


def _check(t_s, angles: Mapping[str, np.ndarray]) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    for j, a in angles.items():
        if np.shape(a) != (t.size, 3):
            raise InputError(
                f"expected angles[{j!r}] with shape (T, 3) = ({t.size}, 3), got {np.shape(a)}"
            )
    return t


def _extremes(a: np.ndarray, k: int) -> tuple:
    """``(min, max, mean)`` of angle component ``k`` of ``a (T, 3)``, NaN ignored (None: none)."""
    v = a[:, k][np.isfinite(a[:, k])]
    return (float(v.min()), float(v.max()), float(v.mean())) if v.size else (None,) * 3


def range_of_motion_table(angles: Mapping[str, np.ndarray]) -> tables.ResultTable:
    """Minimum, maximum, range (max − min) and mean of each joint angle, deg (NaN ignored)."""
    rows = []
    for j, a in angles.items():
        a = np.asarray(a, dtype=float)
        for k, comp in enumerate(angle_words(j)):
            lo, hi, mean = _extremes(a, k)
            vals = (lo, hi, hi - lo, mean) if lo is not None else (None,) * 4
            rows.append(tables.TableRow(labels=(j, comp), values=vals))
    return tables.ResultTable(
        title="Range of motion per joint (deg)",
        label_headers=("Joint", "Angle"),
        value_headers=("min", "max", "range", "mean"),
        rows=tuple(rows),
        digits=1,
        best=False,  # angles: smaller is not better
        notes=(
            "ISB joint coordinate systems (Wu et al. 2002/2005; Grood & Suntay 1983): flexion "
            "about the proximal segment's medio-lateral axis, adduction about the floating axis "
            "(elbow: varus), internal rotation about the distal long axis (elbow: pronation); "
            + (
                "ankle flexion is dorsiflexion (toes up; plantarflexion negative); "
                if any(j.startswith("ankle") for j in angles)
                else ""
            )
            + "zero in the calibration pose.",
            *([_TRUNK_NOTE + "."] if "trunk" in angles else []),
        ),
    )


def angle_extremes_table(angles: Mapping[str, np.ndarray]) -> tables.ResultTable:
    """One row per joint: minimum and maximum of flexion, adduction and internal rotation, deg
    (NaN ignored): what ``kinefuse run`` prints; the report holds :func:`range_of_motion_table`."""
    rows = []
    for j, a in angles.items():
        a = np.asarray(a, dtype=float)
        rows.append(
            tables.TableRow(
                labels=(j,), values=tuple(v for k in range(3) for v in _extremes(a, k)[:2])
            )
        )
    return tables.ResultTable(
        title="Joint angles over the recording (deg)",
        label_headers=("Joint",),
        value_headers=(
            "flexion min",
            "flexion max",
            "adduction min",
            "adduction max",
            "int. rot. min",
            "int. rot. max",
        ),
        rows=tuple(rows),
        digits=1,
        best=False,  # angles: smaller is not better
        notes=(
            "ISB (Wu et al. 2002/2005), zero in the calibration pose"
            + (
                "; ankle flexion = dorsiflexion"
                if any(j.startswith("ankle") for j in angles)
                else ""
            )
            + ". Range and mean per angle, and the time series: the report.",
            *(
                [_TRUNK_NOTE + ", in the adduction and int. rot. columns."]
                if "trunk" in angles
                else []
            ),  # fmt: skip
        ),
    )


def angle_figure(t_s, angles: Mapping[str, np.ndarray]):
    """One panel per joint: flexion, adduction and internal rotation over time, deg."""
    t = _check(t_s, angles)
    n = max(len(angles), 1)
    fig = plots._figure(9.0, 1.9 * n + 0.4)
    axs = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    for ax, (j, a) in zip(axs, angles.items(), strict=False):
        for k, comp in enumerate(angle_words(j)):
            ax.plot(t, np.asarray(a)[:, k], lw=1.0 if k == 0 else 0.7, label=comp)
        ax.set_ylabel(f"{j} (deg)")
        ax.grid(alpha=0.3)
        if ax is axs[0] or j == "trunk":  # the trunk's angles have their own names
            ax.legend(loc="upper right", fontsize=8, ncols=3)
    axs[-1].set_xlabel("time (s)")
    return fig


def angle_section(t_s, angles: Mapping[str, np.ndarray], fig_dir, *, dpi: int = 100) -> str:
    """HTML fragment (``<section id="angles">``) with the table and the figure (PNG embedded,
    also written to ``fig_dir/joint_angles.png``); empty without angles."""
    if not angles:
        return ""
    fig_dir = Path(fig_dir)
    fig_dir.mkdir(parents=True, exist_ok=True)
    png = plots.figure_to_png(angle_figure(t_s, angles), fig_dir / "joint_angles.png", dpi=dpi)
    b64 = base64.b64encode(png).decode("ascii")
    return (
        '<section id="angles"><h2>Joint angles</h2>'
        + tables.to_html(range_of_motion_table(angles))
        + f'<figure><img alt="joint angles over time" src="data:image/png;base64,{b64}">'
        "<figcaption>Joint angles over time, deg (also <code>figures/joint_angles.png</code>)."
        "</figcaption></figure></section>"
    )


def write_angle_report(
    out_dir,
    t_s,
    angles: Mapping[str, np.ndarray],
    *,
    title: str = "kinefuse report",
    notes: Sequence[str] = (),
    warnings: Sequence[str] = (),
    sections: Sequence[str] = (),
    provenance: Mapping | None = None,
    force: bool = False,
    unscored: str = "no reference",
) -> Path:
    """A self-contained ``report.html`` without scores (no reference): warnings (highlighted),
    notes, ``sections`` (HTML fragments, e.g. a coverage table) and joint angles.

    Also writes ``figures/joint_angles.png`` and ``provenance.json`` (which data calibrated
    what). Refuses to overwrite ``report.html`` unless ``force`` (FileExistsError).
    ``unscored`` says in the header why there are no scores.
    """
    out = Path(out_dir)
    path = out / REPORT_NAME
    if path.exists() and not force:
        raise FileExistsError(f"{path} already exists; pass force=True (CLI: --force)")
    t = _check(t_s, angles)
    out.mkdir(parents=True, exist_ok=True)
    e = html.escape
    meta = (
        f"generated {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} by kinefuse {e(__version__)}"
        f" · {t.size} samples ({float(t[-1] - t[0]) if t.size > 1 else 0.0:.1f} s) · "
        f"{e(unscored)}: positions and angles are not scored"
    )
    parts = [
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title><style>{REPORT_CSS}</style></head><body>",
        f'<header><h1>{e(title)}</h1><div class="meta">{meta}</div></header><main>',
    ]
    parts.append(notes_html(notes, warnings))
    parts += sections
    parts.append(angle_section(t, angles, out / "figures"))
    parts.append("</main></body></html>")
    tmp = path.with_name(REPORT_NAME + ".part")
    tmp.write_text("".join(parts), encoding="utf-8")
    tmp.replace(path)
    if provenance is not None:
        (out / "provenance.json").write_text(json.dumps(provenance, indent=2), encoding="utf-8")
    return path
