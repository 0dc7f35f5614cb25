"""Loading a session's streams: the IMU, camera and reference files, with unit checks.

:func:`load_streams` reads the files a :class:`~kinefuse.session_file.SessionConfig` names
into one :class:`~kinefuse.io.Recording` keyed by canonical segment; every problem (unknown
format, unreadable file, unknown sensor, infinite values, wrong units) is a
:class:`~kinefuse.exceptions.ConfigError` naming the session file, the section and the file.
"""

from __future__ import annotations

import difflib
import warnings
from pathlib import Path

import numpy as np

from kinefuse.exceptions import ConfigError, FormatError, InputError, UnitWarning
from kinefuse.io import FORMATS, Recording, load

__all__ = ["FORMAT_ALIASES", "load_streams"]

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


def _format_name(fmt: str, section: str, source: str) -> str:
    key = fmt.strip().lower()
    key = FORMAT_ALIASES.get(key, key.replace("-", "_"))
    if key not in FORMATS:
        near = difflib.get_close_matches(key, [*FORMATS, *FORMAT_ALIASES], n=1)
        fix = f"did you mean {near[0]!r}? " if near else ""
        raise ConfigError(
            f"{source}: [{section}] format: unknown format {fmt!r} ({fix}known formats: "
            f"{', '.join(sorted(FORMATS))})"
        )
    return key


def _load(
    path: Path, fmt: str, section: str, source: str, strict_units: bool, pair=None, options=None
):
    """``kinefuse.io.load`` with session context in every error and unit checks escalated.

    ``options`` (the section's ``[<section>.reader]`` table) go to the reader as keywords.
    """
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
        except FormatError as exc:  # of a pair, the file at fault names its own section
            at = "camera" if pair is not None and Path(exc.path) == Path(pair) else section
            raise ConfigError(f"{source}: [{at}] path: {exc}") from None
        except InputError as exc:  # an option the reader does not take: its table is at fault
            at = f"{section}.reader" if str(exc).startswith("unknown option(s)") else section
            raise ConfigError(f"{source}: [{at}]: {exc}") from None
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
            msgs.append(f"WARNING: {section}: {w.message}")  # the reader's: shown when run
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
        From :func:`kinefuse.session_file.load_session`.
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
    imu = _map_segments(rec, cfg, src)
    notes += _dropped_packets(rec, imu)
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
        reference = _reference_stream(cfg, src, strict_units, notes)
    md = dict(rec.metadata or {})
    md["session"] = str(cfg.path)
    return Recording(imu=imu, vision=vision, reference=reference, metadata=md), notes


def _dropped_packets(rec, imu: dict) -> list[str]:
    """A warning per mapped sensor whose reader counted dropped packets (Xsens DOT's packet
    counter): how many, against the samples kept; the gaps are bridged like any missing
    sample (docs/formats.md)."""
    dropped = (rec.metadata or {}).get("dropped_packets")
    if not isinstance(dropped, dict):
        return []
    out = []
    for seg, st in imu.items():
        key = next((k for k, v in rec.imu.items() if v is st), seg)
        n = int(dropped.get(key, 0) or 0)
        if n > 0:
            kept = st.t_s.size
            out.append(
                f"WARNING: imu: {st.name or key} ({seg}): {n} packets dropped in transmission, "
                f"{100 * n / (n + kept):.0f} % of its samples (the gaps are bridged where short, "
                "else its joints are not available there)"
            )
    return out


def _map_segments(rec, cfg, src: str) -> dict:
    """``[imu.segments]``: segment -> the file's stream of that sensor (by name or key)."""
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
    return imu


def _reference_stream(cfg, src: str, strict_units: bool, notes: list[str]):
    """``[reference]``: its joints (a file without a reference stream gives its camera's)."""
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
    return reference


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
