"""kinefuse's command-line processes turn numpy's transparent-hugepage advice off, unless the user
chose (``kinefuse._memory``). numpy's state is process-wide, so each case runs in its own
interpreter; numpy's own switch, read back, is the oracle (``_set_madvise_hugepage`` returns the
value it replaces)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from kinefuse import _memory

_READ_BACK = """
import json, os
import numpy as np
sub = getattr(np, "_core", None) or np.core
print(json.dumps({"env": os.environ.get("NUMPY_MADVISE_HUGEPAGE"), "result": result,
                  "advice_on": bool(sub.multiarray._set_madvise_hugepage(True))}))
"""


def _run(code: str, env_value: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != _memory.HUGEPAGE_ENV}
    if env_value is not None:
        env[_memory.HUGEPAGE_ENV] = env_value
    proc = subprocess.run(
        [sys.executable, "-c", code + _READ_BACK], capture_output=True, text=True, env=env
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(_memory._numpy_switch() is None, reason="this numpy has no hugepage switch")
def test_prefer_small_pages_turns_the_advice_off_for_this_process_and_its_children():
    code = (
        "from kinefuse._memory import prefer_small_pages, user_chose_pages\n"
        "result = [prefer_small_pages(), user_chose_pages()]\n"
    )
    assert _run(code, None) == {"env": "0", "result": [True, False], "advice_on": False}


@pytest.mark.parametrize("value", ["0", "1"])
def test_a_value_the_user_set_is_kept(value):
    code = (
        "from kinefuse._memory import prefer_small_pages, user_chose_pages\n"
        "result = [prefer_small_pages(), user_chose_pages()]\n"
    )
    assert _run(code, value) == {
        "env": value,
        "result": [False, True],
        "advice_on": value == "1",  # numpy read the user's value at import; nothing changed it
    }


@pytest.mark.skipif(_memory._numpy_switch() is None, reason="this numpy has no hugepage switch")
def test_the_console_script_prefers_small_pages():
    code = (
        "import sys\n"
        "from kinefuse.cli import main\n"
        "sys.argv = ['kinefuse', '--version']\n"
        "try:\n"
        "    main()\n"
        "except SystemExit as exc:\n"
        "    result = exc.code\n"
    )
    assert _run(code, None) == {"env": "0", "result": 0, "advice_on": False}


def test_importing_kinefuse_changes_nothing():
    """A library user's process keeps numpy's own choice (a plain interpreter's is the oracle)."""
    plain = _run("result = None\n", None)
    assert _run("import kinefuse, kinefuse.pipelines.run\nresult = None\n", None) == plain
    assert plain["env"] is None
