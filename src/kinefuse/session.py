"""Session files: a TOML description of one recording and how to process it.

:func:`load_session` parses and validates a session file into a frozen :class:`SessionConfig`;
every problem is a :class:`~kinefuse.exceptions.ConfigError` naming the file, the section and
key, what was wrong and how to fix it, e.g.::

    session.toml: [imu] path: file 'x.csv' not found (relative paths are resolved against the
    TOML's folder)

:func:`session_template` returns the commented template that ``kinefuse init-session`` writes.
Relative paths in a session file are resolved against the folder of the TOML file, so a session
folder can be moved as a whole.
"""

from __future__ import annotations

import difflib
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

__all__ = [
    "CALIBRATIONS",
    "CAMERA_METHODS",
    "METHODS",
    "METHOD_INFO",
    "ROOTS",
    "CalibrationConfig",
    "CameraConfig",
    "ImuConfig",
    "MethodConfig",
    "ReferenceConfig",
    "SessionConfig",
    "SkeletonConfig",
    "load_session",
    "session_template",
]

#: The one method registry: name -> (what it uses, what it does). ``kinefuse init-session``
#: writes these lines into the template.
METHOD_INFO = {
    "paper-a": ("IMUs", "EM-KF/FIR integrated filter on the IMU chain (Sun et al. 2024)"),
    "elm-fir": ("IMUs + camera", "ELM/FIR with IMM fusion of chain and camera (Xu et al. 2023)"),
    "elm-kf": ("IMUs + camera", "the ELM/KF baseline of Xu et al. 2023"),
    "imu-only": ("IMUs", "forward kinematics of the IMU chain, no filtering"),
    "camera-only": ("camera", "the camera joints alone, gaps interpolated (a baseline)"),
    "kinefuse": (
        "IMUs + camera",
        "kinefuse's chain + camera fusion with a learned chain-error model",
    ),
    "offset-interp": (
        "IMUs + camera",
        "baseline: IMU chain + camera-chain offset interpolated across outages (offline)",
    ),
    "offset-hold": (
        "IMUs + camera",
        "baseline: IMU chain + mean offset of the last 5 camera samples (causal)",
    ),
    "camera-gapfill": (
        "camera",
        "the camera, gaps up to 20 frames linearly interpolated (as Pose2Sim)",
    ),
}
#: Processing methods a session can ask for.
METHODS = tuple(METHOD_INFO)
#: Methods that cannot run without a ``[camera]`` section.
CAMERA_METHODS = tuple(m for m, (uses, _) in METHOD_INFO.items() if "camera" in uses)
#: ``[calibration] method`` values: what calibrates the sensor-to-segment axes.
CALIBRATIONS = {
    "static": "a still pose (N-pose or T-pose) found in the IMU data; IMUs only",
    "functional": "movement of adjacent segments (joint centres and axes); IMUs only",
    "vision": "the camera joints in a window; needs [camera]",
    "reference": "the reference joints in a window; needs [reference] (then labelled)",
    "none": "no calibration: the configured sensor axes are used",
}
#: ``[skeleton] root`` values: where the chain starts.
ROOTS = {
    "fixed": "a position measured once (root_position_m, default the origin)",
    "pelvis": "positions relative to the pelvis; hips from the pelvis IMU",
    "vision": "the camera joints; needs [camera]",
    "reference": "the reference joints; needs [reference]",
}

_PATH_HINT = "relative paths are resolved against the TOML's folder"


@dataclass(frozen=True)
class ImuConfig:
    """``[imu]``: the IMU recording.

    Attributes
    ----------
    format : str
        Reader name (see :mod:`kinefuse.io`).
    path : Path
        Absolute path of the recording.
    rate_hz : float or None
        Sampling rate, Hz, when the file has no time stamps (None: from the file).
    segments : dict of str -> str
        Canonical segment name (:data:`kinefuse.conventions.SEGMENTS`) -> sensor name in the file.
    reader : dict
        ``[imu.reader]``: keyword arguments of the format's reader (e.g. ``earth_frame``).
    """

    format: str
    path: Path
    rate_hz: float | None
    segments: dict[str, str]
    reader: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SkeletonConfig:
    """``[skeleton]``: body dimensions.

    Attributes
    ----------
    body_height_m : float or None
        Body height, m, for anthropometric segment lengths (Winter 2009) and the hip width.
    lengths_m : dict of str -> float
        Measured segment lengths, m, by segment name (override the anthropometric ones).
    root : str or None
        :data:`ROOTS` key (None: the default, see :func:`kinefuse.pipelines.process_recording`).
    root_position_m : tuple of float, dict of str -> tuple, or None
        ``root = "fixed"``: the root joint's position (m), or one per chain start.
    axes : dict of str -> str or tuple
        Declared sensor axis along each segment (mounting), e.g. ``thigh_l = "+e1"``.
    """

    body_height_m: float | None
    lengths_m: dict[str, float] = field(default_factory=dict)
    root: str | None = None
    root_position_m: object = None
    axes: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CalibrationConfig:
    """``[calibration]`` (optional): how the sensor-to-segment axes are found.

    Attributes
    ----------
    settings : dict
        ``method`` (:data:`CALIBRATIONS`), ``window_s``, ``start_s``, ``pose`` (``"n"`` /
        ``"t"``), ``facing`` ([x, y, z]), ``heading`` (``"auto"``, ``"none"``, ``"static"``),
        ``flexion_axes`` (``"auto"``, ``"movement"``, ``"pose"``), ``lengths_from_data``
        (bool), ``max_rate_rad_s``, ``max_acc_std_m_s2``, as given.
    """

    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CameraConfig:
    """``[camera]`` (optional): a camera skeleton (Kinect, Azure Kinect, MediaPipe...).

    Attributes
    ----------
    format : str
    path : Path
    availability_threshold : float or None
        Joints whose tracker confidence is below this are treated as unavailable (None: the
        reader's default, e.g. Kinect TrackingState == Tracked).
    reader : dict
        ``[camera.reader]``: keyword arguments of the format's reader, e.g. for a Kinect v2
        recorder CSV ``time_column = "TimeSpan"``, ``time_unit = "ms"``,
        ``confidence_states = {"0" = 0, "0.5" = 1, "1" = 2}``.
    """

    format: str
    path: Path
    availability_threshold: float | None = None
    reader: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ReferenceConfig:
    """``[reference]`` (optional): ground-truth joints (optical mocap) for evaluation only.

    ``align = "rigid"`` asks for a Kabsch rotation + translation of the estimates onto the
    reference before scoring (labelled in every table); default ``"none"``.
    ``reader``: ``[reference.reader]``, keyword arguments of the format's reader (e.g.
    ``length_unit_m`` for a BVH file).
    """

    format: str
    path: Path
    align: str = "none"
    reader: dict = field(default_factory=dict)


@dataclass(frozen=True)
class MethodConfig:
    """``[method]``: which pipeline and its parameters (validated by the pipeline)."""

    name: str
    parameters: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SessionConfig:
    """A validated session file.

    Attributes
    ----------
    path : Path
        The TOML file (absolute).
    name : str
        Session name.
    out_dir : Path
        Output folder (absolute).
    imu : ImuConfig
    skeleton : SkeletonConfig
    camera : CameraConfig or None
    reference : ReferenceConfig or None
    method : MethodConfig
    calibration : CalibrationConfig
    """

    path: Path
    name: str
    out_dir: Path
    imu: ImuConfig
    skeleton: SkeletonConfig
    camera: CameraConfig | None
    reference: ReferenceConfig | None
    method: MethodConfig
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def processing_parameters(self) -> dict:
        """``[method.parameters]`` merged with ``[calibration]``, the root and the alignment.

        Raises
        ------
        ConfigError
            The same setting given in two places with different values.
        """
        params = dict(self.method.parameters)
        c = dict(self.calibration.settings)
        new = {
            "calibration": c.get("method"),
            "calibration_window_s": c.get("window_s"),
            "calibration_start_s": c.get("start_s"),
            "pose": c.get("pose"),
            "facing": c.get("facing"),
            "heading": c.get("heading"),
            "flexion_axes": c.get("flexion_axes"),
            "measured_lengths": c.get("lengths_from_data"),
            "max_rate_rad_s": c.get("max_rate_rad_s"),
            "max_acc_std_m_s2": c.get("max_acc_std_m_s2"),
            "root": self.skeleton.root,
            "root_position_m": self.skeleton.root_position_m,
            "axes": self.skeleton.axes or None,
            "align_to_reference": (
                None
                if self.reference is None or self.reference.align == "none"
                else self.reference.align
            ),
        }
        for k, v in new.items():
            if v is None:
                continue
            if k in params and params[k] != v:
                raise ConfigError(
                    f"{self.path.name}: {k} given twice ([method.parameters] {k} = "
                    f"{params[k]!r} and {v!r}); keep one"
                )
            params[k] = v
        return params

    @property
    def inputs(self) -> tuple[Path, ...]:
        """The session file and every file or folder it reads (never written over)."""
        streams = (self.imu, self.camera, self.reference)
        return (self.path, *(Path(st.path) for st in streams if st is not None))


# --------------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------------


class _Ctx:
    """Builds error messages ``"<file>: [<section>] <key>: <problem> (<fix>)"``."""

    def __init__(self, path: Path):
        self.path = path
        self.base = path.parent

    def error(
        self, section: str, key: str | None, problem: str, fix: str | None = None
    ) -> ConfigError:
        where = f"[{section}]" + (f" {key}" if key else "")
        msg = f"{self.path.name}: {where}: {problem}"
        if fix:
            msg += f" ({fix})"
        return ConfigError(msg)

    def table(self, doc: Mapping, section: str, *, required: bool) -> dict | None:
        value = doc.get(section)
        if value is None:
            if required:
                raise self.error(
                    section,
                    None,
                    "section missing",
                    f"add a [{section}] section; `kinefuse init-session` writes a template",
                )
            return None
        if not isinstance(value, dict):
            raise self.error(
                section,
                None,
                f"expected a table, got {type(value).__name__}",
                f"write it as a [{section}] section",
            )
        return value

    def reader(self, table: Mapping, section: str) -> dict:
        """``[<section>.reader]``: reader keyword arguments (checked by the reader on load)."""
        value = table.get("reader", {})
        if not isinstance(value, dict):
            raise self.error(
                f"{section}.reader",
                None,
                f"expected a table of reader arguments, got {value!r}",
                f'e.g. [{section}.reader] time_column = "TimeSpan"',
            )
        return dict(value)

    def check_keys(self, table: Mapping, section: str, allowed: tuple[str, ...]) -> None:
        for key in table:
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1)
                fix = (
                    f"did you mean {close[0]!r}?"
                    if close
                    else f"allowed keys: {', '.join(allowed)}"
                )
                raise self.error(section, key, "unknown key", fix)

    def string(
        self,
        table: Mapping,
        section: str,
        key: str,
        *,
        required: bool = True,
        default: str | None = None,
    ) -> str | None:
        if key not in table:
            if required:
                raise self.error(section, key, "missing", f'add {key} = "..."')
            return default
        value = table[key]
        if not isinstance(value, str) or not value.strip():
            raise self.error(
                section, key, f"expected a non-empty string, got {value!r}", f'write {key} = "..."'
            )
        return value.strip()

    def number(
        self,
        table: Mapping,
        section: str,
        key: str,
        *,
        required: bool = False,
        positive: bool = True,
        minimum: float | None = None,
    ) -> float | None:
        if key not in table:
            if required:
                raise self.error(section, key, "missing", f"add {key} = <number>")
            return None
        value = table[key]
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
        ):
            raise self.error(
                section,
                key,
                f"expected a number, got {value!r}",
                f"write e.g. {key} = 1.0 without quotes",
            )
        if positive and value <= 0:
            raise self.error(section, key, f"expected a number > 0, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.error(section, key, f"expected a number >= {minimum}, got {value!r}")
        return float(value)

    def file(self, table: Mapping, section: str, key: str = "path") -> Path:
        raw = self.string(table, section, key)
        p = Path(raw).expanduser()
        if not p.is_absolute():
            p = self.base / p
        if not p.exists():
            raise self.error(section, key, f"file {raw!r} not found", _PATH_HINT)
        return p.resolve()


# --------------------------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------------------------


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
        doc = read_toml(
            p, missing=f"session file not found (create one with `kinefuse init-session {p}`)"
        )
    p = p.resolve()
    c = _Ctx(p)
    c.check_keys(
        doc,
        "top level",
        ("session", "imu", "skeleton", "calibration", "camera", "reference", "method"),
    )

    s = c.table(doc, "session", required=True)
    c.check_keys(s, "session", ("name", "out_dir"))
    name = c.string(s, "session", "name")
    out_raw = c.string(s, "session", "out_dir", required=False, default="results")
    out_dir = Path(out_raw).expanduser()
    out_dir = (out_dir if out_dir.is_absolute() else p.parent / out_dir).resolve()

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
        if k not in SEGMENTS:
            close = difflib.get_close_matches(k, SEGMENTS, n=1)
            fix = (
                f"did you mean {close[0]!r}?" if close else f"expected one of {', '.join(SEGMENTS)}"
            )
            raise c.error("imu.segments", repr(k), "unknown segment", fix)
        if not isinstance(v, str) or not v.strip():
            raise c.error(
                "imu.segments", k, f"expected the sensor name as a non-empty string, got {v!r}"
            )
        segments[k] = v.strip()
    imu = ImuConfig(
        format=c.string(t, "imu", "format"),
        path=imu_path,
        rate_hz=c.number(t, "imu", "rate_hz"),
        segments=segments,
        reader=c.reader(t, "imu"),
    )

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
    lengths: dict[str, float] = {}
    raw_lengths = k.get("lengths", {})
    if not isinstance(raw_lengths, dict):
        raise c.error(
            "skeleton.lengths",
            None,
            "expected a table segment = length in m",
            "e.g. [skeleton.lengths] forearm_r = 0.26",
        )
    for seg_name in raw_lengths:
        if seg_name not in SEGMENTS:
            close = difflib.get_close_matches(seg_name, SEGMENTS, n=1)
            fix = (
                f"did you mean {close[0]!r}?" if close else f"expected one of {', '.join(SEGMENTS)}"
            )
            raise c.error("skeleton.lengths", repr(seg_name), "unknown segment", fix)
        val = c.number(raw_lengths, "skeleton.lengths", seg_name, required=True)
        if val > 1.5:
            raise c.error(
                "skeleton.lengths",
                seg_name,
                f"{val} m is not a plausible segment length",
                "lengths are in metres",
            )
        lengths[seg_name] = val
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
        root_pos = (
            {j: tuple(map(float, v)) for j, v in root_pos.items()}
            if isinstance(root_pos, dict)
            else tuple(map(float, root_pos))
        )
    axes = k.get("axes", {})
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
    skeleton = SkeletonConfig(
        body_height_m=height,
        lengths_m=lengths,
        root=root,
        root_position_m=root_pos,
        axes=dict(axes),
    )

    cal = c.table(doc, "calibration", required=False) or {}
    c.check_keys(
        cal,
        "calibration",
        (
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
        ),
    )
    settings = dict(cal)
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
    if "lengths_from_data" in cal and not isinstance(cal["lengths_from_data"], bool):
        raise c.error("calibration", "lengths_from_data", "expected true or false")
    calibration = CalibrationConfig(settings=settings)
    if height is None and not lengths and settings.get("method") != "functional":
        raise c.error(
            "skeleton",
            None,
            "needs body_height_m or [skeleton.lengths] (or [calibration] method = "
            "'functional', which estimates lengths from movement)",
            "add e.g. body_height_m = 1.75",
        )

    camera = None
    cam = c.table(doc, "camera", required=False)
    if cam is not None:
        c.check_keys(cam, "camera", ("format", "path", "availability_threshold", "reader"))
        camera = CameraConfig(
            format=c.string(cam, "camera", "format"),
            path=c.file(cam, "camera"),
            availability_threshold=c.number(
                cam, "camera", "availability_threshold", positive=False, minimum=0.0
            ),
            reader=c.reader(cam, "camera"),
        )

    reference = None
    ref = c.table(doc, "reference", required=False)
    if ref is not None:
        c.check_keys(ref, "reference", ("format", "path", "align", "reader"))
        align = c.string(ref, "reference", "align", required=False, default="none")
        if align not in ("none", "rigid"):
            raise c.error("reference", "align", f"expected 'none' or 'rigid', got {align!r}")
        reference = ReferenceConfig(
            format=c.string(ref, "reference", "format"),
            path=c.file(ref, "reference"),
            align=align,
            reader=c.reader(ref, "reference"),
        )

    m = c.table(doc, "method", required=True)
    c.check_keys(m, "method", ("name", "parameters"))
    mname = c.string(m, "method", "name")
    if mname not in METHODS:
        close = difflib.get_close_matches(mname, METHODS, n=1)
        fix = f"did you mean {close[0]!r}?" if close else f"expected one of {', '.join(METHODS)}"
        raise c.error("method", "name", f"unknown method {mname!r}", fix)
    if mname in CAMERA_METHODS and camera is None:
        raise c.error(
            "method",
            "name",
            f"method {mname!r} needs a camera (it uses {METHOD_INFO[mname][0]})",
            "add a [camera] section or choose 'imu-only' / 'paper-a'",
        )
    cm = settings.get("method")
    if cm == "vision" and camera is None:
        raise c.error("calibration", "method", "'vision' needs a [camera] section")
    if cm == "reference" and reference is None:
        raise c.error("calibration", "method", "'reference' needs a [reference] section")
    if root == "vision" and camera is None:
        raise c.error("skeleton", "root", "'vision' needs a [camera] section")
    if root == "reference" and reference is None:
        raise c.error("skeleton", "root", "'reference' needs a [reference] section")
    if mname in CAMERA_METHODS and root in ("fixed", "pelvis"):
        raise c.error(
            "skeleton", "root", f"method {mname!r} fuses with the camera; it needs root 'vision'"
        )
    params = m.get("parameters", {})
    if not isinstance(params, dict):
        raise c.error("method", "parameters", "expected a table", "write it as [method.parameters]")
    method = MethodConfig(name=mname, parameters=dict(params))

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


_TEMPLATE = """\
# kinefuse session file. Edit the paths and settings, then run:
#     kinefuse run {filename}
# Relative paths are resolved against the folder of this file. Units are SI (m, s, Hz).

[session]
name = "{name}"  # shown in reports
out_dir = "results/{name}"  # output folder; kinefuse refuses to overwrite a report without --force

[imu]
format = "imu_csv"               # reader of the IMU file: one of {formats}
path = "data/imu.csv"            # the IMU recording (a file, or a folder for ximu3 / neura / opensense)
rate_hz = 100.0                  # only used when the file has no time stamps; delete otherwise

[imu.segments]
# canonical segment = sensor name as written in the file
# segments: {segments}
upper_arm_r = "IMU 1"
forearm_r = "IMU 2"

[skeleton]
body_height_m = 1.75             # lengths from body height (Winter 2009 ratios) where not measured
# root: where the chain starts
{roots}
root = "fixed"
root_position_m = [0.0, 0.0, 0.0]  # root = "fixed": the measured root joint (here the shoulder), m

# [skeleton.lengths]             # measured (tape) lengths in m; they win over body height
# upper_arm_r = 0.30
# forearm_r = 0.26

# [skeleton.axes]                # optional: the sensor axis that runs along each segment
# upper_arm_r = "+e1"            # (proximal -> distal); checked against the static pose

[calibration]
# method: what finds each sensor's axis on its segment
{calibrations}
# default: "vision" with a [camera], else "static"
method = "static"
pose = "n"                       # "n": arms hanging, "t": T-pose (static only)
# window_s = 2.0                 # still window length, s; found automatically unless start_s is given
# start_s = 0.0
# heading = "auto"               # 6-D sensors (no magnetometer): "static" aligns their headings
# flexion_axes = "auto"          # elbow/knee flexion axes: "movement" (6-D default) or "pose"

# Optional: a camera skeleton. Needed by {camera_methods}.
# [camera]
# format = "kinect_v2"
# path = "data/kinect.csv"
# availability_threshold = 2     # tracker confidence below this = joint unavailable
# [camera.reader]                # optional: the reader's own arguments (docs/formats.md),
# time_column = "TimeSpan"       # e.g. an LSL-Kinect recorder CSV's time column, Unix ms
# time_unit = "ms"               # ([imu.reader] and [reference.reader] work the same way)

# Optional: ground truth (optical mocap), used ONLY to evaluate (RMSE tables) unless you ask
# otherwise (calibration method = "reference", root = "reference", align = "rigid"; then
# every table says so).
# [reference]
# format = "c3d"
# path = "data/reference.c3d"
# align = "none"                 # "rigid": Kabsch-align the estimates to it before scoring

[method]
{methods}
name = "paper-a"

[method.parameters]
# method-specific settings; leave empty for the defaults. Examples for paper-a:
# q = 1.0          # process-noise scale (paper A elbow test 1)
# r = 0.01         # measurement-noise variance, m^2
"""


def session_template(name: str = "my-session", filename: str = "session.toml") -> str:
    """The commented session template written by ``kinefuse init-session``.

    Parameters
    ----------
    name : str
        Session name (also used for the default output folder).
    filename : str
        File name mentioned in the header comment.

    Returns
    -------
    str
        TOML text; it loads with :func:`load_session` once ``[imu] path`` exists.
    """
    from kinefuse.io import FORMATS

    safe = "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in name) or "session"

    def listing(d: Mapping) -> str:
        w = max(len(k) for k in d) + 2
        return "\n".join(f"#   {k + ' ' * (w - len(k))}: {v}" for k, v in d.items())

    methods = {"name": f"{'uses':<14} : what it does"}
    methods.update({m: f"{uses:<14} : {what}" for m, (uses, what) in METHOD_INFO.items()})
    return _TEMPLATE.format(
        name=safe,
        filename=filename,
        formats=", ".join(sorted(FORMATS)),
        segments=", ".join(SEGMENTS),
        roots=listing(ROOTS),
        calibrations=listing(CALIBRATIONS),
        camera_methods=", ".join(CAMERA_METHODS),
        methods=listing(methods).replace("#   ", "# ", -1),
    )
