"""The test suite itself (issue 12, case 13): kinefuse modules are imported, never skipped;
no test asserts on wall-clock time (speed lives in benchmarks/ and ``kinefuse bench``)."""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).parent


def _sources():
    return {p.name: p.read_text(encoding="utf-8") for p in sorted(TESTS.glob("test_*.py"))}


def test_no_importorskip_of_kinefuse_modules():
    # a broken kinefuse module must fail the suite, not skip its tests
    pattern = re.compile(r"importorskip\(\s*[\"']kinefuse")
    offenders = [name for name, src in _sources().items() if pattern.search(src)]
    assert offenders == []


def test_no_timing_asserts():
    # `assert ... batch_ms < 33.3` and the like: a comparison of a measured time with a bound
    pattern = re.compile(
        r"assert[^\n]*(_ms|elapsed|run_time_s|wall_s|duration_s|per_step)[\"'\]\)]*\s*<\s*[0-9]"
    )
    offenders = [
        f"{name}: {m.group(0)}"
        for name, src in _sources().items()
        if name != Path(__file__).name
        for m in pattern.finditer(src)
    ]
    assert offenders == []
