"""Kinect v2 joint CSV: 25 joints + TrackingState (or LSL-Kinect confidences), wide or long layout.

Wide layout: a time column (``t_s``, ``time_ms``, ``timestamp_us``, ``RelativeTime`` in 100 ns
ticks, LSL-Kinect's ``TimeSpan`` in Unix ms ... any other with ``time_column=`` and
``time_unit=``, or ``frame`` with ``rate_hz=``) and per joint ``<Joint>_X, <Joint>_Y, <Joint>_Z``
and ``<Joint>_TrackingState`` or a confidence ``<Joint>_Conf`` (separators ``_ . : space``; joint
names as Kinect v2 ``JointType`` — ``SpineBase`` ... ``ThumbRight`` — or canonical,
case-insensitive). Long layout: columns ``time, joint, x, y, z, tracking_state`` (one row per
joint and frame). Either may have a body column (``body``/``tracking_id``...). Lines before the
header without a comment prefix (the LSL-Kinect ``Software : LSL_Kinect,...`` line) are a
preamble, kept in ``metadata["preamble"]``. See ``docs/formats.md``.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io._checks import ZERO_RULE, finish_recording, make_metadata, zero_is_missing
from kinefuse.io._names import KINECT_LIMB_JOINTS
from kinefuse.io._text import (
    TIME_COLUMNS,
    Table,
    check_time,
    read_table,
    table_time,
    time_column_s,
)
from kinefuse.io.recording import JointStream, Recording

__all__ = [
    "KINECT_V2_JOINTS",
    "KINECT_V2_TO_CANONICAL",
    "LSL_KINECT_CONFIDENCE",
    "read_kinect_v2_csv",
]

KINECT_V2_JOINTS = (
    "SpineBase",
    "SpineMid",
    "Neck",
    "Head",
    "ShoulderLeft",
    "ElbowLeft",
    "WristLeft",
    "HandLeft",
    "ShoulderRight",
    "ElbowRight",
    "WristRight",
    "HandRight",
    "HipLeft",
    "KneeLeft",
    "AnkleLeft",
    "FootLeft",
    "HipRight",
    "KneeRight",
    "AnkleRight",
    "FootRight",
    "SpineShoulder",
    "HandTipLeft",
    "ThumbLeft",
    "HandTipRight",
    "ThumbRight",
)
#: Canonical names of :data:`KINECT_V2_JOINTS` (hand tips and thumbs are not canonical joints).
KINECT_V2_TO_CANONICAL = (
    "spine_base", "spine_mid", "neck", "head", *KINECT_LIMB_JOINTS,
    "spine_shoulder", "hand_tip_l", "thumb_l", "hand_tip_r", "thumb_r",
)  # fmt: skip

_TRACKING = {"nottracked": 0, "not_tracked": 0, "inferred": 1, "tracked": 2}
_COL = re.compile(
    r"^(?P<joint>.+?)[ _.:](?P<what>x|y|z|trackingstate|tracking_state|state|conf|confidence)$",
    re.IGNORECASE,
)
#: LSL-Kinect's per-joint confidence -> Kinect v2 TrackingState (NotTracked, Inferred, Tracked).
LSL_KINECT_CONFIDENCE = {0.0: 0, 0.5: 1, 1.0: 2}
#: Time columns whose unit is known from the producer: LSL-Kinect's ``TimeSpan`` is Unix time, ms.
_PRODUCER_TIME = {"timespan": 1e-3}
_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "100ns": 1e-7}
_EPOCH_S = 1e8  # times above this (> 3 years) are absolute (Unix) times
_BODY_COLS = ("body", "body_index", "bodyindex", "tracking_id", "trackingid", "body_id")


def _norm(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


_V2_LOOKUP = {_norm(n): i for i, n in enumerate(KINECT_V2_JOINTS)}
_V2_LOOKUP.update({_norm(n): i for i, n in enumerate(KINECT_V2_TO_CANONICAL)})


def _v2_index(tab: Table, name: str, column: str, line: int | None = None) -> int:
    i = _V2_LOOKUP.get(_norm(name))
    if i is None:
        raise FormatError(
            tab.path,
            f"unknown joint {name!r}; expected a Kinect v2 JointType name ({', '.join(KINECT_V2_JOINTS)}) "
            "or its canonical name",
            line=tab.header_line if line is None else line,
            field=column,
        )
    return i


def _states(tab: Table, col: str) -> np.ndarray:
    raw = tab.strings(col)
    out = np.empty(len(raw))
    for k, s in enumerate(raw):
        v = _TRACKING.get(s.lower().replace(" ", ""))
        if v is None:
            try:
                v = float(s) if s else np.nan
            except ValueError:
                raise tab.error_at(
                    k,
                    f"expected a TrackingState (0/1/2 or NotTracked/Inferred/Tracked), found {s!r}",
                    col,
                ) from None
        out[k] = v
    return out


def _pick_body(tab: Table, body):
    lower = {c.lower(): c for c in tab.columns}
    bcol = next((lower[c] for c in _BODY_COLS if c in lower), None)
    if bcol is None:
        if body is not None:
            raise FormatError(
                tab.path, f"body={body!r} given but the file has no body column ({_BODY_COLS})"
            )
        return None, None, []
    ids = tab.strings(bcol)
    counts = Counter(ids)
    notes = []
    if body is None:
        body = counts.most_common(1)[0][0]
        if len(counts) > 1:
            notes.append(
                f"{len(counts)} bodies in the file; kept body {body!r} (most rows); pass body= to choose"
            )
    body = str(body)
    if body not in counts:
        raise FormatError(
            tab.path, f"body {body!r} not found; bodies in the file: {sorted(counts)}", field=bcol
        )
    return np.array([i == body for i in ids]), body, notes


def _is_v2_header(line: str) -> bool:
    """A Kinect v2 CSV header: a ``joint`` column or at least one ``<Joint>_X`` column."""
    cols = [c.strip() for c in re.split(r"[,\t;]", line)]
    if any(c.lower() == "joint" for c in cols):
        return True
    for c in cols:
        m = _COL.match(c)
        if m and _norm(m.group("joint")) in _V2_LOOKUP:
            return True
    return False


def _preamble(comments: list[str]) -> dict[str, str]:
    """``key : value`` pairs of a preamble line (LSL-Kinect: comma-separated, ' : ')."""
    out = {}
    for c in comments:
        for part in c.split(","):
            if ":" in part:
                k, v = part.split(":", 1)
                out[k.strip().lower()] = v.strip()
    return out


def read_kinect_v2_csv(
    path,
    *,
    min_tracking_state: int | None = 2,
    body=None,
    rate_hz: float | None = None,
    units: str = "m",
    time_column: str | None = None,
    time_unit: str | None = None,
    confidence_states: dict | None = None,
) -> Recording:
    """Read Kinect v2 joints from a CSV file.

    Wide and long layouts, see the module docstring and ``docs/formats.md``.

    Parameters
    ----------
    path : str or Path
    min_tracking_state : {0, 1, 2} or None
        A joint is available iff its TrackingState >= this and its coordinates are finite.
        Default 2 (Tracked only, SPEC §2.2). ``None``: finiteness only (no state columns needed).
    body : str or int or None
        Body to read; default the one with the most rows.
    rate_hz : float or None
        Needed with a frame column instead of times (``t = frame / rate``).
    units : {"m", "mm"}
        Unit of the coordinates (CameraSpacePoint is metres).
    time_column : str or None
        Name of the time column; default the first known one.
    time_unit : {"s", "ms", "us", "100ns"} or None
        Unit of ``time_column`` (required with it, unless it is a known column). Times above
        1e8 s are Unix times: shifted to start at 0, the first in ``metadata["t0_unix_s"]``.
    confidence_states : mapping of float -> int or None
        Confidence -> TrackingState of ``<Joint>_Conf``; default :data:`LSL_KINECT_CONFIDENCE`.

    Returns
    -------
    Recording
        ``vision``: positions (T, J, 3) m, Kinect camera frame (x toward the sensor's left, y
        up, z away from it), canonical joint names (``hand_tip_l`` ... for the others);
        ``metadata["tracking_state"]`` (T, J); ``available`` = TrackingState >=
        ``min_tracking_state``, finite and not all zero (:data:`~kinefuse.io._checks.ZERO_RULE`).

    Raises
    ------
    FormatError
        Missing time/coordinate/state column, unknown joint, bad state, time out of order.
    """
    path = Path(path)
    factor = _check_options(units, time_unit)
    conf_map = dict(LSL_KINECT_CONFIDENCE if confidence_states is None else confidence_states)
    tab = read_table(path, is_header=_is_v2_header)
    rows_mask, body_id, notes = _pick_body(tab, body)
    preamble = _preamble(tab.comments)
    t, tcol, pos, state, idx = _read_points(
        tab, rows_mask, min_tracking_state, conf_map, (rate_hz, time_column, time_unit), notes
    )
    t, t0_unix = _from_unix(t)
    notes += _nominal_rate_notes(preamble, t)
    pos *= factor
    zero = zero_is_missing(pos)
    avail = _available(pos, zero, state, min_tracking_state)
    joints = tuple(KINECT_V2_TO_CANONICAL[i] for i in idx)
    js = JointStream(t_s=t, position_m=pos, available=avail, joints=joints, frame="kinect_camera")
    md = make_metadata(
        path,
        "kinect_v2",
        units_converted=["positions mm -> m"] if factor != 1.0 else [],
        joint_map={KINECT_V2_JOINTS[i]: KINECT_V2_TO_CANONICAL[i] for i in idx},
        availability_rule=_availability_rule(min_tracking_state),
        tracking_state=state,
        time_column=tcol,
        t0_unix_s=t0_unix,
        preamble=preamble,
        n_zero_samples=int(zero.sum()),
        body=body_id,
        frame_notes="Kinect camera space: x toward the sensor's left, y up, z away from the sensor, m",
        notes=notes,
    )
    return finish_recording(path, md, vision=js)


def _read_points(tab: Table, rows_mask, min_state, conf_map, timing, notes: list[str]):
    """(t, time column, positions (T, J, 3), states (T, J), joint indices) of either layout."""
    if "joint" in {c.lower() for c in tab.columns}:
        t, pos, state, idx = _read_long(tab, rows_mask, min_state)
        return t, None, pos, state, idx
    _keep_rows(tab, rows_mask)
    t, tcol = _wide_time(tab, *timing)
    pos, state, idx, conf_used = _read_wide(tab, min_state, conf_map)
    if conf_used:
        notes.append(f"TrackingState from the confidence columns via {conf_map}")
    return t, tcol, pos, state, idx


def _check_options(units: str, time_unit: str | None) -> float:
    """The coordinate factor to metres, after checking ``units`` and ``time_unit``."""
    factor = {"m": 1.0, "mm": 1e-3}.get(units)
    if factor is None:
        raise InputError(f"expected units 'm' or 'mm', got {units!r}")
    if time_unit is not None and time_unit not in _TIME_UNITS:
        raise InputError(f"expected time_unit one of {sorted(_TIME_UNITS)}, got {time_unit!r}")
    return factor


def _keep_rows(tab: Table, rows_mask) -> None:
    """Keep the rows of the chosen body (``rows_mask`` None: all rows)."""
    if rows_mask is not None:
        tab.rows = [r for r, m in zip(tab.rows, rows_mask, strict=True) if m]
        tab.lines = tab.lines[rows_mask]


def _from_unix(t: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Absolute (Unix) times shifted to start at 0, with the first; other times unchanged."""
    if t.size and t[0] > _EPOCH_S:
        return t - t[0], float(t[0])
    return t, None


def _nominal_rate_notes(preamble: dict[str, str], t: np.ndarray) -> list[str]:
    """A note when the preamble's nominal rate disagrees (> 10 %) with the timestamps."""
    nominal = preamble.get("stream nominal rate")
    if not nominal or t.size <= 1:
        return []
    measured = 1.0 / float(np.median(np.diff(t)))
    try:
        nominal_hz = float(nominal)
    except ValueError:
        nominal_hz = None
    if nominal_hz and abs(measured - nominal_hz) > 0.1 * nominal_hz:
        return [
            f"preamble says 'Stream nominal rate : {nominal}', the timestamps give {measured:.3g} Hz "
            "(median step); the timestamps are used"
        ]
    return []


def _available(pos: np.ndarray, zero: np.ndarray, state: np.ndarray, min_state) -> np.ndarray:
    """Finite, not all zero and (unless ``min_state`` is None) TrackingState >= ``min_state``."""
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero
    if min_state is not None:
        avail &= state >= min_state
    return avail


def _availability_rule(min_state: int | None) -> str:
    rule = f"TrackingState >= {min_state} and finite" if min_state is not None else "finite"
    return rule + f"; {ZERO_RULE}"


def _wide_time(tab: Table, rate_hz, time_column, time_unit) -> tuple[np.ndarray, str]:
    lower = {c.lower(): c for c in tab.columns}
    if time_column is None:
        known = next((lower[n] for n in _PRODUCER_TIME if n in lower), None)
        if known is None or any(n in lower for n in TIME_COLUMNS):
            return table_time(tab, rate_hz=rate_hz)
        time_column = known
    col = time_column if time_column in tab.columns else lower.get(time_column.lower())
    if col is None:
        raise tab.header_error(
            f"time_column={time_column!r} not found; found columns {tab.columns[:8]}...",
            time_column,
        )
    factor = _TIME_UNITS.get(time_unit) if time_unit else _PRODUCER_TIME.get(col.lower())
    if factor is None:
        raise FormatError(
            tab.path,
            f"unknown unit of time column {col!r}; pass time_unit= (one of {sorted(_TIME_UNITS)})",
            field=col,
        )
    t = tab.floats(col, allow_empty=False) * factor
    return check_time(tab.path, t, tab.lines, col), col


def _read_wide(tab: Table, min_state, conf_map):
    cols: dict[int, dict[str, str]] = {}
    for c in tab.columns:
        m = _COL.match(c)
        if not m:
            continue
        i = _v2_index(tab, m.group("joint"), c)
        what = m.group("what").lower()
        what = "state" if "state" in what else ("conf" if what.startswith("conf") else what)
        cols.setdefault(i, {})[what] = c
    if not cols:
        raise FormatError(
            tab.path,
            f"expected joint columns like 'SpineBase_X'; found {tab.columns}",
            line=tab.header_line,
        )
    idx = sorted(cols)
    pos = np.empty((len(tab), len(idx), 3))
    state = np.full((len(tab), len(idx)), 2.0)
    conf_used = False
    for j, i in enumerate(idx):
        need = ["x", "y", "z"]
        if min_state is not None and "conf" not in cols[i]:
            need.append("state")
        for w in need:
            if w not in cols[i]:
                base = next(iter(cols[i].values()))
                name = f"{KINECT_V2_JOINTS[i]}_{'TrackingState' if w == 'state' else w.upper()}"
                hint = (
                    " (or a '_Conf' column, or pass min_tracking_state=None)"
                    if w == "state"
                    else ""
                )
                raise FormatError(
                    tab.path,
                    f"missing column {name!r} (found {base!r}){hint}",
                    line=tab.header_line,
                    field=name,
                )
        for a, w in enumerate("xyz"):
            pos[:, j, a] = tab.floats(cols[i][w])
        if "state" in cols[i]:
            state[:, j] = _states(tab, cols[i]["state"])
        elif "conf" in cols[i]:
            state[:, j] = _conf_states(tab, cols[i]["conf"], conf_map)
            conf_used = True
    return pos, state, idx, conf_used


def _conf_states(tab: Table, col: str, conf_map) -> np.ndarray:
    conf = tab.floats(col)
    out = np.full(conf.shape, np.nan)
    for v, st in conf_map.items():  # keys may be strings (TOML tables): "0.5" = 1
        out[conf == float(v)] = float(st)
    bad = np.isfinite(conf) & np.isnan(out)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise tab.error_at(
            k,
            f"expected a confidence among {sorted(float(v) for v in conf_map)} (confidence_states=), "
            f"found {float(conf[k])!r}",
            col,
        )
    return out


def _read_long(tab: Table, rows_mask, min_state):
    lower = {c.lower(): c for c in tab.columns}
    need = ["joint", "x", "y", "z"] + (["tracking_state"] if min_state is not None else [])
    aliases = {"tracking_state": ("tracking_state", "trackingstate", "state")}
    colmap = {}
    for n in need:
        c = next((lower[a] for a in aliases.get(n, (n,)) if a in lower), None)
        if c is None:
            raise tab.header_error(f"missing column {n!r}; found {tab.columns}", n)
        colmap[n] = c
    _keep_rows(tab, rows_mask)
    t_rows, tcol = time_column_s(tab)
    d = np.diff(t_rows)
    if np.any(d < 0):
        k = int(np.flatnonzero(d < 0)[0]) + 1
        raise FormatError(
            tab.path,
            f"expected non-decreasing time, found {t_rows[k]!r} after {t_rows[k - 1]!r}",
            line=int(tab.lines[k]),
            field=tcol,
        )
    t, inv = np.unique(t_rows, return_inverse=True)
    jnames = tab.strings(colmap["joint"])
    jidx = np.array(
        [
            _v2_index(tab, n, colmap["joint"], int(ln))
            for n, ln in zip(jnames, tab.lines, strict=True)
        ]
    )
    idx = sorted(set(jidx.tolist()))
    col_of = {i: k for k, i in enumerate(idx)}
    jc = np.array([col_of[i] for i in jidx])
    pos = np.full((t.size, len(idx), 3), np.nan)
    state = np.zeros((t.size, len(idx)))
    seen = np.zeros((t.size, len(idx)), dtype=bool)
    xyz = np.stack([tab.floats(colmap[a]) for a in "xyz"], axis=1)
    st = _states(tab, colmap["tracking_state"]) if min_state is not None else np.full(len(tab), 2.0)
    for r in range(len(tab)):
        a, b = inv[r], jc[r]
        if seen[a, b]:
            raise FormatError(
                tab.path,
                f"duplicate row for joint {jnames[r]!r} at time {t[a]!r}",
                line=int(tab.lines[r]),
                field=colmap["joint"],
            )
        seen[a, b] = True
        pos[a, b] = xyz[r]
        state[a, b] = st[r]
    return t, pos, state, idx
