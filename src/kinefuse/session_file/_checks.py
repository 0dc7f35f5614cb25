"""Validation helpers of the session-file parsers: typed reads that fail with one clear line.

Every problem is a :class:`~kinefuse.exceptions.ConfigError`
``"<file>: [<section>] <key>: <problem> (<fix>)"``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

from kinefuse._validation import did_you_mean
from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import ConfigError

_PATH_HINT = "relative paths are resolved against the TOML's folder"


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
                fix = did_you_mean(key, allowed, f"allowed keys: {', '.join(allowed)}")
                raise self.error(section, key, "unknown key", fix)

    def given(
        self, table: Mapping, section: str, key: str, *, required: bool, example: str
    ) -> bool:
        """Whether ``key`` is in ``table``; a missing ``required`` key is a ConfigError.

        The fix it suggests is ``add <key> = <example>``.
        """
        if key in table:
            return True
        if required:
            raise self.error(section, key, "missing", f"add {key} = {example}")
        return False

    def string(
        self,
        table: Mapping,
        section: str,
        key: str,
        *,
        required: bool = True,
        default: str | None = None,
    ) -> str | None:
        if not self.given(table, section, key, required=required, example='"..."'):
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
        if not self.given(table, section, key, required=required, example="<number>"):
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
            hint = (
                _PATH_HINT
                if Path(raw).expanduser().is_absolute()
                else f"looked for {p}; {_PATH_HINT}"
            )
            raise self.error(section, key, f"file {raw!r} not found", hint)
        return p.resolve()

    def segment(self, section: str, name: str) -> None:
        """``name`` must be a canonical segment (:data:`kinefuse.conventions.SEGMENTS`)."""
        if name not in SEGMENTS:
            fix = did_you_mean(name, SEGMENTS)
            raise self.error(section, repr(name), "unknown segment", fix)
