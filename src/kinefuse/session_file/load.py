"""Loading a session file: :func:`read_toml` and :func:`load_session`, one parser per section.

Every problem is a :class:`~kinefuse.exceptions.ConfigError` naming the file, the section and
key, what was wrong and how to fix it, e.g.::

    session.toml: [imu] path: file 'x.csv' not found (relative paths are resolved against the
    TOML's folder)
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path

from kinefuse import methods
from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import ConfigError
from kinefuse.session_file._checks import _Ctx
from kinefuse.session_file.config import (
    CALIBRATIONS,
    ROOTS,
    CalibrationConfig,
    CameraConfig,
    ImuConfig,
    MethodConfig,
    ReferenceConfig,
    SessionConfig,
    SkeletonConfig,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

__all__ = ["load_session", "read_toml"]

_SECTIONS = ("session", "imu", "skeleton", "calibration", "camera", "reference", "method")
#: Tables of other commands that a session file may hold: ``kinefuse stream`` reads and checks
#: ``[stream]`` (docs/streaming.md); ``kinefuse run`` leaves it alone.
_OTHER_COMMANDS = ("stream",)
_CALIBRATION_KEYS = (
    "method",
    "window_s",
    "start_s",
    "pose",
    "facing",
    "heading",
    "flexion_axes",
    "lengths_from_data",
    "max_rate_rad_s",
    "max_acc_std_m_s2",
)


def read_toml(path: str | Path, *, missing: str = "file not found") -> dict:
    """Parse a TOML file (session files of ``kinefuse run`` and ``kinefuse stream``).

    Raises
    ------
    ConfigError
        ``"{path}: {missing}"`` when there is no such file; ``"{name}: not valid TOML: …"``
        or ``"{name}: not a UTF-8 text file"`` when it cannot be read.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"{p}: {missing}")
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p.name}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p.name}: not a UTF-8 text file") from None


def init_session_hint(recording) -> str:
    """The command that makes a session file from ``recording`` (for error messages)."""
    return f"`kinefuse init-session SESSION.toml --from {recording}`"


def _read_session_toml(p: Path) -> dict:
    """:func:`read_toml` of a session file; a folder, or a file that is not TOML and not named
    ``.toml`` (a recording given where the session belongs), gets the command that makes a
    session from it."""
    make = f"make a session from it with {init_session_hint(p)}"
    if p.is_dir():
        raise ConfigError(f"{p}: a folder, not a session file; {make}")
    try:
        return read_toml(
            p, missing=f"session file not found (create one with `kinefuse init-session {p}`)"
        )
    except ConfigError as exc:
        if p.is_file() and p.suffix.lower() != ".toml":
            raise ConfigError(f"{exc}; if {p.name} is a recording, {make}") from None
        raise


def load_session(path: str | Path, *, document: Mapping | None = None) -> SessionConfig:
    """Read and validate a session TOML file.

    Parameters
    ----------
    path : str or Path
        The session file.
    document : mapping, optional
        The parsed TOML to validate instead of reading ``path`` (``kinefuse batch`` merges a
        study's defaults into it); ``path`` still names the file in messages and is the base of
        relative paths.

    Returns
    -------
    SessionConfig
        With absolute paths (relative ones resolved against the TOML's folder) that exist.

    Raises
    ------
    ConfigError
        The file is missing, is not valid TOML, or a section/key is missing, unknown, of the
        wrong type or names a file that does not exist. The message names the file, section
        and key, and says how to fix it.
    """
    p = Path(path).expanduser()
    doc = document
    if doc is None:
        doc = _read_session_toml(p)
    p = p.resolve()
    c = _Ctx(p)
    c.check_keys(doc, "top level", _SECTIONS + _OTHER_COMMANDS)
    name, out_dir = _session(c, doc)
    imu = _imu(c, doc)
    skeleton = _skeleton(c, doc)
    calibration = _calibration(c, doc)
    if (
        skeleton.body_height_m is None
        and not skeleton.lengths_m
        and calibration.settings.get("method") != "functional"
    ):
        raise c.error(
            "skeleton",
            None,
            "needs body_height_m or [skeleton.lengths] (or [calibration] method = "
            "'functional', which estimates lengths from movement)",
            "add e.g. body_height_m = 1.75",
        )
    camera = _camera(c, doc)
    reference = _reference(c, doc)
    method = _method(c, doc, calibration, skeleton.root, camera, reference)
    return SessionConfig(
        path=p,
        name=name,
        out_dir=out_dir,
        imu=imu,
        skeleton=skeleton,
        camera=camera,
        reference=reference,
        method=method,
        calibration=calibration,
    )


def _session(c: _Ctx, doc: Mapping) -> tuple[str, Path]:
    """``[session]``: the name and the absolute output folder."""
    s = c.table(doc, "session", required=True)
    c.check_keys(s, "session", ("name", "out_dir"))
    name = c.string(s, "session", "name")
    out_raw = c.string(s, "session", "out_dir", required=False, default="results")
    out_dir = Path(out_raw).expanduser()
    return name, (out_dir if out_dir.is_absolute() else c.base / out_dir).resolve()


def _imu(c: _Ctx, doc: Mapping) -> ImuConfig:
    """``[imu]`` and ``[imu.segments]``."""
    t = c.table(doc, "imu", required=True)
    c.check_keys(t, "imu", ("format", "path", "rate_hz", "segments", "reader"))
    imu_path = c.file(t, "imu")
    seg = t.get("segments")
    if seg is None:
        raise c.error(
            "imu.segments",
            None,
            "section missing",
            'add [imu.segments] with lines like forearm_r = "sensor name in the file"',
        )
    if not isinstance(seg, dict) or not seg:
        raise c.error(
            "imu.segments",
            None,
            "expected a non-empty table segment = sensor name",
            'e.g. forearm_r = "IMU 2"',
        )
    segments = {}
    for k, v in seg.items():
        c.segment("imu.segments", k)
        if not isinstance(v, str) or not v.strip():
            raise c.error(
                "imu.segments", k, f"expected the sensor name as a non-empty string, got {v!r}"
            )
        segments[k] = v.strip()
    by_sensor: dict[str, list[str]] = {}
    for k, v in segments.items():
        by_sensor.setdefault(v, []).append(k)
    twice = {v: ks for v, ks in by_sensor.items() if len(ks) > 1}
    if twice:
        v, ks = next(iter(twice.items()))
        raise c.error(
            "imu.segments",
            ks[1],
            f"sensor {v!r} is mapped to {len(ks)} segments ({', '.join(ks)}); one IMU is worn on "
            "one segment",
            "map each segment to its own sensor",
        )
    return ImuConfig(
        format=c.string(t, "imu", "format"),
        path=imu_path,
        rate_hz=c.number(t, "imu", "rate_hz"),
        segments=segments,
        reader=c.reader(t, "imu"),
    )


def _skeleton(c: _Ctx, doc: Mapping) -> SkeletonConfig:
    """``[skeleton]``, ``[skeleton.lengths]`` and ``[skeleton.axes]``."""
    k = c.table(doc, "skeleton", required=True)
    c.check_keys(k, "skeleton", ("body_height_m", "lengths", "root", "root_position_m", "axes"))
    height = c.number(k, "skeleton", "body_height_m")
    if height is not None and not (0.5 <= height <= 2.8):
        raise c.error(
            "skeleton",
            "body_height_m",
            f"{height} m is not a plausible body height",
            "give it in metres, e.g. 1.75",
        )
    lengths = _lengths(c, k.get("lengths", {}))
    root = c.string(k, "skeleton", "root", required=False)
    if root is not None and root not in ROOTS:
        raise c.error(
            "skeleton", "root", f"unknown root {root!r}", f"expected one of {', '.join(ROOTS)}"
        )
    root_pos = k.get("root_position_m")
    if root_pos is not None:
        if root not in (None, "fixed"):
            raise c.error(
                "skeleton", "root_position_m", f"only used with root = 'fixed', not {root!r}"
            )
        root = "fixed"
        root_pos = _root_position(c, root_pos)
    return SkeletonConfig(
        body_height_m=height,
        lengths_m=lengths,
        root=root,
        root_position_m=root_pos,
        axes=_axes(c, k.get("axes", {})),
    )


def _lengths(c: _Ctx, raw_lengths) -> dict[str, float]:
    """``[skeleton.lengths]``: segment -> measured length, m."""
    if not isinstance(raw_lengths, dict):
        raise c.error(
            "skeleton.lengths",
            None,
            "expected a table segment = length in m",
            "e.g. [skeleton.lengths] forearm_r = 0.26",
        )
    lengths: dict[str, float] = {}
    for seg_name in raw_lengths:
        c.segment("skeleton.lengths", seg_name)
        val = c.number(raw_lengths, "skeleton.lengths", seg_name, required=True)
        if val > 1.5:
            raise c.error(
                "skeleton.lengths",
                seg_name,
                f"{val} m is not a plausible segment length",
                "lengths are in metres",
            )
        lengths[seg_name] = val
    return lengths


def _root_position(c: _Ctx, root_pos):
    """``[skeleton] root_position_m``: ``[x, y, z]`` m, or one per chain start."""
    items = root_pos.items() if isinstance(root_pos, dict) else [(None, root_pos)]
    for joint, v in items:
        if (
            not isinstance(v, list)
            or len(v) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        ):
            raise c.error(
                "skeleton",
                "root_position_m" + (f".{joint}" if joint else ""),
                f"expected [x, y, z] in m, got {v!r}",
                "e.g. root_position_m = [0.0, 0.0, 1.4]",
            )
        if any(abs(x) > 100 for x in v):
            raise c.error("skeleton", "root_position_m", f"{v} is not a position in metres")
    if isinstance(root_pos, dict):
        return {j: tuple(map(float, v)) for j, v in root_pos.items()}
    return tuple(map(float, root_pos))


def _axes(c: _Ctx, axes) -> dict:
    """``[skeleton.axes]``: segment -> axis name (``"+e1"``) or ``[x, y, z]``."""
    if not isinstance(axes, dict):
        raise c.error(
            "skeleton.axes", None, "expected a table segment = axis", 'e.g. thigh_l = "+e1"'
        )
    for seg_name, a in axes.items():
        if seg_name not in SEGMENTS:
            raise c.error("skeleton.axes", repr(seg_name), "unknown segment")
        ok = isinstance(a, str) or (
            isinstance(a, list) and len(a) == 3 and all(isinstance(x, (int, float)) for x in a)
        )
        if not ok:
            raise c.error(
                "skeleton.axes",
                seg_name,
                f"expected an axis name or [x, y, z], got {a!r}",
                'e.g. "+e1", "-e2"',
            )
    return dict(axes)


def _calibration(c: _Ctx, doc: Mapping) -> CalibrationConfig:
    """``[calibration]`` (optional)."""
    cal = c.table(doc, "calibration", required=False) or {}
    c.check_keys(cal, "calibration", _CALIBRATION_KEYS)
    if "method" in cal:
        cm = c.string(cal, "calibration", "method")
        if cm not in CALIBRATIONS:
            raise c.error(
                "calibration",
                "method",
                f"unknown calibration method {cm!r}",
                f"expected one of {', '.join(CALIBRATIONS)}",
            )
    for key in ("window_s", "max_rate_rad_s", "max_acc_std_m_s2"):
        c.number(cal, "calibration", key)
    c.number(cal, "calibration", "start_s", positive=False)
    for key, choices in (
        ("pose", ("n", "t")),
        ("heading", ("auto", "none", "static")),
        ("flexion_axes", ("auto", "movement", "pose")),
    ):
        if key in cal and cal[key] not in choices:
            raise c.error(
                "calibration", key, f"expected one of {', '.join(choices)}, got {cal[key]!r}"
            )
    f = cal.get("facing", "auto")
    if f != "auto" and not (
        isinstance(f, list)
        and len(f) == 3
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in f)
        and any(f[:2])
    ):
        raise c.error(
            "calibration",
            "facing",
            f'expected "auto" or a horizontal direction [x, y, z], got {f!r}',
            'e.g. facing = [0, 1, 0] (north), or leave it out: "auto" takes it from the movement',
        )
    if "lengths_from_data" in cal and not isinstance(cal["lengths_from_data"], bool):
        raise c.error("calibration", "lengths_from_data", "expected true or false")
    return CalibrationConfig(settings=dict(cal))


def _camera(c: _Ctx, doc: Mapping) -> CameraConfig | None:
    """``[camera]`` (optional)."""
    cam = c.table(doc, "camera", required=False)
    if cam is None:
        return None
    c.check_keys(cam, "camera", ("format", "path", "availability_threshold", "reader"))
    return CameraConfig(
        format=c.string(cam, "camera", "format"),
        path=c.file(cam, "camera"),
        availability_threshold=c.number(
            cam, "camera", "availability_threshold", positive=False, minimum=0.0
        ),
        reader=c.reader(cam, "camera"),
    )


def _reference(c: _Ctx, doc: Mapping) -> ReferenceConfig | None:
    """``[reference]`` (optional)."""
    ref = c.table(doc, "reference", required=False)
    if ref is None:
        return None
    c.check_keys(ref, "reference", ("format", "path", "align", "reader"))
    align = c.string(ref, "reference", "align", required=False, default="none")
    if align not in ("none", "rigid"):
        raise c.error("reference", "align", f"expected 'none' or 'rigid', got {align!r}")
    return ReferenceConfig(
        format=c.string(ref, "reference", "format"),
        path=c.file(ref, "reference"),
        align=align,
        reader=c.reader(ref, "reference"),
    )


def _method(c: _Ctx, doc: Mapping, calibration, root, camera, reference) -> MethodConfig:
    """``[method]``: a :mod:`kinefuse.methods` name whose inputs are configured, and its
    ``[method.parameters]`` table."""
    m = c.table(doc, "method", required=True)
    c.check_keys(m, "method", ("name", "parameters"))
    mname = c.string(m, "method", "name")
    if mname not in methods.REGISTRY:
        fix = methods.unknown_fix(mname)
        raise c.error("method", "name", f"unknown method {mname!r}", fix)
    _check_needs(c, mname, calibration, root, camera, reference)
    params = m.get("parameters", {})
    if not isinstance(params, dict):
        raise c.error("method", "parameters", "expected a table", "write it as [method.parameters]")
    return MethodConfig(name=mname, parameters=dict(params))


def _check_needs(c: _Ctx, mname: str, calibration, root, camera, reference) -> None:
    """The inputs the method, the calibration and the root need are configured."""
    spec = methods.get(mname)
    cam_method = "camera" in spec.needs
    if cam_method and camera is None:
        raise c.error(
            "method",
            "name",
            f"method {mname!r} needs a camera (it uses {spec.uses})",
            "add a [camera] section or choose 'imu-only' / 'paper-a'",
        )
    cm = calibration.settings.get("method")
    if cm == "vision" and camera is None:
        raise c.error("calibration", "method", "'vision' needs a [camera] section")
    if cm == "reference" and reference is None:
        raise c.error("calibration", "method", "'reference' needs a [reference] section")
    if root == "vision" and camera is None:
        raise c.error("skeleton", "root", "'vision' needs a [camera] section")
    if root == "reference" and reference is None:
        raise c.error("skeleton", "root", "'reference' needs a [reference] section")
    if cam_method and root in ("fixed", "pelvis"):
        raise c.error(
            "skeleton", "root", f"method {mname!r} fuses with the camera; it needs root 'vision'"
        )
