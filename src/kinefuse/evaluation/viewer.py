"""The interactive 3-D skeleton viewer of the HTML report (and of ``kinefuse stream --view``).

The viewer is plain JavaScript (``_viewer/viewer.js``) on a vendored copy of three.js r187
(``vendor/three/``, MIT licence; see its README for how the bundle was made), inlined into the
page so that a report opens offline, from a file, with no network access.

:func:`report_viewer_html` builds the report's section: every series (reference, camera, each
method and an optional whole-body context skeleton) as ``int16`` positions (1 mm steps around
the recording's centre, coarser only beyond +-32 m), joints
coloured by their per-sample source code (:data:`kinefuse.conventions.SOURCE_NAMES`), thinned
to at most ``max_rate_hz`` and to a byte budget so that long recordings stay light.
:func:`viewer_assets` returns the script and style for other pages (the live view).
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Mapping, Sequence
from functools import cache
from importlib import resources

import numpy as np

from kinefuse.conventions import SOURCE_NAMES
from kinefuse.evaluation import plots
from kinefuse.exceptions import InputError

__all__ = [
    "SOURCE_COLORS",
    "THREE_VERSION",
    "downsample_stride",
    "quantization_scale",
    "quantize",
    "report_viewer_html",
    "viewer_assets",
]

#: three.js release inlined into the pages (``vendor/three/three.min.js``).
THREE_VERSION = "r187 (npm three@0.187.0)"

#: Colour of each source code (Okabe & Ito 2008 colour-blind-safe palette, as the report's
#: source timeline): :data:`kinefuse.conventions.SOURCE_NAMES`, "predicted" included (streaming's
#: ``SOURCE_PREDICT`` is that code); other codes (``-1``, no estimate) are grey.
SOURCE_COLORS = plots.code_colors(SOURCE_NAMES)

_MISSING = -32768  # int16 code of a missing (NaN) coordinate

VIEWER_CSS = """
.kf-viewer { display: flex; flex-wrap: wrap; gap: 16px; align-items: flex-start; }
.kf-main { flex: 1 1 620px; min-width: 320px; overflow: hidden; }
.kf-stage canvas { display: block; border: 1px solid var(--line, #d9dee7); border-radius: 4px;
                   cursor: grab; touch-action: none; }
.kf-side { flex: 0 1 330px; font-size: 13px; }
.kf-controls { display: flex; align-items: center; gap: 10px; margin: 8px 0; font-size: 13.5px; }
.kf-controls input[type=range] { flex: 1; }
.kf-controls button { min-width: 84px; }
.kf-time { font-variant-numeric: tabular-nums; min-width: 86px; }
ul.kf-legend { list-style: none; padding: 0; margin: 0 0 10px; }
ul.kf-legend li { margin: 2px 0; }
.kf-legend-title { color: var(--muted, #5b6475); }
.kf-swatch { display: inline-block; vertical-align: middle; }
.kf-swatch.kf-line { width: 18px; height: 4px; }
.kf-swatch.kf-dot { width: 10px; height: 10px; border-radius: 50%; }
.kf-err-table td, .kf-err-table th { padding: 1px 6px !important; }
"""


@cache
def _read(package: str, name: str) -> str:
    return resources.files(package).joinpath(name).read_text(encoding="utf-8")


def viewer_assets() -> tuple[str, str]:
    """``(script, css)``: three.js and the viewer as one script text, and the viewer's style.

    The script defines ``kinefuseReport(data)`` and ``kinefuseLive(meta)``; it contains no
    ``</script`` and loads nothing from the network.
    """
    three = _read("kinefuse.evaluation", "vendor/three/three.min.js")
    viewer = _read("kinefuse.evaluation", "_viewer/viewer.js")
    script = three + "\n" + viewer
    return script.replace("</script", "<\\/script"), VIEWER_CSS


def quantize(position_m: np.ndarray, origin_m, scale_m: float) -> str:
    """Positions as base64 little-endian ``int16`` steps of ``scale_m`` from ``origin_m``.

    Parameters
    ----------
    position_m : array_like, shape (..., 3)
        Positions, m; NaN -> -32768 (missing).
    origin_m : array_like, shape (3,)
    scale_m : float
        One step, m (:func:`quantization_scale`).

    Returns
    -------
    str
        ``round((p - origin) / scale)`` as int16, base64.
    """
    p = (np.asarray(position_m, dtype=float) - np.asarray(origin_m, dtype=float)) / scale_m
    finite = np.isfinite(p)
    q = np.where(finite, np.clip(np.round(p), -32767, 32767), _MISSING).astype("<i2")
    return base64.b64encode(q.tobytes()).decode("ascii")


def quantization_scale(arrays: Sequence[np.ndarray], origin_m) -> float:
    """1 mm, or coarser when the positions reach further than 32.767 m from ``origin_m``."""
    reach = 0.0
    for a in arrays:
        d = np.abs(np.asarray(a, dtype=float).reshape(-1, 3) - np.asarray(origin_m, dtype=float))
        d = d[np.isfinite(d)]
        if d.size:
            reach = max(reach, float(d.max()))
    return max(0.001, reach / 32767.0)


def downsample_stride(
    t_s: np.ndarray, values_per_frame: int, *, max_rate_hz: float, max_bytes: int
) -> int:
    """Keep every k-th frame: at most ``max_rate_hz`` and at most ``max_bytes`` of base64 data.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Frame times, s.
    values_per_frame : int
        ``int16`` values per frame over all series.
    max_rate_hz, max_bytes : float, int

    Returns
    -------
    int
        The stride k >= 1.
    """
    t = np.asarray(t_s, dtype=float)
    T = t.size
    if T < 2:
        return 1
    dt = float(np.median(np.diff(t)))
    k_rate = int(np.ceil(1.0 / (max_rate_hz * dt) - 1e-9)) if dt > 0 else 1
    k_bytes = int(np.ceil(T * values_per_frame * 2 * 4 / 3 / max_bytes))
    return max(1, k_rate, k_bytes)


def _bounds(arrays: Sequence[np.ndarray]) -> tuple[list[float], float]:
    pts = np.concatenate([a.reshape(-1, 3) for a in arrays])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.size == 0:
        return [0.0, 0.0, 0.0, 0.0], 1.0
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    c = 0.5 * (lo + hi)
    radius = max(float(np.max(hi - lo)) / 2, 0.2)
    floor = float(np.percentile(pts[:, 2], 0.5))
    return [float(c[0]), float(c[1]), float(c[2]), floor], radius


def _edge_index(names: Sequence[str], edges) -> list[list[int]]:
    index = {n: i for i, n in enumerate(names)}
    return [[index[a], index[b]] for a, b in edges or () if a in index and b in index]


def report_viewer_html(
    t_s: np.ndarray,
    joints: Sequence[str],
    *,
    reference: np.ndarray | None,
    estimates: Mapping[str, np.ndarray],
    colors: Mapping[str, str],
    edges: Sequence[tuple[str, str]] | None,
    dashed: Sequence[str] = (),
    sources: Mapping[str, np.ndarray] | None = None,
    camera: np.ndarray | None = None,
    body: tuple[Sequence[str], np.ndarray, Sequence[tuple[str, str]]] | None = None,
    shown: Sequence[str] | None = None,
    source_names: Mapping[int, str] = SOURCE_NAMES,
    max_rate_hz: float = 30.0,
    max_bytes: int = 1_500_000,
) -> str:
    """The report section with the interactive viewer (a ``<section>`` with inline scripts).

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Time, s.
    joints : sequence of str, length J
    reference : array_like, shape (T, J, 3), optional
        Drawn black; the per-joint error table is relative to it.
    estimates : mapping method -> array_like, shape (T, J, 3)
        Positions per method, m.
    colors : mapping method -> CSS colour
        Bone colour per method (the figures' colours).
    dashed : sequence of str
        Methods whose bones are dashed (those with a dashed line style in the figures, so that
        methods sharing a colour stay apart).
    edges : sequence of (str, str), optional
        Bones between ``joints`` (without bones the joints are drawn as points only).
    sources : mapping method -> int array, shape (T, J), optional
        Source code per sample; the joints are coloured by it (:data:`SOURCE_COLORS`).
    camera : array_like, shape (T, J, 3), optional
        The camera's positions (NaN in outages), drawn grey.
    body : (names, positions (T, K, 3), edges), optional
        A whole-body context skeleton (e.g. the reference's every joint), drawn light grey.
    shown : sequence of str, optional
        Series ticked when the page opens (default: reference, camera and the first method).
    source_names : mapping int -> str
    max_rate_hz : float
        At most this many frames per second of recording are kept.
    max_bytes : int
        Budget of the encoded positions (the frames are thinned further to stay within it).

    Returns
    -------
    str
        HTML.
    """
    t = np.asarray(t_s, dtype=float)
    series = _series(t, reference, estimates, colors, sources, camera, body)
    if shown is None:
        first = [m for m in estimates][:1]
        shown = ["whole body (reference)", "reference", "camera", *first]
    values = sum(s[2].shape[1] * 3 for s in series)
    k = downsample_stride(t, values, max_rate_hz=max_rate_hz, max_bytes=max_bytes)
    keep = np.arange(0, t.size, k)
    payload = _payload(t, keep, k, joints, edges, series, shown, dashed, source_names)
    script, _ = viewer_assets()
    data = json.dumps(payload, separators=(",", ":")).replace("</", "<\\/")
    return _section(data, script, len(keep), t, k)


def _section(data: str, script: str, n_kept: int, t: np.ndarray, k: int) -> str:
    """The viewer's ``<section>``: container, note, the JSON data and the inlined scripts."""
    rate = 1.0 / (k * float(np.median(np.diff(t)))) if t.size > 1 else 0.0
    e = html.escape
    note = (
        f"Drag to orbit, scroll to zoom, right-drag to pan. {n_kept} of {t.size} samples "
        f"shown ({rate:.0f} Hz); joints coloured by their source per sample, bones by method; "
        f"the table gives each shown method's Euclidean error per joint at the current time. "
        f"three.js {e(THREE_VERSION)}, MIT licence, inlined (works offline)."
    )
    return (
        '<section id="viewer"><h2>3-D viewer</h2>'
        '<div id="kf-viewer" class="kf-viewer"><div class="kf-main"><div class="kf-stage"></div>'
        '<div class="kf-controls"></div></div><div class="kf-side"></div></div>'
        f'<p class="note">{note}</p>'
        f'<script type="application/json" id="kf-viewer-data">{data}</script>'
        f"<script>{script}</script>"
        "<script>kinefuseReport(JSON.parse(document.getElementById('kf-viewer-data').textContent));"
        "</script></section>"
    )


def _series(t, reference, estimates, colors, sources, camera, body) -> list[tuple]:
    """The drawn series: ``(name, kind, positions (T, n, 3), colour, src, own joints, own edges)``."""
    series = []
    if body is not None:
        names, pos, bedges = body
        pos = np.asarray(pos, dtype=float)
        if pos.shape != (t.size, len(names), 3):
            raise InputError(
                f"expected body positions with shape (T, K, 3) = {(t.size, len(names), 3)}, got {pos.shape}"
            )
        series.append(
            (
                "whole body (reference)",
                "body",
                pos,
                "#b9bec8",
                None,
                list(names),
                _edge_index(names, bedges),
            )
        )
    if reference is not None:
        series.append(
            ("reference", "reference", np.asarray(reference, float), "#000000", None, None, None)
        )
    if camera is not None:
        series.append(("camera", "camera", np.asarray(camera, float), "#8a8f99", None, None, None))
    for m, est in estimates.items():
        src = None if not sources or m not in sources else np.asarray(sources[m])
        series.append(
            (m, "method", np.asarray(est, float), colors.get(m, "#444444"), src, None, None)
        )
    return series


def _payload(t, keep, k, joints, edges, series, shown, dashed, source_names) -> dict:
    """The viewer's JSON data: the kept frames, quantized positions relative to an origin."""
    center, radius = _bounds([s[2][keep] for s in series])
    origin = np.round(np.asarray(center[:3]), 1)  # positions are sent relative to it
    scale = quantization_scale([s[2][keep] for s in series], origin)
    center = [
        center[0] - origin[0],
        center[1] - origin[1],
        center[2] - origin[2],
        center[3] - origin[2],
    ]
    payload = {
        "t": [round(float(x), 4) for x in t[keep]],
        "stride": k,
        "joints": list(joints),
        "edges": _edge_index(joints, edges),
        "scale_m": scale,
        "origin_m": [float(x) for x in origin],
        "center": center,
        "radius": radius,
        "source_names": {str(c): n for c, n in source_names.items()},
        "source_colors": {str(c): SOURCE_COLORS.get(c, "#777777") for c in source_names},
        "series": [],
    }
    for name, kind, pos, col, src, own_joints, own_edges in series:
        entry = {"name": name, "kind": kind, "color": col, "visible": name in shown,
                 "pos": quantize(pos[keep], origin, scale)}  # fmt: skip
        if name in dashed and kind == "method":
            entry["dashed"] = True
        if own_joints is not None:
            entry["joints"] = own_joints
            entry["edges"] = own_edges
        if src is not None:
            codes = src[keep]  # negative (no source) -> 255: drawn in the bone colour
            codes = np.where((codes < 0) | (codes > 254), 255, codes).astype(np.uint8)
            entry["src"] = base64.b64encode(codes.tobytes()).decode("ascii")
        payload["series"].append(entry)
    return payload
