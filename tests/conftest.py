"""Shared test fixtures: the location of ../shared/data, seeded RNGs, a machine-local LSL env;
the grouping of tests for parallel runs (pytest-xdist, ``--dist loadgroup``)."""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; tests needing it skip with a reason if absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real-data tests need {SHARED_DATA} (clone with ../shared beside the repo)")
    return SHARED_DATA


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20241123)


#: First lines of every child process that loads pylsl: the machine-local configuration is in
#: effect before liblsl loads; prints ``SKIP:<reason>`` and exits 0 when pylsl cannot load.
LSL_PRELUDE = """
import json, os, sys
from kinefuse.streaming.config import check_lsl_config, LslUnavailable, import_pylsl
assert "pylsl" not in sys.modules
info = check_lsl_config()
assert info["local"], info["problems"]          # in effect before liblsl is loaded
try:
    pylsl = import_pylsl()
    pylsl.library_version()
except LslUnavailable as exc:
    print("SKIP:" + str(exc)); sys.exit(0)
"""


@pytest.fixture
def lsl_env(tmp_path):
    """Environment for a child process: a fresh machine-local LSL config, set before pylsl loads.

    liblsl reads its configuration once per process, so only children started with
    ``lsl_env["env"]`` may load pylsl (the pytest process never does). Keys: ``env``, ``cfg``
    (the lsl_api.cfg), ``log`` (liblsl's log file), ``prefix`` (a unique stream-name prefix,
    also ``$KINEFUSE_TEST_PREFIX``; the ``[lab] SessionID`` is unique too).
    """
    from kinefuse.streaming.config import LSL_CONFIG_ENV, local_lsl_config_text

    sid = f"kftest-{uuid.uuid4().hex[:10]}"
    cfg = tmp_path / "lsl_api.cfg"
    log = tmp_path / "liblsl.log"
    cfg.write_text(local_lsl_config_text(sid, log_level=0, log_file=log), encoding="utf-8")
    env = dict(os.environ, PYTHONUNBUFFERED="1", KINEFUSE_TEST_PREFIX=sid.replace("-", "_"))
    env.pop("KINEFUSE_DEBUG", None)
    env[LSL_CONFIG_ENV] = str(cfg)
    return {"env": env, "cfg": cfg, "log": log, "prefix": sid.replace("-", "_")}


def ctrl_c_default() -> None:
    """``preexec_fn`` of a child process that a test interrupts with SIGINT: Ctrl-C as in a
    terminal, whatever pytest inherited. A background job (CI starts pytest as one) ignores
    SIGINT, and Python keeps an ignored SIGINT ignored: the child would not be interrupted."""
    import signal

    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def cli_stderr(result) -> str:
    """stderr of a typer/click ``CliRunner`` result (older click: mixed into the output)."""
    try:
        return result.stderr
    except ValueError:
        return result.output


# ---- parallel runs (pytest-xdist with --dist loadgroup) ---------------------------------------
# Tests without a group go to whichever worker is free. A group runs on one worker, one test
# after the other:
# - "lsl": every test with a machine-local LSL configuration (``lsl_env``). Their child processes
#   are isolated by a unique session ID, so two at once would be correct, but they wait on
#   stream discovery with timeouts; one at a time keeps them far from those timeouts.
# - a test module with a module- or session-scoped fixture (a demo run, a report, a study on a
#   LocalCluster, ...): its own group, so that the fixture is built once, not once per worker.
# Needed no group: the live view and the Dask cluster bind port 0 (a free port) on 127.0.0.1;
# Chromium runs get a temporary profile each; numba writes each cache file atomically (a
# kernel compiled by both workers at once is written twice, identically); tmp_path is per worker.
_SHARED_FIXTURE = re.compile(r"scope\s*=\s*[\"'](module|session)[\"']")


@functools.cache
def _module_shares_a_fixture(path: Path) -> bool:
    return bool(_SHARED_FIXTURE.search(path.read_text(encoding="utf-8")))


def xdist_group_of(item) -> str | None:
    """The xdist group of a collected test (None: any worker)."""
    if "lsl_env" in getattr(item, "fixturenames", ()):
        return "lsl"
    path = Path(item.path)
    if path.name != "conftest.py" and _module_shares_a_fixture(path):
        return path.name
    return None


def pytest_xdist_node_collection_finished(node, ids):
    """Controller side of ``--dist loadgroup``: stop when no collected test carries its group
    (the worker's ``nodeid@group``), as with pytest 9.2 (pytest-xdist issue #1386): the
    scheduler would then split every group, running module fixtures once per worker and LSL
    tests side by side."""
    if node.config.getoption("dist") != "loadgroup" or any("@" in i for i in ids):
        return
    root = Path(str(node.config.rootpath))
    files = {i.split("::", 1)[0] for i in ids}
    if any(f.endswith(".py") and _module_shares_a_fixture(root / f) for f in files):
        pytest.exit(
            f"pytest-xdist --dist loadgroup does not group tests with pytest {pytest.__version__} "
            "(pytest-xdist issue #1386): install the test extra as pinned in pyproject.toml",
            returncode=4,
        )


@pytest.hookimpl(tryfirst=True)  # before xdist reads the marks (its hook adds @group to node ids)
def pytest_collection_modifyitems(config, items):
    for item in items:
        group = xdist_group_of(item)
        if group is not None and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(group))


# ---- the kernels compiled once, before the workers start (pytest -n N) -----------------------
# Serially, each numba kernel compiles on its first use and every later use loads it from the
# on-disk cache. With xdist, two workers reaching the same cold kernel at once would both compile
# it; so the controller compiles them first, with the steps of ``kinefuse warm-up`` in two
# processes at a time: one compiles the general UFIR, then the constant-velocity UFIR; the other
# the KF, the IMM and the kinefuse fusion's own kernels; once both the general UFIR and that
# process are done, a third compiles the EM-KF and the integrated filter, which use the UFIR's and
# the KF's kernels (loaded, not compiled again). Cold, on 2 cores: about 44 s + 10 s | 25 s + 19 s
# + 8 s, then 44 s.
# The first process then also compiles the dense RTS for 6 states (about 20 s; off the path
# the EM-KF waits on) and the IMM's loop for sizes other than paper B's ("imm-any": about 25 s,
# used only by tests and non-standard IMMs, so not a step of `kinefuse warm-up`); otherwise two
# workers running those tests would both compile them.
_WARM_UP_UFIR = (1, 2, 5, "imm-any")  # WARM_UP_STEPS: UFIR general, constant-velocity, RTS dense
_WARM_UP_OTHER = (0, 4, 6)  # KF/RTS, IMM, the kinefuse fusion (its own kernels)
_WARM_UP_LAST = (3,)  # EM-KF and the integrated filter: after the general UFIR and the KF
_WARM_UP_CODE = (
    "import sys, warnings; warnings.simplefilter('ignore')\n"
    "import numpy as np\n"
    "from kinefuse.filters import IMM\n"
    "from kinefuse.pipelines.warm_up import WARM_UP_STEPS\n"
    "from kinefuse.models import constant_velocity\n"
    "def imm_any():  # two 2-D models: the IMM loop for any sizes (imm_run_any)\n"
    "    imm = IMM(constant_velocity(0.1, 0.5, 0.01, n_axes=2), constant_velocity(0.1, 3.0, 0.002, n_axes=2))\n"
    "    st, _ = imm.filter(np.zeros((1, 4, 2, 2)))\n"
    "    imm.step(st, np.zeros((1, 2, 2)))\n"
    "for a in sys.argv[1:]:\n"
    "    imm_any() if a == 'imm-any' else WARM_UP_STEPS[int(a)][1]()\n"
    "    print('done', a, flush=True)\n"
)


def _warm_up_process(steps):
    return subprocess.Popen(
        [sys.executable, "-c", _WARM_UP_CODE, *map(str, steps)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def pytest_sessionstart(session):
    config = session.config
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return  # an xdist worker (the controller compiled), or a serial run
    tr = config.pluginmanager.get_plugin("terminalreporter")
    say = tr.write_line if tr is not None else print
    say("conftest: compiling the numba kernels in 2 processes before the workers start ...")
    t0 = time.perf_counter()
    ufir = _warm_up_process(_WARM_UP_UFIR)
    other = _warm_up_process(_WARM_UP_OTHER)
    ready = ufir.stdout.readline()  # "done 1": the general UFIR is compiled and cached
    outputs = [(other, other.communicate()[0])]
    last = _warm_up_process(_WARM_UP_LAST)
    outputs += [(ufir, ready + ufir.communicate()[0]), (last, last.communicate()[0])]
    for proc, out in outputs:
        if proc.returncode:  # the tests then compile what they use, and fail where it breaks
            say(f"conftest: kernel warm-up exited {proc.returncode}:\n{out[-2000:]}")
    say(f"conftest: kernels ready in {time.perf_counter() - t0:.1f} s")
