"""C3D reader (optical motion capture) via ``ezc3d`` (optional extra ``kinefuse[c3d]``)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError
from kinefuse.io._common import check_units, make_metadata, map_joints
from kinefuse.io.recording import JointStream, Recording

__all__ = ["read_c3d"]

_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "dm": 0.1}


def _check_header(path: Path) -> None:
    """Validate the 512-byte C3D header and the file length before handing the file to ezc3d.

    ezc3d does not detect a truncated data section (it returns garbage), so the expected size
    is computed from the header: ``(data_start - 1) * 512 + n_frames * frame_bytes``.
    """
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(512)
            param_block = head[0] if head else 0
            fh.seek(max(param_block - 1, 0) * 512)
            param_head = fh.read(4)
    except OSError as e:
        raise FormatError(path, f"could not read the file: {e}") from None
    if len(head) < 512 or head[1] != 0x50 or param_block < 2:
        found = head[:2].hex() if head else "an empty file"
        raise FormatError(
            path,
            f"expected a C3D header (byte 2 = 0x50, parameter block >= 2), found {found}",
            field="header",
        )
    proc = param_head[3] if len(param_head) == 4 else 84
    endian = ">" if proc == 86 else "<"  # 84 Intel, 85 DEC, 86 MIPS (big-endian)
    words = struct.unpack(endian + "9H", head[2:20])
    n_points, n_analog, first, last = words[0], words[1], words[2], words[3]
    if proc == 85:  # DEC F-float: the sign is bit 7 of the second byte
        scale_negative = bool(head[13] & 0x80)
    else:
        scale_negative = struct.unpack(endian + "f", head[12:16])[0] < 0
    data_start = words[7]
    n_frames = last - first + 1
    word_bytes = 4 if scale_negative else 2
    expected = (data_start - 1) * 512 + n_frames * (4 * n_points + n_analog) * word_bytes
    if n_frames > 0 and size < expected:
        raise FormatError(
            path,
            f"truncated C3D: header announces {n_frames} frames of {n_points} points and {n_analog} analog samples "
            f"({expected} bytes), file has {size} bytes",
            field="data",
        )


def read_c3d(path, *, role: str = "reference", units: str | None = None) -> Recording:
    """Read the 3-D points (markers or joint centres) of a C3D file.

    Parameters
    ----------
    path : str or Path
        ``.c3d`` file.
    role : {"reference", "vision"}
        Where the points go in the Recording (optical mocap is usually the reference).
    units : str or None
        Override of the ``POINT:UNITS`` parameter (``mm``, ``cm``, ``m``).

    Returns
    -------
    Recording
        ``reference`` (or ``vision``): positions (T, P, 3) in m (converted from
        ``POINT:UNITS``), frame ``"c3d_lab"`` (the lab frame of the file; often z up), times
        ``n / POINT:RATE``. Labels that name a joint (canonical names, Kinect-style
        ``ShoulderLeft``, Plug-in-Gait joint centres ``LFEO``...) become canonical joint names;
        other labels are kept (``metadata["joint_map"]``). ``available`` = finite and residual
        >= 0 (C3D marks invalid points with a negative residual).

    Raises
    ------
    FormatError
        Not a C3D file, truncated data, unknown units.
    ImportError
        ``ezc3d`` is not installed (``pip install kinefuse[c3d]``).
    """
    path = Path(path)
    if role not in ("reference", "vision"):
        raise FormatError(path, f"expected role 'reference' or 'vision', got {role!r}")
    _check_header(path)
    try:
        import ezc3d
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("reading C3D needs ezc3d: pip install 'kinefuse[c3d]'") from e
    try:
        c = ezc3d.c3d(str(path))
    except Exception as e:
        raise FormatError(path, f"ezc3d could not parse the file: {e}") from None
    point = c["parameters"]["POINT"]
    labels = [str(s).strip() for s in point["LABELS"]["value"]]
    pts = np.asarray(c["data"]["points"], dtype=float)  # (4, P, T)
    if pts.ndim != 3 or pts.shape[0] != 4 or pts.shape[1] != len(labels):
        raise FormatError(
            path, f"expected points (4, {len(labels)}, T), found {pts.shape}", field="POINT:LABELS"
        )
    unit = units
    if unit is None:
        uv = point["UNITS"]["value"] if "UNITS" in point else []
        unit = str(uv[0]).strip() if len(uv) else "mm"
    factor = _TO_M.get(unit.lower())
    if factor is None:
        raise FormatError(
            path,
            f"expected POINT:UNITS one of {sorted(_TO_M)}, found {unit!r}",
            field="POINT:UNITS",
        )
    rate = float(np.asarray(point["RATE"]["value"]).reshape(-1)[0])
    if not rate > 0:
        raise FormatError(path, f"expected a positive POINT:RATE, found {rate}", field="POINT:RATE")
    pos = np.transpose(pts[:3], (2, 1, 0)) * factor  # (T, P, 3)
    avail = np.all(np.isfinite(pos), axis=-1)
    res = c["data"]["meta_points"].get("residuals") if "meta_points" in c["data"] else None
    if res is not None and np.asarray(res).shape == (1, pts.shape[1], pts.shape[2]):
        avail &= np.asarray(res)[0].T >= 0
    joints, jmap = map_joints(labels)
    t = np.arange(pos.shape[0]) / rate
    js = JointStream(t_s=t, position_m=pos, available=avail, joints=joints, frame="c3d_lab")
    first = int(c["header"]["points"]["first_frame"])
    md = make_metadata(
        path,
        "c3d",
        units_converted=[f"points {unit} -> m"] if factor != 1.0 else [],
        joint_map=jmap,
        rate_hz=rate,
        first_frame=first,
        availability_rule="finite and residual >= 0",
    )
    rec = Recording(**{role: js}, metadata=md)
    check_units(rec, where=str(path))
    return rec
