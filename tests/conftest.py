"""Shared test fixtures: the location of ../shared/data, seeded RNGs, a machine-local LSL env."""

from __future__ import annotations

import os
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


def cli_stderr(result) -> str:
    """stderr of a typer/click ``CliRunner`` result (older click: mixed into the output)."""
    try:
        return result.stderr
    except ValueError:
        return result.output
