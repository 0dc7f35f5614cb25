"""A session template filled from a recording: ``kinefuse init-session --from RECORDING``.

:func:`sketch_recording` loads the recording once and keeps what a session file needs (the
reader, the path as the session will write it, which sensors the reader recognised as which
segment, whether it holds a camera or a reference); :func:`filled_template` writes the commented
template of :func:`~kinefuse.session_file.template.session_template` with those filled in and
the choices that follow from them (root, calibration, method), each line still commented.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import InputError
from kinefuse.io import detect_format, load
from kinefuse.session_file.template import session_template

__all__ = ["NO_HEIGHT_RATIO", "RecordingSketch", "filled_template", "sketch_recording"]

_LEGS = {"thigh_l", "thigh_r", "shank_l", "shank_r"}
#: Chain segments whose length body height cannot give (no ratio in
#: :data:`kinefuse.kinematics.skeleton.ANTHROPOMETRIC_RATIOS`; this layer cannot import it, a test
#: keeps the two in step): output only with a measured length; without one a foot still serves
#: the ankle angles (static) or joint centre (functional), a hand the wrist centre (functional).
NO_HEIGHT_RATIO = ("foot_l", "foot_r", "hand_l", "hand_r")
#: The joint each limb segment starts at (a fixed root is the first mapped segment's). The
#: readers' table (kinefuse.io.motion) would import SciPy into `kinefuse --help`.
_PROXIMAL_JOINT = {"upper_arm": "shoulder", "forearm": "elbow", "hand": "wrist",
                   "thigh": "hip", "shank": "knee", "foot": "ankle"}  # fmt: skip
#: What mapping a foot or hand with its measured length adds under static calibration.
_DISTAL_GAIN = {"foot": "the toe and the ankle angles", "hand": "the fingertip"}


class RecordingSketch(NamedTuple):
    """What a session file needs to know about a recording (:func:`sketch_recording`)."""

    format: str
    """Reader name (:data:`kinefuse.io.FORMATS`)."""
    path: str
    """The recording's path as the session writes it: relative to the session's folder when
    that is possible, POSIX separators."""
    segments: dict
    """Canonical segment -> the sensor's name in the file, for the sensors the reader recognised."""
    unmapped: tuple
    """Names of the sensors not recognised as a segment."""
    camera: bool
    """The recording holds camera joints."""
    reference: bool
    """The recording holds reference (ground-truth) joints."""
    no_still_window: str = ""
    """Empty when the mapped sensors hold still somewhere (or nobody looked); else why a static
    calibration cannot work here (the stillest window and its motion), and the template
    chooses functional calibration."""
    camera_path: str = ""
    """The ``[camera] path`` when it is another file than ``path`` (a UTD-MHAD trial: the
    skeleton file, ``path`` the inertial one); empty: ``path``."""
    whole_folder: str = ""
    """The folder ``path`` sits in when that folder is itself one recording of the same format
    (one sensor's file of an Xsens DOT or OpenSense set): passing it maps every sensor."""


def sketch_recording(
    recording: Path, session_dir: Path, fmt: str | None = None, still: Callable | None = None
) -> RecordingSketch:
    """Load ``recording`` (format detected unless ``fmt``) and sketch it for a session file.

    Parameters
    ----------
    recording, session_dir : Path
        The recording; the folder the session file will be in.
    fmt : str, optional
        Reader name (default: detected).
    still : callable, optional
        ``still(streams) -> str``: empty when the IMU streams hold still for a static
        calibration, else why not
        (:func:`kinefuse.pipelines.run.calibration.no_still_window`; this layer cannot import
        it). Given, and the recording has no camera, it is asked about the mapped sensors; its
        answer is :attr:`RecordingSketch.no_still_window`.

    Raises
    ------
    InputError
        The recording does not exist, or holds no IMU stream.
    FormatError
        Unknown or unreadable format (the reader's message).
    """
    p = Path(recording).expanduser()
    if not p.exists():
        raise InputError(f"--from {recording}: file or folder not found")
    fmt = fmt or detect_format(p)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader's notes reach the user at `kinefuse run`
        rec = load(p, format=fmt)
    if not rec.imu:
        raise InputError(_no_imu_message(recording, fmt, rec))
    segments, unmapped = {}, []
    for key, st in rec.imu.items():
        name = st.name or key
        if key in SEGMENTS and key not in segments:
            segments[key] = name
        else:
            unmapped.append(name)
    # a recording of two files (UTD-MHAD: inertial + skeleton, read as a pair): the IMU section
    # names the inertial file and the camera section the skeleton file
    files = (rec.metadata or {}).get("files")  # other readers list their files
    files = files if isinstance(files, dict) else {}
    pair = bool(files.get("inertial") and files.get("skeleton") and rec.vision is not None)
    imu_path = Path(files["inertial"]) if pair else p
    mapped = {s: rec.imu[s] for s in segments}
    whole = _whole_folder(p, fmt) if not pair else ""
    return RecordingSketch(fmt, _session_path(imu_path, session_dir),
                           dict(sorted(segments.items(), key=_order)), tuple(unmapped),
                           rec.vision is not None, rec.reference is not None,
                           still(mapped) if still and mapped and rec.vision is None else "",
                           _session_path(Path(files["skeleton"]), session_dir) if pair else "",
                           whole)  # fmt: skip


def _no_imu_message(recording, fmt: str, rec) -> str:
    """Why ``--from`` refuses a recording without IMUs, and where its positions can go instead."""
    msg = f"--from {recording}: no IMU stream in this {fmt} recording"
    if rec.vision is not None:
        use = "[camera] path (a camera input to fuse with the IMUs)"
    elif rec.reference is not None:
        use = "[reference] path (a reference to evaluate against)"
    else:
        return msg
    return (
        f"{msg}; its joint or marker positions can be a session's {use}: run init-session "
        f"--from the IMU recording, then add this file there"
    )


def _whole_folder(p: Path, fmt: str) -> str:
    """``str(p.parent)`` when ``p`` is one of several files (same suffix) of a folder the
    ``fmt`` reader reads whole (one file per sensor); not when ``p`` is the folder's only such
    file (the folder would read the same sensors)."""
    if not p.is_file():
        return ""
    if not any(q != p and q.suffix.lower() == p.suffix.lower() for q in p.parent.iterdir()):
        return ""
    try:
        same = detect_format(p.parent) == fmt
    except (ValueError, OSError):  # the folder is not one recording: nothing to suggest
        return ""
    return str(p.parent) if same else ""


def _session_path(p: Path, session_dir: Path) -> str:
    """``p`` as a session file writes it: relative below the session's folder (the pair moves
    together), else absolute; POSIX separators."""
    try:
        rel = os.path.relpath(p.resolve(), Path(session_dir).resolve())
    except ValueError:  # another drive (Windows)
        rel = str(p.resolve())
    if rel.startswith(".."):
        rel = str(p.resolve())
    return Path(rel).as_posix()


def _order(item) -> int:
    return SEGMENTS.index(item[0])


def _chest_comment(calibration: str, mapped) -> str:
    """What the chest IMU gives the session (the shoulders with both arms; with a static
    calibration their angles, and the trunk's with the pelvis), as a line comment."""
    uses = []
    if {"upper_arm_l", "upper_arm_r"} <= set(mapped):
        uses.append(
            "the shoulders hang from it"
            + (" (and their angles)" if calibration == "static" else "")
        )
    if "pelvis" in mapped and calibration == "static":
        uses.append("with the pelvis: the trunk angles")
    return f"  # {'; '.join(uses)}" if uses else ""


def _segment_line(s: str, n: str, calibration: str, mapped) -> str:
    """The ``[imu.segments]`` line of segment ``s`` (sensor ``n``): a foot or hand, which body
    height cannot size, is mapped where the calibration uses it without a length, else
    commented with what its measured length adds."""
    if s == "chest":
        return f'{s} = "{n}"' + _chest_comment(calibration, mapped)
    if s not in NO_HEIGHT_RATIO:
        return f'{s} = "{n}"'
    joint = "ankle" if s.startswith("foot") else "wrist"
    if calibration == "functional":
        return f'{s} = "{n}"  # locates the {joint} (functional calibration); no length: no toe/finger joint'
    if calibration == "static" and joint == "ankle" and f"shank_{s[-1]}" in mapped:
        return (
            f'{s} = "{n}"  # the ankle angles; [skeleton.lengths] {s} (ankle to toe) adds the toe'
        )
    return f'# {s} = "{n}"  # needs [skeleton.lengths] {s} (body height gives none): then {_DISTAL_GAIN[s[:-2]]}'


def filled_template(name: str, filename: str, sk: RecordingSketch) -> str:
    """The session template with ``sk`` filled in (see the module docstring)."""
    text = session_template(name, filename=filename)
    legs = "pelvis" in sk.segments and bool(_LEGS & set(sk.segments))
    root = "pelvis" if legs else ("vision" if sk.camera else "fixed")
    functional = bool(sk.no_still_window)
    calibration = "vision" if sk.camera else ("functional" if functional else "static")
    seg_lines = [_segment_line(s, n, calibration, sk.segments) for s, n in sk.segments.items()]
    seg_lines = seg_lines or ["# (no sensor was recognised: map them below)"]
    seg_lines += [f'# ??? = "{n}"  # not recognised: name its segment' for n in sk.unmapped]
    reps = [
        ('format = "imu_csv"               #', f'format = "{sk.format}"  {" " * max(0, 22 - len(sk.format))}#'),
        ('path = "data/imu.csv"            #', f'path = "{sk.path}"  #'),
        ("rate_hz = 100.0                  # only used when the file has no time stamps; delete otherwise\n", ""),
        ('upper_arm_r = "IMU 1"\nforearm_r = "IMU 2"', "\n".join(seg_lines)),
        ('method = "static"\n', f'method = "{calibration}"'
         + (f"  # {sk.no_still_window}\n" if functional else "\n")),
        ('name = "paper-a"\n', f'name = "{"kinefuse" if sk.camera else "imu-only"}"\n'),
    ]  # fmt: skip
    first = next((s for s in sk.segments if s[:-2] in _PROXIMAL_JOINT), None)
    arms = {s[-1] for s in sk.segments if s.startswith(("upper_arm_", "forearm_", "hand_"))}
    if root == "fixed" and len(arms) == 2:  # the shoulders hang from the trunk IMU
        trunk = next((s for s in ("chest", "pelvis") if s in sk.segments), None)
        reps.append(
            (
                "the measured root joint (here the shoulder), m",
                "the mid-shoulder point, m; "
                + (
                    f"the shoulders hang from the {trunk} IMU"
                    if trunk
                    else "map 'chest' (the shoulders hang from it), or give each shoulder: "
                    "{shoulder_l = [...], shoulder_r = [...]}"
                ),
            )
        )
    elif root == "fixed" and first is not None and not first.startswith("upper_arm"):
        joint = f"{_PROXIMAL_JOINT[first[:-2]]}_{first[-1]}"  # the chain starts there
        reps.append(
            (
                "the measured root joint (here the shoulder), m",
                f"the measured root joint ({joint}), m",
            )
        )
    if root != "fixed":
        reps.append((
            'root = "fixed"\nroot_position_m = [0.0, 0.0, 0.0]  # root = "fixed": the measured root joint (here the shoulder), m\n',
            f'root = "{root}"\n',
        ))  # fmt: skip
    if sk.camera:
        reps.append(('# [camera]\n# format = "kinect_v2"\n# path = "data/kinect.csv"\n',
                     f'[camera]\nformat = "{sk.format}"\npath = "{sk.camera_path or sk.path}"\n'))  # fmt: skip
    if sk.reference:
        reps.append(('# [reference]\n# format = "c3d"\n# path = "data/reference.c3d"\n# align',
                     f'[reference]\nformat = "{sk.format}"\npath = "{sk.path}"\nalign'))  # fmt: skip
    for old, new in reps:
        if old not in text:  # the template and this function change together (tested)
            raise AssertionError(f"session template: {old[:40]!r} not found")
        text = text.replace(old, new, 1)
    head = (
        f"# Filled from {sk.path} ({sk.format}): {len(sk.segments)} sensor(s) mapped to segments"
        + (f", {len(sk.unmapped)} not recognised (see [imu.segments])" if sk.unmapped else "")
        + ". Check every line before running.\n"
    )
    return head + text
