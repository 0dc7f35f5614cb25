"""Kinect skeleton readers: Kinect v2 joint CSV (25 joints + TrackingState) and Azure Kinect
body-tracking JSON (32 joints, the ``offline_processor`` layout, optional confidence levels).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io._common import (
    KINECT_LIMB_JOINTS,
    TIME_COLUMNS,
    ZERO_RULE,
    Table,
    check_time,
    check_units,
    make_metadata,
    read_table,
    table_time,
    zero_is_missing,
)
from kinefuse.io.recording import JointStream, Recording

__all__ = [
    "LSL_KINECT_CONFIDENCE",
    "AZURE_JOINTS",
    "AZURE_TO_CANONICAL",
    "KINECT_V2_JOINTS",
    "KINECT_V2_TO_CANONICAL",
    "read_azure_kinect_json",
    "read_kinect_v2_csv",
]

#: Kinect v2 ``JointType`` names in index order 0..24.
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
#: Azure Kinect ``k4abt_joint_id_t`` names in index order 0..31.
AZURE_JOINTS = (
    "PELVIS",
    "SPINE_NAVEL",
    "SPINE_CHEST",
    "NECK",
    "CLAVICLE_LEFT",
    "SHOULDER_LEFT",
    "ELBOW_LEFT",
    "WRIST_LEFT",
    "HAND_LEFT",
    "HANDTIP_LEFT",
    "THUMB_LEFT",
    "CLAVICLE_RIGHT",
    "SHOULDER_RIGHT",
    "ELBOW_RIGHT",
    "WRIST_RIGHT",
    "HAND_RIGHT",
    "HANDTIP_RIGHT",
    "THUMB_RIGHT",
    "HIP_LEFT",
    "KNEE_LEFT",
    "ANKLE_LEFT",
    "FOOT_LEFT",
    "HIP_RIGHT",
    "KNEE_RIGHT",
    "ANKLE_RIGHT",
    "FOOT_RIGHT",
    "HEAD",
    "NOSE",
    "EYE_LEFT",
    "EAR_LEFT",
    "EYE_RIGHT",
    "EAR_RIGHT",
)
#: Canonical names of :data:`AZURE_JOINTS`. SPINE_CHEST sits lower than Kinect v2's SpineShoulder,
#: so it is kept as ``spine_chest``; NECK -> ``neck``, SPINE_NAVEL -> ``spine_mid``.
AZURE_TO_CANONICAL = (
    "pelvis",
    "spine_mid",
    "spine_chest",
    "neck",
    "clavicle_l",
    "shoulder_l",
    "elbow_l",
    "wrist_l",
    "hand_l",
    "hand_tip_l",
    "thumb_l",
    "clavicle_r",
    "shoulder_r",
    "elbow_r",
    "wrist_r",
    "hand_r",
    "hand_tip_r",
    "thumb_r",
    "hip_l",
    "knee_l",
    "ankle_l",
    "foot_l",
    "hip_r",
    "knee_r",
    "ankle_r",
    "foot_r",
    "head",
    "nose",
    "eye_l",
    "ear_l",
    "eye_r",
    "ear_r",
)

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
                raise FormatError(
                    tab.path,
                    f"expected a TrackingState (0/1/2 or NotTracked/Inferred/Tracked), found {s!r}",
                    line=int(tab.lines[k]),
                    field=col,
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
    """Read Kinect v2 joints from a CSV file (wide or long layout, see ``docs/formats.md``).

    Wide layout: a time column (``t_s``, ``time_ms``, ``timestamp_us``, ``RelativeTime`` in
    100 ns ticks, LSL-Kinect's ``TimeSpan`` in Unix ms ... any other with ``time_column=`` and
    ``time_unit=``, or ``frame`` with ``rate_hz=``) and per joint ``<Joint>_X, <Joint>_Y,
    <Joint>_Z`` and ``<Joint>_TrackingState`` or a confidence ``<Joint>_Conf`` (separators
    ``_ . : space``; joint names as Kinect v2 ``JointType`` — ``SpineBase`` ... ``ThumbRight`` —
    or canonical, case-insensitive). Long layout: columns ``time, joint, x, y, z,
    tracking_state`` (one row per joint and frame). Either may have a body column
    (``body``/``tracking_id``...). Lines before the header without a comment prefix (the
    LSL-Kinect ``Software : LSL_Kinect,...`` line) are a preamble, kept in
    ``metadata["preamble"]``.

    Parameters
    ----------
    path : str or Path
    min_tracking_state : {0, 1, 2} or None
        A joint is available iff its TrackingState >= this and its coordinates are finite.
        Default 2 (Tracked only, SPEC §2.2). ``None``: finiteness only (no state columns
        needed).
    body : str or int or None
        Body to read when the file has several; default the one with the most rows.
    rate_hz : float or None
        Needed when the file has a frame column instead of times (then ``t = frame / rate``);
        ignored when the file has times.
    units : {"m", "mm"}
        Unit of the coordinates (CameraSpacePoint is metres).
    time_column : str or None
        Name of the time column; default the first known one (see above).
    time_unit : {"s", "ms", "us", "100ns"} or None
        Unit of ``time_column`` (required with it, unless it is a known column). Times above
        1e8 s are absolute (Unix) times: they are shifted to start at 0 and the first is kept in
        ``metadata["t0_unix_s"]``.
    confidence_states : mapping of float -> int or None
        Confidence value -> TrackingState for ``<Joint>_Conf`` columns (used when there is no
        TrackingState column). Default :data:`LSL_KINECT_CONFIDENCE` (0 -> NotTracked,
        0.5 -> Inferred, 1 -> Tracked).

    Returns
    -------
    Recording
        ``vision``: positions (T, J, 3) in m in the Kinect camera frame (x toward the sensor's
        left, y up, z away from the sensor), canonical joint names (``hand_tip_l`` etc. for the
        non-canonical ones); ``metadata["tracking_state"]`` (T, J); ``metadata["time_column"]``;
        ``available`` = TrackingState >= ``min_tracking_state``, finite and not all zero
        (:data:`kinefuse.io._common.ZERO_RULE`).

    Raises
    ------
    FormatError
        Missing time/coordinate/state column, unknown joint name, bad state value,
        non-monotonic time, duplicate (time, joint) rows.
    """
    path = Path(path)
    factor = {"m": 1.0, "mm": 1e-3}.get(units)
    if factor is None:
        raise InputError(f"expected units 'm' or 'mm', got {units!r}")
    if time_unit is not None and time_unit not in _TIME_UNITS:
        raise InputError(f"expected time_unit one of {sorted(_TIME_UNITS)}, got {time_unit!r}")
    conf_map = dict(LSL_KINECT_CONFIDENCE if confidence_states is None else confidence_states)
    tab = read_table(path, is_header=_is_v2_header)
    lower = {c.lower(): c for c in tab.columns}
    rows_mask, body_id, notes = _pick_body(tab, body)
    preamble = _preamble(tab.comments)
    if "joint" in lower:
        t, pos, state, idx = _read_long(tab, lower, rows_mask, min_tracking_state)
        tcol = None
    else:
        if rows_mask is not None:
            tab.rows = [r for r, m in zip(tab.rows, rows_mask, strict=True) if m]
            tab.lines = tab.lines[rows_mask]
        t, tcol = _wide_time(tab, rate_hz, time_column, time_unit)
        pos, state, idx, conf_used = _read_wide(tab, min_tracking_state, conf_map)
        if conf_used:
            notes.append(f"TrackingState from the confidence columns via {conf_map}")
    t0_unix = None
    if t.size and t[0] > _EPOCH_S:
        t0_unix = float(t[0])
        t = t - t[0]
    nominal = preamble.get("stream nominal rate")
    if nominal and t.size > 1:
        measured = 1.0 / float(np.median(np.diff(t)))
        try:
            nominal_hz = float(nominal)
        except ValueError:
            nominal_hz = None
        if nominal_hz and abs(measured - nominal_hz) > 0.1 * nominal_hz:
            notes.append(
                f"preamble says 'Stream nominal rate : {nominal}', the timestamps give {measured:.3g} Hz "
                "(median step); the timestamps are used"
            )
    pos *= factor
    zero = zero_is_missing(pos)
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero
    if min_tracking_state is not None:
        avail &= state >= min_tracking_state
    joints = tuple(KINECT_V2_TO_CANONICAL[i] for i in idx)
    js = JointStream(t_s=t, position_m=pos, available=avail, joints=joints, frame="kinect_camera")
    md = make_metadata(
        path,
        "kinect_v2",
        units_converted=["positions mm -> m"] if factor != 1.0 else [],
        joint_map={KINECT_V2_JOINTS[i]: KINECT_V2_TO_CANONICAL[i] for i in idx},
        availability_rule=(
            f"TrackingState >= {min_tracking_state} and finite"
            if min_tracking_state is not None
            else "finite"
        )
        + f"; {ZERO_RULE}",
        tracking_state=state,
        time_column=tcol,
        t0_unix_s=t0_unix,
        preamble=preamble,
        n_zero_samples=int(zero.sum()),
        body=body_id,
        frame_notes="Kinect camera space: x toward the sensor's left, y up, z away from the sensor, m",
        notes=notes,
    )
    rec = Recording(vision=js, metadata=md)
    check_units(rec, where=str(path))
    return rec


def _wide_time(tab: Table, rate_hz, time_column, time_unit) -> tuple[np.ndarray, str]:
    lower = {c.lower(): c for c in tab.columns}
    if time_column is None:
        known = next((lower[n] for n in _PRODUCER_TIME if n in lower), None)
        if known is None or any(n in lower for n in TIME_COLUMNS):
            return table_time(tab, rate_hz=rate_hz)
        time_column = known
    col = time_column if time_column in tab.columns else lower.get(time_column.lower())
    if col is None:
        raise FormatError(
            tab.path,
            f"time_column={time_column!r} not found; found columns {tab.columns[:8]}...",
            line=tab.header_line,
            field=time_column,
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
        raise FormatError(
            tab.path,
            f"expected a confidence among {sorted(float(v) for v in conf_map)} (confidence_states=), "
            f"found {float(conf[k])!r}",
            line=int(tab.lines[k]),
            field=col,
        )
    return out


def _read_long(tab: Table, lower, rows_mask, min_state):
    need = ["joint", "x", "y", "z"] + (["tracking_state"] if min_state is not None else [])
    aliases = {"tracking_state": ("tracking_state", "trackingstate", "state")}
    colmap = {}
    for n in need:
        c = next((lower[a] for a in aliases.get(n, (n,)) if a in lower), None)
        if c is None:
            raise FormatError(
                tab.path,
                f"missing column {n!r}; found {tab.columns}",
                line=tab.header_line,
                field=n,
            )
        colmap[n] = c
    if rows_mask is not None:
        tab.rows = [r for r, m in zip(tab.rows, rows_mask, strict=True) if m]
        tab.lines = tab.lines[rows_mask]
    t_rows, tcol = _long_time(tab)
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


def _long_time(tab: Table):
    lower = {c.lower(): c for c in tab.columns}
    for name, factor in TIME_COLUMNS.items():
        if name in lower:
            return tab.floats(lower[name], allow_empty=False) * factor, lower[name]
    raise FormatError(
        tab.path,
        f"missing time column: expected one of {sorted(TIME_COLUMNS)}",
        line=tab.header_line,
        field="t_s",
    )


# ------------------------------------------------------------------------------------------------
# Azure Kinect
# ------------------------------------------------------------------------------------------------
_CONF_KEYS = ("joint_confidence_levels", "confidence_levels", "joint_confidences", "confidence")


def _load_json(path: Path):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise FormatError(path, f"expected UTF-8 JSON text: {e}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(
            path, f"invalid JSON ({e.msg}, column {e.colno}); truncated file?", line=e.lineno
        ) from None


def read_azure_kinect_json(path, *, min_confidence: int | None = 2, body_id=None) -> Recording:
    """Read Azure Kinect body-tracking JSON (Microsoft ``offline_processor`` layout).

    Layout: ``{"joint_names": [32 names], "frames": [{"timestamp_usec": int, "bodies":
    [{"body_id": int, "joint_positions": [[x, y, z] x 32] (mm), "joint_orientations":
    [[w, x, y, z] x 32], "joint_confidence_levels": [32 ints] (optional)}]}]}``.

    Parameters
    ----------
    path : str or Path
    min_confidence : {0, 1, 2, 3} or None
        A joint is available iff its confidence level (``K4ABT_JOINT_CONFIDENCE_NONE=0, LOW=1,
        MEDIUM=2, HIGH=3``) >= this and its position is finite. Default 2 (MEDIUM, the highest
        level the SDK reports; LOW = occluded, predicted), the analogue of Kinect v2 Tracked.
        Files without confidence levels (the stock offline_processor) fall back to finiteness
        (noted in metadata). ``None``: finiteness only.
    body_id : int or None
        Body to read; default the body present in the most frames.

    Returns
    -------
    Recording
        ``vision``: positions (T, 32, 3) in m (file mm) in the Azure Kinect depth-camera frame
        (x right, y down, z forward), canonical joint names (:data:`AZURE_TO_CANONICAL`),
        times ``(timestamp_usec - first) * 1e-6`` s; frames without the body are unavailable.
        ``metadata["confidence"]`` (T, 32), -1 where absent.

    Raises
    ------
    FormatError
        Invalid/truncated JSON, missing keys, wrong joint counts, non-monotonic timestamps.
    """
    path = Path(path)
    d = _load_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("frames"), list):
        raise FormatError(path, "expected a JSON object with a 'frames' list", field="frames")
    names = d.get("joint_names", list(AZURE_JOINTS))
    if list(names) != list(AZURE_JOINTS):
        raise FormatError(
            path,
            f"expected the 32 Azure Kinect joint names in k4abt order, found {names}",
            field="joint_names",
        )
    frames = d["frames"]
    if not frames:
        raise FormatError(path, "expected at least one frame, found none", field="frames")
    counts: Counter = Counter()
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict) or "timestamp_usec" not in fr or "bodies" not in fr:
            raise FormatError(
                path,
                f"frame {k}: expected keys 'timestamp_usec' and 'bodies'",
                field=f"frames[{k}]",
            )
        for b in fr["bodies"] or []:
            counts[b.get("body_id")] += 1
    notes = []
    if body_id is None:
        if not counts:
            raise FormatError(path, "no body in any frame", field="bodies")
        body_id = counts.most_common(1)[0][0]
        if len(counts) > 1:
            notes.append(
                f"{len(counts)} bodies; kept body_id {body_id} (most frames); pass body_id= to choose"
            )
    elif body_id not in counts:
        raise FormatError(
            path, f"body_id {body_id!r} not found; bodies: {sorted(counts)}", field="body_id"
        )
    T, J = len(frames), len(AZURE_JOINTS)
    ts = np.empty(T)
    pos = np.full((T, J, 3), np.nan)
    conf = np.full((T, J), -1.0)
    has_conf = False
    for k, fr in enumerate(frames):
        try:
            ts[k] = float(fr["timestamp_usec"])
        except (TypeError, ValueError):
            raise FormatError(
                path,
                f"frame {k}: expected a number, found {fr['timestamp_usec']!r}",
                field=f"frames[{k}].timestamp_usec",
            ) from None
        for b in fr["bodies"] or []:
            if b.get("body_id") != body_id:
                continue
            jp = np.asarray(b.get("joint_positions", []), dtype=float)
            if jp.shape != (J, 3):
                raise FormatError(
                    path,
                    f"frame {k}: expected joint_positions (32, 3), found {jp.shape}",
                    field=f"frames[{k}].joint_positions",
                )
            pos[k] = jp
            ck = next((c for c in _CONF_KEYS if c in b), None)
            if ck is not None:
                cv = np.asarray(b[ck], dtype=float)
                if cv.shape != (J,):
                    raise FormatError(
                        path,
                        f"frame {k}: expected {ck} (32,), found {cv.shape}",
                        field=f"frames[{k}].{ck}",
                    )
                conf[k] = cv
                has_conf = True
    t_us = check_time(path, ts, None, "timestamp_usec")
    t = (t_us - t_us[0]) * 1e-6
    pos *= 1e-3
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero_is_missing(pos)
    rule = f"finite; {ZERO_RULE}"
    if min_confidence is not None:
        if has_conf:
            avail &= conf >= min_confidence
            rule = f"confidence level >= {min_confidence} and finite; {ZERO_RULE}"
        else:
            notes.append(
                "no joint confidence levels in the file; availability = body present and finite"
            )
    js = JointStream(
        t_s=t,
        position_m=pos,
        available=avail,
        joints=AZURE_TO_CANONICAL,
        frame="azure_depth_camera",
    )
    md = make_metadata(
        path,
        "azure_kinect",
        units_converted=["positions mm -> m", "timestamp us -> s"],
        joint_map=dict(zip(AZURE_JOINTS, AZURE_TO_CANONICAL, strict=True)),
        availability_rule=rule,
        confidence=conf,
        body_id=body_id,
        t0_us=float(t_us[0]),
        frame_notes="Azure Kinect depth camera: x right, y down, z forward (m)",
        notes=notes,
    )
    rec = Recording(vision=js, metadata=md)
    check_units(rec, where=str(path))
    return rec
