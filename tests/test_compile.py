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


def _tree(tmp_path, sources):
    """A fake ``kinefuse`` package under ``tmp_path`` with the given kernel module sources and a
    cache file per module; returns the root."""
    for name, text in sources.items():
        path = tmp_path.joinpath(*name.split(".")).with_suffix(".py")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        cache = path.parent / "__pycache__"
        cache.mkdir(exist_ok=True)
        (cache / f"{path.stem}.f-10.py311.nbi").write_text("index")
        (cache / f"{path.stem}.f-10.py311.1.nbc").write_text("code")
    return tmp_path


def test_stale_kernel_caches_dropped_through_inlined_imports(tmp_path, monkeypatch):
    """Numba checks a cached kernel against its own file only; a change in a module it imports
    (an inlined helper) must drop its cache too, and leave unrelated modules' caches alone."""
    from kinefuse._kernel_mode import drop_stale_kernel_caches

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    mods = ("kinefuse.a._helpers", "kinefuse.a._run", "kinefuse.a._top", "kinefuse.b._other")
    root = _tree(
        tmp_path,
        {
            mods[0]: "def h(): return 1\n",
            mods[1]: "from kinefuse.a._helpers import h\n",
            mods[2]: "from kinefuse.a._run import h\nfrom numpy import zeros\n",
            mods[3]: "x = 1\n",
        },
    )
    cache_a = root / "kinefuse" / "a" / "__pycache__"
    # first run: no stamps yet, every existing cache is dropped once
    assert drop_stale_kernel_caches(root, mods) == list(mods)
    assert drop_stale_kernel_caches(root, mods) == []
    for m in mods:  # numba compiles again
        _tree(root, {m: root.joinpath(*m.split(".")).with_suffix(".py").read_text()})
    assert drop_stale_kernel_caches(root, mods) == []
    # a helper changes: it and both of its (transitive) importers are dropped, not the other
    (root / "kinefuse" / "a" / "_helpers.py").write_text("def h(): return 2\n")
    assert drop_stale_kernel_caches(root, mods) == list(mods[:3])
    assert not list(cache_a.glob("_run.*.nb*")) and not list(cache_a.glob("_top.*.nb*"))
    assert list((root / "kinefuse" / "b" / "__pycache__").glob("_other.*.nb*"))
    assert drop_stale_kernel_caches(root, mods) == []


def test_stale_kernel_caches_in_the_user_cache_dir(tmp_path, monkeypatch):
    """With NUMBA_CACHE_DIR set, numba's mirror directory (``<dir>_<sha1 of the dir>``) is the
    one checked and stamped."""
    import hashlib

    from kinefuse._kernel_mode import drop_stale_kernel_caches

    user = tmp_path / "user"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(user))
    root = _tree(tmp_path / "src", {"kinefuse.a._k": "y = 1\n"})
    src_dir = root / "kinefuse" / "a"
    mirror = user / f"a_{hashlib.sha1(str(src_dir).encode()).hexdigest()}"
    assert drop_stale_kernel_caches(root, ("kinefuse.a._k",)) == ["kinefuse.a._k"]  # in-tree
    assert (mirror / "_k.kinefuse-deps").is_file()  # stamped before numba writes there
    (mirror / "_k.f-1.py311.nbi").write_text("index")
    assert drop_stale_kernel_caches(root, ("kinefuse.a._k",)) == []
    (src_dir / "_k.py").write_text("y = 2\n")
    assert drop_stale_kernel_caches(root, ("kinefuse.a._k",)) == ["kinefuse.a._k"]
    assert not (mirror / "_k.f-1.py311.nbi").exists()


def test_warm_up_compiles_every_kernel_of_the_fusion():
    # `kinefuse warm-up` = the filters' steps, then the fusion's: after its step, every kernel
    # of the fusion has a compiled specialisation (a first run then loads, not compiles, them)
    from kinefuse.filters import warm_up as filters_warm_up
    from kinefuse.pipelines import _kinefuse_kernels, warm_up

    steps = warm_up.WARM_UP_STEPS
    assert steps[: len(filters_warm_up.WARM_UP_STEPS)] == filters_warm_up.WARM_UP_STEPS
    assert len(steps) == len(filters_warm_up.WARM_UP_STEPS) + 1
    steps[-1][1]()
    for name in _kinefuse_kernels.__all__:
        assert getattr(_kinefuse_kernels, name).signatures, name
