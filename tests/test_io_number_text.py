"""Number text of the writers: the table formatter equals the value-by-value one.

Oracle: :func:`kinefuse.io._write.fmt_float` (one value at a time, the writers' rule: fixed point,
NaN/inf as an empty field, a value that rounds to zero as ``0``) and ``str(int(v))`` for flags.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinefuse.io._write import fixed_point_rows, fmt_float

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
