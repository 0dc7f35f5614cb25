"""The calibrated IMU chain of a session as a file, ``chain.json``, for live capture.

``kinefuse run`` calibrates from the recording (static or functional: IMUs only) and writes the
chain it then used: each segment's long axis in its *sensor* frame, its length, the root joint
and, for a pelvis root, the hips as offsets in the pelvis sensor's frame (the shoulders, where a
trunk IMU places them, as offsets in its frame, from the mid-hip or the mid-shoulder point
``spine_shoulder``; ``offset_segments`` names the chest when the hips hang from the pelvis);
where the calibration gave segment frames (joint angles), each segment's
``R_sensor_from_segment`` (``segment_frames``, rows of the 3 × 3 matrix).
``kinefuse stream SESSION --chain chain.json`` runs that same chain on live orientation streams
(:mod:`kinefuse.streaming`): the positions and joint angles equal the offline ones on the same
samples.

Only IMU-only roots are described (``pelvis``: hips from the pelvis IMU; ``fixed``: a root
joint at a measured position); a camera or reference root has no live counterpart here. 6-D
sensors (headings aligned by a static calibration) get ``"heading": {"from": "pose",
"window_s": W, "reference": SEGMENT, "pose_yaw_deg": {SEGMENT: deg}}``: live streams have
headings of their own, which the engine finds again from the same still pose at the start of
streaming, keeping the segment frames' relative headings in the calibration pose
(:mod:`kinefuse.streaming.heading`); after a functional calibration they are refused.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from kinefuse.exceptions import InputError
from kinefuse.kinematics import Skeleton
from kinefuse.kinematics.static import relative_yaw, window_orientations
from kinefuse.pipelines.run.chain import (
    hip_offsets_in_pelvis_sensor,
    shoulder_offsets_m,
    trunk_frame_in_sensor,
)

__all__ = [
    "CHAIN_FILE",
    "chain_description",
    "read_chain",
    "segment_frames_from_chain",
    "skeleton_from_chain",
]

#: File name of the description in a session's output folder.
CHAIN_FILE = "chain.json"
_FORMAT = "kinefuse-chain"
_VERSION = 1


def chain_description(sk: Skeleton, root_kind: str, params: Mapping, cal, body_height_m,
                      trunk: str | None = None, recording=None):  # fmt: skip
    """``(description, None)`` of the calibrated chain ``sk`` (axes in the sensor frames,
    resolved lengths), or ``(None, why)`` when it cannot run live. ``trunk``: the IMU the
    shoulders are placed from (:func:`~kinefuse.pipelines.run.chain.shoulder_trunk`), if so;
    ``recording``: the calibrated one (6-D: the frames' headings in its pose are kept)."""
    if root_kind not in ("pelvis", "fixed"):
        return None, f"its root ({root_kind!r}) comes from a stream kinefuse stream does not read"
    six_d = cal is not None and any(abs(h) > 1e-9 for h in (cal.world_heading_deg or {}).values())
    if six_d and cal.still is None:
        return None, (
            "6-D sensors whose headings a functional calibration aligned: live streams have "
            "headings of their own, and only a static pose can find them again"
        )
    rp = params.get("root_position_m", (0.0, 0.0, 0.0))
    if isinstance(rp, Mapping):
        return None, "a root position per chain start"
    segs = [
        {"name": s, "parent": int(p), "proximal": a, "distal": b, "length_m": float(L),
         "axis_sensor": [float(v) for v in ax]}
        for s, p, a, b, L, ax in zip(sk.segments, sk.parents, sk.proximal, sk.distal,
                                     sk.lengths_m, sk.axes, strict=True)
    ]  # fmt: skip
    d = {"format": _FORMAT, "version": _VERSION, "root_kind": root_kind,
         "root_position_m": [float(v) for v in rp], "segments": segs}  # fmt: skip
    starts = {a for a, p in zip(sk.proximal, sk.parents, strict=True) if p < 0}
    offsets = {}
    if root_kind == "pelvis":  # the hips as the offline chain places them (_hip_roots)
        offsets = hip_offsets_in_pelvis_sensor(cal, body_height_m)[0]
        d["root"], d["root_segment"] = "pelvis", "pelvis"
    elif trunk is not None:  # fixed: the measured point is the mid-shoulder point
        d["root"], d["root_segment"] = "spine_shoulder", trunk
    else:
        d["root"], d["root_segment"] = sk.root, None
    if trunk is not None:  # the shoulders as the offline chain places them (_shoulder_roots)
        R = trunk_frame_in_sensor(cal, trunk)
        sh = shoulder_offsets_m(body_height_m, above_hips=root_kind == "pelvis")
        offsets.update({j: R @ o for j, o in sh.items()})
        if trunk != d["root_segment"]:  # hips on the pelvis, shoulders on the chest
            d["offset_segments"] = {j: trunk for j in sh if j in starts}
    d["offsets_m"] = {j: [float(v) for v in o] for j, o in offsets.items() if j in starts}
    frames = {} if cal is None else cal.frames  # the chain's, and feet for the ankle angles
    d["segment_frames"] = {s: np.asarray(F, float).tolist() for s, F in frames.items()}
    if six_d:  # the engine finds each live sensor's heading from the pose (streaming.heading)
        carriers = (d["root_segment"], *d.get("offset_segments", {}).values())
        lack = [s for s in dict.fromkeys((*sk.segments, *carriers)) if s and s not in frames]
        if lack:
            return None, f"6-D sensors, and no segment frame for {lack} to align them live"
        ref = next(s for s, h in cal.world_heading_deg.items() if abs(h) <= 1e-9)
        d["heading"] = {"from": "pose", "window_s": float(cal.window_s[1] - cal.window_s[0]),
                        "reference": ref,  # the sensor whose heading the outputs keep
                        "pose_yaw_deg": _pose_yaw_deg(recording, cal, frames, ref)}  # fmt: skip
    return d, None


def _pose_yaw_deg(recording, cal, frames, ref: str) -> dict[str, float]:
    """Each calibrated segment frame's heading relative to ``ref``'s in the calibration pose,
    deg, in the calibration's common heading (0 where the frames agree there)."""
    imus = {s: recording.imu[s] for s in frames}
    _, R_mean = window_orientations(imus, cal.still)
    S = {s: cal.heading_matrix(s) @ R_mean[s] @ np.asarray(F, float) for s, F in frames.items()}
    return {s: float(np.degrees(relative_yaw(S[ref], S[s]))) for s in frames}


def read_chain(path) -> dict:
    """Read and check a ``chain.json`` (``InputError`` naming the file and what is wrong)."""
    p = Path(path).expanduser()
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(
            f"--chain {p}: file not found (kinefuse run writes {CHAIN_FILE})"
        ) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"--chain {p}: not a JSON file ({exc})") from None
    if not isinstance(d, dict) or d.get("format") != _FORMAT or d.get("version") != _VERSION:
        raise InputError(
            f"--chain {p}: expected a {CHAIN_FILE} written by kinefuse run (format "
            f"{_FORMAT!r}, version {_VERSION})"
        )
    skeleton_from_chain(d, str(p))  # every field checked once, here
    segment_frames_from_chain(d, str(p))
    carriers = d.get("offset_segments", {})
    if not isinstance(carriers, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in carriers.items()
    ):
        raise InputError(
            f"--chain {p}: offset_segments: expected {{joint: segment}} names, got {carriers!r}"
        )
    h = d.get("heading")
    if h is not None:
        w = h.get("window_s") if isinstance(h, dict) else None
        yaw = h.get("pose_yaw_deg", {}) if isinstance(h, dict) else None
        if (not isinstance(h, dict) or h.get("from") != "pose" or isinstance(w, bool)
                or not isinstance(w, (int, float)) or not w > 0
                or not isinstance(h.get("reference"), str) or not isinstance(yaw, dict)
                or not all(isinstance(v, (int, float)) and np.isfinite(v) for v in yaw.values())):  # fmt: skip
            raise InputError(
                f'--chain {p}: heading: expected {{"from": "pose", "window_s": > 0, "reference": '
                f'segment, "pose_yaw_deg": {{segment: deg}}}}, got {h!r}'
            )
    return d


def skeleton_from_chain(d: Mapping, source: str = CHAIN_FILE) -> tuple[Skeleton, tuple]:
    """The :class:`~kinefuse.kinematics.Skeleton` (sensor-frame axes) and root position of a
    chain description."""
    try:
        segs = d["segments"]
        sk = Skeleton(
            segments=tuple(s["name"] for s in segs),
            parents=tuple(int(s["parent"]) for s in segs),
            proximal=tuple(s["proximal"] for s in segs),
            distal=tuple(s["distal"] for s in segs),
            lengths_m=tuple(float(s["length_m"]) for s in segs),
            axes=np.array([s["axis_sensor"] for s in segs], dtype=float),
            root=d["root"],
            root_segment=d["root_segment"],
            offsets_m={j: np.array(v, dtype=float) for j, v in d["offsets_m"].items()},
        )
        root = tuple(float(v) for v in d["root_position_m"])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"{source}: malformed chain description ({type(exc).__name__}: {exc})"
        ) from None
    if len(root) != 3:
        raise InputError(f"{source}: root_position_m: expected 3 numbers, got {len(root)}")
    return sk, root


def segment_frames_from_chain(d: Mapping, source: str = CHAIN_FILE) -> dict[str, np.ndarray]:
    """``R_sensor_from_segment (3, 3)`` per segment of a chain description (empty: none, e.g.
    a chain file written before joint angles went live)."""
    out = {}
    for s, F in (d.get("segment_frames") or {}).items():
        try:
            R = np.array(F, dtype=float)
        except (TypeError, ValueError):
            R = np.zeros(0)
        if (
            R.shape != (3, 3)
            or not np.all(np.isfinite(R))
            or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
            or np.linalg.det(R) < 0
        ):
            raise InputError(
                f"{source}: segment_frames[{s!r}]: expected a 3 x 3 rotation matrix, got {F!r}"
            )
        out[s] = R
    return out
