"""The one exceptions module of kinefuse.

All errors raised on bad user input are subclasses of the built-in ``ValueError`` /
``TypeError`` so callers may catch either the specific or the generic type.
"""

from __future__ import annotations


class KinefuseError(Exception):
    """Base class of all kinefuse-specific errors."""


class InputError(KinefuseError, ValueError):
    """Bad input (shape, dtype, value); the message says what was expected and what was found."""


class FormatError(InputError):
    """A file could not be read: the message names the file, line/field, expected and found."""

    def __init__(self, path, message: str, *, line: int | None = None, field: str | None = None):
        where = str(path)
        if line is not None:
            where += f", line {line}"
        if field is not None:
            where += f", field {field!r}"
        super().__init__(f"{where}: {message}")
        self.path = path
        self.line = line
        self.field = field


class ConfigError(InputError):
    """A session configuration problem: names the key and the fix."""


class NumericalWarning(UserWarning):
    """Recoverable numerical trouble (e.g. a covariance that had to be regularised)."""


class UnitWarning(UserWarning):
    """Data whose magnitude suggests a unit other than the declared SI one (e.g. mm, g, deg/s)."""


class FormatWarning(UserWarning):
    """A file that can be read but disagrees with itself (e.g. a header count that the rows do not match)."""
