"""MediaPipe Pose landmarks (33 landmarks + visibility), world landmarks in metres; CSV or JSON."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import ZERO_RULE, check_units, make_metadata, zero_is_missing
from kinefuse.io._text import check_time, read_json, read_table, table_time
from kinefuse.io.recording import JointStream, Recording

__all__ = ["MEDIAPIPE_LANDMARKS", "MEDIAPIPE_TO_CANONICAL", "read_mediapipe"]

#: MediaPipe Pose landmark names, index order 0..32.
MEDIAPIPE_LANDMARKS = (
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)
_CANON = {
    "left_shoulder": "shoulder_l",
    "right_shoulder": "shoulder_r",
    "left_elbow": "elbow_l",
    "right_elbow": "elbow_r",
    "left_wrist": "wrist_l",
    "right_wrist": "wrist_r",
    "left_hip": "hip_l",
    "right_hip": "hip_r",
    "left_knee": "knee_l",
    "right_knee": "knee_r",
    "left_ankle": "ankle_l",
    "right_ankle": "ankle_r",
    "left_foot_index": "foot_l",
    "right_foot_index": "foot_r",
}
#: Output joint names: canonical where the landmark is a canonical joint, else the MediaPipe name.
MEDIAPIPE_TO_CANONICAL = tuple(_CANON.get(n, n) for n in MEDIAPIPE_LANDMARKS)

_LOOKUP = {n: i for i, n in enumerate(MEDIAPIPE_LANDMARKS)}
_LOOKUP.update({n: i for i, n in enumerate(MEDIAPIPE_TO_CANONICAL)})
_LOOKUP.update({str(i): i for i in range(33)})
_COL = re.compile(r"^(?P<lm>.+)_(?P<what>x|y|z|visibility|vis)$", re.IGNORECASE)
_TIME_KEYS = {
    "timestamp_ms": 1e-3,
    "time_ms": 1e-3,
    "t_s": 1.0,
    "time_s": 1.0,
    "timestamp_us": 1e-6,
}


def read_mediapipe(
    path, *, min_visibility: float | None = 0.5, rate_hz: float | None = None
) -> Recording:
    """Read MediaPipe Pose world landmarks from CSV or JSON (layouts in ``docs/formats.md``).

    CSV: a time column (``t_s``, ``timestamp_ms``...; or ``frame`` with ``rate_hz=``) and per
    landmark ``<name>_x, <name>_y, <name>_z`` and optionally ``<name>_visibility``, where
    ``<name>`` is the MediaPipe name (``left_wrist``), its index (``15``) or its canonical name
    (``wrist_l``). Landmarks absent from the header are not read.

    JSON: ``{"frames": [{"timestamp_ms": float, "world_landmarks": [33 x {"x","y","z",
    "visibility"}] or [33 x [x, y, z, visibility]] or null}]}`` or a bare list of such frames.
    Frames with ``null``/empty landmarks (no pose detected) are unavailable. Only world
    landmarks (metres) are accepted: normalised image ``landmarks`` are refused.

    Parameters
    ----------
    path : str or Path
    min_visibility : float or None
        A landmark is available iff visibility >= this and finite. Default 0.5 (MediaPipe's own
        default detection/tracking confidence). ``None``: finiteness only.
    rate_hz : float or None
        Frame rate when the file has frame numbers instead of times.

    Returns
    -------
    Recording
        ``vision``: positions (T, L, 3) in m, frame ``"mediapipe_world"`` (origin at the hip
        midpoint; x, y, z along image right, image down and depth), joint names from
        :data:`MEDIAPIPE_TO_CANONICAL`; ``metadata["visibility"]`` (T, L).

    Raises
    ------
    FormatError
        Missing time/coordinate columns or keys, unknown landmark name, wrong landmark count,
        invalid JSON, non-monotonic time.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        t, pos, vis, idx = _read_json(path, rate_hz)
    else:
        t, pos, vis, idx = _read_csv(path, rate_hz)
    avail = np.all(np.isfinite(pos), axis=-1) & ~zero_is_missing(pos)
    if min_visibility is not None:
        avail &= np.nan_to_num(vis, nan=1.0) >= float(min_visibility)
    joints = tuple(MEDIAPIPE_TO_CANONICAL[i] for i in idx)
    js = JointStream(t_s=t, position_m=pos, available=avail, joints=joints, frame="mediapipe_world")
    md = make_metadata(
        path,
        "mediapipe",
        units_converted=[],
        joint_map={MEDIAPIPE_LANDMARKS[i]: MEDIAPIPE_TO_CANONICAL[i] for i in idx},
        availability_rule=(
            f"visibility >= {min_visibility} and finite" if min_visibility is not None else "finite"
        )
        + f"; {ZERO_RULE}",
        visibility=vis,
        frame_notes="MediaPipe world landmarks: metres, origin at the hip midpoint, axes image-right/down/depth",
    )
    rec = Recording(vision=js, metadata=md)
    check_units(rec, where=str(path))
    return rec


def _read_csv(path: Path, rate_hz):
    tab = read_table(path)
    t, _ = table_time(tab, rate_hz=rate_hz)
    cols: dict[int, dict[str, str]] = {}
    for c in tab.columns:
        m = _COL.match(c)
        if not m:
            continue
        lm = m.group("lm").lower()
        i = _LOOKUP.get(lm)
        if i is None:
            raise FormatError(
                path,
                f"unknown landmark {m.group('lm')!r}; expected a MediaPipe Pose name ({', '.join(MEDIAPIPE_LANDMARKS)}) or index 0-32",
                line=tab.header_line,
                field=c,
            )
        w = m.group("what").lower()
        cols.setdefault(i, {})["visibility" if w.startswith("vis") else w] = c
    if not cols:
        raise FormatError(
            path,
            f"expected landmark columns like 'left_wrist_x'; found {tab.columns}",
            line=tab.header_line,
        )
    idx = sorted(cols)
    pos = np.empty((len(tab), len(idx), 3))
    vis = np.full((len(tab), len(idx)), np.nan)
    for j, i in enumerate(idx):
        for a, w in enumerate("xyz"):
            if w not in cols[i]:
                name = f"{MEDIAPIPE_LANDMARKS[i]}_{w}"
                raise FormatError(
                    path, f"missing column {name!r}", line=tab.header_line, field=name
                )
            pos[:, j, a] = tab.floats(cols[i][w])
        if "visibility" in cols[i]:
            vis[:, j] = tab.floats(cols[i]["visibility"])
    return t, pos, vis, idx


def _lm_array(path: Path, k: int, lms) -> np.ndarray:
    out = np.full((33, 4), np.nan)
    if not lms:
        return out
    if len(lms) != 33:
        raise FormatError(
            path,
            f"frame {k}: expected 33 landmarks, found {len(lms)}",
            field=f"frames[{k}].world_landmarks",
        )
    for i, lm in enumerate(lms):
        try:
            if isinstance(lm, dict):
                out[i, :3] = [float(lm["x"]), float(lm["y"]), float(lm["z"])]
                out[i, 3] = float(lm.get("visibility", np.nan))
            else:
                v = [float(x) for x in lm]
                if len(v) not in (3, 4):
                    raise ValueError
                out[i, : len(v)] = v
        except (KeyError, TypeError, ValueError):
            raise FormatError(
                path,
                f"frame {k}: expected landmark {i} as {{x, y, z, visibility}} or [x, y, z(, v)], found {lm!r}",
                field=f"frames[{k}].world_landmarks[{i}]",
            ) from None
    return out


def _read_json(path: Path, rate_hz):
    d = read_json(path)
    frames = d.get("frames") if isinstance(d, dict) else d
    if not isinstance(frames, list) or not frames:
        raise FormatError(
            path, "expected a non-empty list of frames (or an object with 'frames')", field="frames"
        )
    T = len(frames)
    arr = np.full((T, 33, 4), np.nan)
    t = np.full(T, np.nan)
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise FormatError(
                path,
                f"frame {k}: expected an object, found {type(fr).__name__}",
                field=f"frames[{k}]",
            )
        key = next((kk for kk in _TIME_KEYS if kk in fr), None)
        if key is not None:
            try:
                t[k] = float(fr[key]) * _TIME_KEYS[key]
            except (TypeError, ValueError):
                raise FormatError(
                    path,
                    f"frame {k}: expected a number, found {fr[key]!r}",
                    field=f"frames[{k}].{key}",
                ) from None
        elif rate_hz is not None:
            t[k] = k / float(rate_hz)
        else:
            raise FormatError(
                path,
                f"frame {k}: missing time key (one of {sorted(_TIME_KEYS)}); or pass rate_hz=",
                field=f"frames[{k}]",
            )
        if "world_landmarks" in fr:
            arr[k] = _lm_array(path, k, fr["world_landmarks"])
        elif "pose_world_landmarks" in fr:
            arr[k] = _lm_array(path, k, fr["pose_world_landmarks"])
        elif "landmarks" in fr:
            raise FormatError(
                path,
                f"frame {k}: found normalised image 'landmarks' only; expected 'world_landmarks' in metres",
                field=f"frames[{k}].landmarks",
            )
        else:
            raise FormatError(
                path, f"frame {k}: missing key 'world_landmarks'", field=f"frames[{k}]"
            )
    t = check_time(path, t, None, "timestamp")
    return t, arr[..., :3], arr[..., 3], list(range(33))
