"""Format registry and :func:`load`: detection from content, extension and folder layout.

Readers are imported lazily (by module and function name), so ``load`` works for formats whose
module lands later and importing :mod:`kinefuse.io` stays cheap.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
from dataclasses import dataclass
from pathlib import Path

import scipy  # scipy.io loads on first use (SciPy imports its subpackages lazily)

from kinefuse.exceptions import FormatError, InputError
from kinefuse.io._unsupported import looks_like, unsupported_message
from kinefuse.io.recording import Recording

__all__ = ["FORMATS", "detect_format", "load"]


@dataclass(frozen=True)
class _Format:
    """One format :func:`load` reads: ``kinefuse.io.<module>.<function>``.

    ``extensions`` and ``sniff`` (a function of that module, ``sniff(head: str) -> bool`` on the
    file's first 8 KiB of text) let a format be detected without a rule in this module: they
    are tried after the built-in rules found nothing.
    """

    module: str
    function: str
    description: str
    extensions: tuple[str, ...] = ()
    sniff: str | None = None


_REGISTRY: dict[str, _Format] = {
    "utd_mhad": _Format(
        "utd_mhad",
        "read_utd_mhad",
        "UTD-MHAD trial: inertial .mat (wrist/thigh acc+gyr) + Kinect v1 skeleton .mat",
    ),
    "opensense": _Format(
        "opensense",
        "read_opensense",
        "Xsens MT Manager .txt exports (OpenSense): acc + orientation matrix",
    ),
    "qmt": _Format(
        "qmt", "read_qmt", "qmt example .mat: time vector + one struct per IMU (acc, gyr)"
    ),
    "ximu3": _Format(
        "ximu3", "read_ximu3", "x-IMU3 log: folder of sensor folders with Inertial/Quaternion CSVs"
    ),
    "broad": _Format(
        "broad", "read_broad", "BROAD .mat: IMU acc/gyr/mag + OptiTrack orientation and position"
    ),
    "c3d": _Format("c3d", "read_c3d", "C3D optical motion capture points (via ezc3d)"),
    "trc": _Format("trc", "read_trc", "TRC marker file (OpenSim / Motion Analysis)"),
    "kinect_v2": _Format(
        "kinect_v2", "read_kinect_v2_csv", "Kinect v2 joint CSV: 25 joints + TrackingState"
    ),
    "azure_kinect": _Format(
        "azure_kinect", "read_azure_kinect_json", "Azure Kinect body-tracking JSON: 32 joints"
    ),
    "mediapipe": _Format(
        "mediapipe",
        "read_mediapipe",
        "MediaPipe Pose world landmarks (CSV or JSON), 33 + visibility",
    ),
    "imu_csv": _Format(
        "generic_csv",
        "read_imu_csv",
        "kinefuse generic IMU CSV (t_s, sensor, qw.., acc_.., gyr_..)",
    ),
    "joint_csv": _Format(
        "generic_csv", "read_joint_csv", "kinefuse generic joint CSV (t_s, <joint>_x/_y/_z...)"
    ),
    "neura": _Format(
        "neura", "read_neura", "gaittoolbox / Neura sparse CSV: Xsens IMUs + Vicon joint centres"
    ),
    "cmu": _Format(
        "cmu", "read_asf_amc", "CMU ASF/AMC optical mocap (pass the .amc; asf_path= optional)"
    ),
    "bvh": _Format("bvh", "read_bvh", "BVH motion capture"),
    "opensense_sto": _Format(
        "opensim", "read_opensense_sto", "OpenSense orientation .sto (DataType=Quaternion)"
    ),
    "opensim_table": _Format(
        "opensim", "read_opensim_mot", "OpenSim .mot/.sto table (joint coordinates, units)"
    ),
    "mvnx": _Format("mvnx", "read_mvnx", "Xsens MVN MVNX: segments, sensors, calibration poses"),
    "xsens_dot": _Format(
        "xsens_dot", "read_xsens_dot", "Movella/Xsens DOT CSV (file or folder, SampleTimeFine)"
    ),
    "xio_csv": _Format(
        "xio_csv", "read_xio_csv", "x-io plain CSV: Time (s), Gyroscope, Accelerometer"
    ),
    "qualisys_tsv": _Format(
        "qualisys",
        "read_qualisys_tsv",
        "Qualisys QTM TSV export: 3D marker trajectories (mm)",
        extensions=(".tsv",),
        sniff="sniff",
    ),
}

#: Format name -> one-line description of every format :func:`load` knows.
FORMATS: dict[str, str] = {k: v.description for k, v in _REGISTRY.items()}


def _known() -> str:
    return ", ".join(sorted(FORMATS))


def _reader(fmt: str):
    if fmt not in _REGISTRY:
        raise InputError(f"unknown format {fmt!r}; known formats: {_known()}")
    spec = _REGISTRY[fmt]
    modname = f"kinefuse.io.{spec.module}"
    try:
        mod = importlib.import_module(modname)
    except ModuleNotFoundError as e:
        if e.name == modname:
            raise InputError(
                f"format {fmt!r}: reader module {modname} is not available in this installation"
            ) from e
        raise
    fn = getattr(mod, spec.function, None)
    if fn is None:
        raise InputError(f"format {fmt!r}: {modname} has no function {spec.function!r}")
    return fn


def _head(path: Path, n: int = 8192) -> str:
    try:
        with open(path, "rb") as fh:
            return fh.read(n).decode("utf-8", errors="replace")
    except OSError:
        return ""


def _detect_csv(path: Path) -> str | None:
    if (path.parent / "Inertial.csv").is_file():  # any CSV of an x-IMU3 sensor folder
        return "ximu3"
    head = _head(path)
    lines = [ln for ln in head.splitlines() if ln.strip()]
    if not lines:
        return None
    first = lines[0].strip().lower()
    if first.startswith("# kinefuse-imu-csv"):
        return "imu_csv"
    if first.startswith("# kinefuse-joint-csv"):
        return "joint_csv"
    if any(ln.startswith("PacketCounter,") and "SampleTimeFine" in ln for ln in lines):
        return "xsens_dot"
    body = [ln for ln in lines if not ln.lstrip().startswith(("#", "//"))]
    if not body:
        return None
    header = body[0].lower()
    if header.startswith("software : lsl_kinect") and len(body) > 1:  # preamble without '#'
        header = body[1].lower()
    cols = [c.strip() for c in header.replace("\t", ",").replace(";", ",").split(",")]
    if (
        cols
        and cols[0].startswith("timestamp (")
        and any("gyroscope" in c or c in ("w", "x") for c in cols)
    ):
        return "ximu3"
    if cols and cols[0].startswith("time (") and any(c.startswith("gyroscope x") for c in cols):
        return "xio_csv"
    if head.lstrip().startswith("//") and any(
        c.startswith(("ori_", "rfeo_", "pelv_", "acc_1")) for c in cols
    ):
        return "neura"
    if any(c in ("qw", "acc_x", "gyr_x") for c in cols):
        return "imu_csv"
    norm = {c.replace(" ", "").replace(".", "_") for c in cols}
    if any(c.endswith(("trackingstate", "tracking_state")) for c in norm) or any(
        c.startswith(("spinebase", "spineshoulder")) for c in norm
    ):
        return "kinect_v2"
    if any(c.endswith("_visibility") for c in cols) or any(
        c.startswith(("nose_", "left_wrist_", "left_foot_index_", "right_eye_")) for c in cols
    ):
        return "mediapipe"
    if any(c.endswith("_x") for c in cols):
        return "joint_csv"
    return None


def _detect_mat(path: Path) -> str | None:
    try:
        names = {n: cls for n, _shape, cls in scipy.io.whosmat(path)}
    except Exception as e:
        raise FormatError(
            path, f"expected a MATLAB v5 file, could not read its variable list: {e}"
        ) from None
    if "d_iner" in names or "d_skel" in names:
        return "utd_mhad"
    if "imu_gyr" in names and "opt_quat" in names:
        return "broad"
    if "t" in names and any(cls == "struct" for cls in names.values()):
        return "qmt"
    return None


def _detect_dir(path: Path) -> str | None:
    if (path / "Inertial.csv").is_file() or any(
        (p / "Inertial.csv").is_file() for p in path.iterdir() if p.is_dir()
    ):
        return "ximu3"
    if (path / "imu").is_dir() and (path / "vicon").is_dir():
        return "neura"
    if any("PacketCounter" in _head(p, 4096) for p in path.glob("*.txt")):
        return "opensense"
    if any(_detect_csv(p) == "xsens_dot" for p in path.glob("*.csv")):
        return "xsens_dot"
    if (path / "Inertial").is_dir() and (path / "Skeleton").is_dir():
        raise FormatError(
            path,
            "this is a UTD-MHAD dataset root; pass one trial's file, e.g. Inertial/a1_s1_t1_inertial.mat",
        )
    return None


def detect_format(path) -> str:
    """Name of the format of ``path`` (a file or a folder), detected from content and layout.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    FormatError
        The format could not be recognised: "unsupported format: this looks like X; kinefuse
        reads: ..." (what the file appears to be, and the known formats).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    fmt = None
    if path.is_dir():
        fmt = _detect_dir(path)
        only = _only_recording(path) if fmt is None else None
        if only is not None:
            return detect_format(only)
    else:
        ext = path.suffix.lower()
        if ext == ".mat":
            fmt = _detect_mat(path)
        elif ext == ".c3d":
            fmt = "c3d"
        elif ext == ".trc":
            fmt = "trc"
        elif ext == ".bvh":
            fmt = "bvh"
        elif ext == ".amc":
            fmt = "cmu"
        elif ext == ".asf":
            raise FormatError(
                path,
                "an ASF file holds only the skeleton; pass the motion (.amc) file (asf_path= optional)",
            )
        elif ext in (".mvnx", ".xml") and "<mvnx" in _head(path, 4096):
            fmt = "mvnx"
        elif ext in (".sto", ".mot"):
            quat = "DataType=Quaternion" in _head(path, 4096)
            fmt = "opensense_sto" if quat else "opensim_table"
        elif ext == ".json":
            fmt = _detect_json(path)
        elif ext == ".txt" and "PacketCounter" in _head(path, 4096):
            fmt = "opensense"
        elif ext in (".csv", ".txt", ".tsv"):
            fmt = _detect_csv(path)
    if fmt is None and path.is_file():
        fmt = _sniff(path)
    if fmt is None:
        raise FormatError(path, unsupported_message(path, FORMATS, _detect_entry))
    return fmt


#: Formats whose reader takes a folder.
_FOLDER_FORMATS = frozenset({"ximu3", "neura", "opensense", "xsens_dot"})


def _only_recording(folder: Path, format: str | None = None) -> Path | None:
    """The one file of ``folder`` kinefuse can read (of ``format``, when given), when there is
    exactly one and the folder's layout is no format's own (e.g. a dataset folder holding one
    ``.mat`` next to its README and licence); else None."""
    found = []
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        try:
            fmt = detect_format(p)
        except (ValueError, OSError):
            continue
        if format is None or fmt == format:
            found.append(p)
        if len(found) > 1:
            return None
    return found[0] if found else None


def _sniff(path: Path) -> str | None:
    """The first registered format whose extensions include ``path``'s and whose sniff accepts it."""
    ext = path.suffix.lower()
    for fmt, spec in _REGISTRY.items():
        if spec.sniff and ext in spec.extensions:
            sniff = getattr(importlib.import_module(f"kinefuse.io.{spec.module}"), spec.sniff)
            if sniff(_head(path)):
                return fmt
    return None


def _detect_entry(p: Path) -> str | None:
    """Format of one entry of a folder (sub-folders by layout only), for the unsupported message."""
    return _detect_dir(p) if p.is_dir() else detect_format(p)


def _detect_json(path: Path) -> str | None:
    head = _head(path, 65536)
    if '"bodies"' in head or '"joint_names"' in head:
        return "azure_kinect"
    if "world_landmarks" in head or '"landmarks"' in head:
        return "mediapipe"
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if isinstance(d, dict) and "frames" in d and d["frames"] and isinstance(d["frames"][0], dict):
        return "azure_kinect" if "bodies" in d["frames"][0] else "mediapipe"
    return None


def _check_options(reader, fmt: str, options) -> None:
    """Options ``load`` passes on must be keyword arguments of the reader (a TypeError named
    the Python function and not the option's use)."""
    params = inspect.signature(reader).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return
    known = [n for n, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY
             or (p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD and n != "path")]  # fmt: skip
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise InputError(
            f"unknown option(s) {unknown} for the {fmt!r} reader; it takes {sorted(known) or 'none'}"
        )


def load(path, format: str | None = None, **options) -> Recording:
    """Read a recording in any supported format into a :class:`~kinefuse.io.recording.Recording`.

    Parameters
    ----------
    path : str or Path or (path, path)
        A file, a dataset folder (x-IMU3 log, OpenSense folder, Neura sample), a folder holding
        exactly one readable recording besides other files (e.g. a README and a licence: that
        recording is read), or a pair of files (UTD-MHAD inertial + skeleton, in either order).
    format : str or None
        A key of :data:`FORMATS`; ``None`` detects it from content, extension and layout.
    **options
        Passed to the reader (see each reader's docstring), e.g. ``min_tracking_state=1``.

    Returns
    -------
    Recording

    Raises
    ------
    InputError
        Unknown ``format`` (the message lists the known ones).
    FormatError
        Undetectable or malformed input (file, line/field, expected and found).
    FileNotFoundError
        ``path`` does not exist.
    """
    if isinstance(path, (list, tuple)):
        if len(path) != 2:
            raise InputError(f"expected one path or a pair of paths, got {len(path)} paths")
        a, b = (Path(p) for p in path)
        if format not in (None, "utd_mhad"):
            raise InputError(
                f"a pair of paths is only meaningful for format 'utd_mhad', got {format!r}"
            )
        if "skeleton" in a.name.lower() and "inertial" in b.name.lower():
            a, b = b, a
        return _reader("utd_mhad")(a, skeleton_path=b, **options)
    if format is not None and format not in _REGISTRY:
        raise InputError(f"unknown format {format!r}; known formats: {_known()}")
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"expected path as a file or folder path, got {type(path).__name__}")
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or directory")
    if p.is_dir() and format not in _FOLDER_FORMATS and (format or _detect_dir(p) is None):
        only = _only_recording(p, format)  # a folder around one recording: that file
        if only is None and format is not None:
            raise FormatError(
                p, f"format {format!r} reads one file; this is {looks_like(p, _detect_entry)}"
            )
        p = only or p
    fmt = format or detect_format(p)
    reader = _reader(fmt)
    _check_options(reader, fmt, options)
    try:
        return reader(p, **options)
    except FormatError as exc:
        if format is None:
            raise
        try:  # a reader forced on another format's file: say what the file looks like
            seen = detect_format(p)
        except (FormatError, OSError):
            raise exc from None
        if seen != format:
            exc.args = (f"{exc.args[0]} (read as {format!r}, as asked; it looks like {seen!r})",)
        raise
