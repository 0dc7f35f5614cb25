"""Figures of an evaluation: trajectories, error CDFs, branch/source timelines, 3-D skeletons.

Every function returns a :class:`matplotlib.figure.Figure` built without ``pyplot`` and rendered
with the Agg canvas, so nothing ever opens a window and no global pyplot state is touched
(safe in tests, servers and threads). :func:`figure_to_png` turns a figure into PNG bytes.

Conventions: the reference is drawn black, camera outages are shaded grey, each method keeps
one colour (and, with more than six methods, one line style) across all figures
(:func:`method_colors`, :func:`method_linestyles`). The palettes are colour-blind safe: Paul
Tol's "muted" qualitative scheme for methods (Tol 2021, https://personal.sron.nl/~pault/) and
Okabe & Ito (2008) for per-sample codes (filter branch, data source).
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the 3-D projection)
from PIL import Image
from PIL.PngImagePlugin import PngInfo

__all__ = [
    "cdf_figure",
    "code_colors",
    "figure_to_png",
    "method_colors",
    "method_linestyles",
    "outage_runs",
    "rmse_bar_figure",
    "short_method_labels",
    "skeleton_figure",
    "timeline_figure",
    "trajectory_figure",
    "with_caption",
]

#: Paul Tol's "muted" qualitative palette (colour-blind safe), one colour per method.
TOL_MUTED = (
    "#332288",
    "#CC6677",
    "#117733",
    "#88CCEE",
    "#882255",
    "#999933",
    "#44AA99",
    "#AA4499",
    "#DDCC77",
)
#: Okabe & Ito (2008) colours (black left out), one per code of a timeline / joint source.
OKABE_ITO = ("#0072B2", "#E69F00", "#CC79A7", "#009E73", "#D55E00", "#56B4E9", "#F0E442")
_LINESTYLES = ("-", (0, (5, 2)), (0, (1, 1.2)), (0, (6, 2, 1.5, 2)))
_HATCHES = ("", "//", "..", "xx")
_REF_COLOR = "black"
_OUTAGE_COLOR = "#9aa3b0"  # grey: outages never look like a method or a code
_BODY_COLOR = "#c3c8d1"


def method_colors(methods: Sequence[str]) -> dict[str, str]:
    """One stable colour per method (in the given order), from :data:`TOL_MUTED`."""
    return {m: TOL_MUTED[i % len(TOL_MUTED)] for i, m in enumerate(methods)}


def method_linestyles(methods: Sequence[str]) -> dict[str, object]:
    """One line style per method: solid for up to six methods, else four styles in turn.

    With more methods than colours tell apart at a glance, neighbours in the palette also
    differ in dash pattern (method i gets style ``i % 4``).
    """
    if len(methods) <= 6:
        return {m: "-" for m in methods}
    return {m: _LINESTYLES[i % len(_LINESTYLES)] for i, m in enumerate(methods)}


def code_colors(codes) -> dict[int, str]:
    """Colour per integer code (sorted order -> :data:`OKABE_ITO`), as in the 3-D viewer."""
    return {int(c): OKABE_ITO[i % len(OKABE_ITO)] for i, c in enumerate(sorted(codes))}


def _drawn(arr) -> bool:
    return bool(np.any(np.isfinite(np.asarray(arr, dtype=float))))


def _figure(width_in: float, height_in: float) -> Figure:
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def figure_to_png(
    fig: Figure, path: str | Path | None = None, *, dpi: int = 110, palette: bool = True
) -> bytes:
    """Render ``fig`` to PNG bytes (and write them to ``path`` if given).

    With ``palette`` the image is stored with an adaptive 256-colour palette (Pillow, no
    dithering): plots have few distinct colours, and the file is about a third of the RGBA
    one with no visible difference.

    The pixels are those of ``fig.savefig(..., dpi=dpi)``. ``savefig`` with a layout engine
    draws a figure twice (a layout pass, then the pixels) and encodes a PNG that the palette
    step would decode again; one Agg draw does both the constrained layout and the pixels, so
    2-D figures are drawn once (the demo's 20 figures: 10.4 s -> 7.9 s, byte-identical). A 3-D
    axes places its tick labels from the draw before, so figures with one go through
    ``savefig``.
    """
    img = _rgba(fig, dpi)
    out = io.BytesIO()
    if palette:
        img = img.convert("RGB")
        img = img.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
        img.save(out, format="PNG")  # optimize=True: 7 % smaller, 8x slower to write
    else:
        info = PngInfo()
        info.add_text("Software", "kinefuse")
        img.save(out, format="PNG", pnginfo=info)
    data = out.getvalue()
    if path is not None:
        Path(path).write_bytes(data)
    return data


def _rgba(fig: Figure, dpi: float) -> Image.Image:
    """``fig`` rendered at ``dpi`` as an RGBA image (``fig``'s own dpi is kept)."""
    if any(ax.name == "3d" for ax in fig.axes):
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi)
        return Image.open(io.BytesIO(buf.getvalue())).convert("RGBA")
    dpi0 = fig.dpi
    fig.set_dpi(dpi)
    try:
        canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
        canvas.draw()
        size = canvas.get_width_height(physical=True)
        return Image.frombuffer("RGBA", size, canvas.buffer_rgba(), "raw", "RGBA", 0, 1).copy()
    finally:
        fig.set_dpi(dpi0)


def outage_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs of True in a 1-D boolean mask as ``[(start, stop), ...]`` (stop exclusive)."""
    m = np.asarray(mask, dtype=bool).ravel()
    if m.size == 0:
        return []
    d = np.diff(np.concatenate(([0], m.astype(np.int8), [0])))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def _shade(ax, t_s: np.ndarray, mask, label: bool = False) -> None:
    if mask is None:
        return
    dt = float(np.median(np.diff(t_s))) if t_s.size > 1 else 0.0
    for i, (a, b) in enumerate(outage_runs(mask)):
        ax.axvspan(
            t_s[a],
            t_s[b - 1] + dt,
            color=_OUTAGE_COLOR,
            alpha=0.25,
            lw=0,
            label="camera outage" if (label and i == 0) else None,
        )


def trajectory_figure(
    t_s,
    reference,
    estimates: Mapping[str, np.ndarray],
    *,
    outage=None,
    measurement=None,
    joint: str = "",
    axis_labels: Sequence[str] = ("East", "North", "Up"),
    colors: Mapping[str, str] | None = None,
    dotted: Sequence[str] = (),
    linestyles: Mapping[str, object] | None = None,
) -> Figure:
    """Positions of one joint per axis (reference, each method) and the error over time.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Time, s.
    reference : array_like, shape (T, 3)
        Reference positions, m (NaN gaps are left blank).
    estimates : mapping of str -> array_like, shape (T, 3)
        Positions of each method, m.
    outage : array_like of bool, shape (T,), optional
        Camera outages, shaded.
    measurement : array_like, shape (T, 3), optional
        Raw input (e.g. camera) drawn as grey dots.
    joint : str
        Joint name for the title.
    axis_labels : sequence of 3 str
    colors : mapping method -> colour, optional
    dotted : sequence of str
        Methods drawn as small dots instead of lines (raw, noisy inputs).
    linestyles : mapping method -> matplotlib line style, optional
        Default :func:`method_linestyles`.

    Returns
    -------
    Figure
        Four stacked panels: one per axis and the Euclidean error of each method. Methods
        without any estimate at this joint are neither drawn nor in the legend; the legend
        lists exactly what is drawn.
    """
    t = np.asarray(t_s, dtype=float)
    ref = np.asarray(reference, dtype=float)
    colors = dict(colors or method_colors(list(estimates)))
    styles = dict(linestyles or method_linestyles(list(estimates)))
    estimates = {m: e for m, e in estimates.items() if _drawn(e)}
    if measurement is not None and not _drawn(measurement):
        measurement = None
    fig = _figure(10, 8.2)
    axs = fig.subplots(4, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1, 1, 0.9]})
    for a, ax in enumerate(axs[:3]):
        _axis_panel(ax, a, t, ref, estimates, measurement, outage, colors, styles, dotted)
        ax.set_ylabel(f"{axis_labels[a]} (m)")
    _error_panel(axs[3], t, ref, estimates, outage, colors, styles, dotted)
    handles, labels = axs[0].get_legend_handles_labels()
    short, caption = short_method_labels(labels)
    fig.legend(
        handles,
        [short[lb] for lb in labels],
        loc="outside upper center",
        ncols=min(len(labels), 6),
        frameon=False,
        markerscale=3,
        handlelength=3,
    )
    title = f"{joint}: position per axis and Euclidean error" if joint else "Position per axis"
    axs[0].set_title(with_caption(fig, title, caption), fontweight="bold")
    return fig


def _error_panel(ax, t, ref, estimates, outage, colors, styles, dotted) -> None:
    """The bottom panel of :func:`trajectory_figure`: each method's Euclidean error."""
    _shade(ax, t, outage)
    for m, est in estimates.items():
        err = np.linalg.norm(np.asarray(est) - ref, axis=-1)
        style = (
            {"ls": "none", "marker": ".", "ms": 2.5}
            if m in dotted
            else {"lw": 1.0, "ls": styles.get(m, "-")}
        )
        ax.plot(t, err, color=colors.get(m), **style)
    ax.set_ylabel("error (m)")
    ax.set_xlabel("time (s)")
    ax.grid(alpha=0.3)
    ax.set_ylim(bottom=0)


def _axis_panel(ax, a, t, ref, estimates, measurement, outage, colors, styles, dotted) -> None:
    """Axis ``a`` of :func:`trajectory_figure`: outages, camera dots, reference, methods."""
    _shade(ax, t, outage, label=(a == 0))
    if measurement is not None:
        ax.plot(
            t,
            np.asarray(measurement)[:, a],
            ".",
            color="0.35",
            ms=2.2,
            zorder=5,  # on top: the "camera only" method runs right under these dots
            label="camera (input)" if a == 0 else None,
        )
    ax.plot(t, ref[:, a], color=_REF_COLOR, lw=1.6, zorder=3, label="reference" if a == 0 else None)
    for m, est in estimates.items():
        style = (
            {"ls": "none", "marker": ".", "ms": 2.5}
            if m in dotted
            else {"lw": 1.1, "alpha": 0.9, "ls": styles.get(m, "-")}
        )
        ax.plot(t, np.asarray(est)[:, a], color=colors.get(m), label=m if a == 0 else None, **style)
    ax.grid(alpha=0.3)


def cdf_figure(
    cdfs: Mapping[str, tuple[np.ndarray, np.ndarray]],
    *,
    outage_cdfs: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
    p: float = 0.9,
    joint: str = "",
    colors: Mapping[str, str] | None = None,
    linestyles: Mapping[str, object] | None = None,
) -> Figure:
    """Empirical CDFs of the Euclidean position error, all samples and (optionally) outages only.

    Parameters
    ----------
    cdfs : mapping method -> (sorted_errors, probabilities)
        As returned by :func:`kinefuse.evaluation.metrics.error_cdf`.
    outage_cdfs : mapping method -> (sorted_errors, probabilities), optional
        The same inside camera outages (second panel).
    p : float
        CDF level marked by a dashed line; each method's error there is printed in the legend.
    joint : str
    colors : mapping method -> colour, optional

    Returns
    -------
    Figure
    """
    colors = dict(colors or method_colors(list(cdfs)))
    styles = dict(linestyles or method_linestyles(list(cdfs)))
    short, caption = short_method_labels(list(cdfs))
    panels = [("all samples", cdfs)]
    if outage_cdfs is not None and any(x.size for x, _ in outage_cdfs.values()):
        panels.append(("inside camera outages", outage_cdfs))
    fig = _figure(5.0 * len(panels) + 0.5, 4.0)
    axs = np.atleast_1d(fig.subplots(1, len(panels), sharey=True))
    for ax, (name, data) in zip(axs, panels, strict=True):
        for m, (x, prob) in data.items():
            if x.size == 0:
                continue
            k = int(np.clip(np.ceil(p * x.size - 1e-9) - 1, 0, x.size - 1))
            ax.plot(
                np.concatenate(([0.0], x)),
                np.concatenate(([0.0], prob)),
                drawstyle="steps-post",
                color=colors.get(m),
                lw=1.4,
                ls=styles.get(m, "-"),
                label=f"{short.get(m, m)}  ({x[k]:.3f} m at {p:g})",
            )
            ax.plot([x[k]], [prob[k]], "o", color=colors.get(m), ms=4)
        ax.axhline(p, color="0.4", ls="--", lw=0.8)
        ax.set_xlim(left=0)
        ax.set_ylim(0, 1.01)
        ax.set_xlabel("position error (m)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize="small", handlelength=3)
    axs[0].set_ylabel("CDF")
    fig.suptitle(with_caption(fig, f"{joint}: error CDF" if joint else "Error CDF", caption))
    return fig


def timeline_figure(
    t_s,
    codes: Mapping[str, np.ndarray],
    names: Mapping[int, str],
    joints: Sequence[str],
    *,
    outage=None,
    title: str = "Active branch per sample",
) -> Figure:
    """Which filter branch / data source each method used at each sample, per joint.

    Parameters
    ----------
    t_s : array_like, shape (T,)
    codes : mapping method -> array_like of int, shape (T, J)
        Per-sample codes (e.g. :data:`kinefuse.conventions.MODE_NAMES` keys); negative = none.
    names : mapping int -> str
        Legend names of the codes.
    joints : sequence of str, length J
    outage : array_like of bool, shape (T, J), optional
        Adds a "camera" row per joint (orange = outage).
    title : str

    Returns
    -------
    Figure
    """
    t = np.asarray(t_s, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    code_list = sorted(names)
    cmap = code_colors(code_list)
    rows = []  # (label, kind, data)
    for j, joint in enumerate(joints):
        if outage is not None:
            rows.append((f"{joint} · camera", "outage", np.asarray(outage)[:, j]))
        for m, c in codes.items():
            rows.append((f"{joint} · {m}", "code", np.asarray(c)[:, j]))
    fig = _figure(10, 0.9 + 0.32 * max(len(rows), 1))
    ax = fig.add_subplot()
    for r, (_label, kind, data) in enumerate(rows):
        y = len(rows) - 1 - r
        if kind == "outage":
            spans = [(t[a], t[b - 1] + dt - t[a]) for a, b in outage_runs(data)]
            ax.broken_barh(spans, (y - 0.35, 0.7), color=_OUTAGE_COLOR)
        else:
            for c in code_list:
                spans = [(t[a], t[b - 1] + dt - t[a]) for a, b in outage_runs(data == c)]
                if spans:
                    ax.broken_barh(spans, (y - 0.35, 0.7), color=cmap[c])
    ax.set_yticks(range(len(rows)), [lbl for lbl, _, _ in rows][::-1], fontsize="small")
    ax.set_ylim(-0.6, len(rows) - 0.4)
    if t.size:
        ax.set_xlim(t[0], t[-1] + dt)
    ax.set_xlabel("time (s)")
    used = set()
    for c in codes.values():
        used.update(np.unique(np.asarray(c)).tolist())
    handles = [Patch(color=cmap[c], label=names[c]) for c in code_list if c in used]
    if outage is not None:
        handles.append(Patch(color=_OUTAGE_COLOR, label="camera outage"))
    fig.legend(
        handles=handles, loc="outside upper center", ncols=max(len(handles), 1), frameon=False
    )
    ax.set_title(title, fontweight="bold")
    return fig


def skeleton_figure(
    reference,
    estimates: Mapping[str, np.ndarray],
    joints: Sequence[str],
    edges: Sequence[tuple[str, str]],
    instants: Sequence[int],
    *,
    t_s=None,
    colors: Mapping[str, str] | None = None,
    linestyles: Mapping[str, object] | None = None,
    body=None,
) -> Figure:
    """3-D skeleton snapshots (reference and each method) at a few sample indices.

    Parameters
    ----------
    reference : array_like, shape (T, J, 3)
    estimates : mapping method -> array_like, shape (T, J, 3)
    joints : sequence of str, length J
    edges : sequence of (str, str)
        Bones as pairs of joint names; pairs naming unknown joints are skipped.
    instants : sequence of int
        Sample indices to draw (one 3-D panel each).
    t_s : array_like, shape (T,), optional
        For panel titles.
    colors : mapping method -> colour, optional
    linestyles : mapping method -> line style, optional
    body : (names, positions (T, K, 3), edges), optional
        Whole-body context (e.g. every joint of the reference) drawn light grey; the
        evaluated limbs are attached to it (a bone from a body joint to an evaluated joint
        is drawn for the reference and each method).

    Returns
    -------
    Figure
        One panel per instant (two rows when there are more than three), the axes equal
        and fitted to the whole body, a legend of exactly the series drawn.
    """
    ref = np.asarray(reference, dtype=float)
    colors = dict(colors or method_colors(list(estimates)))
    styles = dict(linestyles or method_linestyles(list(estimates)))
    index = {n: i for i, n in enumerate(joints)}
    bones = [(index[a], index[b]) for a, b in edges if a in index and b in index]
    ctx = _body_context(body, index)
    instants = list(instants)
    n = max(len(instants), 1)
    ncols = n if n <= 3 else (n + 1) // 2
    nrows = 1 if n <= 3 else 2
    fig = _figure(5.0 * ncols, 5.2 * nrows + 0.8)
    pts = [ref[k] for k in instants] + [
        np.asarray(e)[k] for e in estimates.values() for k in instants
    ]
    if ctx.pos is not None:
        pts += [ctx.pos[k] for k in instants]
    allp = np.concatenate([p[np.all(np.isfinite(p), axis=-1)] for p in pts] or [np.zeros((1, 3))])
    if allp.size == 0:
        allp = np.zeros((1, 3))
    center = 0.5 * (allp.min(0) + allp.max(0))
    half = max(float((allp.max(0) - allp.min(0)).max()) / 2, 0.05) * 1.05
    series = [("reference", ref, _REF_COLOR, 2.4, "-")] + [
        (m, np.asarray(e), colors.get(m), 1.5, styles.get(m, "-"))
        for m, e in estimates.items()
        if _drawn(e)
    ]
    for p_i, k in enumerate(instants):
        ax = fig.add_subplot(nrows, ncols, p_i + 1, projection="3d")
        _snapshot(ax, k, p_i == 0, series, bones, ctx)
        _cube_axes(ax, center, half)
        ax.set_title(f"t = {float(np.asarray(t_s)[k]):.2f} s" if t_s is not None else f"sample {k}")
    handles, labels = fig.axes[0].get_legend_handles_labels() if fig.axes else ([], [])
    short, caption = short_method_labels(labels)
    fig.legend(
        handles, [short[lb] for lb in labels], loc="outside lower center",
        ncols=min(len(labels), 5), frameon=False, handlelength=3,
    )  # fmt: skip
    fig.suptitle(with_caption(fig, "Skeleton snapshots", caption), fontweight="bold")
    return fig


class _BodyContext(NamedTuple):
    """Whole-body context of :func:`skeleton_figure`: positions (T, K, 3), its own bones and
    the bones from a context joint to an evaluated joint (drawn per series)."""

    pos: np.ndarray | None
    bones: list[tuple[int, int]]
    attach: list[tuple[int, int]]


def _body_context(body, index: dict[str, int]) -> _BodyContext:
    if body is None:
        return _BodyContext(None, [], [])
    b_names, b_pos, b_edges = body
    b_pos = np.asarray(b_pos, dtype=float)
    bi = {n: i for i, n in enumerate(b_names)}
    b_bones = [
        (bi[a], bi[b])
        for a, b in b_edges
        if a in bi and b in bi and not (a in index and b in index)
    ]
    # bones from a context joint (not evaluated) to an evaluated joint: drawn per series
    attach = [(bi[a], index[b]) for a, b in b_edges if a in bi and a not in index and b in index]
    attach += [(bi[b], index[a]) for a, b in b_edges if b in bi and b not in index and a in index]
    return _BodyContext(b_pos, b_bones, attach)


def _snapshot(ax, k: int, first: bool, series, bones, ctx: _BodyContext) -> None:
    """One 3-D panel at sample ``k``: the body context, then each series' bones and joints."""
    b_bones = ctx.bones
    if ctx.pos is not None:
        q = ctx.pos[k]
        for a, b in b_bones:
            ax.plot(*zip(q[a], q[b], strict=True), color=_BODY_COLOR, lw=3.0, solid_capstyle="round",
                    label="whole body (reference)" if (first and (a, b) == b_bones[0]) else None)  # fmt: skip
    for name, arr, col, lw, ls in series:
        p = arr[k]
        for a, b in bones:
            ax.plot(*zip(p[a], p[b], strict=True), color=col, lw=lw, ls=ls)
        if ctx.pos is not None:
            for a, b in ctx.attach:
                ax.plot(*zip(ctx.pos[k, a], p[b], strict=True), color=col, lw=lw, ls=ls)
        ax.scatter(*p.T, color=col, s=16 if name == "reference" else 9, depthshade=False)
        if first:
            ax.plot([], [], color=col, lw=lw, ls=ls, marker="o", ms=3, label=name)


def _cube_axes(ax, center, half: float) -> None:
    """Equal 3-D axes of half-width ``half`` about ``center``, a fixed view, small labels."""
    ax.set_xlim(center[0] - half, center[0] + half)
    ax.set_ylim(center[1] - half, center[1] + half)
    ax.set_zlim(center[2] - half, center[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=12, azim=-60)
    ax.set_xlabel("x (m)", fontsize="small")
    ax.set_ylabel("y (m)", fontsize="small")
    ax.set_zlabel("z, up (m)", fontsize="small")
    ax.tick_params(labelsize="x-small")


def short_method_labels(methods: Sequence[str], wrap: int = 0) -> tuple[dict[str, str], str]:
    """Short labels of ``methods`` ("IMU only [calibrated on ..., ...]") for ticks and legends,
    and a caption for what they leave out.

    When every method that carries a bracketed tag carries the same one, the labels are the
    names and the caption gives the tag once: "every estimate: [tag]", or, when some methods
    (e.g. the reference) have none, the tagged names end in " *" and the caption is
    "* [tag]". Otherwise the labels keep their tags (on new lines of at most ``wrap``
    characters if ``wrap``) and the caption is empty."""
    parts = {m: (m.split(" [", 1) + [""])[:2] for m in methods}
    tags = {tag.rstrip("]") for _, tag in parts.values() if tag}
    if len(tags) == 1:
        (common,) = tags
        every = all(tag for _, tag in parts.values())
        labels = {m: name + ("" if every or not tag else " *") for m, (name, tag) in parts.items()}
        return labels, (f"every estimate: [{common}]" if every else f"* [{common}]")
    labels = {}
    for m, (name, tag) in parts.items():
        own = tag.rstrip("]")
        if own and wrap:
            labels[m] = name + "\n" + "\n".join(textwrap.wrap(f"[{own}]", wrap))
        else:
            labels[m] = m
    return labels, ""


def with_caption(fig: Figure, title: str, caption: str) -> str:
    """``title`` with ``caption`` on the lines below it (none when empty), wrapped to the
    figure's width (about 8 characters of a bold 10-pt title per inch)."""
    width = max(30, int(8 * fig.get_figwidth()))
    return title + "".join("\n" + ln for ln in textwrap.wrap(caption, width)) if caption else title


def rmse_bar_figure(result, *, colors: Mapping[str, str] | None = None) -> Figure:
    """Grouped bars of the papers' mean RMSE per joint and method (overall and in outages).

    A method with no estimate at a joint gets no bar there (not a zero bar); with more than
    six methods the bars are also hatched (one pattern per line style of
    :func:`method_linestyles`).
    """
    colors = dict(colors or method_colors(result.methods))
    many = len(result.methods) > 6
    short, common = short_method_labels(result.methods, wrap=40)
    panels = [("all samples", result.mean_rmse)]
    if result.has_outages:
        panels.append(("inside camera outages", result.mean_rmse_outage))
    J, M = len(result.joints), len(result.methods)
    fig = _figure(max(5.0, 1.1 * J * len(panels) + 3), 3.8)
    axs = np.atleast_1d(fig.subplots(1, len(panels), sharey=True))
    width = 0.8 / max(M, 1)
    x = np.arange(J)
    for ax, (name, data) in zip(axs, panels, strict=True):
        for m, method in enumerate(result.methods):
            ax.bar(
                x + (m - (M - 1) / 2) * width,
                data[m],  # NaN: no bar
                width,
                color=colors.get(method),
                hatch=_HATCHES[m % len(_HATCHES)] if many else None,
                edgecolor="white" if many else None,
                lw=0,
                label=short[method],
            )
        ax.set_xticks(x, result.joints, rotation=30 if J > 4 else 0)
        ax.set_title(name)
        ax.grid(axis="y", alpha=0.3)
    axs[0].set_ylabel("mean RMSE (m)")
    axs[-1].legend(fontsize="small", ncols=2 if M > 6 else 1)
    # the shared tag once here, not in every legend entry (long tags squeezed the axes to nothing)
    fig.suptitle(with_caption(fig, "Mean RMSE per joint (mean of per-axis RMSEs)", common))
    return fig
