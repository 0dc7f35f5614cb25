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
    assert "pip install" in demo and "pip install" in test and test.endswith("pytest")


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


@pytest.mark.parametrize(
    "code", re.findall(r"```python\n(.*?)```", README, flags=re.S), ids=lambda c: c.splitlines()[0]
)
def test_readme_python_examples_run(code):
    exec(compile(code, "README.md", "exec"), {})
