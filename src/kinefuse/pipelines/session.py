"""``kinefuse run`` and ``kinefuse evaluate``: a user's own recording, end to end.

:func:`run_session` processes the recording a session TOML describes
(:func:`kinefuse.session.load_session`): it loads the IMU file and the optional camera and
reference, maps sensors to segments, estimates missing orientations from raw data, builds the
skeleton, calibrates, runs the method, writes the joint positions as CSV (with per-sample source,
filter branch and standard deviation) and TRC (OpenSim), the joint angles as CSV and ``.mot``
(where the calibration gives segment frames), an HTML report, and, with a reference in the
output's frame, the metrics. :func:`evaluate_recording` runs one method on any loadable recording that has a
reference and returns the per-joint tables. :func:`process_recording` is the shared core.

Method parameters (``[method.parameters]`` of the session file; all optional)
-----------------------------------------------------------------------------
``calibration``
    ``"static"``, ``"functional"``, ``"vision"``, ``"reference"`` or ``"none"`` (default:
    ``"vision"`` with a camera, else ``"static"``; the reference only when asked). The session
    file's ``[calibration] method`` sets it.
``calibration_window_s``, ``calibration_start_s``
    Calibration window, s (default 2 s; static calibration searches the earliest still window
    unless the start is given). ``[calibration] window_s`` / ``start_s``.
``pose``, ``facing``, ``heading``, ``max_rate_rad_s``, ``max_acc_std_m_s2``
    Static calibration: ``"n"`` (default) or ``"t"``; the subject's facing in the IMU world
    frame (default north); ``"auto"`` (default: align 6-D sensors' headings at the pose),
    ``"none"`` or ``"static"``; the stillness thresholds
    (:func:`kinefuse.kinematics.find_still_window`).
``flexion_axes``
    Static calibration: the flexion axes of elbows and knees from the movement (``"movement"``,
    :func:`kinefuse.kinematics.hinge.hinge_frames`) or from ``facing`` (``"pose"``); ``"auto"``
    (default): from the movement when the headings are aligned at the pose (6-D sensors).
``align``
    Camera/reference frame alignment of the calibration: ``"auto"`` (default), ``"none"``,
    ``"heading"``, ``"rotation"``.
``root``, ``root_position_m``
    Where the chain's root joints (shoulders, hips, or the proximal joint of any segment
    without a mapped parent) are: ``"fixed"`` (``root_position_m`` [x, y, z] m, or one per
    root joint; default the origin), ``"pelvis"`` (hips from the pelvis IMU, mid-hip origin),
    ``"vision"`` (``"camera"``) or ``"reference"``. Default: the camera if there is one, else
    ``"pelvis"`` for leg chains with a pelvis IMU, else ``"fixed"``. ``[skeleton] root``.
``axes``
    Declared sensor axis along each segment (``[skeleton.axes]``): the sensor axes without
    calibration, the check of the static pose otherwise.
``align_to_reference``
    ``"none"`` (default) or ``"rigid"``: Kabsch-align the estimates to the reference before
    scoring (labelled). ``[reference] align``.
``rate_hz``
    Output/filter rate, Hz (default 30 for ``paper-a`` and the camera methods, else the root
    stream's own timeline).
``filter``
    ``imu-only`` only: ``"none"`` (default), ``"kf"``, ``"fir"``, ``"em-kf"``, ``"em-kf-fir"``;
    ``paper-a`` uses ``"em-kf-fir"`` unless told otherwise.
``q``, ``r``, ``horizon``, ``threshold1``, ``threshold2``, ``n_em_iter``
    Paper A filter settings (:func:`kinefuse.pipelines.upper_limb`); ``q`` and ``r`` may be
    one number or a table per joint or joint kind (``{knee = 0.1, ankle = 0.2}``).
``q``, ``r_imu``, ``r_cam``, ``horizon``, ``n_hidden``, ``train_window``, ...
    Paper B settings (:class:`kinefuse.pipelines.VisionParams`) for ``elm-fir``, ``elm-kf``,
    ``imu-only`` / ``camera-only`` with a camera, and ``kinefuse``.
``measured_lengths``
    Use the segment lengths measured in the calibration window (``[calibration]
    lengths_from_data``; default true for ``"vision"``, false otherwise: the reference gives
    lengths only when asked). Explicit ``[skeleton.lengths]`` always win; ``body_height_m``
    (Winter 2009 ratios) fills the rest.
``orientation_params``
    VQF parameters for sensors without an orientation (:func:`kinefuse.orientation.estimate`).
``estimate_orientation``
    ``"auto"`` (default: estimate sensor orientations from acc + gyr with VQF only when no
    mapped sensor has one in the file), ``true`` (for every sensor without one) or ``false``
    (never); an estimate is always reported as a warning.
``strict_units``
    Default true: magnitudes that look like wrong units (acc in g, gyro in deg/s, positions in
    mm; :func:`kinefuse.io.check_units`) are an error instead of a warning.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from kinefuse.conventions import (
    MODE_NAMES,
    SEGMENTS,
    SOURCE_BRIDGED,
    SOURCE_IMU,
    SOURCE_KINDS,
    SOURCE_NAMES,
    SOURCE_PREDICTED,
)
from kinefuse.exceptions import ConfigError, InputError, UnitWarning
from kinefuse.session import CAMERA_METHODS

__all__ = [
    "FORMAT_ALIASES",
    "SEGMENT_JOINTS",
    "SessionOutput",
    "build_chain",
    "evaluate_recording",
    "load_streams",
    "process_recording",
    "run_session",
]

#: Session-file format names accepted besides the :data:`kinefuse.io.FORMATS` keys.
FORMAT_ALIASES = {
    "csv": "imu_csv",
    "imu-csv": "imu_csv",
    "joint-csv": "joint_csv",
    "joints-csv": "joint_csv",
    "kinect": "kinect_v2",
    "kinect-csv": "kinect_v2",
    "kinect-v2": "kinect_v2",
    "azure-kinect": "azure_kinect",
    "utd-mhad": "utd_mhad",
    "gaittoolbox": "neura",
    "asf-amc": "cmu",
}

#: Proximal and distal joint of every limb segment (segments with a length).
SEGMENT_JOINTS = {
    **{f"upper_arm_{s}": (f"shoulder_{s}", f"elbow_{s}") for s in "lr"},
    **{f"forearm_{s}": (f"elbow_{s}", f"wrist_{s}") for s in "lr"},
    **{f"thigh_{s}": (f"hip_{s}", f"knee_{s}") for s in "lr"},
    **{f"shank_{s}": (f"knee_{s}", f"ankle_{s}") for s in "lr"},
    **{f"foot_{s}": (f"ankle_{s}", f"foot_{s}") for s in "lr"},
}

_FILTERS = ("none", "kf", "fir", "em-kf", "em-kf-fir")
_CALIBRATIONS = ("static", "functional", "reference", "vision", "none")
_CAMERA_METHODS = CAMERA_METHODS  # the one registry: kinefuse.session.METHOD_INFO
#: Root kinds; "camera" is the old spelling of "vision".
_ROOTS = ("fixed", "pelvis", "vision", "camera", "reference")
_HEADINGS = ("auto", "none", "static")
#: Plausible flexion of hinge joints, deg (1st-99th percentile check of the joint angles):
#: knee -10 (hyperextension) to 150, elbow -10 to 160 (e.g. Soucie et al. 2011, Haemophilia 17).
_HINGE_RANGE_DEG = {"knee": (-10.0, 150.0), "elbow": (-10.0, 160.0)}
_PAPER_A_KEYS = ("q", "r", "horizon", "threshold1", "threshold2", "n_em_iter")
_VISION_KEYS = (
    "q",
    "r_imu",
    "r_cam",
    "horizon",
    "transition",
    "mu_floor",
    "n_hidden",
    "alpha",
    "linear_skip",
    "train_window",
    "elm2_input",
    "clip_factor",
    "min_train",
    "fixed_lag",
    "seed",
)
_GENERAL_KEYS = (
    "calibration",
    "facing",
    "heading",
    "flexion_axes",
    "root_position_m",
    "axes",
    "align_to_reference",
    "max_rate_rad_s",
    "max_acc_std_m_s2",
    "calibration_window_s",
    "calibration_start_s",
    "pose",
    "align",
    "root",
    "rate_hz",
    "filter",
    "measured_lengths",
    "orientation_params",
    "strict_units",
    "causal",
    "estimate_orientation",
)
_METHOD_LABELS = {
    "paper-a": "EM-KF/FIR",
    "elm-fir": "ELM/FIR",
    "elm-kf": "ELM/KF",
    "imu-only": "IMU only",
    "camera-only": "camera only",
    "kinefuse": "kinefuse",
    "offset-interp": "offset interp",
    "offset-hold": "offset hold",
    "camera-gapfill": "camera gap-fill",
}


@dataclass(eq=False)
class SessionOutput:
    """Result of :func:`process_recording`.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Output timeline, s.
    joints : tuple of str
        Output joints (distal joints of the mapped segments).
    position : ndarray, shape (T, J, 3)
        Estimated joint positions, m, in ``frame``.
    std_m : ndarray, shape (T, J, 3)
        Per-axis standard deviation, m (NaN where the method gives none).
    source : ndarray of int, shape (T, J)
        :data:`kinefuse.conventions.SOURCE_NAMES` code per sample (-1: no estimate).
    mode : ndarray of int, shape (T, J)
        :data:`kinefuse.conventions.MODE_NAMES` filter branch per sample (-1: no filter).
    frame : str
        Frame of the positions (the root stream's, or ``"ENU chest-relative"``).
    method : str
        Method name; ``label`` is its table label.
    label : str
    chain : ndarray, shape (T, J, 3)
        The unfiltered IMU chain, m (same frame).
    camera : ndarray, shape (T, J, 3) or None
        Camera positions of the output joints in the same frame (NaN where unavailable).
    reference : ndarray, shape (T, J, 3) or None
        Reference positions at ``t_s`` in the same frame (NaN where unavailable).
    run_time_s : float
        Wall-clock time of the method (chain excluded), s.
    edges : tuple of (str, str)
        Bones between output joints (report skeleton).
    notes : list of str
        What was done (calibration, lengths, alignments) and warnings.
    root : str
        Where the chain's root joints are (e.g. "pelvis (mid-hip) at [0, 0, 0] m ...").
    provenance : dict
        Which data calibrated what: calibration, heading, segment lengths and their sources,
        root, alignment, labels (also written to ``metrics.json``).
    angles : dict of str -> ndarray, shape (T, 3)
        Joint angles, deg, ``[flexion, adduction, internal_rotation]`` (ISB), where the
        calibration gives segment frames.
    sensor_orientations : dict of str -> ndarray, shape (T, 4)
        Calibrated sensor orientations per segment, ``q_world_from_sensor`` (wxyz) on ``t_s``
        with the calibration's heading corrections applied (one world frame for all sensors),
        for OpenSense IK.
    tag : str
        Label suffix of scores that used the reference beyond evaluation (e.g.
        ``" [calibrated on reference]"``); empty otherwise.
    baselines : dict of str -> ndarray, shape (T, J, 3)
        With a camera method: the simple baselines on the same chain and camera, by table
        label (``offset interp``, ``offset hold``, ``camera gap-fill``;
        :func:`kinefuse.pipelines.vision_assisted`), m, same frame.
    available : ndarray of bool, shape (T, J) or None
        The sample is backed by the inputs the method needs (see :func:`apply_coverage`);
        False where a stream did not cover it, even if the filter predicted a position.
    coverage : dict of str -> ndarray of bool
        Per input stream whether it covered each output sample: ``"imu <segment>"`` (T,),
        ``"imu"``, ``"root"``, ``"camera"``, ``"reference"`` (T, J) per output joint.
    warnings : list of str
        Short coverage and other problems the user must see (also in ``notes``).
    """

    t_s: np.ndarray
    joints: tuple[str, ...]
    position: np.ndarray
    std_m: np.ndarray
    source: np.ndarray
    mode: np.ndarray
    frame: str
    method: str
    label: str
    chain: np.ndarray
    camera: np.ndarray | None = None
    reference: np.ndarray | None = None
    run_time_s: float = float("nan")
    edges: tuple[tuple[str, str], ...] = ()
    notes: list[str] = field(default_factory=list)
    root: str = ""
    provenance: dict = field(default_factory=dict)
    angles: dict = field(default_factory=dict)
    sensor_orientations: dict = field(default_factory=dict)
    tag: str = ""
    baselines: dict[str, np.ndarray] = field(default_factory=dict)
    available: np.ndarray | None = None
    coverage: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def trajectories(self) -> dict[str, np.ndarray]:
        """Evaluated trajectories by their table label (tags such as "[calibrated on reference]")."""
        position = self.position
        if self.available is not None:  # predictions no input backs are not scored (issue 12)
            position = np.where(self.available[..., None], position, np.nan)
        est = {self.label + self.tag: position}
        if self.method != "camera-only" and not np.array_equal(
            self.position, self.chain, equal_nan=True
        ):
            est["IMU chain" + self.tag] = self.chain
        if (
            self.camera is not None
            and self.method != "camera-only"
            and self.reference is not None
            and not np.array_equal(self.camera, self.reference, equal_nan=True)
        ):
            est["camera" + (" [aligned to reference]" if "aligned" in self.tag else "")] = (
                self.camera
            )
        est.update({k + self.tag: v for k, v in self.baselines.items() if k != self.label})
        return est

    def evaluation(self):
        """Metrics of the method, the unfiltered IMU chain and the camera vs the reference.

        Returns
        -------
        EvaluationResult or None
            None without a reference.
        """
        from kinefuse.evaluation import evaluate

        if self.reference is None:
            return None
        est = self.trajectories()
        outage = None
        if self.camera is not None:
            outage = ~np.all(np.isfinite(self.camera), axis=-1)
        return evaluate(
            est,
            self.reference,
            outage,
            {self.label + self.tag: self.run_time_s} if math.isfinite(self.run_time_s) else None,
            joints=self.joints,
        )


# --------------------------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------------------------


def _format_name(fmt: str, section: str, source: str) -> str:
    from kinefuse.io import FORMATS

    key = fmt.strip().lower()
    key = FORMAT_ALIASES.get(key, key.replace("-", "_"))
    if key not in FORMATS:
        known = ", ".join(sorted({*FORMATS, *FORMAT_ALIASES}))
        raise ConfigError(
            f"{source}: [{section}] format: unknown format {fmt!r} (known formats: {known})"
        )
    return key


def _load(
    path: Path, fmt: str, section: str, source: str, strict_units: bool, pair=None, options=None
):
    """``kinefuse.io.load`` with session context in every error and unit checks escalated.

    ``options`` (the section's ``[<section>.reader]`` table) go to the reader as keywords.
    """
    from kinefuse.exceptions import FormatError
    from kinefuse.io import load

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UnitWarning)
        try:
            rec = load(path if pair is None else (path, pair), format=fmt, **(options or {}))
        except TypeError as exc:
            if "keyword argument" not in str(exc):
                raise
            raise ConfigError(
                f"{source}: [{section}.reader]: {exc} (see the {fmt!r} reader's parameters in "
                "docs/formats.md)"
            ) from None
        except FileNotFoundError as exc:
            raise ConfigError(f"{source}: [{section}] path: {exc}") from None
        except FormatError as exc:
            raise ConfigError(f"{source}: [{section}] path: {exc}") from None
        except InputError as exc:
            raise ConfigError(f"{source}: [{section}]: {exc}") from None
    _check_no_inf(rec, path, section, source)
    msgs = []
    for w in caught:
        if issubclass(w.category, UnitWarning) and strict_units:
            raise ConfigError(
                f"{source}: [{section}] path: wrong units? {w.message} (kinefuse expects SI "
                "units; fix the file, declare its unit in the file header, or set "
                "strict_units = false in [method.parameters])"
            )
        if not issubclass(w.category, DeprecationWarning):
            msgs.append(f"{section}: {w.message}")
    return rec, msgs


_IMU_COLUMNS = {
    "q_world_from_sensor": ("qw", "qx", "qy", "qz"),
    "acc_m_s2": ("acc_x", "acc_y", "acc_z"),
    "gyr_rad_s": ("gyr_x", "gyr_y", "gyr_z"),
    "mag": ("mag_x", "mag_y", "mag_z"),
}


def _check_no_inf(rec, path: Path, section: str, source: str) -> None:
    """Inf is never data: an error naming file, stream, column and sample (issue 12).

    Readers of text tables already name the file line; this catches every other reader.
    """

    def fail(what: str, column: str, t_s: np.ndarray, k: int, n: int) -> None:
        raise ConfigError(
            f"{source}: [{section}] path: {Path(path).name}: {what}, column {column}: infinite "
            f"value at sample {k} (t = {t_s[k]:.3f} s; {n} infinite in all); kinefuse does not "
            "replace it: fix the file (an empty field or NaN marks a missing sample)"
        )

    for key, st in (rec.imu or {}).items():
        for attr, cols in _IMU_COLUMNS.items():
            a = getattr(st, attr)
            if a is None:
                continue
            bad = np.isinf(a)
            if np.any(bad):
                k, c = (int(i[0]) for i in np.nonzero(bad))
                fail(f"sensor {st.name or key!r}", cols[c], st.t_s, k, int(bad.sum()))
    for role in ("vision", "reference"):
        stream = getattr(rec, role, None)
        if stream is None:
            continue
        bad = np.isinf(stream.position_m)
        if np.any(bad):
            k, j, c = (int(i[0]) for i in np.nonzero(bad))
            fail(f"{role} joint {stream.joints[j]!r}", "xyz"[c], stream.t_s, k, int(bad.sum()))


def load_streams(cfg, *, strict_units: bool = True):
    """Load the IMU, camera and reference files of a session into one Recording.

    Parameters
    ----------
    cfg : SessionConfig
        From :func:`kinefuse.session.load_session`.
    strict_units : bool
        Raise on magnitudes that suggest wrong units instead of warning.

    Returns
    -------
    recording : Recording
        ``imu`` keyed by the session's canonical segments (only the mapped ones), ``vision``
        and ``reference`` as configured (a reference file without a reference stream, e.g. a
        UTD-MHAD skeleton, gives its camera joints as the reference).
    notes : list of str

    Raises
    ------
    ConfigError
        Unknown format, unreadable file (the reader's message with file, line and field), a
        sensor name not in the file, a stream without valid samples, wrong units.
    """
    from kinefuse.io import Recording

    src = cfg.path.name
    notes: list[str] = []
    fmt = _format_name(cfg.imu.format, "imu", src)
    cam_fmt = _format_name(cfg.camera.format, "camera", src) if cfg.camera else None
    pair = None
    if fmt == "utd_mhad" and cam_fmt == "utd_mhad":
        pair = cfg.camera.path  # one trial: inertial + skeleton, timed together
    rec, msgs = _load(cfg.imu.path, fmt, "imu", src, strict_units, pair, cfg.imu.reader)
    notes += msgs
    if not rec.imu:
        raise ConfigError(f"{src}: [imu] path: the file holds no IMU data ({cfg.imu.path.name})")
    imu = {}
    available = {}
    for key, st in rec.imu.items():
        available.setdefault(st.name, key)
        available.setdefault(key, key)
    sensor_names = (rec.metadata or {}).get("sensor_names") or {}
    for seg, key in sensor_names.items():
        available.setdefault(key, seg)
    for seg, sensor in cfg.imu.segments.items():
        key = available.get(sensor)
        if key is None:
            names = sorted({st.name or k for k, st in rec.imu.items()} | set(rec.imu))
            raise ConfigError(
                f"{src}: [imu.segments] {seg}: sensor {sensor!r} not in {cfg.imu.path.name} "
                f"(its sensors: {', '.join(names)})"
            )
        st = rec.imu[key]
        _check_stream(st, seg, sensor, src)
        imu[seg] = st
    vision = None
    if cfg.camera is not None:
        if pair is not None:
            vision = rec.vision
        else:
            crec, msgs = _load(
                cfg.camera.path, cam_fmt, "camera", src, strict_units, options=cfg.camera.reader
            )
            notes += msgs
            vision = crec.vision if crec.vision is not None else crec.reference
        if vision is None:
            raise ConfigError(
                f"{src}: [camera] path: {cfg.camera.path.name} holds no joint positions"
            )
        if cfg.camera.availability_threshold is not None:
            notes.append(
                "camera availability_threshold is applied by the reader's tracking state; "
                "the generic readers use finite samples"
            )
        _check_joints(vision, "camera", src)
    reference = None
    if cfg.reference is not None:
        ref_fmt = _format_name(cfg.reference.format, "reference", src)
        rrec, msgs = _load(
            cfg.reference.path,
            ref_fmt,
            "reference",
            src,
            strict_units,
            options=cfg.reference.reader,
        )
        notes += msgs
        reference = rrec.reference if rrec.reference is not None else rrec.vision
        if reference is None:
            raise ConfigError(
                f"{src}: [reference] path: {cfg.reference.path.name} holds no joint positions"
            )
        if rrec.reference is None:
            notes.append(
                f"reference: {cfg.reference.path.name} has no separate reference; its camera "
                "joints are used as the reference (as paper A uses Kinect)"
            )
        _check_joints(reference, "reference", src)
    md = dict(rec.metadata or {})
    md["session"] = str(cfg.path)
    return Recording(imu=imu, vision=vision, reference=reference, metadata=md), notes


def _check_stream(st, seg: str, sensor: str, src: str) -> None:
    arrays = [a for a in (st.q_world_from_sensor, st.acc_m_s2, st.gyr_rad_s) if a is not None]
    if not arrays:
        raise ConfigError(
            f"{src}: [imu.segments] {seg}: sensor {sensor!r} has neither an orientation nor raw "
            "acc + gyr data"
        )
    if st.q_world_from_sensor is not None:
        ok = np.all(np.isfinite(st.q_world_from_sensor), axis=1)
    else:
        ok = np.all(np.isfinite(st.acc_m_s2), axis=1) & np.all(np.isfinite(st.gyr_rad_s), axis=1)
    if not np.any(ok):
        raise ConfigError(
            f"{src}: [imu.segments] {seg}: sensor {sensor!r} has no valid sample (all NaN)"
        )
    if np.sum(ok) < 2:
        k = int(np.flatnonzero(ok)[0])
        raise ConfigError(
            f"{src}: [imu.segments] {seg}: sensor {sensor!r} has a single valid sample (t = "
            f"{st.t_s[k]:.3f} s); an IMU stream needs a sample rate (at least 2 samples)"
        )


def _check_joints(stream, what: str, src: str) -> None:
    if not np.any(stream.available):
        raise ConfigError(f"{src}: [{what}] path: no valid joint position in the file (all NaN)")


# --------------------------------------------------------------------------------------------
# chain
# --------------------------------------------------------------------------------------------


def _ensure_orientations(
    recording, params: Mapping, notes: list[str], warnings_out: list[str]
) -> set[str]:
    """Estimate ``q_world_from_sensor`` with VQF for the streams that have raw data only.

    The policy is ``estimate_orientation`` of ``[method.parameters]``: ``"auto"`` (default)
    estimates only when no mapped sensor has an orientation (a raw-only recording), ``true``
    for every sensor without one, ``false`` never. The substitution is always reported (a
    warning in the run summary and the report), never silent.

    Returns the segments whose orientation is 6-D (no magnetometer: arbitrary heading).
    """
    from dataclasses import replace

    from kinefuse.orientation import estimate

    vqf_params = params.get("orientation_params")
    policy = params.get("estimate_orientation", "auto")
    if policy not in ("auto", True, False):
        raise ConfigError(
            f"[method.parameters] estimate_orientation: expected true, false or 'auto', got "
            f"{policy!r}"
        )
    lacking = [seg for seg, st in recording.imu.items() if st.q_world_from_sensor is None]
    having = [seg for seg in recording.imu if seg not in lacking]
    if lacking and (policy is False or (policy == "auto" and having)):
        why = (
            f"while {', '.join(having)} {'has' if len(having) == 1 else 'have'} one"
            if having
            else "and estimate_orientation = false"
        )
        raise InputError(
            f"no orientation for {', '.join(lacking)} in the IMU file (quaternion columns "
            f"missing or all empty) {why}; kinefuse does not substitute an estimate silently: "
            "set estimate_orientation = true in [method.parameters] to estimate it from acc + "
            "gyr with VQF, or fix the file"
        )
    six_d: set[str] = set()
    for seg, st in list(recording.imu.items()):
        if st.q_world_from_sensor is not None:
            continue
        ok = np.all(np.isfinite(st.acc_m_s2), axis=1) & np.all(np.isfinite(st.gyr_rad_s), axis=1)
        acc, gyr = st.acc_m_s2, st.gyr_rad_s
        if not np.all(ok):  # hold the last valid sample across gaps (VQF needs finite input)
            idx = np.maximum.accumulate(np.where(ok, np.arange(ok.size), 0))
            first = int(np.flatnonzero(ok)[0])
            idx[:first] = first
            acc, gyr = acc[idx], gyr[idx]
        mag = None
        if st.mag is not None and np.all(np.isfinite(st.mag)):
            mag = st.mag
        try:
            q = estimate(acc, gyr, mag, rate_hz=st.rate_hz, params=vqf_params)
        except InputError as exc:
            raise InputError(f"IMU {seg!r}: orientation estimation failed: {exc}") from None
        q[~ok] = np.nan
        recording.imu[seg] = replace(st, q_world_from_sensor=q)
        notes.append(
            f"{seg}: orientation estimated from raw data with VQF "
            f"({'9D, magnetometer' if mag is not None else '6D, arbitrary heading'})"
        )
        if mag is None:
            six_d.add(seg)
    if lacking:
        msg = (
            f"the IMU file has no orientation for {', '.join(lacking)}: estimated from acc + "
            "gyr with VQF (policy estimate_orientation = "
            f"{'true' if policy is True else 'auto: no sensor has one'})"
        )
        notes.append(f"WARNING: {msg}")
        warnings_out.append(msg)
    return six_d


def build_chain(
    segments: Sequence[str],
    lengths: Mapping[str, float],
    axes: Mapping[str, object] | None = None,
):
    """A Skeleton over the given limb segments, rooted at the proximal joints of unparented ones.

    Parameters
    ----------
    segments : sequence of str
        Limb segments (:data:`SEGMENT_JOINTS` keys), e.g. ``("thigh_l", "shank_l")`` or
        ``("forearm_r",)``; a segment's parent is the segment whose distal joint is its
        proximal joint, if given.
    lengths : mapping of str -> float
        Length of every segment, m.
    axes : mapping, optional
        Segment axis in each sensor frame (default ``+e2``).

    Returns
    -------
    Skeleton
        Parents before children; the first root joint is ``root``, further roots are offset
        joints of unknown offset (to be given as root positions, e.g. from a camera).
    roots : tuple of str
        The root joints, whose positions must be supplied.
    """
    from kinefuse.kinematics import Skeleton

    segs = [s for s in SEGMENT_JOINTS if s in set(segments)]
    unknown = sorted(set(segments) - set(SEGMENT_JOINTS))
    if unknown:
        raise InputError(f"segments {unknown} have no length; expected limb segments")
    order: list[str] = []
    pending = list(segs)
    distal = {SEGMENT_JOINTS[s][1]: s for s in segs}
    while pending:
        for s in list(pending):
            parent = distal.get(SEGMENT_JOINTS[s][0])
            if parent is None or parent in order:
                order.append(s)
                pending.remove(s)
    parents = []
    roots: list[str] = []
    for s in order:
        parent = distal.get(SEGMENT_JOINTS[s][0])
        parents.append(-1 if parent is None else order.index(parent))
        if parent is None and SEGMENT_JOINTS[s][0] not in roots:
            roots.append(SEGMENT_JOINTS[s][0])
    axes = dict(axes or {})
    sk = Skeleton(
        segments=tuple(order),
        parents=tuple(parents),
        proximal=tuple(SEGMENT_JOINTS[s][0] for s in order),
        distal=tuple(SEGMENT_JOINTS[s][1] for s in order),
        lengths_m=tuple(float(lengths[s]) for s in order),
        axes=np.array([axes.get(s, (0.0, 1.0, 0.0)) for s in order], dtype=float),
        root=roots[0],
        root_segment="pelvis" if len(roots) > 1 else None,
        offsets_m={j: (np.nan,) * 3 for j in roots[1:]},
    )
    return sk, tuple(roots)


def _timeline(t_src: np.ndarray, rate_hz: float | None) -> np.ndarray:
    if rate_hz is None or t_src.size < 2:
        return t_src
    src_rate = 1.0 / float(np.median(np.diff(t_src)))
    if abs(src_rate - rate_hz) <= 0.05 * rate_hz:
        return t_src
    n = int(np.floor((t_src[-1] - t_src[0]) * rate_hz + 1e-9)) + 1
    return t_src[0] + np.arange(n) / rate_hz


def _at(stream, joint: str, t: np.ndarray, *, fill: bool) -> np.ndarray:
    """Positions of one joint at ``t``: linear interpolation (across gaps if ``fill``)."""
    from kinefuse.io import resample_positions

    p = stream.position(joint)
    ok = np.all(np.isfinite(p), axis=1)
    if not np.any(ok):
        return np.full((t.size, 3), np.nan)
    if fill:
        return np.stack([np.interp(t, stream.t_s[ok], p[ok, k]) for k in range(3)], axis=-1)
    out, _ = resample_positions(stream.t_s, p, t)
    return out


def _number_or_table(value, joints: Sequence[str], name: str) -> list[float]:
    if isinstance(value, Mapping):
        out = []
        for j in joints:
            v = value.get(j, value.get(j.rsplit("_", 1)[0]))
            if v is None:
                raise ConfigError(
                    f"[method.parameters] {name}: no value for joint {j!r} (give {j} or "
                    f"{j.rsplit('_', 1)[0]})"
                )
            out.append(v)
        return out
    return [value] * len(joints)


def _check_params(params: Mapping, method: str) -> None:
    allowed = set(_GENERAL_KEYS) | set(_PAPER_A_KEYS) | set(_VISION_KEYS)
    unknown = sorted(set(params) - allowed)
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], sorted(allowed), n=1)
        hint = f"did you mean {close[0]!r}?" if close else f"allowed: {', '.join(sorted(allowed))}"
        raise ConfigError(f"[method.parameters] {unknown[0]}: unknown parameter ({hint})")
    for key, choices in (
        ("calibration", _CALIBRATIONS),
        ("filter", _FILTERS),
        ("root", _ROOTS),
        ("heading", _HEADINGS),
        ("flexion_axes", ("auto", "movement", "pose")),
        ("pose", ("n", "t")),
        ("align_to_reference", ("none", "rigid")),
    ):
        if key in params and params[key] not in choices:
            raise ConfigError(
                f"[method.parameters] {key}: expected one of {', '.join(choices)}, got "
                f"{params[key]!r}"
            )
    if "rate_hz" in params:
        v = params["rate_hz"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ConfigError(f"[method.parameters] rate_hz: expected a number > 0, got {v!r}")
    for key in ("root_position_m", "facing"):
        if key in params and not isinstance(params[key], Mapping):
            v = np.asarray(params[key], dtype=object)
            if v.shape != (3,) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v
            ):
                raise ConfigError(
                    f"[method.parameters] {key}: expected [x, y, z] in m, got {params[key]!r}"
                )


def _rigid_align(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """Best rotation + translation of ``est (T, J, 3)`` onto ``ref``; aligned copy and RMS (m)."""
    from kinefuse.kinematics import kabsch_rotation

    P, Q = est.reshape(-1, 3), ref.reshape(-1, 3)
    ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(Q), axis=1)
    cp, cq = P[ok].mean(axis=0), Q[ok].mean(axis=0)
    R = kabsch_rotation(P[ok] - cp, Q[ok] - cq)
    out = (est - cp) @ R.T + cq
    return out, float(np.sqrt(np.nanmean(np.sum((out - ref) ** 2, axis=-1))))


# --------------------------------------------------------------------------------------------
# coverage: which input backs each output sample (issue 12)
# --------------------------------------------------------------------------------------------

#: Longest interval between two IMU orientation samples interpolated across, s (SLERP); a
#: stream sampled more sparsely covers only its own sample times.
IMU_MAX_GAP_S = 0.25
#: Longest gap of the root stream (camera or reference root joints) bridged by linear
#: interpolation, s; beyond it, or outside the stream, the chain has no root.
ROOT_MAX_GAP_S = 1.0
#: A joint whose available fraction is below this gets a coverage warning.
COVERAGE_WARN_FRACTION = 0.95


def _valid_span(t: np.ndarray, ok: np.ndarray) -> tuple[float, float] | None:
    idx = np.flatnonzero(ok)
    return None if idx.size == 0 else (float(t[idx[0]]), float(t[idx[-1]]))


def _imu_span(st) -> tuple[float, float] | None:
    return _valid_span(st.t_s, np.all(np.isfinite(st.q_world_from_sensor), axis=1))


def _stream_span(stream) -> tuple[float, float] | None:
    return _valid_span(stream.t_s, np.any(stream.available, axis=1))


def _check_overlap(recording, root_stream, root_name: str) -> None:
    """Streams that never overlap in time are an error naming the spans (not a calibration one)."""
    spans = {seg: _imu_span(st) for seg, st in recording.imu.items()}
    common = (max(a for a, _ in spans.values()), min(b for _, b in spans.values()))
    if common[0] > common[1]:
        listed = ", ".join(f"{seg} {a:.2f}-{b:.2f} s" for seg, (a, b) in spans.items())
        raise InputError(
            f"the IMU streams do not overlap in time ({listed}): no instant has every mapped "
            "sensor; check the files' clocks or map sensors of one recording"
        )
    root = _stream_span(root_stream)
    if root is None or root[0] > common[1] or root[1] < common[0]:
        where = "no valid sample" if root is None else f"{root[0]:.2f}-{root[1]:.2f} s"
        raise InputError(
            f"the IMU streams ({common[0]:.2f}-{common[1]:.2f} s) and the {root_name} "
            f"({where}) do not overlap in time; check the clocks (time offset) of the files"
        )


def _extend_to_imu(t: np.ndarray, recording) -> np.ndarray:
    """The root timeline extended (same step) over the span the IMUs cover; never cut."""
    if t.size < 2:
        return t
    spans = [sp for sp in (_imu_span(st) for st in recording.imu.values()) if sp is not None]
    a, b = min(sp[0] for sp in spans), max(sp[1] for sp in spans)
    dt = float(np.median(np.diff(t)))
    n_before = int(np.floor((t[0] - a) / dt + 1e-9)) if a < t[0] - 0.5 * dt else 0
    n_after = int(np.floor((b - t[-1]) / dt + 1e-9)) if b > t[-1] + 0.5 * dt else 0
    if not (n_before or n_after):
        return t
    before = t[0] - dt * np.arange(n_before, 0, -1)
    after = t[-1] + dt * np.arange(1, n_after + 1)
    return np.concatenate([before, t, after])


def _covered(t_src, p, t: np.ndarray, max_gap_s: float | None = None) -> np.ndarray:
    from kinefuse.io import resample_positions

    return resample_positions(t_src, p, t, max_gap_s=max_gap_s)[1]


def _input_coverage(recording, sk, root_stream, t: np.ndarray, joints):
    """Per-sample coverage of the chain's inputs on ``t``.

    Returns
    -------
    coverage : dict
        ``"imu <segment>"`` (T,) per IMU; ``"imu"`` (T, J): every IMU of the joint's chain;
        ``"root"`` (T, J): the root stream has the chain's root joint there (usual sampling).
    root_ok : ndarray of bool, shape (T, J)
        The root is usable: data, or a gap of at most :data:`ROOT_MAX_GAP_S` interpolated
        across (never extrapolated).
    """
    cov: dict[str, np.ndarray] = {}
    extra = [s for s in (sk.root_segment,) if s and s in recording.imu and root_stream is None]
    for seg in (*sk.segments, *extra):
        st = recording.imu[seg]
        q = st.q_world_from_sensor
        step = float(np.median(np.diff(st.t_s))) if st.t_s.size > 1 else 0.0
        gap = min(1.5 * step, IMU_MAX_GAP_S) if step > 0 else IMU_MAX_GAP_S
        cov[f"imu {seg}"] = _covered(st.t_s, q, t, gap) if st.t_s.size > 1 else np.isin(t, st.t_s)
    seg_of = dict(zip(sk.distal, sk.segments, strict=True))
    parent = {
        s: (sk.segments[p] if p >= 0 else None)
        for s, p in zip(sk.segments, sk.parents, strict=True)
    }
    T = t.size
    imu = np.ones((T, len(joints)), bool)
    root = np.ones((T, len(joints)), bool)
    root_ok = np.ones((T, len(joints)), bool)
    step = 0.0
    if root_stream is not None and root_stream.t_s.size > 1:
        step = float(np.median(np.diff(root_stream.t_s)))
    for j, joint in enumerate(joints):
        s = seg_of[joint]
        while s is not None:
            imu[:, j] &= cov[f"imu {s}"]
            top, s = s, parent[s]
        r = sk.proximal[sk.segments.index(top)]
        if root_stream is None:  # fixed root, or hips from the pelvis IMU (its coverage)
            for seg in extra:
                root[:, j] &= cov[f"imu {seg}"]
            root_ok[:, j] = root[:, j]
        elif r in root_stream.joints:
            p = root_stream.position(r)
            root[:, j] = _covered(root_stream.t_s, p, t)
            root_ok[:, j] = _covered(root_stream.t_s, p, t, max(ROOT_MAX_GAP_S, 1.5 * step))
    cov["imu"], cov["root"] = imu, root
    return cov, root_ok


def apply_coverage(
    out: SessionOutput,
    coverage: Mapping,
    root_ok: np.ndarray,
    joints,
    method: str,
    root_name: str = "root",
) -> None:
    """Set ``available``, ``coverage`` and the predicted source code of ``out`` in place.

    A sample is *available* when its position is finite and the inputs of the method back
    it: the IMUs of the joint's chain and the chain's root (``paper-a``, ``imu-only``), that
    or the camera (the camera methods), the camera (``camera-only``). Elsewhere the source is
    :data:`~kinefuse.conventions.SOURCE_PREDICTED` and ``available`` is False, whatever the
    filter predicted. An IMU-chain sample whose root was interpolated across a gap of the
    root stream is ``SOURCE_BRIDGED``. Warnings are added for joints below
    :data:`COVERAGE_WARN_FRACTION`.
    """
    cols = [list(joints).index(j) for j in out.joints]
    T, J = out.position.shape[:2]
    cov = {k: (v if v.ndim == 1 else v[:, cols]) for k, v in coverage.items()}
    chain_ok = cov["imu"] & root_ok[:, cols]
    finite = np.all(np.isfinite(out.position), axis=-1)
    cam = np.zeros((T, J), bool) if out.camera is None else np.all(np.isfinite(out.camera), -1)
    if out.camera is not None:
        cov["camera"] = cam
    if out.reference is not None:
        cov["reference"] = np.all(np.isfinite(out.reference), axis=-1)
    if method == "camera-only":
        backed = cam
    elif method in _CAMERA_METHODS:
        backed = chain_ok | cam
    else:
        backed = chain_ok
    out.available = finite & backed
    out.source = np.where(finite & ~backed, SOURCE_PREDICTED, out.source).astype(np.int64)
    root_gap = out.available & chain_ok & ~cov["root"] & (out.source == SOURCE_IMU)
    out.source[root_gap] = SOURCE_BRIDGED  # root interpolated across a gap of its stream
    out.coverage = cov
    span = f"{out.t_s[0]:.2f}-{out.t_s[-1]:.2f} s" if T else "no samples"
    for j, joint in enumerate(out.joints):
        frac = float(np.mean(out.available[:, j])) if T else 0.0
        if frac >= COVERAGE_WARN_FRACTION:
            continue
        label = {"root": f"the chain's root ({root_name})"}
        short = [
            k.split(" ", 1)[1] + " IMU" if k.startswith("imu ") else label.get(k, k)
            for k, v in cov.items()
            if k != "reference" and k != "imu" and np.mean(v if v.ndim == 1 else v[:, j]) < 0.999
        ]
        why = f"; not covered by: {', '.join(short)}" if short else ""
        msg = (
            f"{joint}: only {frac:.0%} of the {T} output samples ({span}) are backed by the "
            f"inputs{why}; the rest is predicted (source 'predicted', available = 0)"
        )
        out.warnings.append(msg)
        out.notes.append(f"WARNING: {msg}")
    n_pred = int(np.sum(finite & ~backed))
    if n_pred and out.reference is not None:
        out.notes.append(
            f"metrics: the {n_pred} predicted joint samples (no input backs them) are excluded; "
            "every method is scored on the samples it outputs as available"
        )
    for joint, row in coverage_counts(out).items():
        kinds = ", ".join(f"{row[k]} {k}" for k in ("measured", "fused", "bridged", "predicted"))
        streams = ", ".join(f"{k[:-8]} {v}" for k, v in row.items() if k.endswith(" covered"))
        out.notes.append(
            f"coverage {joint}: {row['available']} of {row['samples']} samples available "
            f"({kinds}); covered by {streams}"
        )
    if out.reference is not None and T:
        frac = float(np.mean(np.any(cov["reference"], axis=1)))
        if frac < COVERAGE_WARN_FRACTION:
            msg = (
                f"the reference covers only {frac:.0%} of the {T} output samples ({span}); "
                "the metrics are computed on that part only"
            )
            out.warnings.append(msg)
            out.notes.append(f"WARNING: {msg}")


def coverage_counts(out: SessionOutput) -> dict:
    """Per joint: samples, available, each source kind and each stream's covered samples."""
    kinds = ("measured", "fused", "bridged", "predicted")
    res = {}
    for j, joint in enumerate(out.joints):
        src = out.source[:, j]
        row = {"samples": int(src.size), "available": int(np.sum(out.available[:, j]))}
        for kind in kinds:
            codes = [c for c, k in SOURCE_KINDS.items() if k == kind]
            row[kind] = int(np.sum(np.isin(src, codes)))
        row["none"] = int(np.sum(src < 0))
        for name, v in out.coverage.items():
            if name != "imu" and not name.startswith("imu "):
                row[f"{name} covered"] = int(np.sum(v[:, j]))
        row["imu covered"] = int(np.sum(out.coverage["imu"][:, j]))
        res[joint] = row
    return res


def coverage_table(out: SessionOutput):
    """:func:`coverage_counts` as a :class:`~kinefuse.evaluation.tables.ResultTable`."""
    from kinefuse.evaluation.tables import ResultTable, TableRow

    counts = coverage_counts(out)
    headers = tuple(next(iter(counts.values())))
    return ResultTable(
        title="Coverage per joint (output samples)",
        label_headers=("Joint",),
        value_headers=headers,
        rows=tuple(
            TableRow((joint,), tuple(float(row[h]) for h in headers))
            for joint, row in counts.items()
        ),
        digits=0,
        notes=(
            "available = backed by the inputs the method needs; measured = one stream (IMU "
            "chain or camera), fused = camera-fused, bridged = outage bridged by the learned "
            "model, predicted = no input (the filter's prediction, never available).",
        ),
    )


# --------------------------------------------------------------------------------------------
# the core
# --------------------------------------------------------------------------------------------


def _plan(recording, method: str, params: Mapping, segs: Sequence[str]) -> dict:
    """Resolve calibration, root and alignment; refuse impossible combinations before any work."""
    has_cam = recording.vision is not None
    has_ref = recording.reference is not None
    if method in _CAMERA_METHODS and not has_cam:
        raise ConfigError(
            f"method {method!r} needs a camera (it fuses the IMU chain with camera joints); add "
            "a [camera] section, or use 'paper-a' / 'imu-only' for IMUs alone"
        )
    calib = params.get("calibration", "vision" if has_cam else "static")
    if calib == "vision" and not has_cam:
        raise ConfigError(
            "calibration 'vision' needs a [camera]; use 'static' (a still pose) or 'functional'"
        )
    if calib == "reference" and not has_ref:
        raise ConfigError("calibration 'reference' needs a [reference] section")
    legs = any(s.startswith(("thigh_", "shank_", "foot_")) for s in segs)
    starts = {
        SEGMENT_JOINTS[s][0]
        for s in segs
        if SEGMENT_JOINTS[s][0] not in {SEGMENT_JOINTS[x][1] for x in segs}
    }
    hips = sorted(j for j in starts if j.startswith("hip_"))
    if "root" in params:
        root = "vision" if params["root"] == "camera" else params["root"]
    elif has_cam:
        root = "vision"
    elif hips and "pelvis" in recording.imu:
        root = "pelvis"
    else:
        root = "fixed"
    if root == "vision" and not has_cam:
        raise ConfigError("root 'vision' (camera joints) needs a [camera] section")
    if root == "reference" and not has_ref:
        raise ConfigError("root 'reference' needs a [reference] section")
    if root in ("fixed", "pelvis") and method in _CAMERA_METHODS:
        raise ConfigError(
            f"method {method!r} fuses with camera joints in the camera frame; it needs root "
            "'vision' (default with a camera), not {root!r}"
        )
    if root == "pelvis" and not (legs and hips):
        raise ConfigError(
            "root 'pelvis' places the hips from the pelvis IMU; it needs thigh segments (chains "
            f"starting at the hips), got chains starting at {sorted(starts)}; use root 'fixed'"
        )
    if root in ("fixed", "pelvis") and hips and "pelvis" not in recording.imu:
        if not (root == "fixed" and isinstance(params.get("root_position_m"), Mapping)):
            raise ConfigError(
                f"root {root!r}: the hips {hips} are placed from the pelvis IMU; map 'pelvis' in "
                "[imu.segments], or give each hip in root_position_m = {hip_l = [...], ...}"
            )
    if root == "fixed" and isinstance(params.get("root_position_m"), Mapping):
        lack = sorted(starts - set(params["root_position_m"]))
        if lack:
            raise ConfigError(f"root_position_m: no position for the chain start(s) {lack}")
    align = params.get("align_to_reference", "none")
    if align != "none" and not has_ref:
        raise ConfigError("align_to_reference needs a [reference] section")
    if calib == "functional":
        from kinefuse.kinematics import calibrate

        if "functional" not in (calibrate.__doc__ or ""):
            raise ConfigError(
                "calibration 'functional' is not available in this version; use 'static'"
            )
    return {"calibration": calib, "root": root, "hips": hips, "align": align}


def _declared_axes(value, segs) -> dict[str, tuple]:
    """``[skeleton.axes]``: segment -> sensor axis along it (names ``"+e1"``... or 3-vectors)."""
    from kinefuse.kinematics import AXES

    out = {}
    for s, a in dict(value or {}).items():
        if s not in SEGMENT_JOINTS and s != "pelvis":
            raise ConfigError(f"[skeleton.axes] {s}: not a limb segment or 'pelvis'")
        if isinstance(a, str):
            if a not in AXES:
                raise ConfigError(
                    f"[skeleton.axes] {s}: unknown axis {a!r}; expected one of {sorted(AXES)}"
                )
            a = AXES[a]
        v = np.asarray(a, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
            raise ConfigError(f"[skeleton.axes] {s}: expected an axis name or [x, y, z], got {a!r}")
        out[s] = tuple(v / np.linalg.norm(v))
    return out


def _hip_roots(recording, cal, t, origin, body_height_m, notes) -> dict[str, np.ndarray]:
    """Hip joint centres from the pelvis IMU: origin (mid-hip) ± half the hip width along Z."""
    from kinefuse.kinematics import ANTHROPOMETRIC_RATIOS, segment_orientations
    from kinefuse.kinematics.forward import as_rotation_matrices
    from kinefuse.orientation.resample import slerp_resample

    if body_height_m is None:
        raise ConfigError(
            "the hips are placed from the pelvis IMU with the hip width 0.191 x body height "
            "(Winter 2009); give [skeleton] body_height_m"
        )
    w = ANTHROPOMETRIC_RATIOS["hip_width"] * float(body_height_m)
    if cal is not None and "pelvis" in cal.frames:
        R = segment_orientations(recording, cal, t, ["pelvis"])["pelvis"]
        how = "the pelvis frame of the static calibration (Z = right in the pose)"
    else:
        st = recording.imu["pelvis"]
        R = as_rotation_matrices(slerp_resample(st.t_s, st.q_world_from_sensor, t))
        R = R[..., [1, 2, 0]]  # right-front-up sensor: ISB X fwd = y, Y up = z, Z right = x
        how = "the pelvis sensor frame taken as right-front-up (no calibrated pelvis frame)"
    notes.append(
        f"hips: pelvis origin (mid-hip) ± {w / 2:.3f} m along the pelvis right axis "
        f"(hip width 0.191 x {float(body_height_m):g} m, Winter 2009), from {how}"
    )
    right = R[..., :, 2]
    return {"hip_l": origin - 0.5 * w * right, "hip_r": origin + 0.5 * w * right}


def process_recording(
    recording,
    method: str,
    parameters: Mapping | None = None,
    *,
    lengths: Mapping[str, float] | None = None,
    body_height_m: float | None = None,
) -> SessionOutput:
    """Run one method on a recording whose IMUs are keyed by canonical segment.

    Parameters
    ----------
    recording : Recording
        ``imu`` keyed by canonical segment (orientation or raw acc + gyr), optional ``vision``
        (camera) and ``reference``.
    method : str
        A :data:`kinefuse.session.METHODS` name.
    parameters : mapping, optional
        ``[method.parameters]`` (see the module docstring).
    lengths : mapping of str -> float, optional
        Measured segment lengths, m (win over everything else).
    body_height_m : float, optional
        Body height for anthropometric lengths (Winter 2009) and the hip width.

    Returns
    -------
    SessionOutput

    Raises
    ------
    ConfigError
        Bad parameters, a method or calibration that needs a camera or reference without one,
        a root that cannot be placed, no limb segment, a segment without a length: all before
        any processing.
    InputError
        Problems found in the data (no still window, missing root joints...).

    Notes
    -----
    The IMU chain (SPEC §2.1) starts at the *root joints*, the proximal joints of segments
    whose parent segment carries no IMU (the hips for thigh + shank, the shoulder for the upper
    arm). ``root`` says where they are: ``"fixed"`` (``root_position_m``, measured once, as
    paper A's shoulder; default origin, i.e. positions relative to the root joint),
    ``"pelvis"`` (hips from the pelvis IMU, positions relative to the mid-hip point),
    ``"vision"`` (camera joints, gaps interpolated) or ``"reference"`` (only when asked: the
    reference is evaluation-only by default). Nothing else is taken from a reference unless
    asked (``calibration = "reference"``, ``measured_lengths = true``,
    ``align_to_reference = "rigid"``); tables of scores that used it are labelled.
    """
    from kinefuse.session import METHODS

    if method not in METHODS:
        raise ConfigError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    params = dict(parameters or {})
    _check_params(params, method)
    notes: list[str] = []
    has_cam = recording.vision is not None
    run_warnings: list[str] = []
    segs = [s for s in SEGMENT_JOINTS if s in recording.imu]
    if not segs:
        raise ConfigError(
            "no limb segment among the mapped sensors "
            f"{sorted(recording.imu)}; map at least one of {', '.join(SEGMENT_JOINTS)}"
        )
    plan = _plan(recording, method, params, segs)
    calib, root_kind = plan["calibration"], plan["root"]
    from kinefuse.kinematics import segment_lengths

    measured = dict(lengths or {})
    use_stream_lengths = bool(params.get("measured_lengths", calib == "vision"))
    if calib not in ("vision", "reference", "functional") or not use_stream_lengths:
        try:  # a missing length is refused before any work
            segment_lengths(segs, measured=measured, height_m=body_height_m)
        except InputError as exc:
            if calib != "functional":
                raise ConfigError(str(exc)) from None
    six_d = _ensure_orientations(recording, params, notes, run_warnings)

    root_stream = None
    if root_kind == "vision":
        root_stream = recording.vision
    elif root_kind == "reference":
        root_stream = recording.reference
    default_rate = 30.0 if method in ("paper-a", *_CAMERA_METHODS) else None
    rate = params.get("rate_hz", default_rate)
    if root_stream is not None:
        t = _timeline(root_stream.t_s, None if rate is None else float(rate))
        _check_overlap(recording, root_stream, "camera" if root_kind == "vision" else root_kind)
        t = _extend_to_imu(t, recording)
    else:
        t0 = max(float(recording.imu[s].t_s[0]) for s in segs)
        t1 = min(float(recording.imu[s].t_s[-1]) for s in segs)
        base = recording.imu[segs[0]].t_s
        base = base[(base >= t0 - 1e-9) & (base <= t1 + 1e-9)]
        t = _timeline(base, None if rate is None else float(rate))

    # calibration
    from kinefuse.kinematics import calibrate, chain_positions
    from kinefuse.kinematics.angles import JOINTS

    axes_decl = _declared_axes(params.get("axes"), segs)
    cal_segs = list(segs) + (["pelvis"] if root_kind == "pelvis" else [])
    sk, roots = build_chain(segs, dict.fromkeys(segs, 0.3), axes_decl)
    if root_kind == "pelvis":
        sk = replace(sk, root_segment="pelvis")
    cal = None
    provenance: dict = {"calibration": calib, "root": root_kind}
    if calib != "none":
        window = float(params.get("calibration_window_s", 2.0))
        start = params.get("calibration_start_s")
        kw = {"window_s": window, "start_s": None if start is None else float(start)}
        if calib == "static":
            heading = params.get("heading", "auto")
            if heading == "auto":
                heading = "static" if six_d else "none"
            kw.update(
                pose=params.get("pose", "n"),
                facing=tuple(params.get("facing", (0.0, 1.0, 0.0))),
                heading=heading,
                flexion_axes=params.get("flexion_axes", "auto"),
                mounting={s: a for s, a in axes_decl.items() if s in cal_segs},
                segments=cal_segs,
            )
            for k in ("max_rate_rad_s", "max_acc_std_m_s2"):
                if k in params:
                    kw[k] = float(params[k])
        elif calib in ("vision", "reference"):
            kw["align"] = params.get("align", "auto")
        elif calib == "functional":
            kw["mounting"] = {s: a for s, a in axes_decl.items() if s in cal_segs}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cal = calibrate(recording, sk, calib, **kw)
        notes += [f"calibration: {w.message}" for w in caught]
        if calib == "functional" and cal.declared:
            notes.append(
                "calibration: no sensor beyond the distal joint of "
                f"{', '.join(cal.declared)}: the declared sensor axis ([skeleton.axes]) is its "
                "axis and its length comes from the session"
            )
        if calib == "functional" and getattr(cal, "heading", "shared") == "estimate":
            from kinefuse.kinematics.functional import align_headings

            recording = align_headings(recording, cal)
            notes.append(
                "heading: each sensor's world frame turned into its chain's first sensor's, "
                "from the joint constraints of the functional calibration (deg): "
                + ", ".join(f"{s} {v:.1f}" for s, v in cal.heading_deg.items())
            )
            provenance["heading"] = "joint constraints (functional)"
        res = ", ".join(f"{s} {v:.1f}" for s, v in cal.residual_deg.items())
        what = {
            "static": "still pose, IMU data only",
            "functional": "movement, IMU data only",
            "vision": "camera joints",
            "reference": "REFERENCE joints (evaluation data used for calibration, as asked)",
        }[calib]
        line = (
            f"calibration {calib!r} ({what}) over {cal.window_s[0]:.2f}-{cal.window_s[1]:.2f} s, "
            f"alignment {cal.align!r}; RMS residual (deg): {res}"
        )
        if cal.still is not None:
            line += f"; stillness {cal.still.describe()}"
        if cal.pose_residual_deg:
            line += "; declared sensor axis vs the pose (deg): " + ", ".join(
                f"{s} {v:.1f}" for s, v in cal.pose_residual_deg.items()
            )
        notes.append(line)
        provenance["calibration_window_s"] = list(cal.window_s)
        if calib == "static":
            f = [float(x) for x in params.get("facing", (0.0, 1.0, 0.0))]
            hinged = sorted(cal.hinge_residual_rad_s)
            moved = {s for j in hinged for s in JOINTS[j][:2]}
            rest = [s for s in cal.frames if s not in moved]
            if hinged:
                notes.append(
                    "segment frames: long axes from the still pose; flexion axes of "
                    f"{', '.join(hinged)} from the movement (the two sensors' relative rotation, "
                    "Laidig et al. 2017's elbow model; RMS residual rad/s: "
                    + ", ".join(f"{j} {cal.hinge_residual_rad_s[j]:.2f}" for j in hinged)
                    + "), sign by anatomy (the larger excursion from the pose is flexion); the "
                    "facing is not used for them"
                )
                provenance["flexion_axes"] = {j: "movement" for j in hinged}
            if rest:
                notes.append(
                    f"segment frames of {', '.join(rest)}: anterior axis = the facing direction "
                    f"{f} (world frame) in the still pose, as declared ([calibration] facing; "
                    "default north); flexion axes follow from it"
                )
                provenance["facing"] = f
            if cal.world_heading_deg:
                notes.append(
                    "heading: 6-D orientations (arbitrary heading per sensor) brought into the "
                    f"heading of {cal_segs[0]} from the static pose, assuming all sensors face "
                    "the same way on the body; applied (deg): "
                    + ", ".join(f"{s} {v:.1f}" for s, v in cal.world_heading_deg.items())
                )
                provenance["heading"] = "static pose"
            else:
                notes.append(
                    "heading: orientations kept as estimated (shared, magnetometer-referenced "
                    "north)"
                    if not six_d
                    else "heading: not aligned (heading = 'none')"
                )
                provenance["heading"] = "none"
    else:
        notes.append("calibration: none; the segment axes are the configured sensor axes")
    derived = {}
    if (
        use_stream_lengths
        and cal is not None
        and cal.lengths_m
        and calib in ("vision", "reference")
    ):
        src = "camera" if calib == "vision" else "REFERENCE"
        derived = {s: (v, f"{src} (calibration window)") for s, v in cal.lengths_m.items()}
    functional = dict(cal.lengths_m) if cal is not None and calib == "functional" else {}
    if root_kind == "vision" and use_stream_lengths:
        from kinefuse.kinematics import lengths_from_joints

        got = lengths_from_joints(
            recording.vision, [(s, *SEGMENT_JOINTS[s]) for s in segs], missing="skip"
        )
        for s, v in got.items():
            derived.setdefault(s, (v, "camera (median)"))
    try:
        seg_lengths, how = segment_lengths(
            segs,
            measured=measured,
            height_m=body_height_m,
            functional=functional,
            derived=derived,
        )
    except InputError as exc:
        raise ConfigError(str(exc)) from None
    notes.append(
        "segment lengths (m): " + ", ".join(f"{s} {seg_lengths[s]:.3f} ({how[s]})" for s in segs)
    )
    provenance["segment_lengths"] = {
        s: {"m": round(seg_lengths[s], 6), "source": how[s]} for s in segs
    }
    sk, roots = build_chain(segs, seg_lengths, axes_decl)
    if cal is not None:
        sk = cal.apply(sk, lengths=False)

    # roots
    root_name = {"vision": "camera", "reference": "reference"}.get(root_kind, root_kind)
    if root_stream is not None:
        lack = [j for j in roots if j not in root_stream.joints]
        if lack:
            raise InputError(
                f"the chain starts at {list(roots)}, but the {root_name} stream lacks {lack} "
                f"(it has {list(root_stream.joints)})"
            )
        root_pos = {j: _at(root_stream, j, t, fill=True) for j in roots}
        frame = root_stream.frame
        root_desc = f"{', '.join(roots)} from the {root_name}"
    else:
        rp = params.get("root_position_m", (0.0, 0.0, 0.0))
        if isinstance(rp, Mapping):
            root_pos = {j: np.tile(np.asarray(rp[j], dtype=float), (t.size, 1)) for j in roots}
            root_desc = "fixed " + ", ".join(f"{j} at {list(rp[j])} m" for j in roots)
        else:
            origin = np.tile(np.asarray(rp, dtype=float), (t.size, 1))
            if plan["hips"]:
                root_pos = _hip_roots(recording, cal, t, origin, body_height_m, notes)
                root_pos.update({j: origin for j in roots if j not in root_pos})
                root_desc = (
                    f"pelvis (mid-hip) at {list(map(float, rp))} m, hips from the pelvis IMU"
                )
            else:
                root_pos = {j: origin for j in roots}
                root_desc = f"fixed {', '.join(roots)} at {list(map(float, rp))} m"
        frame = "ENU"
        if cal is not None and cal.world_heading_deg:
            frame += f" (heading of the {cal_segs[0]} sensor)"
        zero = not isinstance(rp, Mapping) and not np.any(np.asarray(rp, dtype=float))
        if zero:
            frame += (
                ", relative to the pelvis (mid-hip)"
                if plan["hips"]
                else f", relative to {roots[0]}"
            )
    provenance["root_position"] = root_desc
    source = "vision" if root_kind == "vision" else "reference"
    chain_st = chain_positions(recording, sk, cal, root=root_pos, source=source, t_s=t)
    joints = tuple(s for s in sk.distal)
    chain = np.stack([chain_st.position(j, masked=False) for j in joints], axis=1)
    coverage, root_ok = _input_coverage(recording, sk, root_stream, t, joints)
    chain[~(coverage["imu"] & root_ok)] = np.nan  # no chain without its inputs
    notes.append(
        f"IMU chain from {root_desc}"
        f"{' (gaps interpolated)' if root_kind == 'vision' else ''} through "
        f"{', '.join(sk.segments)}; {t.size} samples at "
        f"{1.0 / float(np.median(np.diff(t))) if t.size > 1 else float('nan'):.1f} Hz; "
        f"frame: {frame}"
    )

    T, J = t.size, len(joints)
    camera = None
    if has_cam:
        cam = recording.vision
        camera = np.stack(
            [
                _at(cam, j, t, fill=False) if j in cam.joints else np.full((T, 3), np.nan)
                for j in joints
            ],
            axis=1,
        )
        if cal is not None and cal.R_world_from_camera is not None and root_kind != "vision":
            camera = camera @ np.asarray(cal.R_world_from_camera).T
    reference = None
    if recording.reference is not None:
        ref = recording.reference
        reference = np.stack(
            [
                _at(ref, j, t, fill=False) if j in ref.joints else np.full((T, 3), np.nan)
                for j in joints
            ],
            axis=1,
        )

    out = SessionOutput(
        t_s=t,
        joints=joints,
        position=chain.copy(),
        std_m=np.full((T, J, 3), np.nan),
        source=np.where(np.all(np.isfinite(chain), -1), SOURCE_IMU, -1).astype(np.int64),
        mode=np.full((T, J), -1, dtype=np.int64),
        frame=frame,
        method=method,
        label=_METHOD_LABELS[method],
        chain=chain,
        camera=camera,
        reference=reference,
        edges=tuple((p, d) for p, d in zip(sk.proximal, sk.distal, strict=True) if p in joints),
        notes=notes,
        warnings=run_warnings,
        root=root_desc,
        provenance=provenance,
    )
    if cal is not None:
        from scipy.spatial.transform import Rotation

        from kinefuse.orientation.resample import slerp_resample

        for s in cal.axes:
            st = recording.imu.get(s)
            if st is None or st.q_world_from_sensor is None:
                continue
            q = slerp_resample(st.t_s, st.q_world_from_sensor, t)
            ok = np.all(np.isfinite(q), axis=1)
            qw = np.full(q.shape, np.nan)
            if np.any(ok):
                H = Rotation.from_matrix(cal.heading_matrix(s))
                qw[ok] = (H * Rotation.from_quat(q[ok], scalar_first=True)).as_quat(
                    scalar_first=True
                )
            out.sensor_orientations[s] = qw
    if cal is not None and cal.frames:
        from kinefuse.kinematics import joint_angles, segment_orientations

        out.angles = joint_angles(segment_orientations(recording, cal, t))
        if out.angles:
            notes.append(
                "joint angles (deg, ISB: Wu et al. 2002/2005, Grood & Suntay 1983; zero in the "
                f"calibration pose): {', '.join(out.angles)}"
            )
        for j, a in out.angles.items():
            lo, hi = _HINGE_RANGE_DEG.get(j.rsplit("_", 1)[0], (-np.inf, np.inf))
            f = a[:, 0][np.isfinite(a[:, 0])]
            if f.size and (np.percentile(f, 1) < lo or np.percentile(f, 99) > hi):
                notes.append(
                    f"warning: {j} flexion spans {f.min():.0f} to {f.max():.0f} deg, beyond the "
                    f"anatomical {lo:.0f} to {hi:.0f} deg: the facing direction or the pose is "
                    "probably wrong (the facing, the pose, or too little flexion to fit its axis: "
                    "see the calibration notes; [calibration] flexion_axes, facing)"
                )
    dt = float(np.median(np.diff(t))) if T > 1 else 1.0 / 30.0
    t0 = time.perf_counter()
    flt = params.get("filter", "em-kf-fir" if method == "paper-a" else "none")
    if method in ("paper-a", "imu-only"):
        if flt != "none":
            t0 = _paper_a_filter(out, chain, dt, flt, params)
            out.label = {"kf": "KF", "fir": "FIR", "em-kf": "EM-KF", "em-kf-fir": "EM-KF/FIR"}[flt]
            if method == "imu-only":
                out.label = f"IMU only + {out.label}"
    else:
        _vision(out, recording, chain, camera, dt, method, params, cal)
    out.run_time_s = time.perf_counter() - t0
    apply_coverage(out, coverage, root_ok, joints, method, root_name)
    if method in _CAMERA_METHODS and out.camera is not None:
        out.baselines = _baselines(out.chain, out.camera, dt, out.joints)
    tags = []
    if calib == "reference":
        tags.append("calibrated on reference")
    if any("REFERENCE" in v["source"] for v in provenance["segment_lengths"].values()):
        tags.append("lengths from reference")
    if out.reference is not None and out.frame != "ENU chest-relative":
        ref_frame = recording.reference.frame
        if plan["align"] == "rigid":
            for name in ("position", "chain", "camera"):
                arr = getattr(out, name)
                if arr is not None and np.any(np.isfinite(arr)):
                    setattr(out, name, _rigid_align(arr, reference)[0])
            out.baselines = {
                k: _rigid_align(v, reference)[0] if np.any(np.isfinite(v)) else v
                for k, v in out.baselines.items()
            }
            tags.append("aligned to reference")
            notes.append(
                "estimates rigidly aligned to the reference (Kabsch rotation + translation over "
                "all samples, as asked: align_to_reference = 'rigid') before evaluation"
            )
            provenance["alignment"] = "rigid (Kabsch) to the reference, as asked"
        elif ref_frame != out.frame:
            notes.append(
                f"no scores: the output frame ({out.frame}) is not the reference frame "
                f"({ref_frame}); positions in different frames are not comparable. Set "
                "align_to_reference = 'rigid' for scores after a rigid alignment (labelled), or "
                "root = 'reference' to start the chain at the reference joints"
            )
            out.reference = None
            provenance["alignment"] = "none (frames differ: not scored)"
        else:
            provenance["alignment"] = "none"
    out.tag = f" [{', '.join(tags)}]" if tags else ""
    provenance["labels"] = out.tag.strip() or "IMU/camera data only"
    return out


def _paper_a_filter(out: SessionOutput, chain, dt, flt: str, params: Mapping) -> float:
    """Paper A's filter per joint, in place; returns the start time of the timed run."""
    from kinefuse.pipelines import upper_limb

    kw = {k: params[k] for k in ("horizon", "threshold1", "threshold2", "n_em_iter") if k in params}
    q = _number_or_table(params.get("q", 0.1), out.joints, "q")
    r = _number_or_table(params.get("r", 0.01), out.joints, "r")
    ok = np.any(np.all(np.isfinite(chain), axis=-1), axis=0)
    if not np.all(ok):
        bad = [j for j, o in zip(out.joints, ok, strict=True) if not o]
        raise InputError(f"the IMU chain has no valid sample for {bad}")
    method = "em-kf-fir" if flt == "em-kf-fir" else flt
    try:
        # compile outside the timed run (numba compiles on the first call)
        z0 = chain[:, 0][np.all(np.isfinite(chain[:, 0]), axis=1)][:30]
        with warnings.catch_warnings():  # e.g. "horizon longer than the series": warm-up only
            warnings.simplefilter("ignore")
            upper_limb(z0, None, dt, method, q=q[0], r=r[0], **kw)
        t0 = time.perf_counter()
        for j, name in enumerate(out.joints):
            res = upper_limb(chain[:, j], None, dt, method, q=q[j], r=r[j], joints=(name,), **kw)
            out.position[:, j] = res.position[:, 0]
            out.std_m[:, j] = np.sqrt(np.diagonal(res.cov[:, 0], axis1=-2, axis2=-1))
            out.mode[:, j] = res.mode[:, 0]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[method.parameters]: {exc}") from None
    out.notes.append(
        f"filter {flt} (paper A) per joint, dt = {dt * 1e3:.1f} ms, q = {params.get('q', 0.1)}, "
        f"r = {params.get('r', 0.01)}"
    )
    return t0


def _vision(out: SessionOutput, recording, chain, camera, dt, method, params, cal) -> None:
    from kinefuse.pipelines import METHODS, VisionParams, vision_assisted

    if method not in METHODS:
        raise ConfigError(
            f"method {method!r} is not available in this installation (available: "
            f"{', '.join(sorted(METHODS))})"
        )
    vp = {k: params[k] for k in _VISION_KEYS if k in params}
    try:
        vparams = VisionParams(**vp)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[method.parameters]: {exc}") from None
    causal = bool(params.get("causal", False))
    full = {"chest", "upper_arm_l", "upper_arm_r", "forearm_l", "forearm_r"} | {
        "thigh_l",
        "thigh_r",
        "shank_l",
        "shank_r",
    }
    cam = recording.vision
    if full <= set(recording.imu) and "spine_shoulder" in cam.joints:
        from kinefuse.pipelines import vision_assisted_from_recording

        joints = tuple(j for j in out.joints if j in cam.joints)
        rate = 1.0 / dt
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fused = vision_assisted_from_recording(
                recording, None, cal, method, rate, joints=joints, causal=causal, params=vparams
            )
        if fused.t_s.size != out.t_s.size:
            raise InputError(
                f"camera timeline ({fused.t_s.size} samples) differs from the output timeline"
            )
        out.joints = joints
        out.position = fused.result.position
        out.chain = fused.z_imu
        out.camera = fused.z_cam
        out.reference = fused.reference
        out.std_m = np.sqrt(np.diagonal(fused.result.cov, axis1=-2, axis2=-1))
        out.source = fused.result.source.astype(np.int64)
        out.mode = np.full(out.source.shape, -1, dtype=np.int64)
        out.frame = "ENU chest-relative"
        out.notes.append(
            f"paper B pipeline {method!r} from the chest IMU (Xu 2023, SPEC §10.3); positions "
            "relative to spine_shoulder"
        )
        return
    avail = np.all(np.isfinite(camera), axis=-1)
    keep = [j for j in range(len(out.joints)) if np.any(avail[:, j]) or method != "camera-only"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = vision_assisted(
            chain[:, keep],
            camera[:, keep],
            avail[:, keep],
            dt,
            method,
            joints=[out.joints[j] for j in keep],
            causal=causal,
            params=vparams,
        )
    out.position = np.full_like(chain, np.nan)
    out.position[:, keep] = res.position
    out.std_m[:, keep] = np.sqrt(np.diagonal(res.cov, axis1=-2, axis2=-1))
    out.source[:, keep] = res.source
    out.notes.append(
        f"paper B pipeline {method!r} per joint (Xu 2023, SPEC §10.3) on the IMU chain and the "
        "camera joints"
    )


def _baselines(chain, camera, dt, joints) -> dict[str, np.ndarray]:
    """The simple baselines (offset interp / hold, camera gap-fill) on one chain and camera."""
    from kinefuse.pipelines import vision_assisted
    from kinefuse.pipelines.labels import BASELINE_METHODS

    avail = np.all(np.isfinite(camera), axis=-1)
    keep = [j for j in range(len(joints)) if np.any(np.all(np.isfinite(chain[:, j]), axis=-1))]
    out = {}
    for m in BASELINE_METHODS:
        pos = np.full(chain.shape, np.nan)
        if keep:
            res = vision_assisted(
                chain[:, keep],
                camera[:, keep],
                avail[:, keep],
                dt,
                m,
                joints=[joints[j] for j in keep],
            )
            pos[:, keep] = res.position
        out[_METHOD_LABELS[m]] = pos
    return out


# --------------------------------------------------------------------------------------------
# back-ends
# --------------------------------------------------------------------------------------------


def _outputs(out_dir: Path, stem: str) -> dict[str, Path]:
    """Every result ``kinefuse run`` may write into ``out_dir`` (all replaced as one set)."""
    from kinefuse.evaluation.report import REPORT_NAME

    return {
        "csv": out_dir / f"{stem}_joints.csv",
        "trc": out_dir / f"{stem}_joints.trc",
        "angles_csv": out_dir / f"{stem}_angles.csv",
        "mot": out_dir / f"{stem}_angles.mot",
        "orientations_sto": out_dir / f"{stem}_orientations.sto",
        "report": out_dir / REPORT_NAME,
        "metrics": out_dir / "metrics.json",
        "provenance": out_dir / "provenance.json",
        "figures": out_dir / "figures",
    }


def output_paths(cfg, out_dir=None) -> tuple[Path, ...]:
    """Every path :func:`run_session` may write for ``cfg`` (``--json`` may be none of them)."""
    return tuple(_outputs(Path(cfg.out_dir if out_dir is None else out_dir), _stem(cfg)).values())


def _stem(cfg) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in cfg.name) or "session"


def run_session(path, out_dir=None, force: bool = False) -> dict:
    """Back-end of ``kinefuse run``: process the recording a session file describes.

    Parameters
    ----------
    path : str or Path or SessionConfig
        Session TOML (:func:`kinefuse.session.load_session`), or an already validated one.
    out_dir : str or Path, optional
        Output folder (default the session's ``out_dir``); created if needed.
    force : bool
        Replace the results of an earlier run in ``out_dir``.

    Returns
    -------
    dict
        ``outputs`` (paths of the CSV and TRC), ``evaluation`` (EvaluationResult, with a
        reference), ``report`` (Path, with a reference), ``notes``.

    Raises
    ------
    ConfigError
        Invalid session, unknown format, unreadable file, unknown sensor, wrong units, no
        valid samples, a method that needs a camera without one.
    InputError
        Data that cannot be processed (the message says what and where); an output folder
        that is a file, not writable, or whose outputs would overwrite an input (checked
        before any processing).
    FileExistsError
        Any earlier result (joints CSV/TRC, ``report.html``, ``metrics.json``, ``figures/``)
        exists and ``force`` is False (checked before any processing; nothing is written).

    Notes
    -----
    Outputs in ``out_dir``: ``<name>_joints.csv`` (kinefuse joint CSV: ``t_s``, per joint
    ``_x/_y/_z`` in m, ``_available``, ``_source`` (:data:`kinefuse.conventions.SOURCE_NAMES`),
    ``_mode`` (:data:`kinefuse.conventions.MODE_NAMES`, -1 without a filter), ``_std_m_x/y/z``
    (m)); ``<name>_joints.trc`` (OpenSim, m); with a calibration ``<name>_orientations.sto``
    (OpenSense orientation table of the calibrated sensor orientations, input of OpenSense IK);
    with a reference ``report.html``, ``figures/``, ``metrics.json``.

    The results are written atomically (:class:`kinefuse.io.output_folder.OutputFolder`):
    staged in a hidden temporary folder and moved into ``out_dir`` only when complete, so an
    interrupted or failed run leaves the previous results untouched. Files get the mode the
    user's umask gives.
    """
    from kinefuse.io.output_folder import OutputFolder
    from kinefuse.session import SessionConfig, load_session

    cfg = path if isinstance(path, SessionConfig) else load_session(path)
    out_dir = Path(cfg.out_dir if out_dir is None else out_dir)
    targets = _outputs(out_dir, _stem(cfg))
    stage = OutputFolder(
        out_dir,
        [p.name for p in targets.values()],
        force=force,
        protect=cfg.inputs,
        what="output folder",
    )
    try:
        summary = _run_and_write(cfg, stage.path)
        stage.commit()
    except BaseException:
        stage.discard()
        raise
    final = {p: out_dir / p.name for p in summary["outputs"]}
    summary["outputs"] = [final[p] for p in summary["outputs"]]
    if summary.get("report") is not None:
        summary["report"] = out_dir / summary["report"].name
    return summary


def _run_and_write(cfg, folder: Path) -> dict:
    """Process the session and write every result into ``folder`` (the staging folder)."""
    from kinefuse.io import JointStream, write_joint_csv, write_trc

    targets = _outputs(folder, _stem(cfg))
    params = cfg.processing_parameters()
    strict = params.get("strict_units", True)
    recording, notes = load_streams(cfg, strict_units=bool(strict))
    try:
        out = process_recording(
            recording,
            cfg.method.name,
            params,
            lengths=cfg.skeleton.lengths_m,
            body_height_m=cfg.skeleton.body_height_m,
        )
    except ConfigError as exc:
        raise ConfigError(f"{cfg.path.name}: {exc}") from None
    out.notes[:0] = notes
    stream = JointStream(
        t_s=out.t_s,
        position_m=out.position,
        available=out.available,
        joints=out.joints,
        frame=out.frame,
    )
    extra = {"source": out.source, "mode": out.mode, "std_m": out.std_m}
    for name, v in out.coverage.items():  # "imu thigh_r" (T,) -> imu_thigh_r_covered
        extra[f"{name.replace(' ', '_')}_covered"] = v.astype(np.int8)
    csv = write_joint_csv(
        targets["csv"],
        stream,
        extra,
        metadata={
            "session": cfg.name,
            "method": cfg.method.name,
            "root": out.root,
            "source_codes": ", ".join(
                f"{k}={v} ({SOURCE_KINDS[k]})" for k, v in SOURCE_NAMES.items()
            ),
            "mode_codes": ", ".join(f"{k}={v}" for k, v in MODE_NAMES.items()),
            "available": "1 where the inputs the method needs cover the sample (else the "
            "position, if any, is a prediction)",
            "covered": "<stream>_covered: 1 where that input stream has data at the sample",
        },
    )
    trc = write_trc(targets["trc"], stream, note=f"root: {out.root}; frame: {out.frame}")
    summary: dict = {
        "outputs": [csv, trc],
        "notes": out.notes,
        "provenance": out.provenance,
        "coverage": coverage_counts(out),
        "warnings": list(out.warnings),
        "tables": [coverage_table(out)],
    }
    if out.sensor_orientations:
        from kinefuse.io import ImuStream
        from kinefuse.io.opensim import write_opensense_sto

        imus = {
            s: ImuStream(t_s=out.t_s, q_world_from_sensor=q, name=s)
            for s, q in out.sensor_orientations.items()
        }
        sto = write_opensense_sto(targets["orientations_sto"], imus)
        summary["outputs"].append(sto)
        out.notes.append(
            f"OpenSense: {sto.name} holds the calibrated sensor orientations (heading corrections "
            f"applied, frame {out.frame}) for OpenSense IK; for a z-up world set "
            "sensor_to_opensim_rotations = -1.5707963 0 0 in the IMU IK setup"
        )
    if out.angles:
        summary["outputs"] += _write_angles(out, targets, cfg, False)
        summary["angles_deg"] = {
            j: {
                "flexion_min": float(np.nanmin(a[:, 0])),
                "flexion_max": float(np.nanmax(a[:, 0])),
            }
            for j, a in out.angles.items()
        }
    from kinefuse.evaluation.angles import angle_section, write_angle_report

    title = f"kinefuse: {cfg.name} ({cfg.method.name})"
    ev = out.evaluation()
    if ev is not None:
        from kinefuse.evaluation import write_report

        summary["evaluation"] = ev
        summary["report"] = write_report(
            folder,
            ev,
            out.trajectories(),
            out.reference,
            out.t_s,
            modes={ev.methods[0]: out.mode} if np.any(out.mode >= 0) else None,
            sources={ev.methods[0]: out.source},
            skeleton_edges=out.edges or None,
            title=title,
            notes=out.notes,
            sections=[angle_section(out.t_s, out.angles, folder / "figures")],
            extra_metrics={"provenance": out.provenance},
        )
    else:
        summary["report"] = write_angle_report(
            folder,
            out.t_s,
            out.angles,
            title=title,
            notes=out.notes,
            provenance=out.provenance,
        )
    return summary


def _write_angles(out: SessionOutput, targets: Mapping[str, Path], cfg, force: bool) -> list:
    """Joint angles next to the positions: CSV (``t_s`` + one column per angle) and ``.mot``."""
    from kinefuse.io._common import write_text_safely
    from kinefuse.io.mot import write_mot
    from kinefuse.kinematics import JOINT_ANGLE_COMPONENTS

    cols = {
        f"{j}_{c}_deg": a[:, k]
        for j, a in out.angles.items()
        for k, c in enumerate(JOINT_ANGLE_COMPONENTS)
    }
    head = [
        "# kinefuse joint angles (deg), ISB conventions (Wu et al. 2002/2005, Grood & Suntay 1983)",
        f"# session: {cfg.name}",
        f"# method: {cfg.method.name}",
        f"# calibration: {out.provenance.get('calibration')}",
        f"# root: {out.root}",
        f"# frame: {out.frame}",
        "t_s," + ",".join(cols),
    ]
    rows = [
        ",".join(
            [repr(float(t))] + [f"{v[i]:.4f}" if np.isfinite(v[i]) else "" for v in cols.values()]
        )
        for i, t in enumerate(out.t_s)
    ]
    csv = write_text_safely(targets["angles_csv"], "\n".join(head + rows) + "\n", force=force)
    mot = write_mot(
        targets["mot"],
        out.t_s,
        {k[: -len("_deg")]: v for k, v in cols.items()},
        name=f"{cfg.name} joint angles",
        metadata={
            "convention": "ISB (Wu 2002/2005), flexion first",
            "calibration": str(out.provenance.get("calibration")),
            "root": out.root,
            "frame": out.frame,
        },
        force=force,
    )
    return [csv, mot]


def evaluate_recording(
    path,
    method: str,
    parameters: Mapping | None = None,
    *,
    format: str | None = None,
    calibration: str | None = None,
    root: str | None = None,
    align: str | None = None,
    body_height_m: float | None = None,
):
    """Back-end of ``kinefuse evaluate``: one method on a recording with a reference.

    Parameters
    ----------
    path : str or Path
        Anything :func:`kinefuse.io.load` reads (a file or a dataset folder), with a reference
        (or a camera, which then serves as the reference, as in paper A).
    method : str
        A :data:`kinefuse.session.METHODS` name.
    parameters : mapping, optional
        As ``[method.parameters]``; ``calibration``, ``root`` and ``align`` below override it.
    format : str, optional
        A :data:`kinefuse.io.FORMATS` key (default: detected).
    calibration : str, optional
        ``"static"`` (default: a still pose in the IMU data), ``"functional"``, ``"vision"``
        or ``"reference"`` (then axes *and* segment lengths come from the reference, and every
        table says "[calibrated on reference, lengths from reference]").
    root : str, optional
        Where the chain starts (default ``"reference"``: the root joints, e.g. the hips, are
        taken as measured by the reference, as paper A measures the shoulder; this is said in
        the notes, not a calibration).
    align : {"none", "rigid"}, optional
        ``"rigid"``: Kabsch-align the estimates to the reference before scoring (labelled).
    body_height_m : float, optional
        Body height for anthropometric segment lengths (Winter 2009).

    Returns
    -------
    EvaluationResult
        The method, the unfiltered IMU chain and the camera (if any) per joint.

    Raises
    ------
    InputError
        Unreadable file, no reference, no limb IMU, a method that needs a camera without one,
        no still window for static calibration.
    """
    from dataclasses import replace

    from kinefuse.exceptions import FormatError
    from kinefuse.io import FORMATS, load

    if format is not None and format not in FORMATS:
        raise InputError(
            f"--format: unknown format {format!r}; expected one of {', '.join(sorted(FORMATS))}"
        )
    try:
        rec = load(path, format=format)
    except FileNotFoundError as exc:
        raise InputError(f"{path}: {exc}") from None
    except FormatError:
        raise
    imu = {k: v for k, v in rec.imu.items() if k in SEGMENTS}
    if not imu:
        raise InputError(f"{path}: no IMU on a canonical segment (found {sorted(rec.imu)})")
    params = dict(parameters or {})
    if rec.reference is None:
        if rec.vision is None:
            raise InputError(f"{path}: the recording has no reference to evaluate against")
        if method in _CAMERA_METHODS:
            raise InputError(
                f"{path}: method {method!r} needs a camera, and this recording's only joint "
                "stream is used as the reference; try 'imu-only' or 'paper-a'"
            )
        rec = replace(rec, reference=rec.vision)
    rec = replace(rec, imu=imu)
    if method not in _CAMERA_METHODS:
        if rec.vision is not None:
            rec = replace(rec, vision=None)
        params["root"] = root or params.get("root", "reference")
    elif root is not None:
        params["root"] = root
    if calibration is not None:
        params["calibration"] = calibration
    params.setdefault("calibration", "vision" if rec.vision is not None else "static")
    if params["calibration"] == "reference":
        params.setdefault("measured_lengths", True)
    if align is not None:
        params["align_to_reference"] = align
    try:
        out = process_recording(rec, method, params, body_height_m=body_height_m)
    except ConfigError as exc:
        raise InputError(f"{path}: {exc}") from None
    ev = out.evaluation()
    if ev is None:
        raise InputError(f"{path}: nothing to score: {out.notes[-1]}")
    return ev
