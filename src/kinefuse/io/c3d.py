"""C3D reader (optical motion capture) via ``ezc3d`` (optional extra ``kinefuse[c3d]``).

What becomes a joint: only markers. C3D stores modelled quantities as "points" too (Plug-in-Gait
writes joint angles, forces, moments and powers as 3-vectors); the groups ``POINT:ANGLES``,
``FORCES``, ``MOMENTS``, ``POWERS``, ``SCALARS`` and ``REACTIONS`` say which labels those are. They
are kept apart in ``metadata["c3d_other_points"]`` in their own units, never scaled to metres.
Analog channels (force plates, EMG) are kept in ``metadata["analog"]``.
"""

from __future__ import annotations

import struct
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError, FormatWarning, InputError
from kinefuse.io._checks import ZERO_RULE, finish_recording, make_metadata, zero_samples
from kinefuse.io._names import map_joints
from kinefuse.io.recording import JointStream, Recording

__all__ = ["C3D_NON_MARKER_GROUPS", "LABEL_RULES", "read_c3d"]

_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "dm": 0.1}

#: ``POINT`` parameters listing labels that are not marker positions, and the parameter naming
#: their unit.
C3D_NON_MARKER_GROUPS = {
    "ANGLES": "ANGLE_UNITS",
    "FORCES": "FORCE_UNITS",
    "MOMENTS": "MOMENT_UNITS",
    "POWERS": "POWER_UNITS",
    "SCALARS": "SCALAR_UNITS",
    "REACTIONS": "REACTION_UNITS",
}


def _check_header(path: Path) -> dict:
    """Validate the 512-byte C3D header; return the layout needed to check the file length.

    The header's 16-bit first/last-frame words are not trusted (Optotrak writes a last frame of
    1149 for 29 frames); the announced frame count is ``POINT:FRAMES``, read here from the raw
    parameter section because ezc3d silently shortens it to what a truncated file holds.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
            param_block = head[0] if head else 0
            fh.seek(max(param_block - 1, 0) * 512)
            params = fh.read(4)
            if len(params) == 4:
                params += fh.read(max(params[2] - 1, 0) * 512 + 508)
    except OSError as e:
        raise FormatError(path, f"could not read the file: {e}") from None
    if len(head) < 512 or head[1] != 0x50 or param_block < 2:
        if not head:
            found = "an empty file"
        elif len(head) < 512:
            found = f"a file of {len(head)} bytes (a C3D header block is 512)"
        else:
            found = f"first bytes 0x{head[0]:02x} 0x{head[1]:02x} (not a C3D file)"
        raise FormatError(
            path,
            f"expected a C3D header (byte 2 = 0x50, parameter block >= 2), found {found}",
            field="header",
        )
    proc = params[3] if len(params) >= 4 else 84
    endian = ">" if proc == 86 else "<"  # 84 Intel, 85 DEC, 86 MIPS (big-endian)
    words = struct.unpack(endian + "9H", head[2:20])
    if proc == 85:  # DEC F-float: the sign is bit 7 of the second byte
        scale_negative = bool(head[13] & 0x80)
    else:
        scale_negative = struct.unpack(endian + "f", head[12:16])[0] < 0
    frames = _raw_point_frames(params, endian, proc == 85)
    return {
        "data_start": words[7],
        "word_bytes": 4 if scale_negative else 2,
        "points": words[0],
        "analogs": words[1],
        "frames": frames if frames is not None else words[3] - words[2] + 1,
        "frames_from": "POINT:FRAMES" if frames is not None else "the header",
    }


def _raw_point_frames(params: bytes, endian: str, dec: bool) -> int | None:
    """``POINT:FRAMES`` from the raw C3D parameter section (None when absent or unreadable)."""
    try:
        pos, groups, found = 4, {}, []
        while pos + 2 <= len(params):
            nchar, gid = struct.unpack("bb", params[pos : pos + 2])
            if nchar == 0:
                break
            name = params[pos + 2 : pos + 2 + abs(nchar)].decode("ascii", "replace").upper()
            p = pos + 2 + abs(nchar)
            (offset,) = struct.unpack(endian + "h", params[p : p + 2])
            if gid < 0:
                groups[-gid] = name
            elif name == "FRAMES":
                found.append((gid, p + 2))
            if offset <= 0:
                break
            pos = p + offset
        for gid, q in found:
            if groups.get(gid) != "POINT":
                continue
            kind, ndims = struct.unpack("bB", params[q : q + 2])
            v = q + 2 + ndims
            if kind == 2:
                return struct.unpack(endian + "H", params[v : v + 2])[0]
            if kind == 4:
                raw = params[v : v + 4]
                if dec:
                    return int(round(struct.unpack("<f", raw[2:4] + raw[0:2])[0] / 4.0))
                return int(round(struct.unpack(endian + "f", raw)[0]))
    except (struct.error, ValueError):
        return None
    return None


def _check_size(path: Path, layout: dict) -> int | None:
    """Compare the file length with the announced frames (ezc3d does not detect truncation).

    Returns None when the announced frames fit, else the number of whole frames the data section
    holds when it ends exactly on a frame boundary (the Optotrak writer announces 1149 frames and
    writes 29: read them, as ezc3d does); a data section ending inside a frame is a truncated file.
    """
    n_frames, n_points, n_analog = layout["frames"], layout["points"], layout["analogs"]
    start = (layout["data_start"] - 1) * 512
    frame_bytes = (4 * n_points + n_analog) * layout["word_bytes"]
    expected = start + n_frames * frame_bytes
    size = path.stat().st_size
    if n_frames <= 0 or size >= expected or frame_bytes == 0:
        return None
    whole, rest = divmod(max(size - start, 0), frame_bytes)
    if rest or whole == 0:
        raise FormatError(
            path,
            f"truncated C3D: {layout['frames_from']} announces {n_frames} frames of {n_points} points and "
            f"{n_analog} analog samples ({expected} bytes), file has {size} bytes (ends inside frame "
            f"{whole + 1})",
            field="data",
        )
    return int(whole)


def _strings(group: dict, name: str) -> list[str]:
    """A parameter's string values, continued in ``NAME2``, ``NAME3`` ... (C3D's 255 limit)."""
    out: list[str] = []
    k = 1
    while True:
        key = name if k == 1 else f"{name}{k}"
        if key not in group:
            return out
        out += [str(s).strip() for s in np.asarray(group[key]["value"]).reshape(-1)]
        k += 1


def _first(group: dict, name: str, default=None):
    if name not in group:
        return default
    v = np.asarray(group[name]["value"]).reshape(-1)
    return v[0] if v.size else default


def _unique_labels(labels: list[str], prefix: str) -> tuple[list[str], list[str]]:
    """Empty labels -> ``<prefix><n>`` (1-based index); repeated labels -> ``<label>_2``, ``_3``..."""
    notes = []
    out = []
    for i, lab in enumerate(labels):
        if not lab:
            lab = f"{prefix}{i + 1}"
            notes.append(f"{prefix.rstrip('_')} {i + 1} has an empty label; named {lab!r}")
        out.append(lab)
    seen: Counter = Counter()
    total = Counter(out)
    for i, lab in enumerate(out):
        if total[lab] > 1:
            seen[lab] += 1
            if seen[lab] > 1:
                new = f"{lab}_{seen[lab]}"
                while new in total:
                    new += "_"
                notes.append(f"label {lab!r} repeated; occurrence {seen[lab]} named {new!r}")
                out[i] = new
    return out, notes


def read_c3d(
    path,
    *,
    role: str = "reference",
    units: str | None = None,
    zero_is_missing_points: bool = True,
    analog: bool = True,
) -> Recording:
    """Read the marker positions (and, kept apart, the other points and analog channels) of a C3D.

    Parameters
    ----------
    path : str or Path
        ``.c3d`` file.
    role : {"reference", "vision"}
        Where the markers go in the Recording (optical mocap is usually the reference).
    units : str or None
        Override of the ``POINT:UNITS`` parameter (``mm``, ``cm``, ``m``).
    zero_is_missing_points : bool
        Treat a marker whose three coordinates are all exactly 0 as missing
        (:data:`kinefuse.io._checks.ZERO_RULE`).
    analog : bool
        Keep the analog channels in ``metadata["analog"]``.

    Returns
    -------
    Recording
        ``reference`` (or ``vision``): marker positions (T, P, 3) in m, frame ``"c3d_lab"`` (the
        file's lab frame; often z up), times ``n / POINT:RATE``, labels as :data:`LABEL_RULES`. ``available`` = finite,
        residual >= 0 (C3D marks invalid points with a negative residual) and not all zero.
        ``metadata["c3d_other_points"]``: ``{group: {"labels", "values" (T, K, 3), "unit"}}``
        (file units, e.g. deg, N, N.mm, W), not joints. ``metadata["analog"]`` (when
        ``analog``): ``{"t_s" (N,), "values" (N, C), "labels", "units", "rate_hz"}``, values
        as ezc3d scales them (``ANALOG:SCALE``, ``GEN_SCALE``, ``OFFSET`` applied).

    Raises
    ------
    FormatError
        Not a C3D file, truncated data, unknown units, fewer labels than ``POINT:USED``.
    ImportError
        ``ezc3d`` is not installed (``pip install kinefuse[c3d]``).
    """
    path = Path(path)
    if role not in ("reference", "vision"):
        raise InputError(f"expected role 'reference' or 'vision', got {role!r}")
    c, pts, notes = _open(path)
    original, labels = _point_labels(path, point := c["parameters"]["POINT"], pts.shape[1], notes)
    unit, factor = _point_unit(path, point, units)
    rate = _point_rate(path, point)
    raw = np.transpose(pts[:3], (2, 1, 0))  # (T, P, 3), file units
    valid = _valid_points(c, raw)
    other, non_marker = _non_marker_points(point, original, labels, raw, valid, notes)
    keep = np.flatnonzero(~non_marker)
    pos = raw[:, keep] * factor  # the markers, m
    zero, n_zero = zero_samples(pos, zero_is_missing_points)
    avail = valid[:, keep] & ~zero
    joints, jmap = map_joints([labels[i] for i in keep])
    js = JointStream(
        t_s=np.arange(len(raw)) / rate,
        position_m=pos,
        available=avail,
        joints=joints,
        frame="c3d_lab",
    )
    md = make_metadata(
        path,
        "c3d",
        units_converted=[f"points {unit} -> m"] if factor != 1.0 else [],
        joint_map=jmap,
        rate_hz=rate,
        first_frame=int(c["header"]["points"]["first_frame"]),
        availability_rule="finite and residual >= 0"
        + (f"; {ZERO_RULE}" if zero_is_missing_points else ""),
        n_zero_samples=n_zero,
        c3d_other_points=other,
        notes=notes,
    )
    if analog:
        md["analog"] = _analog(c, path)
    return finish_recording(path, md, **{role: js})


#: How :func:`read_c3d` names the points: the first ``POINT:USED`` of ``POINT:LABELS``
#: (continued in ``LABELS2``...); an empty label becomes ``point_<n>`` (1-based), the 2nd, 3rd
#: ... occurrence of a repeated label ``<label>_2``, ``<label>_3``. Labels that name a joint
#: (canonical names, Kinect-style ``ShoulderLeft``, Plug-in-Gait joint centres ``LFEO``...)
#: become canonical joint names; others are kept (``metadata["joint_map"]``).
LABEL_RULES = (
    "first POINT:USED labels; empty -> point_<n>; repeated -> <label>_2 ...; joints mapped"
)


def _open(path: Path):
    """(ezc3d object, points (4, P, T), notes) after checking the header and the file length."""
    layout = _check_header(path)
    whole = _check_size(path, layout)
    try:
        import ezc3d  # optional dependency (kinefuse[c3d])
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("reading C3D needs ezc3d: pip install 'kinefuse[c3d]'") from e
    try:
        c = ezc3d.c3d(str(path))
    except Exception as e:
        raise FormatError(path, f"ezc3d could not parse the file: {e}") from None
    pts = np.asarray(c["data"]["points"], dtype=float)  # (4, P, T)
    if pts.ndim != 3 or pts.shape[0] != 4:
        raise FormatError(path, f"expected points (4, P, T), found {pts.shape}", field="POINT")
    notes = []
    if whole is not None:
        if pts.shape[2] != whole:
            raise FormatError(
                path,
                f"expected {whole} whole frames in the data section, ezc3d read {pts.shape[2]}",
                field="data",
            )
        msg = (
            f"{path}: {layout['frames_from']} announces {layout['frames']} frames but the data section holds "
            f"{whole} whole frames; read them (as ezc3d does)"
        )
        warnings.warn(msg, FormatWarning, stacklevel=3)
        notes.append(msg)
    return c, pts, notes


def _point_labels(path: Path, point, n_points: int, notes: list[str]):
    """(the first USED labels as in the file, the same made unique) of the ``POINT`` group."""
    used = int(_first(point, "USED", n_points))
    all_labels = _strings(point, "LABELS")
    if used != n_points or len(all_labels) < used:
        raise FormatError(
            path,
            f"expected POINT:USED = {n_points} points with at least as many labels, found "
            f"USED = {used} and {len(all_labels)} labels",
            field="POINT:LABELS",
        )
    if len(all_labels) > used:
        notes.append(f"POINT:LABELS has {len(all_labels)} entries; the first USED = {used} read")
    labels, label_notes = _unique_labels(all_labels[:used], "point_")
    notes += label_notes
    return all_labels[:used], labels


def _point_unit(path: Path, point, units: str | None) -> tuple[str, float]:
    unit = units
    if unit is None:
        unit = str(_first(point, "UNITS", "mm")).strip() or "mm"
    factor = _TO_M.get(unit.lower())
    if factor is None:
        raise FormatError(
            path,
            f"expected POINT:UNITS one of {sorted(_TO_M)}, found {unit!r}",
            field="POINT:UNITS",
        )
    return unit, factor


def _point_rate(path: Path, point) -> float:
    rate = float(_first(point, "RATE", 0.0))
    if not rate > 0:
        raise FormatError(path, f"expected a positive POINT:RATE, found {rate}", field="POINT:RATE")
    return rate


def _valid_points(c, raw: np.ndarray) -> np.ndarray:
    """Finite samples with a residual >= 0 where the file has residuals, (T, P)."""
    T, P = raw.shape[:2]
    valid = np.all(np.isfinite(raw), axis=-1)
    res = c["data"]["meta_points"].get("residuals") if "meta_points" in c["data"] else None
    if res is not None and np.asarray(res).shape == (1, P, T):
        valid &= np.asarray(res)[0].T >= 0
    return valid


def _non_marker_points(point, original, labels, raw, valid, notes: list[str]):
    """The points of :data:`C3D_NON_MARKER_GROUPS` by group, and the mask of those points."""
    other: dict[str, dict] = {}
    non_marker = np.zeros(len(original), dtype=bool)
    for grp, unit_key in C3D_NON_MARKER_GROUPS.items():
        names = {s for s in _strings(point, grp) if s}
        idx = [i for i, s in enumerate(original) if s in names and not non_marker[i]]
        if not idx:
            continue
        non_marker[idx] = True
        vals = np.where(valid[:, idx, None], raw[:, idx], np.nan)
        other[grp] = {
            "labels": tuple(labels[i] for i in idx),
            "values": vals,
            "unit": str(_first(point, unit_key, "")).strip(),
        }
    if other:
        notes.append(
            "not joints (kept in metadata['c3d_other_points']): "
            + ", ".join(f"{len(v['labels'])} {g.lower()}" for g, v in other.items())
        )
    return other, non_marker


def _analog(c, path: Path) -> dict | None:
    """The analog channels as ezc3d scales them, or None when the file has none."""
    group = c["parameters"].get("ANALOG", {})
    a = np.asarray(c["data"]["analogs"], dtype=float)  # (1, C, N)
    if a.ndim != 3 or a.shape[1] == 0 or a.shape[2] == 0:
        return None
    rate = float(_first(group, "RATE", 0.0))
    if not rate > 0:
        raise FormatError(
            path, f"expected a positive ANALOG:RATE, found {rate}", field="ANALOG:RATE"
        )
    C = a.shape[1]
    labels, _ = _unique_labels((_strings(group, "LABELS") + [""] * C)[:C], "analog_")
    units = (_strings(group, "UNITS") + [""] * C)[:C]
    return {
        "t_s": np.arange(a.shape[2]) / rate,
        "values": a[0].T.copy(),
        "labels": tuple(labels),
        "units": tuple(units),
        "rate_hz": rate,
    }
