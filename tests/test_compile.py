"""Interpreted kernels (used by a first `kinefuse demo`) give the compiled kernels' results."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from kinefuse import _compile

_CHILD = """
import json, sys
import numpy as np
from kinefuse import _compile
assert _compile.interpret_kernels(), "kernel modules were imported too early"
from kinefuse.filters import IntegratedFilter, UFIRFilter
from kinefuse.filters._kernels import kf_update
from kinefuse.models import constant_velocity
assert not hasattr(kf_update, "py_func"), "kernels should be plain functions"
z = np.array(json.loads(sys.stdin.read()))
m = constant_velocity(1 / 30, 1.0, 0.01)
out = {"int": IntegratedFilter(m).filter(z)[1].position.tolist(),
       "ufir": UFIRFilter(m, horizon=10).filter(z)[1].position.tolist()}
print(json.dumps(out))
"""


def test_interpreted_kernels_equal_compiled(rng):
    from kinefuse.filters import IntegratedFilter, UFIRFilter
    from kinefuse.models import constant_velocity

    z = np.cumsum(rng.normal(scale=0.05, size=(2, 80, 3)), axis=1)
    z[1, 30:34] = np.nan
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD],
        input=json.dumps(z.tolist()),
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    child = json.loads(proc.stdout)
    m = constant_velocity(1 / 30, 1.0, 0.01)
    np.testing.assert_allclose(child["int"], IntegratedFilter(m).filter(z)[1].position, atol=1e-12)
    np.testing.assert_allclose(
        child["ufir"], UFIRFilter(m, horizon=10).filter(z)[1].position, atol=1e-12
    )


def test_interpret_refused_once_kernels_are_imported():
    import kinefuse.filters  # noqa: F401  (imports the kernel modules)

    assert _compile.interpret_kernels() is False
    assert _compile.interpreting() is False


def test_kernels_cached_looks_in_the_user_cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert _compile.kernels_cached() is False
    for _sub, pattern in _compile._SENTINELS:
        d = tmp_path / "x" / "filters"
        d.mkdir(parents=True, exist_ok=True)
        (d / pattern.replace("*", "12.py311")).write_text("")
    assert _compile.kernels_cached() is True
