"""Number text of the writers: the table formatters equal the value-by-value ones.

Oracle: :func:`kinefuse.io._write.fmt_float` (one value at a time, the writers' rule: fixed point,
NaN/inf as an empty field, a value that rounds to zero as ``0``) and ``str(int(v))`` for flags;
for the orientation ``.sto``, each value's ``repr`` (``NaN`` if not finite); for the ``.mot``
and the joint-angle CSV, each value's f-string fixed point (``NaN`` / empty if not finite).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinefuse.io._write import fixed_point_rows, fmt_float
from kinefuse.io.mot import _mot_rows
from kinefuse.io.opensim import _sto_rows
from kinefuse.pipelines.run.write import _angle_rows

_SPECIAL = [0.0, -0.0, 1e-12, -1e-12, 4.9999e-7, -5e-7, 0.5, -0.5, 1e20, -1e20, np.nan, np.inf,
            -np.inf, 1.0, -1.0, 123.456789012]  # fmt: skip


def _reference(cols, decimals, sep):
    out = []
    for i in range(len(cols[0]) if cols else 0):
        fields = []
        for c in cols:
            v = c[i]
            fields.append(str(int(v)) if c.dtype.kind in "biu" else fmt_float(float(v), decimals))
        out.append(sep.join(fields))
    return out


@settings(max_examples=60, deadline=None, database=None, derandomize=True)
@given(
    T=st.integers(0, 12),
    n=st.integers(1, 5),
    decimals=st.integers(0, 9),
    sep=st.sampled_from([",", "\t", ";"]),
    seed=st.integers(0, 2**31 - 1),
)
def test_table_text_equals_value_by_value(T, n, decimals, sep, seed):
    rng = np.random.default_rng(seed)
    cols = []
    for _ in range(n):
        kind = rng.integers(0, 4)
        if kind == 0:  # awkward values: zeros of both signs, rounding edges, NaN, inf
            cols.append(rng.choice(_SPECIAL, T))
        elif kind == 1:
            cols.append(rng.standard_normal(T) * 10.0 ** rng.integers(-8, 6))
        elif kind == 2:
            cols.append(rng.random(T) < 0.5)
        else:
            cols.append(rng.integers(-5, 5, T))
    assert fixed_point_rows(cols, decimals, sep) == _reference(cols, decimals, sep)


def test_a_text_column_is_left_to_the_caller():
    with pytest.raises(TypeError, match="not a number column"):
        fixed_point_rows([np.zeros(2), np.array(["a", "b"])], 3)


def _sto_value(v: float) -> str:
    """One .sto value as OpenSense's files hold it: shortest round-trip repr, NaN if not finite."""
    return repr(float(v)) if math.isfinite(v) else "NaN"


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(0, 12),
    k=st.integers(1, 3),
    data=st.data(),
)
def test_sto_rows_equal_formatting_value_by_value(n, k, data):
    """The one-pass .sto rows equal joining each value's repr (NaN for nan, +-inf)."""
    vals = st.floats(allow_nan=True, allow_infinity=True, width=64)
    t = np.array(data.draw(st.lists(vals, min_size=n, max_size=n)), float)
    qs = [np.array(data.draw(st.lists(st.lists(vals, min_size=4, max_size=4), min_size=n,
                                      max_size=n)), float).reshape(n, 4) for _ in range(k)]  # fmt: skip
    want = [
        "\t".join([_sto_value(t[i])] + [",".join(_sto_value(v) for v in q[i]) for q in qs])
        for i in range(n)
    ]
    assert _sto_rows(t, qs) == want


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(0, 12),
    k=st.integers(0, 4),
    decimals=st.integers(0, 12),
    data=st.data(),
)
def test_mot_rows_equal_formatting_value_by_value(n, k, decimals, data):
    """The one-pass .mot rows equal formatting each value (time with at least 9 digits), as the
    writer did value by value: ``NaN`` for nan and ±inf, ``-0.000`` kept as it is."""
    vals = st.floats(allow_nan=True, allow_infinity=True, width=64)
    M = np.array(data.draw(st.lists(st.lists(vals, min_size=k + 1, max_size=k + 1), min_size=n,
                                    max_size=n)), float).reshape(n, k + 1)  # fmt: skip
    dt = max(decimals, 9)
    want = [
        "\t".join(
            f"{x:.{dt if c == 0 else decimals}f}" if math.isfinite(x) else "NaN"
            for c, x in enumerate(row)
        )
        for row in M.tolist()
    ]
    assert _mot_rows(M, decimals) == want


@settings(max_examples=200, deadline=None)
@given(n=st.integers(0, 12), k=st.integers(0, 4), data=st.data())
def test_angle_csv_rows_equal_formatting_value_by_value(n, k, data):
    """The joint-angle CSV rows: time as repr, angles with 4 decimals, empty if not finite."""
    vals = st.floats(allow_nan=True, allow_infinity=True, width=64)
    t = np.array(data.draw(st.lists(st.floats(0, 1e6), min_size=n, max_size=n)), float)
    cols = [np.array(data.draw(st.lists(vals, min_size=n, max_size=n)), float) for _ in range(k)]
    want = [
        ",".join([repr(float(t[i]))] + [f"{v[i]:.4f}" if np.isfinite(v[i]) else "" for v in cols])
        for i in range(n)
    ]
    assert _angle_rows(t, cols) == want
