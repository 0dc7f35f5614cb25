"""The README's code is executed: its Python examples run, and CI runs its test command."""

from __future__ import annotations

import re
import subprocess

import pytest

from conftest import REPO_ROOT

README = (REPO_ROOT / "README.md").read_text(encoding="utf-8")


def _block_after(marker: str) -> str:
    m = re.search(re.escape(marker) + r"\s*```bash\n(.*?)```", README, flags=re.S)
    assert m, f"README has no ```bash block after {marker}"
    return m.group(1).strip()


def test_readme_first_section_has_the_two_setup_commands():
    first = README.split("\n## ", 2)[1]  # "Get started" section
    demo = _block_after("<!-- ci:demo -->")
    test = _block_after("<!-- ci:test -->")
    assert demo in first and test in first
    assert demo.endswith("kinefuse demo")
    assert "pip install" in demo and "pip install" in test
    assert test.split("&&")[-1].split()[0] == "pytest", test  # the suite itself, last


def test_ci_runs_exactly_the_readme_test_command():
    script = (REPO_ROOT / ".ci" / "run").read_text(encoding="utf-8")
    # .ci/run reads the command out of the README block; check the extraction gives that block
    awk = re.search(r"test_cmd=\$\(awk '(.*?)' README.md\)", script)
    assert awk, ".ci/run must extract the test command from README.md"
    out = subprocess.run(
        ["awk", awk.group(1), str(REPO_ROOT / "README.md")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert out == _block_after("<!-- ci:test -->")


def _run_ci_on_a_fake_tree(tmp_path, test_body: str, env_extra: dict, files=None):
    """.ci/run on a fake checkout whose README test command runs one test; returns the result."""
    import os
    import shutil
    import sys

    (tmp_path / ".ci").mkdir()
    shutil.copy(REPO_ROOT / ".ci" / "run", tmp_path / ".ci" / "run")
    (tmp_path / "test_one.py").write_text(f"def test_one():\n    {test_body}\n")
    for name, text in (files or {}).items():
        (tmp_path / name).write_text(text)
    cmd = f"{sys.executable} -m pytest -q -p no:cacheprovider test_one.py"
    (tmp_path / "README.md").write_text(f"<!-- ci:test -->\n```bash\n{cmd}\n```\n")
    # a stand-in `chromium` on PATH: the script's browser install step is not under test here
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    (fake_bin / "chromium").write_text("#!/bin/sh\nexit 0\n")
    (fake_bin / "chromium").chmod(0o755)
    env = {**os.environ, "PATH": f"{fake_bin}{os.pathsep}{os.environ['PATH']}", **env_extra}
    return subprocess.run(
        ["bash", str(tmp_path / ".ci" / "run")],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
    )


@pytest.mark.parametrize("passes", [True, False], ids=["tests-pass", "tests-fail"])
def test_ci_prints_verdict_and_duration_even_when_a_test_fails(tmp_path, passes):
    # issue 12: with `set -e` a failing pytest used to end .ci/run before its summary line
    # (the lint steps are tested below)
    res = _run_ci_on_a_fake_tree(tmp_path, f"assert {passes}", {"KINEFUSE_CI_LINT": "0"})
    verdict = "PASSED" if passes else "FAILED"
    assert re.search(rf"^ci: {verdict}.* in \d+ s$", res.stdout, flags=re.M), res.stdout
    assert (res.returncode == 0) == passes


@pytest.mark.parametrize("fatal", ["0", "1"], ids=["format-reported", "format-fatal"])
def test_ci_lints_after_the_tests(tmp_path, fatal):
    # .ci/run: `ruff check` always fatal; `ruff format --check` and `lint-imports` fatal only
    # when their switch says so (a fake tree: one unformatted file, no import contract)
    switches = {"KINEFUSE_CI_FORMAT_FATAL": fatal, "KINEFUSE_CI_IMPORTS_FATAL": "0"}
    res = _run_ci_on_a_fake_tree(
        tmp_path, "assert True", switches, files={"unformatted.py": "x=[1,\n2]\n"}
    )
    out = res.stdout
    assert "ci: lint: ruff check passed" in out, out
    assert re.search(r"^1 file would be reformatted", out, flags=re.M), out
    assert "ci: lint: lint-imports found problems" in out, out  # no contract here: reported
    assert re.search(r"^1 passed in [0-9.]+s$", out, flags=re.M), out  # the runner's closing line
    if fatal == "1":
        assert "ci: lint: ruff format --check FAILED" in out, out
        assert re.search(r"^ci: FAILED: ruff format --check .* in \d+ s$", out, flags=re.M), out
        assert res.returncode == 1
    else:
        assert "ci: lint: ruff format --check found problems" in out, out
        assert re.search(r"^ci: PASSED .* in \d+ s$", out, flags=re.M), out
        assert res.returncode == 0


@pytest.mark.parametrize(
    "code", re.findall(r"```python\n(.*?)```", README, flags=re.S), ids=lambda c: c.splitlines()[0]
)
def test_readme_python_examples_run(code):
    exec(compile(code, "README.md", "exec"), {})
