"""The numeric fast path of ``read_table`` (NumPy's C parser) against the row-by-row reader.

Oracle: the row-by-row path (Python's ``str.split`` and ``float``, the reader every format used
before). On random tables, mixing numbers in several spellings, text columns, empty fields
(NaN on both paths) and what the fast path must hand back (±inf, comments, blank lines, extra
or missing fields, spellings only Python accepts), both give the same table: the same numbers
bit for bit, the same text, the same line numbers, and the same error where a field is bad.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kinefuse.exceptions import FormatError
from kinefuse.io._text import read_table

_FLOATS = st.floats(allow_nan=True, allow_infinity=False, width=64)
_SPELLINGS = (repr, lambda v: f"{v:.3e}", lambda v: f"{v:g}", lambda v: f" {v!r} ", str)
#: fields the fast path must refuse, or parse as Python does
_ODD = ("", "inf", "-Infinity", "1_000", "NaN", "nan", "+5", "1.", ".5", "abc", "  ")


@st.composite
def tables(draw):
    n_cols = draw(st.integers(1, 5))
    n_rows = draw(st.integers(1, 25))
    text_cols = draw(st.sets(st.integers(0, n_cols - 1), max_size=2))
    rows = []
    for _ in range(n_rows):
        row = []
        for c in range(n_cols):
            if c in text_cols:
                row.append(draw(st.sampled_from(["chest", "thigh_l", "7", "x y"])))
            elif draw(st.integers(0, 40)) == 0:
                row.append(draw(st.sampled_from(_ODD)))
            elif draw(st.integers(0, 8)) == 0:
                row.append("")  # missing: runs of them, at either end of a line
            else:
                row.append(draw(st.sampled_from(_SPELLINGS))(draw(_FLOATS)))
        rows.append(",".join(row))
    extra = draw(st.integers(0, 12))  # now and then a line the fast path must hand back
    if extra == 1:
        rows.insert(draw(st.integers(0, len(rows))), "# a comment, in the data")
    elif extra == 2:
        rows.insert(draw(st.integers(0, len(rows))), "")
    elif extra == 3:
        k = draw(st.integers(0, len(rows) - 1))
        rows[k] += ","  # a trailing empty field (allowed) or, twice, ...
        rows[k] += draw(st.sampled_from(["", "1"]))  # ... an extra one (refused)
    elif extra == 4 and n_cols > 1:
        k = draw(st.integers(0, len(rows) - 1))
        rows[k] = rows[k].rsplit(",", 1)[0]  # a missing field
    header = ",".join(f"c{c}" for c in range(n_cols))
    return "# kinefuse-test 1\n" + header + "\n" + "\n".join(rows) + "\n"


def _read(path, fast):
    try:
        return read_table(path, fast=fast), None
    except FormatError as exc:
        return None, str(exc)


def _column(tab, name):
    out = {}
    try:
        out["floats"] = tab.floats(name)
    except FormatError as exc:
        out["floats"] = str(exc)
    try:
        out["strict"] = tab.floats(name, allow_empty=False)
    except FormatError as exc:
        out["strict"] = str(exc)
    out["strings"] = tab.strings(name)
    return out


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(text=tables())
def test_fast_path_reads_what_the_row_reader_reads(tmp_path, text):
    path = tmp_path / "t.csv"
    path.write_text(text, encoding="utf-8")
    fast, fast_err = _read(path, True)
    slow, slow_err = _read(path, False)
    assert fast_err == slow_err
    if slow is None:
        return
    assert len(fast) == len(slow) and fast.columns == slow.columns
    np.testing.assert_array_equal(fast.lines, slow.lines)
    assert fast.comments == slow.comments
    for name in slow.columns:
        a, b = _column(fast, name), _column(slow, name)
        assert a["strings"] == b["strings"], name
        for key in ("floats", "strict"):
            if isinstance(b[key], str):
                assert a[key] == b[key], (name, key)
            else:  # bit for bit (NaN where NaN; -0.0 stays -0.0)
                assert a[key].tobytes() == b[key].tobytes(), (name, key)


def test_the_fast_path_is_taken_on_a_plain_numeric_table_and_not_otherwise(tmp_path):
    """It must actually run (else the test above compares the row reader with itself)."""
    p = tmp_path / "t.csv"
    p.write_text("t_s,sensor,x\n0.0,chest,1.5\n0.01,chest,nan\n", encoding="utf-8")
    tab = read_table(p, fast=True)
    assert tab.rows is None and isinstance(tab.parsed["x"], np.ndarray)
    assert tab.parsed["sensor"] == ["chest", "chest"]
    np.testing.assert_array_equal(tab.floats("x"), [1.5, np.nan])
    assert tab.strings("t_s") == ["0.0", "0.01"] and tab.rows is not None  # split on demand
    p.write_text("t_s,sensor,x,y\n0.0,chest,,1\n0.1,chest,2,\n", encoding="utf-8")
    tab = read_table(p, fast=True)  # empty fields: NaN on the fast path too
    assert tab.rows is None and tab.empty_filled
    np.testing.assert_array_equal(tab.floats("x"), [np.nan, 2.0])
    np.testing.assert_array_equal(tab.floats("t_s", allow_empty=False), [0.0, 0.1])
    with pytest.raises(FormatError, match="line 2.*empty field"):
        tab.floats("x", allow_empty=False)  # the row reader names it
    for bad in ("0.0,,1.5\n", "# note\n", "\n", "0.0,chest,1,\n"):
        p.write_text("t_s,sensor,x\n0.0,chest,1.5\n" + bad, encoding="utf-8")
        assert read_table(p, fast=True).rows is not None, bad
    p.write_text("sensor,x\nchest,1.5\n#chest,2.5\n", encoding="utf-8")  # a text first column
    assert read_table(p, fast=True).strings("sensor") == ["chest"]


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("0.01,chest,,1,0,0", "line 4"),  # an empty quaternion field: NaN is allowed, then
        ("0.01,chest,inf,0,0,0", "expected a finite number, found 'inf'"),
        ("0.01,chest,1,0,0", "expected 6 fields as in the header, found 5"),
        ("0.01,chest,1,0,0,0,1", "expected 6 fields as in the header, found 7"),
    ],
)
def test_imu_csv_errors_are_the_row_readers(tmp_path, row, message):
    """Through the IMU CSV reader: what the fast path hands back is reported as before."""
    from kinefuse.io import read_imu_csv

    p = tmp_path / "imu.csv"
    p.write_text(
        "# kinefuse-imu-csv 1\nt_s,sensor,qw,qx,qy,qz\n0.0,chest,1,0,0,0\n" + row + "\n",
        encoding="utf-8",
    )
    if message == "line 4":  # an empty field is a missing sample, not an error
        rec = read_imu_csv(p)
        assert np.isnan(rec.imu["chest"].q_world_from_sensor[1, 0])
        return
    with pytest.raises(FormatError, match=message):
        read_imu_csv(p)
