"""Study files: many recordings, shared defaults, per-recording overrides.

A study is a TOML file (or, without one, a folder or glob of session files). It lists the
recordings and what to run on each; :func:`load_study` validates it into a :class:`Study` whose
:attr:`Study.tasks` are the (recording, method) pairs ``kinefuse batch`` schedules. Each task's
session is validated by :func:`kinefuse.session_file.load_session`, exactly as ``kinefuse run``
validates a session file. Example::

    [study]
    name = "utd-wrist"                       # default: the file name
    out_dir = "results/utd-wrist"            # default: results/<name> beside the study file
    methods = ["imu-only", "elm-fir", "kinefuse"]   # default: each session's own [method] name

    [defaults]                               # session-file sections shared by every recording
    skeleton = { body_height_m = 1.75 }
    method = { parameters = { calibration = "vision", calibration_window_s = 10.0 } }

    [[recordings]]                           # session files: paths or globs
    sessions = ["sessions/*.toml"]

    [[recordings]]                           # data files: one recording per file the glob matches
    files = "data/utd_mhad/Inertial/a*_s[1-6]_t*_inertial.mat"
    pattern = 'a(?P<a>\\d+)_s(?P<s>\\d+)_t(?P<t>\\d+)_inertial'  # fields for the template
    [recordings.session]                     # the session; {path} {dir} {stem} {name} and the
    session = { name = "a{a}-s{s}-t{t}" }    # pattern's fields are filled in per file
    imu = { format = "utd_mhad", path = "{path}", segments = { forearm_r = "utd_mhad_inertial" } }
    camera = { format = "utd_mhad", path = "{dir}/../Skeleton/a{a}_s{s}_t{t}_skeleton.mat" }
    reference = { format = "utd_mhad", path = "{dir}/../Skeleton/a{a}_s{s}_t{t}_skeleton.mat" }

    [overrides."a9-*"]                       # recordings whose name matches (fnmatch glob)
    method = { parameters = { q = 0.2 } }
    methods = ["imu-only"]                   # optional: other methods for these recordings

Precedence: ``[defaults]`` < the recording's own session < every matching ``[overrides]`` (in
file order) < the study's ``methods`` (which set ``[method] name``). A setting that a session file
can give in two places (``[method.parameters] calibration`` and ``[calibration] method``, ...:
:data:`_SAME_SETTING`) is one setting here: the higher layer's value wins, in whichever place it
is given, instead of the two being refused as "given twice". Relative paths in the study
file are resolved against its folder, those of a session file against the session's folder. The
sessions' own ``out_dir`` is not used: a batch writes every recording's outputs under the
study's ``out_dir`` (``recordings/<recording>/<method>/``).

Every unknown key is refused with the closest allowed one ("did you mean"), as in session files.
Problems of one recording's session (a missing file, a bad key in that session) do not stop the
study: the task is recorded as failed with its one-line error.
"""

from __future__ import annotations

import copy
import difflib
import fnmatch
import glob as _glob
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from kinefuse.exceptions import ConfigError
from kinefuse.methods import unknown_fix
from kinefuse.session_file import (
    METHODS,
    SECTION_PARAMETERS,
    _Ctx,
    init_session_hint,
    load_session,
    read_toml,
)

__all__ = ["Study", "Task", "load_study", "study_from_sessions"]

_STUDY_KEYS = ("study", "defaults", "recordings", "overrides")
_STUDY_SECTION_KEYS = ("name", "out_dir", "methods")
_RECORDING_KEYS = ("sessions", "files", "pattern", "session")
_PATH_SECTIONS = ("imu", "camera", "reference")
_FIELD = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")


@dataclass(frozen=True)
class Task:
    """One recording x one method.

    Attributes
    ----------
    recording : str
        Recording name (the session's ``[session] name``, made file-name safe).
    method : str
        A :data:`kinefuse.session_file.METHODS` name, or ``""`` when the session itself is invalid.
    source : Path
        The session file (or the study file for a templated recording); named in messages and
        the base of relative paths.
    document : dict
        The merged session document (:func:`kinefuse.session_file.load_session` validates it).
    error : str or None
        Why the session cannot be built (the task is then recorded as failed, not run).
    """

    recording: str
    method: str
    source: Path
    document: dict = field(default_factory=dict, compare=False)
    error: str | None = None

    @property
    def key(self) -> str:
        """Unique task id ``recording/method``."""
        return f"{self.recording}/{self.method or '-'}"


@dataclass(frozen=True)
class Study:
    """A validated study.

    Attributes
    ----------
    name : str
    path : Path or None
        The study file (None for a folder or glob of session files).
    out_dir : Path
        Output folder (absolute).
    tasks : tuple of Task
        In study order: recordings in listing order, methods in the study's order.
    """

    name: str
    path: Path | None
    out_dir: Path
    tasks: tuple[Task, ...]

    @property
    def recordings(self) -> tuple[str, ...]:
        """Recording names, in order, without repeats."""
        return tuple(dict.fromkeys(t.recording for t in self.tasks))

    @property
    def methods(self) -> tuple[str, ...]:
        """Methods of the valid tasks, in order, without repeats."""
        return tuple(dict.fromkeys(t.method for t in self.tasks if t.method))


def safe_name(name: str) -> str:
    """File-name-safe form of a name, as ``kinefuse run`` names its outputs."""
    return "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in name) or "session"


def _merge(base: Mapping, over: Mapping) -> dict:
    """Deep merge: tables merge key by key, everything else in ``over`` wins."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


#: One setting that a session file can give in two places: ``[method.parameters] <name>`` and
#: a key of another section (:data:`kinefuse.session_file.SECTION_PARAMETERS`). A study's
#: layers (:func:`_layer`) treat both spellings as one setting.
_SAME_SETTING: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = tuple(
    (("method", "parameters", param), where) for param, where in SECTION_PARAMETERS.items()
)


def _has(doc: Mapping, keys: Sequence[str]) -> bool:
    for k in keys:
        if not isinstance(doc, Mapping) or k not in doc:
            return False
        doc = doc[k]
    return True


def _layer(base: Mapping, over: Mapping) -> dict:
    """``over`` (the layer of higher precedence) merged over ``base``.

    A setting with two spellings (:data:`_SAME_SETTING`) that ``over`` gives is first removed
    from ``base`` in the other spelling, so that ``over`` wins instead of the two making a
    "given twice" conflict (e.g. a study default ``[method.parameters] calibration = "vision"``
    under a session's own ``[calibration] method = "functional"``). The same spelling merges
    as any key (:func:`_merge`).
    """
    out = copy.deepcopy(dict(base))
    for spellings in _SAME_SETTING:
        said = [s for s in spellings if _has(over, s)]
        for s in spellings:
            if said and s not in said and _has(out, s):
                *parents, leaf = s
                table = out
                for k in parents:
                    table = table[k]
                del table[leaf]
    return _merge(out, over)


def _absolute_paths(doc: dict, base: Path) -> dict:
    """``doc`` with the relative ``path`` of [imu]/[camera]/[reference] made absolute."""
    out = copy.deepcopy(doc)
    for sec in _PATH_SECTIONS:
        t = out.get(sec)
        if isinstance(t, dict) and isinstance(t.get("path"), str) and t["path"].strip():
            p = Path(t["path"].strip()).expanduser()
            t["path"] = str(p if p.is_absolute() else base / p)
    return out


def _check_sections(c: _Ctx, doc: Mapping, where: str, *, extra: tuple[str, ...] = ()) -> None:
    """Refuse unknown sections / keys in a study's defaults or overrides ("did you mean").

    The keys are checked by :func:`kinefuse.session_file.load_session` itself, on a probe session
    made of ``doc`` over a minimal valid one, so the allowed keys have one source of truth;
    only its "unknown ..." errors are reported here (everything else is checked per recording).
    """
    if "session" in doc:
        raise c.error(where, "session", "not allowed here", "each recording names its own session")
    body = {k: v for k, v in doc.items() if k not in extra}
    stub = str(c.path)  # an existing file: load_session only checks that paths exist
    probe = _merge(
        {
            "session": {"name": "probe"},
            "imu": {"format": "csv", "path": stub, "segments": {"forearm_r": "x"}},
            "skeleton": {"body_height_m": 1.75},
            "method": {"name": "imu-only"},
        },
        body,
    )
    for sec in _PATH_SECTIONS:
        if isinstance(probe.get(sec), dict):
            probe[sec].setdefault("format", "csv")
            probe[sec]["path"] = stub
    if isinstance(probe.get("method"), dict):
        probe["method"]["name"] = "imu-only"
    try:
        load_session(c.path, document=probe)
    except ConfigError as exc:
        msg = str(exc)
        m = re.match(r"^[^:]*: \[([^\]]*)\](.*)$", msg)
        if m and "unknown" in m.group(2):
            section = where if m.group(1) == "top level" else f"{where}.{m.group(1)}"
            raise ConfigError(f"{c.path.name}: [{section}]{m.group(2)}") from None


def _methods(c: _Ctx, table: Mapping, section: str) -> tuple[str, ...] | None:
    if "methods" not in table:
        return None
    raw = table["methods"]
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or not raw or not all(isinstance(m, str) for m in raw):
        raise c.error(section, "methods", f"expected a list of method names, got {raw!r}")
    for m in raw:
        if m not in METHODS:
            fix = unknown_fix(m, METHODS)
            raise c.error(section, "methods", f"unknown method {m!r}", fix)
    return tuple(dict.fromkeys(raw))


def _strings(c: _Ctx, table: Mapping, section: str, key: str) -> list[str]:
    raw = table[key]
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or not raw or not all(isinstance(x, str) and x for x in raw):
        raise c.error(section, key, f"expected a path, a glob or a list of them, got {raw!r}")
    return raw


def _expand(patterns: Sequence[str], base: Path, c: _Ctx, section: str, key: str) -> list[Path]:
    out: list[Path] = []
    for pat in patterns:
        p = Path(pat).expanduser()
        full = str(p if p.is_absolute() else base / p)
        hits = sorted(_glob.glob(full, recursive=True)) if _glob.has_magic(full) else [full]
        hits = [h for h in hits if Path(h).is_file()]
        if not hits:
            raise c.error(
                section,
                key,
                f"{pat!r} matches no file",
                "relative paths and globs are resolved against the study file's folder",
            )
        out += [Path(h).resolve() for h in hits]
    return list(dict.fromkeys(out))


def _fill(value, fields: Mapping[str, str], c: _Ctx, section: str):
    """Fill ``{field}`` placeholders in every string of a template."""
    if isinstance(value, Mapping):
        return {k: _fill(v, fields, c, section) for k, v in value.items()}
    if isinstance(value, list):
        return [_fill(v, fields, c, section) for v in value]
    if isinstance(value, str):
        for name in _FIELD.findall(value):
            if name not in fields:
                close = difflib.get_close_matches(name, list(fields), n=1)
                fix = (
                    f"did you mean {{{close[0]}}}?"
                    if close
                    else f"available: {', '.join('{' + f + '}' for f in fields)}"
                )
                raise c.error(section, "session", f"unknown placeholder {{{name}}}", fix)
        return _FIELD.sub(lambda m: fields[m.group(1)], value)
    return value


def _session_name(doc: Mapping, fallback: str) -> str:
    s = doc.get("session")
    name = s.get("name") if isinstance(s, Mapping) else None
    return safe_name(name.strip() if isinstance(name, str) and name.strip() else fallback)


def _task_list(
    entries: list[tuple[str, Path, dict, str | None]],
    defaults: dict,
    overrides: list[tuple[str, dict, tuple[str, ...] | None]],
    methods: tuple[str, ...] | None,
    c: _Ctx | None,
) -> tuple[Task, ...]:
    """Merge defaults and overrides into each recording; one Task per recording x method."""
    tasks: list[Task] = []
    seen: dict[str, Path] = {}
    for name, source, doc, error in entries:
        if name in seen:
            msg = f"two recordings are named {name!r}: {seen[name]} and {source}"
            if c is None:
                raise ConfigError(msg + " (give each session a distinct [session] name)")
            raise c.error("recordings", None, msg, "give each session a distinct [session] name")
        seen[name] = source
        if error is not None:
            tasks.append(Task(name, "", source, {}, error))
            continue
        merged = _layer(defaults, doc)
        mine = methods
        for pattern, over, over_methods in overrides:
            if fnmatch.fnmatchcase(name, pattern):
                merged = _layer(merged, over)
                mine = over_methods or mine
        if mine is None:
            m = merged.get("method")
            own = m.get("name") if isinstance(m, Mapping) else None
            mine = (own,) if isinstance(own, str) else ("",)
        for method in mine:
            d = copy.deepcopy(merged)
            if method:
                d.setdefault("method", {})
                if isinstance(d["method"], dict):
                    d["method"]["name"] = method
            err = None
            try:
                load_session(source, document=d)
            except ConfigError as exc:
                err = str(exc)
            tasks.append(Task(name, method, source, d, err))
    return tuple(tasks)


def load_study(path: str | Path) -> Study:
    """Read and validate a study TOML file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Study

    Raises
    ------
    ConfigError
        The file is missing or not valid TOML, a section or key is unknown ("did you mean"),
        a glob matches nothing, two recordings share a name, a method is unknown. Problems of
        one recording's session do not raise: its task carries the error.
    """
    p = Path(path).expanduser()
    doc = read_toml(p, missing="study file not found")
    p = p.resolve()
    c = _Ctx(p)
    base = p.parent
    c.check_keys(doc, "top level", _STUDY_KEYS)
    s = c.table(doc, "study", required=False) or {}
    c.check_keys(s, "study", _STUDY_SECTION_KEYS)
    name = c.string(s, "study", "name", required=False, default=p.stem)
    out_raw = c.string(s, "study", "out_dir", required=False, default=f"results/{safe_name(name)}")
    out_dir = Path(out_raw).expanduser()
    out_dir = (out_dir if out_dir.is_absolute() else base / out_dir).resolve()
    methods = _methods(c, s, "study")

    defaults = c.table(doc, "defaults", required=False) or {}
    _check_sections(c, defaults, "defaults")
    defaults = _absolute_paths(defaults, base)

    overrides = _overrides(c, doc, base)
    entries: list[tuple[str, Path, dict, str | None]] = []
    for i, r in enumerate(_recording_tables(c, doc), start=1):
        entries += _recording_entries(c, r, f"recordings #{i}", base, p)
    tasks = _task_list(entries, defaults, overrides, methods, c)
    return Study(name=name, path=p, out_dir=out_dir, tasks=tasks)


def _overrides(c: _Ctx, doc: Mapping, base: Path) -> list:
    """``[overrides."PATTERN"]`` tables: ``(pattern, body with absolute paths, methods)``."""
    overrides = []
    ov = c.table(doc, "overrides", required=False) or {}
    for pattern, body in ov.items():
        where = f"overrides.{pattern!r}"
        if not isinstance(body, dict):
            raise c.error(where, None, "expected a table", f'write it as [overrides."{pattern}"]')
        _check_sections(c, body, where, extra=("methods",))
        over_methods = _methods(c, body, where)
        body = _absolute_paths({k: v for k, v in body.items() if k != "methods"}, base)
        overrides.append((pattern, body, over_methods))
    return overrides


def _recording_tables(c: _Ctx, doc: Mapping) -> list:
    """The ``[[recordings]]`` tables (one table is accepted as a list of one)."""
    recs = doc.get("recordings")
    if recs is None:
        raise c.error(
            "recordings", None, "missing", 'add [[recordings]] with sessions = ["sessions/*.toml"]'
        )
    if isinstance(recs, dict):
        recs = [recs]
    if not isinstance(recs, list) or not recs:
        raise c.error("recordings", None, "expected [[recordings]] tables")
    return recs


def _recording_entries(c: _Ctx, r, where: str, base: Path, p: Path) -> list:
    """One ``[[recordings]]`` table's entries ``(name, source, session document, error)``."""
    if not isinstance(r, dict):
        raise c.error(where, None, "expected a table", "write it as [[recordings]]")
    c.check_keys(r, where, _RECORDING_KEYS)
    if ("sessions" in r) == ("files" in r):
        raise c.error(
            where,
            None,
            "needs exactly one of sessions = [...] (session files) or files = '...' (data "
            "files with a [recordings.session] template)",
        )
    if "sessions" in r:
        for bad in ("pattern", "session"):
            if bad in r:
                raise c.error(where, bad, "only used with files = '...'")
        return [
            _session_entry(f)
            for f in _expand(_strings(c, r, where, "sessions"), base, c, where, "sessions")
        ]
    template = r.get("session")
    if not isinstance(template, dict):
        raise c.error(
            where,
            "session",
            "missing",
            "add a [recordings.session] table: the session with {path} placeholders",
        )
    pattern = None
    if "pattern" in r:
        raw = c.string(r, where, "pattern")
        try:
            pattern = re.compile(raw)
        except re.error as exc:
            raise c.error(where, "pattern", f"not a valid regular expression: {exc}") from None
    entries = []
    for f in _expand(_strings(c, r, where, "files"), base, c, where, "files"):
        fields = {"path": str(f), "dir": str(f.parent), "stem": f.stem, "name": f.name}
        if pattern is not None:
            m = pattern.search(f.name)
            if m is None:
                raise c.error(where, "pattern", f"does not match the file name {f.name!r}")
            fields.update({k: v for k, v in m.groupdict().items() if v is not None})
        body = _absolute_paths(_fill(template, fields, c, where), base)
        entries.append((_session_name(body, f.stem), p, body, None))
    return entries


def _session_entry(f: Path) -> tuple[str, Path, dict, str | None]:
    try:
        d = read_toml(f, missing="session file not found")
    except ConfigError as exc:
        return safe_name(f.stem), f, {}, str(exc)
    return _session_name(d, f.stem), f, d, None


def study_from_sessions(
    target: str | Path, methods: Sequence[str] | None = None, out_dir: str | Path | None = None
) -> Study:
    """A study made of a folder (its ``*.toml``) or a glob of session files.

    Parameters
    ----------
    target : str or Path
        Folder or glob.
    methods : sequence of str, optional
        Methods to run on every session (default: each session's own).
    out_dir : str or Path, optional
        Default ``./<folder name>-batch``.

    Raises
    ------
    ConfigError
        ``target`` does not exist, nothing matches, a method is unknown, two sessions share a
        name.
    """
    t = Path(target).expanduser()
    if not _glob.has_magic(str(t)) and not t.exists():
        raise ConfigError(
            f"{target}: no such file or folder (expected a study file, a folder of session "
            "files or a glob of them)"
        )
    if t.is_file() and t.suffix.lower() != ".toml" and not _glob.has_magic(str(t)):
        raise ConfigError(
            f"{target}: not a study or session file (*.toml); a recording needs a session: "
            f"{init_session_hint(target)}"
        )
    if t.is_dir():
        files = sorted(t.glob("*.toml"))
        name = t.resolve().name
    else:
        files = sorted(Path(h) for h in _glob.glob(str(t), recursive=True))
        name = t.parent.resolve().name if _glob.has_magic(str(t)) else t.stem
    files = [f.resolve() for f in files if f.is_file()]
    if not files:
        raise ConfigError(f"{target}: no session files (*.toml) found")
    for m in methods or ():
        if m not in METHODS:
            fix = unknown_fix(m, METHODS)
            raise ConfigError(f"--method: unknown method {m!r} ({fix})")
    entries = [_session_entry(f) for f in files]
    tasks = _task_list(entries, {}, [], tuple(methods) if methods else None, None)
    out = Path(out_dir) if out_dir is not None else Path(f"{safe_name(name)}-batch")
    return Study(name=name, path=None, out_dir=out.resolve(), tasks=tasks)
