"""Configuration of the online path: the machine-local LSL configuration and stream sessions.

Network safety
--------------
Lab Streaming Layer discovers streams by multicast and broadcast on the local network unless
told otherwise. liblsl reads its configuration file once, from the path in the ``LSLAPICFG``
environment variable (then ``./lsl_api.cfg``, ``~/lsl_api/lsl_api.cfg``,
``/etc/lsl_api/lsl_api.cfg``), when it first needs it. kinefuse therefore never imports
``pylsl`` at module level: every LSL use goes through :func:`import_pylsl`, which first calls
:func:`ensure_local_lsl_config`. Without ``LSLAPICFG`` that writes the packaged template
``lslapi.cfg`` (``[ports] IPv6 = disable``, ``[multicast] ResolveScope = machine``,
``MachineAddresses = {127.0.0.1}``, ``Interfaces = {127.0.0.1}``, ``[lab] KnownPeers =
{127.0.0.1}``, ``SessionID``) into a per-user folder and points ``LSLAPICFG`` at it, so
discovery stays on this machine. A ``LSLAPICFG`` set by the user is respected (e.g. to reach a
camera on another machine); :func:`check_lsl_config` tells whether it is machine-local.

Stream sessions
---------------
:class:`StreamConfig` describes one online run (which LSL streams, which processor, the
engine's timing parameters); :func:`load_stream_config` reads it from a TOML file with a
``[stream]`` section (plus optional ``[skeleton]`` and ``[method]`` as in offline sessions), and
:func:`stream_config_from_session` derives it from an offline
:class:`~kinefuse.session_file.SessionConfig`. The processor a session's method streams with is
its online form in the registry :mod:`kinefuse.methods`; a method without one is refused (or,
where the registry names a substitute, run with a warning that the config's ``notes`` keep).
"""

from __future__ import annotations

import getpass
import logging
import math
import os
import re
import sys
import tempfile
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from string import Template

from kinefuse import methods
from kinefuse.conventions import PAPER_B_JOINTS
from kinefuse.exceptions import ConfigError, InputError
from kinefuse.kinematics import full_body
from kinefuse.session_file import _Ctx, read_toml

__all__ = [
    "LSL_CONFIG_ENV",
    "LOCAL_SETTINGS",
    "PROCESSORS",
    "LslUnavailable",
    "StreamConfig",
    "check_lsl_config",
    "ensure_local_lsl_config",
    "import_pylsl",
    "load_stream_config",
    "local_lsl_config_text",
    "parse_lsl_config",
    "stream_config_from_session",
]

log = logging.getLogger("kinefuse.streaming")

#: Environment variable through which liblsl finds its configuration file.
LSL_CONFIG_ENV = "LSLAPICFG"

#: Settings that make LSL machine-local: ``(section, key) -> value`` (case-insensitive values).
LOCAL_SETTINGS = {
    ("ports", "IPv6"): "disable",
    ("multicast", "ResolveScope"): "machine",
    ("multicast", "MachineAddresses"): "{127.0.0.1}",
}

#: Processor names accepted by :class:`StreamConfig` (see :mod:`kinefuse.streaming.engine`):
#: :data:`kinefuse.methods.PROCESSORS`.
PROCESSORS = tuple(methods.PROCESSORS)

_WE_SET_ENV = {"value": None}


class LslUnavailable(ImportError):
    """pylsl (or the liblsl it loads) cannot be used; the message says why."""


# ------------------------------------------------------------------------------ LSL config
def local_lsl_config_text(
    session_id: str = "kinefuse", *, log_level: int = -2, log_file: str | Path | None = None
) -> str:
    """Text of a machine-local ``lsl_api.cfg`` (the packaged template ``lslapi.cfg`` filled in).

    Parameters
    ----------
    session_id : str
        ``[lab] SessionID``: only streams of the same session id see each other. Letters,
        digits, ``-``, ``_`` and ``.`` only.
    log_level : int
        ``[log] level`` of liblsl (-3 ... 9; -2 = errors and warnings only, 0 = info).
    log_file : path, optional
        ``[log] file``: liblsl logs there instead of stderr.

    Returns
    -------
    str
    """
    if not isinstance(session_id, str) or not re.fullmatch(r"[A-Za-z0-9_.\-]+", session_id):
        raise InputError(
            f"expected session_id of letters, digits, '-', '_', '.', got {session_id!r}"
        )
    if isinstance(log_level, bool) or not isinstance(log_level, int) or not -3 <= log_level <= 9:
        raise InputError(f"expected log_level as an int in [-3, 9], got {log_level!r}")
    template = Template(files("kinefuse.streaming").joinpath("lslapi.cfg").read_text("utf-8"))
    return template.substitute(
        session_id=session_id,
        log_level=str(log_level),
        log_file_line="" if log_file is None else f"file = {Path(log_file)}",
    )


def _user_config_dir() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME")
    if base:
        return Path(base) / "kinefuse"
    home = Path.home()
    if home.is_dir() and os.access(home, os.W_OK):
        return home / ".config" / "kinefuse"
    return (
        Path(tempfile.gettempdir()) / f"kinefuse-{os.getuid() if hasattr(os, 'getuid') else 'user'}"
    )


def parse_lsl_config(path: str | Path) -> dict[tuple[str, str], str]:
    """Read an ``lsl_api.cfg`` (INI) into ``{(section, key): value}``.

    Lines starting with ``;`` or ``#`` are comments. Raises ValueError naming the file and line
    on a malformed line.
    """
    p = Path(path)
    out: dict[tuple[str, str], str] = {}
    section = ""
    for i, raw in enumerate(p.read_text(encoding="utf-8").splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] in ";#":
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1].strip()
            continue
        if "=" not in line:
            raise ConfigError(f"{p}, line {i}: expected 'key = value' or '[section]', got {raw!r}")
        key, value = (s.strip() for s in line.split("=", 1))
        out[(section, key)] = value
    return out


def check_lsl_config(path: str | Path | None = None) -> dict:
    """Tell whether an LSL configuration file keeps discovery on this machine.

    Parameters
    ----------
    path : path, optional
        File to check (default: ``$LSLAPICFG``).

    Returns
    -------
    dict
        ``path`` (Path or None), ``exists``, ``settings`` (parsed), ``local`` (True when every
        :data:`LOCAL_SETTINGS` entry is present with its value and no ``AddressesOverride`` or
        ``TTLOverride`` widens it), ``problems`` (list of str).
    """
    p = path if path is not None else os.environ.get(LSL_CONFIG_ENV)
    if p is None:
        return {"path": None, "exists": False, "settings": {}, "local": False,
                "problems": [f"{LSL_CONFIG_ENV} is not set"]}  # fmt: skip
    p = Path(p)
    if not p.is_file():
        return {"path": p, "exists": False, "settings": {}, "local": False,
                "problems": [f"{p} does not exist"]}  # fmt: skip
    settings = parse_lsl_config(p)
    lower = {(s.lower(), k.lower()): v for (s, k), v in settings.items()}
    problems = []
    for (sec, key), want in LOCAL_SETTINGS.items():
        got = lower.get((sec.lower(), key.lower()))
        norm = None if got is None else got.replace(" ", "").lower()
        ok = norm == want.lower() or (want == "disable" and norm == "disabled")
        if not ok:
            elsewhere = [f"[{s}]" for s, k in settings if k.lower() == key.lower()]
            hint = f" (it is under {', '.join(elsewhere)})" if got is None and elsewhere else ""
            problems.append(f"[{sec}] {key} = {want} expected, got {got!r}{hint}")
    for key in ("AddressesOverride", "TTLOverride"):
        if ("multicast", key.lower()) in lower:
            problems.append(f"[multicast] {key} is set: it overrides ResolveScope")
    return {"path": p, "exists": True, "settings": settings, "local": not problems,
            "problems": problems}  # fmt: skip


def ensure_local_lsl_config(
    directory: str | Path | None = None,
    *,
    session_id: str | None = None,
    log_file: str | Path | None = None,
    force: bool = False,
) -> Path:
    """Make sure liblsl will read a machine-local configuration; return the file in effect.

    Call before pylsl is imported (:func:`import_pylsl` does). When ``LSLAPICFG`` is unset (or
    ``force``), writes :func:`local_lsl_config_text` to ``directory/lsl_api.cfg`` (default a
    per-user folder: ``$XDG_CONFIG_HOME/kinefuse``, ``~/.config/kinefuse`` or
    ``$TMPDIR/kinefuse-<uid>``) and sets ``LSLAPICFG`` to it. A ``LSLAPICFG`` set by the user
    is kept; a warning is issued when it is not machine-local (:func:`check_lsl_config`).

    Parameters
    ----------
    directory : path, optional
        Folder for the file.
    session_id : str, optional
        ``[lab] SessionID`` (default ``$KINEFUSE_LSL_SESSION`` or ``kinefuse-<user>``).
    log_file : path, optional
        liblsl log file (``[log] file``).
    force : bool
        Overwrite ``LSLAPICFG`` even when set.

    Returns
    -------
    Path
        The configuration file liblsl will read.

    Warns
    -----
    UserWarning
        If pylsl was already imported before the variable was set (liblsl may have read
        another configuration), or a user-set file is not machine-local.
    """
    current = os.environ.get(LSL_CONFIG_ENV)
    if current and not force:
        info = check_lsl_config(current)
        if not info["local"] and _WE_SET_ENV["value"] != current:
            warnings.warn(
                f"{LSL_CONFIG_ENV}={current} is not a machine-local LSL configuration "
                f"({'; '.join(info['problems'])}): LSL discovery may use the network",
                UserWarning,
                stacklevel=2,
            )
        return Path(current)
    if "pylsl" in sys.modules:
        warnings.warn(
            f"pylsl was imported before {LSL_CONFIG_ENV} was set: liblsl may already use its "
            "default (network-wide) configuration; import kinefuse.streaming first",
            UserWarning,
            stacklevel=2,
        )
    if session_id is None:
        session_id = os.environ.get("KINEFUSE_LSL_SESSION") or _default_session_id()
    d = Path(directory) if directory is not None else _user_config_dir()
    d.mkdir(parents=True, exist_ok=True)
    path = d / "lsl_api.cfg"
    text = local_lsl_config_text(session_id, log_file=log_file)
    if not path.is_file() or path.read_text(encoding="utf-8") != text:
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    os.environ[LSL_CONFIG_ENV] = str(path)
    _WE_SET_ENV["value"] = str(path)
    log.info("LSL configuration: %s (machine-local, session %s)", path, session_id)
    return path


def _default_session_id() -> str:
    try:
        user = getpass.getuser()
    except Exception:
        user = "user"
    user = re.sub(r"[^A-Za-z0-9_.\-]", "_", user) or "user"
    return f"kinefuse-{user}"


def import_pylsl():
    """Import pylsl after :func:`ensure_local_lsl_config`; the only way kinefuse loads pylsl.

    Returns
    -------
    module
        ``pylsl``.

    Raises
    ------
    LslUnavailable
        pylsl is not installed (``pip install kinefuse[lsl]``) or cannot load liblsl.
    """
    if _PYLSL["module"] is not None:  # checked and loaded once: liblsl's configuration is fixed
        return _PYLSL["module"]
    ensure_local_lsl_config()
    try:
        import pylsl
    except (ImportError, OSError, RuntimeError) as exc:
        raise LslUnavailable(
            f"Lab Streaming Layer is not available: {exc} (install with `pip install "
            "kinefuse[lsl]`; pylsl's wheels ship liblsl)"
        ) from exc
    _PYLSL["module"] = pylsl
    return pylsl


_PYLSL: dict = {"module": None}


# ------------------------------------------------------------------------------ stream sessions
@dataclass(frozen=True)
class StreamConfig:
    """One online run: inputs, outputs, processor and timing.

    Attributes
    ----------
    name_prefix : str
        Default stream names: ``{prefix}_imu_{segment}``, ``{prefix}_camera``,
        ``{prefix}_fused`` (as published by :func:`kinefuse.streaming.run_replay`).
    imu_streams : dict of str -> str
        Segment -> LSL stream name; segments not listed use the prefix rule.
    camera_stream : str or None
        LSL name of the camera skeleton stream; ``""`` = no camera; None = prefix rule.
    output_stream : str or None
        Name of the fused outlet (None = prefix rule).
    joints : tuple of str
        Output joints (default the eight of paper B).
    processor : str
        Per-frame processor, one of :data:`PROCESSORS` (:mod:`kinefuse.streaming.engine`).
    lag : int
        Fixed-lag smoother lag, frames (output delayed by ``lag`` frames; 0 = filtered).
    body_height_m : float
        Body height for the anthropometric skeleton, m.
    lengths_m : dict of str -> float
        Measured segment lengths, m.
    output_rate_hz : float
        Output rate without a camera, Hz (with a camera: one output per camera frame).
    max_latency_s : float
        How long a frame waits for late IMU samples before it is processed with held
        orientations (flagged), s.
    stale_after_s : float
        An IMU stream silent for longer is stale (its joints go predict-only), s.
    gap_factor : float
        A step between consecutive samples larger than ``gap_factor`` × the nominal period is
        a gap (never interpolated across), reported as a time jump.
    resolve_timeout_s : float
        Time to wait for each input stream when resolving, s.
    clock : {"manual", "lsl"}
        ``"manual"``: timestamps + ``inlet.time_correction()`` (refreshed every 5 s);
        ``"lsl"``: liblsl post-processing ``proc_clocksync | proc_dejitter | proc_monotonize``.
    q, r_imu, r_camera : float
        Process noise (m/s)² per frame and measurement variances (m²) of the processors.
    notes : tuple of str
        What was substituted when the config was derived (e.g. the processor streaming runs
        for a method without an online form); not a ``[stream]`` key.
    chain : mapping or None
        A calibrated chain written by ``kinefuse run``
        (:mod:`kinefuse.pipelines.run.chain_file`): the engine runs it (its segments, sensor-
        frame axes, lengths, root) instead of paper B's full body, without a camera; not a
        ``[stream]`` key (``kinefuse stream --chain``).
    """

    name_prefix: str = "kinefuse"
    imu_streams: Mapping[str, str] = field(default_factory=dict)
    camera_stream: str | None = None
    output_stream: str | None = None
    joints: tuple[str, ...] = PAPER_B_JOINTS
    processor: str = "kf-fusion"
    lag: int = 0
    body_height_m: float = 1.75
    lengths_m: Mapping[str, float] = field(default_factory=dict)
    output_rate_hz: float = 30.0
    max_latency_s: float = 0.1
    stale_after_s: float = 0.25
    gap_factor: float = 2.5
    resolve_timeout_s: float = 5.0
    clock: str = "manual"
    q: float = 0.05
    r_imu: float = 4e-4
    r_camera: float = 9e-4
    notes: tuple[str, ...] = ()
    chain: Mapping | None = None

    def __post_init__(self):
        if not isinstance(self.name_prefix, str) or not self.name_prefix:
            raise ConfigError(
                f"[stream] name_prefix: expected a non-empty string, got {self.name_prefix!r}"
            )
        if self.processor not in PROCESSORS:
            raise ConfigError(
                f"[stream] processor: unknown processor {self.processor!r}; expected one of {PROCESSORS}"
            )
        if self.clock not in ("manual", "lsl"):
            raise ConfigError(f"[stream] clock: expected 'manual' or 'lsl', got {self.clock!r}")
        if isinstance(self.lag, bool) or not isinstance(self.lag, int) or self.lag < 0:
            raise ConfigError(f"[stream] lag: expected an int >= 0 (frames), got {self.lag!r}")
        for name in ("body_height_m", "output_rate_hz", "max_latency_s", "stale_after_s",
                     "resolve_timeout_s", "q", "r_imu", "r_camera"):  # fmt: skip
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float))
                or not math.isfinite(v)
                or v <= 0
            ):
                raise ConfigError(f"[stream] {name}: expected a finite number > 0, got {v!r}")
        if not (isinstance(self.gap_factor, (int, float)) and self.gap_factor > 1):
            raise ConfigError(
                f"[stream] gap_factor: expected a number > 1, got {self.gap_factor!r}"
            )
        object.__setattr__(self, "joints", tuple(self.joints))
        object.__setattr__(self, "imu_streams", dict(self.imu_streams))
        object.__setattr__(self, "lengths_m", dict(self.lengths_m))
        object.__setattr__(self, "notes", tuple(self.notes))

    def imu_stream_name(self, segment: str) -> str:
        """LSL name of the IMU stream of ``segment``."""
        return self.imu_streams.get(segment, f"{self.name_prefix}_imu_{segment}")

    @property
    def camera_stream_name(self) -> str | None:
        """LSL name of the camera stream, or None without a camera."""
        if self.camera_stream is None:
            return f"{self.name_prefix}_camera"
        return self.camera_stream or None

    @property
    def output_stream_name(self) -> str:
        """LSL name of the fused output stream."""
        return self.output_stream or f"{self.name_prefix}_fused"


_STREAM_KEYS = tuple(
    f
    for f in StreamConfig.__dataclass_fields__
    if f not in ("body_height_m", "lengths_m", "notes", "chain")
)


def online_processor(method: str, source: str = "session") -> tuple[str, str | None]:
    """The streaming processor of a :mod:`kinefuse.methods` method.

    Parameters
    ----------
    method : str
        A registered method name.
    source : str
        Named in messages (the session file).

    Returns
    -------
    processor : str
        Its online form, or the registry's substitute.
    note : str or None
        Without an online form: what is run instead (also issued as a UserWarning).

    Raises
    ------
    ConfigError
        Unknown method, or a method with neither an online form nor a substitute.
    """
    try:
        spec = methods.get(method)
    except ConfigError as exc:
        raise ConfigError(f"{source}: [method] name: {exc}") from None
    if spec.online is not None:
        return spec.online, None
    online = methods.names(form="online")
    if spec.online_substitute is None:
        raise ConfigError(
            f"{source}: [method] name = {method!r} has no online form (it exists as "
            f"{', '.join(spec.forms)}); kinefuse stream runs {', '.join(online)}: choose one of "
            f"them, or process the recording offline with `kinefuse run`"
        )
    note = (
        f"method {method!r} has no online form; streaming runs the {spec.online_substitute!r} "
        f"processor instead ({methods.PROCESSORS[spec.online_substitute]})"
    )
    warnings.warn(f"{source}: {note}", UserWarning, stacklevel=3)
    return spec.online_substitute, note


def load_stream_config(path: str | Path) -> StreamConfig:
    """Read a streaming session TOML file.

    The file has a ``[stream]`` table whose keys are :class:`StreamConfig` fields
    (``imu_streams`` as a sub-table ``[stream.imu_streams]`` segment = name), and optionally
    ``[skeleton] body_height_m`` / ``[skeleton.lengths]`` and ``[method] name`` (without a
    ``[stream] processor``, the method's online form selects it: :func:`online_processor`).
    Other tables (``[session]``, ``[imu]``...) are ignored, so one
    file can serve offline and online runs.

    Raises
    ------
    ConfigError
        Missing file, invalid TOML, unknown key or invalid value (names the key), a method
        without an online form (and no ``[stream] processor``).
    """
    p = Path(path).expanduser()
    doc = read_toml(p, missing="stream session file not found")
    c = _Ctx(p)  # the offline sections' checks: "<file>: [stream] <key>: unknown key (...)"
    st = dict(c.table(doc, "stream", required=False) or {})
    c.check_keys(st, "stream", _STREAM_KEYS)
    kw = dict(st)
    if "joints" in kw:
        kw["joints"] = tuple(kw["joints"])
    sk = doc.get("skeleton") or {}
    if "body_height_m" in sk:
        kw["body_height_m"] = sk["body_height_m"]
    if "lengths" in sk:
        kw["lengths_m"] = dict(sk["lengths"])
    method = (doc.get("method") or {}).get("name")
    if method is not None and "processor" not in kw:
        kw["processor"], note = online_processor(method, p.name)
        kw["notes"] = () if note is None else (note,)
    try:
        return StreamConfig(**kw)
    except ConfigError as exc:
        raise ConfigError(f"{p.name}: {exc}") from None
    except TypeError as exc:
        raise ConfigError(f"{p.name}: [stream] {exc}") from None


def _offline_only(session) -> list[str]:
    """What an offline session asks for that the online engine would ignore: a calibration,
    declared segment axes, a root other than the camera, segments outside its chain."""
    out = []
    p = session.processing_parameters()  # [calibration] and [skeleton] merged with the method's
    if p.get("calibration") not in (None, "none"):
        out.append(f"calibration {p['calibration']!r}")
    if p.get("axes"):
        out.append(f"declared segment axes ({', '.join(sorted(p['axes']))})")
    if p.get("root") not in (None, "vision"):
        out.append(f"root {p['root']!r}")
    sk = full_body(height_m=1.75)  # the online engine's chain (runner.engine_skeleton)
    extra = sorted(set(session.imu.segments) - {sk.root_segment, *sk.segments})
    if extra:
        out.append(f"[imu.segments] {', '.join(extra)} (not in the online chain)")
    return out


def stream_config_from_session(session, chain: Mapping | None = None, **overrides) -> StreamConfig:
    """A :class:`StreamConfig` from an offline :class:`~kinefuse.session_file.SessionConfig`.

    Uses the session name as the stream prefix, its skeleton (height, lengths) and its
    method's online form (:func:`online_processor`: ``paper-a`` -> the paper-A processor,
    ``elm-fir`` / ``elm-kf`` -> the online paper-B processor; ``imu-only`` -> the paper-A
    processor with a warning kept in ``notes``; a method without an online form is refused).

    Raises
    ------
    ConfigError
        The session's method has no online form and no substitute; the session asks for what
        the online engine does not do (:func:`_offline_only`), which it would otherwise ignore.
    """
    source = Path(getattr(session, "path", "session")).name
    refused = _offline_only(session) if chain is None else _not_in_chain(session, chain)
    if refused and chain is not None:
        raise ConfigError(f"{source}: {'; '.join(refused)}: stream the session the chain came from")
    if refused:
        raise ConfigError(
            f"{source}: kinefuse stream cannot honour {'; '.join(refused)} by itself. Without "
            "--chain the online engine runs paper B's full-body chain (chest + upper arms, "
            "forearms, thighs, shanks) on the streamed orientations as segment orientations, "
            f"without calibration. With IMUs only (a pelvis or fixed root), kinefuse run {source} "
            f"calibrates and writes chain.json: kinefuse stream {source} --chain "
            "<out_dir>/chain.json runs that chain"
        )
    processor, note = online_processor(session.method.name, source)
    notes = () if note is None else (note,)
    if chain is None and session.processing_parameters().get("calibration") is None:
        default = "vision" if session.camera is not None else "static"
        msg = (
            f"{source}: kinefuse run calibrates this session ({default!r}, the default); "
            "kinefuse stream does not: the streamed orientations are taken as the segments' own "
            '(set [calibration] method = "none" to say so)'
        )
        warnings.warn(msg, UserWarning, stacklevel=2)
        notes += (msg,)
    kw = {
        "name_prefix": re.sub(r"[^A-Za-z0-9_.\-]", "_", session.name) or "kinefuse",
        "processor": processor,
        "notes": notes,
        "lengths_m": dict(session.skeleton.lengths_m),
    }
    if session.skeleton.body_height_m is not None:
        kw["body_height_m"] = session.skeleton.body_height_m
    if session.camera is None or chain is not None:
        kw["camera_stream"] = ""
    if chain is not None:
        kw["chain"] = chain
        kw["joints"] = tuple(s["distal"] for s in chain["segments"])
    kw.update(overrides)
    return StreamConfig(**kw)


def _not_in_chain(session, chain: Mapping) -> list[str]:
    """With a calibrated chain: the session's segments must be the chain's (the calibration,
    axes and root are the chain's own), or read for joint angles only (the feet; the pelvis and
    chest of the trunk angles, with a frame in the chain)."""
    segs = (
        {s["name"] for s in chain["segments"]}
        | ({chain["root_segment"]} if chain.get("root_segment") else set())
        | set((chain.get("offset_segments") or {}).values())
        | ({"pelvis", "chest"} & set(chain.get("segment_frames") or {}))
    )
    extra = sorted(set(session.imu.segments) - segs - {"foot_l", "foot_r", "hand_l", "hand_r"})
    return [f"[imu.segments] {', '.join(extra)} (not in the chain file)"] if extra else []
