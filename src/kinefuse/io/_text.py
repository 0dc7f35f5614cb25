"""Reading text files: delimited tables with a comment preamble, JSON, header numbers, time columns.

Private module. Readers validate at their boundary and raise
:class:`~kinefuse.exceptions.FormatError` naming the file, line/field, expected and found.
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError

__all__ = [
    "TIME_COLUMNS",
    "Table",
    "check_time",
    "header_number",
    "read_json",
    "read_table",
    "read_text",
    "table_time",
    "time_column_s",
    "unit_triplet",
]


@dataclass
class Table:
    """A delimited text table held as strings, with the file line number of every row.

    Attributes
    ----------
    path : Path
        The file read.
    columns : list of str
        Header names, stripped.
    rows : list of list of str, or None
        Fields of each data row (already padded/validated to ``len(columns)``); None when
        :func:`read_table` took its numeric fast path (``fast=True``): the columns are then
        held parsed, and the rows are split only if a method needs a numeric column's text.
    lines : ndarray of int, shape (n,)
        1-based line number of each row in the file.
    comments : list of str
        Comment lines before the header, without the comment prefix.
    header_line : int
        1-based line number of the header.
    """

    path: Path
    columns: list[str]
    rows: list[list[str]]
    lines: np.ndarray
    comments: list[str] = field(default_factory=list)
    header_line: int = 1
    #: fast path: column name -> float64 array, or list of str (a text column)
    parsed: dict | None = field(default=None, repr=False)
    #: fast path: the data lines, split into ``rows`` on demand
    data_lines: list | None = field(default=None, repr=False)
    delimiter: str = ","
    #: fast path: an empty field was read as NaN (``floats(allow_empty=False)`` checks again)
    empty_filled: bool = False

    def __len__(self) -> int:
        return len(self.lines)

    def _split_rows(self) -> list[list[str]]:
        """``rows``, split from the fast path's data lines on first need."""
        if self.rows is None:
            self.rows = [ln.split(self.delimiter)[: len(self.columns)] for ln in self.data_lines]
        return self.rows

    def has(self, name: str) -> bool:
        return name in self.columns

    def index(self, name: str) -> int:
        try:
            return self.columns.index(name)
        except ValueError:
            raise FormatError(
                self.path,
                f"missing column {name!r}; found columns {self.columns}",
                line=self.header_line,
                field=name,
            ) from None

    def strings(self, name: str) -> list[str]:
        i = self.index(name)
        if self.parsed is not None and isinstance(self.parsed.get(name), list):
            return [v.strip() for v in self.parsed[name]]
        return [r[i].strip() for r in self._split_rows()]

    def floats(self, name: str, *, allow_empty: bool = True) -> np.ndarray:
        """Column ``name`` as float64; empty fields are NaN when ``allow_empty``.

        Raises
        ------
        FormatError
            Naming the line and column of the first field that is not a number.
        """
        i = self.index(name)
        got = self.parsed.get(name) if self.parsed is not None else None
        if isinstance(got, np.ndarray) and (
            allow_empty or not self.empty_filled or not np.isnan(got).any()
        ):  # (a NaN that was an empty field where none is allowed: the row reader names it)
            return got.copy()
        raw = [r[i] for r in self._split_rows()]
        try:
            out = np.array(raw, dtype=np.float64)
        except ValueError:
            out = None
        if out is not None:
            self._check_no_inf(out, raw, name)
            return out
        out = np.empty(len(raw), dtype=np.float64)
        for k, v in enumerate(raw):
            s = v.strip()
            if not s:
                if not allow_empty:
                    raise self.error_at(k, "expected a number, found an empty field", name)
                out[k] = np.nan
                continue
            try:
                out[k] = float(s)
            except ValueError:
                raise self.error_at(k, f"expected a number, found {s!r}", name) from None
        self._check_no_inf(out, raw, name)
        return out

    def column_group(self, names: Sequence[str]) -> np.ndarray | None:
        """Columns ``names`` as (n, len(names)) floats; None when none is there.

        Raises
        ------
        FormatError
            Some but not all of ``names`` are there (naming the first missing one).
        """
        present = [self.has(n) for n in names]
        if not any(present):
            return None
        if not all(present):
            missing = next(n for n, p in zip(names, present, strict=True) if not p)
            raise self.header_error(
                f"missing column {missing!r} (found {names[present.index(True)]!r})", missing
            )
        return np.stack([self.floats(n) for n in names], axis=1)

    def error_at(self, k: int, message: str, field: str) -> FormatError:
        """A FormatError naming row ``k``'s line and column ``field`` (raise it)."""
        return FormatError(self.path, message, line=int(self.lines[k]), field=field)

    def header_error(self, message: str, field: str | None = None) -> FormatError:
        """A FormatError naming the header line (raise it)."""
        return FormatError(self.path, message, line=self.header_line, field=field)

    def _check_no_inf(self, out: np.ndarray, raw: list[str], name: str) -> None:
        """Infinite values are never data (NaN, an empty field, is missing): issue 12."""
        bad = np.flatnonzero(np.isinf(out))
        if bad.size:
            k = int(bad[0])
            raise self.error_at(
                k,
                f"expected a finite number, found {raw[k].strip()!r} ({bad.size} infinite "
                "value(s) in this column); leave the field empty for a missing sample",
                name,
            )

    def comment_dict(self) -> dict[str, str]:
        """``key: value`` pairs found in the comment lines (keys lower-cased)."""
        out = {}
        for c in self.comments:
            if ":" in c:
                k, v = c.split(":", 1)
                out[k.strip().lower()] = v.strip()
        return out


def read_text(path: Path) -> str:
    try:
        raw = path.read_bytes()
    except IsADirectoryError:
        raise FormatError(path, "expected a file, found a directory") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise FormatError(
            path, f"expected UTF-8 text, found undecodable byte 0x{raw[e.start]:02x}", line=line
        ) from None


def read_table(
    path,
    *,
    delimiter: str | None = None,
    comment_prefixes: Sequence[str] = ("#", "//"),
    min_rows: int = 1,
    is_header=None,
    fast: bool = False,
) -> Table:
    """Read a delimited text file with an optional comment preamble and one header line.

    Parameters
    ----------
    path : str or Path
        The file.
    delimiter : str or None
        Field separator; ``None`` sniffs the header (tab, then ``,``, then ``;``).
    comment_prefixes : sequence of str
        Lines starting with one of these are comments (kept when they precede the header).
    min_rows : int
        Minimum number of data rows; fewer is a truncated file.
    is_header : callable or None
        ``is_header(line) -> bool``: the header is the first line it accepts; lines before it are
        a preamble, kept in ``comments`` (for exports whose preamble has no comment prefix).
        None: the first line that is not a comment.
    fast : bool
        Try the numeric fast path first (NumPy's C parser, :func:`numpy.loadtxt`, 2-4x faster
        on a large file): when every data line has the header's field count and no comment or
        blank line, and every column whose first field reads as a number reads as one on every
        row (finite or NaN; an empty field is NaN, as row by row). Otherwise, or on any doubt,
        the rows are read one by one as without it; the numbers are the same either way (both
        parse with Python's correctly rounded conversion).

    Returns
    -------
    Table

    Raises
    ------
    FormatError
        Empty file, too few rows, or a row with a different number of fields than the header
        (naming the line, the expected and found counts).
    """
    path = Path(path)
    lines = read_text(path).splitlines()
    k, comments = _preamble(path, lines, tuple(comment_prefixes), is_header)
    header = lines[k]
    if delimiter is None:
        delimiter = (
            "\t" if "\t" in header else ("," if "," in header else (";" if ";" in header else ","))
        )
    columns = [c.strip() for c in header.split(delimiter)]
    while columns and not columns[-1]:
        columns.pop()
    header_line = k + 1
    if fast:
        got = _parse_numeric(lines[k + 1 :], columns, delimiter, tuple(comment_prefixes))
        if got is not None and len(lines) - k - 1 >= min_rows:
            n = len(lines) - k - 1
            return Table(path, columns, None, np.arange(k + 2, k + 2 + n), comments, header_line,
                         got[0], lines[k + 1 :], delimiter, got[1])  # fmt: skip
    rows, line_no = _rows(path, lines, k + 1, len(columns), delimiter, tuple(comment_prefixes))
    if len(rows) < min_rows:
        raise FormatError(
            path, f"expected at least {min_rows} data rows after the header, found {len(rows)}"
        )
    return Table(path, columns, rows, np.asarray(line_no, dtype=int), comments, header_line)


def _parse_numeric(
    data: list[str], columns: list[str], delimiter: str, prefixes: tuple
) -> tuple[dict, bool] | None:
    """Columns of ``data`` (the lines after the header) by :func:`numpy.loadtxt`: name ->
    float64 array, or list of str for a column whose first field is not a number; and whether
    an empty field was read as NaN. None when a line has another field count, the data has a
    comment, blank line, ±inf, an empty text field, or loadtxt refuses a field
    (``read_table`` then reads row by row, which names it). A comment line (``prefixes``)
    cannot pass: its first field is not a number, and a text first column is checked."""
    n, d = len(columns), delimiter
    if not data or len(set(columns)) != n:
        return None
    counts = np.fromiter((ln.count(d) for ln in data), np.int64, len(data))
    if np.any(counts != n - 1):
        return None
    filled = data
    blob = "\n".join(data)
    empty = d + d in blob or f"\n{d}" in blob or f"{d}\n" in blob
    empty = empty or blob.startswith(d) or blob.endswith(d)
    if empty and n > 1:  # empty fields are missing samples: NaN, as the row reader reads them
        blob = blob.replace(d + d, f"{d}nan{d}").replace(d + d, f"{d}nan{d}")
        blob = blob.replace(f"\n{d}", f"\nnan{d}").replace(f"{d}\n", f"{d}nan\n")
        blob = ("nan" if blob.startswith(d) else "") + blob + ("nan" if blob.endswith(d) else "")
        filled = blob.split("\n")
    text = []
    for i, f in enumerate(filled[0].split(d)):
        try:
            float(f)
        except ValueError:
            text.append(i)
    numeric = [i for i in range(n) if i not in text]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # any warning ("input contained no data"...): not here
            values = np.loadtxt(filled, delimiter=d, usecols=numeric, comments=None,
                                dtype=np.float64, ndmin=2)  # fmt: skip
    except (ValueError, Warning):
        return None
    if values.shape != (len(data), len(numeric)) or np.isinf(values).any():
        return None
    out: dict = {columns[i]: np.ascontiguousarray(values[:, k]) for k, i in enumerate(numeric)}
    for i in text:
        col = [ln.split(d, i + 1)[i] for ln in data]
        if any(not v.strip() for v in col):
            return None
        # a comment line fails a number in the first column; a text first column is checked
        if i == 0 and any(v.lstrip().startswith(prefixes) for v in col):
            return None
        out[columns[i]] = col
    return out, bool(empty)


def _preamble(path: Path, lines: list[str], prefixes: tuple, is_header) -> tuple[int, list[str]]:
    """(index of the header line, the comment/preamble lines before it without their prefix)."""
    comments: list[str] = []
    k = 0
    while k < len(lines) and (not lines[k].strip() or lines[k].lstrip().startswith(prefixes)):
        s = lines[k].strip()
        for p in prefixes:
            if s.startswith(p):
                s = s[len(p) :].strip()
                break
        if s:
            comments.append(s)
        k += 1
    if is_header is not None:
        j = k
        while j < len(lines) and not is_header(lines[j]):
            j += 1
        if j >= len(lines):
            raise FormatError(
                path,
                "expected a header line with column names, found none that this reader recognises",
            )
        comments += [ln.strip() for ln in lines[k:j] if ln.strip()]
        k = j
    if k >= len(lines):
        raise FormatError(
            path,
            "expected a header line with column names, found no data (empty or truncated file)",
        )
    return k, comments


def _rows(path: Path, lines: list[str], start: int, n: int, delimiter: str, prefixes: tuple):
    """Fields of the data rows from line index ``start`` (each ``n`` fields) and their line numbers."""
    rows: list[list[str]] = []
    line_no: list[int] = []
    for j in range(start, len(lines)):
        ln = lines[j]
        if not ln.strip() or ln.lstrip().startswith(prefixes):
            continue
        f = ln.split(delimiter)
        if len(f) > n and not any(x.strip() for x in f[n:]):
            f = f[:n]
        if len(f) != n:
            what = "truncated line?" if len(f) < n else "extra fields"
            raise FormatError(
                path, f"expected {n} fields as in the header, found {len(f)} ({what})", line=j + 1
            )
        rows.append(f)
        line_no.append(j + 1)
    return rows, line_no


def check_time(path, t: np.ndarray, lines: np.ndarray | None, field: str) -> np.ndarray:
    """Require finite, strictly increasing times; otherwise a FormatError naming the line."""
    t = np.asarray(t, dtype=float)
    bad = ~np.isfinite(t)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(
            path,
            f"expected a finite time, found {float(t[i])!r}",
            line=None if lines is None else int(lines[i]),
            field=field,
        )
    if t.size > 1:
        d = np.diff(t)
        if np.any(d <= 0):
            i = int(np.flatnonzero(d <= 0)[0]) + 1
            raise FormatError(
                path,
                f"expected strictly increasing time, found {float(t[i])!r} after {float(t[i - 1])!r} (non-monotonic or duplicate)",
                line=None if lines is None else int(lines[i]),
                field=field,
            )
    return t


TIME_COLUMNS = {
    # lower-cased column name -> factor to seconds
    "t_s": 1.0,
    "time_s": 1.0,
    "time": 1.0,
    "timestamp_s": 1.0,
    "t_ms": 1e-3,
    "time_ms": 1e-3,
    "timestamp_ms": 1e-3,
    "t_us": 1e-6,
    "time_us": 1e-6,
    "timestamp_us": 1e-6,
    "timestamp_usec": 1e-6,
    "relative_time_100ns": 1e-7,
    "relativetime": 1e-7,
}


def table_time(table: Table, *, rate_hz: float | None = None) -> tuple[np.ndarray, str]:
    """Time in seconds from the table's time column, or ``frame / rate_hz``.

    Returns
    -------
    t_s : ndarray, shape (n,)
    column : str
        The column used (``"<row index>"`` if neither a time nor a frame column exists).
    """
    lower = {c.lower(): c for c in table.columns}
    for name, factor in TIME_COLUMNS.items():
        if name in lower:
            col = lower[name]
            t = table.floats(col, allow_empty=False) * factor
            return check_time(table.path, t, table.lines, col), col
    for name in ("frame", "frame#", "frame_index"):
        if name in lower:
            if rate_hz is None:
                raise FormatError(
                    table.path,
                    f"found a frame column but no time column (one of {sorted(TIME_COLUMNS)}); pass rate_hz=",
                    line=table.header_line,
                )
            col = lower[name]
            t = table.floats(col, allow_empty=False) / float(rate_hz)
            return check_time(table.path, t, table.lines, col), col
    if rate_hz is not None:
        return np.arange(len(table)) / float(rate_hz), "<row index>"
    raise FormatError(
        table.path,
        f"missing time column: expected one of {sorted(TIME_COLUMNS)} (or a 'frame' column with rate_hz=)",
        line=table.header_line,
        field="t_s",
    )


def time_column_s(tab: Table) -> tuple[np.ndarray, str]:
    """Times (s) of the first known time column, unchecked (rows may interleave streams).

    For tables whose rows interleave sensors or joints, so that monotonicity is checked per
    stream by the caller; :func:`table_time` checks it for the whole column.
    """
    lower = {c.lower(): c for c in tab.columns}
    for name, factor in TIME_COLUMNS.items():
        if name in lower:
            return tab.floats(lower[name], allow_empty=False) * factor, lower[name]
    raise tab.header_error(f"missing time column: expected one of {sorted(TIME_COLUMNS)}", "t_s")


def read_json(path: Path):
    """The parsed JSON of ``path``; a FormatError names the line of invalid or truncated JSON."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise FormatError(path, f"expected UTF-8 JSON text: {e}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(
            path, f"invalid JSON ({e.msg}, column {e.colno}); truncated file?", line=e.lineno
        ) from None


def header_number(path, value, field: str, *, cast=float, what: str = "a number"):
    """``cast(value)`` of a header field; a FormatError naming ``field`` when it is not one."""
    try:
        return cast(value)
    except (TypeError, ValueError):
        raise FormatError(path, f"expected {what}, got {value!r}", field=field) from None


_UNIT_SUFFIX = re.compile(r"\(([^)]*)\)\s*$")


def unit_triplet(tab: Table, prefix: str) -> tuple[np.ndarray, str]:
    """Columns ``<prefix> X (unit)``, ``<prefix> Y (unit)``, ``<prefix> Z (unit)`` as (n, 3), and the unit.

    The x-io style of naming columns (x-IMU3 logs, x-io's plain CSV); the unit must be the same
    for the three axes.
    """
    names = []
    units = set()
    for ax in "XYZ":
        hit = [c for c in tab.columns if c.startswith(f"{prefix} {ax}")]
        if not hit:
            raise FormatError(
                tab.path,
                f"missing column '{prefix} {ax} (...)'; found {tab.columns}",
                line=tab.header_line,
                field=f"{prefix} {ax}",
            )
        names.append(hit[0])
        m = _UNIT_SUFFIX.search(hit[0])
        units.add(m.group(1).strip().lower() if m else "")
    if len(units) != 1:
        raise FormatError(
            tab.path,
            f"expected one unit for {prefix} X/Y/Z, found {sorted(units)}",
            line=tab.header_line,
        )
    return np.stack([tab.floats(n) for n in names], axis=1), units.pop()
