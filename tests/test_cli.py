"""The command shell: help everywhere, exit codes, one-line errors, templates, overwrite protection."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import cli_stderr
from kinefuse import cli
from kinefuse.exceptions import ConfigError
from kinefuse.session_file import METHODS, load_session, session_template

COMMANDS = ("demo", "run", "init-session", "evaluate", "experiment", "bench", "stream", "replay")

runner = CliRunner()


def _assert_one_line_error(result, code: int, *needles: str) -> str:
    err = cli_stderr(result)
    assert result.exit_code == code, (result.exit_code, result.output, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("kinefuse: error: ")
    assert "Traceback" not in result.output + err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.mark.parametrize("args", [["--help"], ["-h"], *([c, "--help"] for c in COMMANDS)])
def test_help_everywhere(args):
    result = runner.invoke(cli.app, args)
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output
    assert "Exit codes" in result.output


def test_help_keeps_every_bracketed_word():
    """rich reads ``[word]`` in a help text as markup and drops it (``pip install
    'kinefuse[batch]'`` printed as ``'kinefuse'``): every bracketed word of every command's
    help and option help is printed (escaped as ``\\[word]`` where needed)."""
    import re

    import typer.main

    group = typer.main.get_command(cli.app)
    checked = 0
    for name, cmd in group.commands.items():
        texts = [cmd.help or ""] + [getattr(p, "help", None) or "" for p in cmd.params]
        words = {w.replace("\\", "") for w in re.findall(r"\\?\[[^\]\s]+\]", " ".join(texts))}
        if not words:
            continue
        out = runner.invoke(cli.app, [name, "--help"], env={"COLUMNS": "250"}).output
        assert {w for w in words if w not in out} == set(), name
        checked += len(words)
    assert checked >= 1  # experiment's 'kinefuse[batch]'


_HELP_CHILD = """
import json, sys
from kinefuse import cli
from kinefuse._kernel_mode import KERNEL_MODULES
sys.argv = ["kinefuse", "--help"]
try:
    cli.main()
except SystemExit:
    pass
heavy = ("numba", "matplotlib", "scipy.io", "scipy.signal", "scipy.spatial", "kinefuse.filters",
         "kinefuse.streaming", "kinefuse.batch", "kinefuse.evaluation.report", *KERNEL_MODULES)
print("RESULT:" + json.dumps([m for m in heavy if m in sys.modules]))
"""


def test_help_imports_no_numba_matplotlib_scipy_subpackages():
    # `kinefuse --help` stays fast, and `kinefuse demo` can still switch to interpreted kernels
    proc = subprocess.run(
        [sys.executable, "-c", _HELP_CHILD], capture_output=True, text=True, check=True, timeout=300
    )
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT:"))
    assert json.loads(line[len("RESULT:") :]) == []


def test_no_arguments_shows_help():
    result = runner.invoke(cli.app, [])
    assert "demo" in result.output + cli_stderr(result)


def test_version():
    result = runner.invoke(cli.app, ["--version"])
    assert result.exit_code == 0 and result.output.startswith("kinefuse ")


def test_usage_error_exits_2():
    assert runner.invoke(cli.app, ["demo", "--no-such-option"]).exit_code == 2
    assert runner.invoke(cli.app, ["no-such-command"]).exit_code == 2
    assert runner.invoke(cli.app, ["evaluate", "x.csv"]).exit_code == 2  # --method missing


def test_missing_session_file_exits_2(tmp_path):
    result = runner.invoke(cli.app, ["run", str(tmp_path / "nope.toml")])
    _assert_one_line_error(result, 2, "nope.toml", "session file not found", "init-session")


def test_invalid_session_exits_2_naming_key(tmp_path):
    p = tmp_path / "session.toml"
    p.write_text(session_template("x"), encoding="utf-8")
    result = runner.invoke(cli.app, ["run", str(p)])
    _assert_one_line_error(
        result, 2, "session.toml: [imu] path: file 'data/imu.csv' not found", "TOML's folder"
    )


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (
            ["evaluate", "missing.c3d", "--method", "paper-a"],
            "RECORDING missing.c3d: file not found",
        ),
        (["experiment", "paper-c"], "unknown experiment 'paper-c'"),
        (
            ["experiment", "paper-a", "--data", "no/such/dir"],
            "--data no/such/dir: folder not found",
        ),
        (["replay", "missing.csv"], "RECORDING missing.csv: file not found"),
    ],
)
def test_bad_input_exits_2_one_line(args, needle, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _assert_one_line_error(runner.invoke(cli.app, args), 2, needle)


def test_unknown_method_exits_2(tmp_path):
    rec = tmp_path / "rec.csv"
    rec.write_text("t\n0\n")
    result = runner.invoke(cli.app, ["evaluate", str(rec), "--method", "paper-z"])
    _assert_one_line_error(result, 2, "unknown method 'paper-z'", METHODS[0])


# ------------------------------------------------------------------------------------------
# back-ends: lazy import, errors mapped to exit codes
# ------------------------------------------------------------------------------------------


@pytest.fixture
def fake_backend(tmp_path, monkeypatch):
    """Point `bench` at a module written on the fly; returns a function writing its body."""
    monkeypatch.syspath_prepend(str(tmp_path))

    def make(body: str, name: str = "kf_fake_backend") -> None:
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(body), encoding="utf-8")
        sys.modules.pop(name, None)
        monkeypatch.setitem(cli.BACKENDS, "bench", (name, "run_bench"))

    yield make
    sys.modules.pop("kf_fake_backend", None)


def test_missing_backend_is_not_available_exit_1(monkeypatch):
    monkeypatch.setitem(cli.BACKENDS, "bench", ("kinefuse.no_such_module", "run_bench"))
    result = runner.invoke(cli.app, ["bench", "--quick"])
    _assert_one_line_error(
        result,
        1,
        "`kinefuse bench` is not available in this version",
        "kinefuse.no_such_module.run_bench",
    )


def test_backend_missing_function_exit_1(fake_backend):
    fake_backend("x = 1\n")
    _assert_one_line_error(runner.invoke(cli.app, ["bench"]), 1, "not available in this version")


def test_backend_missing_optional_dependency_exit_1(fake_backend):
    fake_backend("import kf_optional_dependency_that_is_absent\n")
    _assert_one_line_error(
        runner.invoke(cli.app, ["bench"]),
        1,
        "needs the optional package 'kf_optional_dependency_that_is_absent'",
    )


def test_backend_input_error_exit_2_and_debug_traceback(fake_backend):
    fake_backend(
        """
        from kinefuse.exceptions import FormatError
        def run_bench(quick):
            raise FormatError("rec.csv", "expected 7 columns, got 5", line=12)
        """
    )
    _assert_one_line_error(
        runner.invoke(cli.app, ["bench"]), 2, "rec.csv, line 12: expected 7 columns, got 5"
    )
    result = runner.invoke(cli.app, ["--debug", "bench"])
    assert result.exit_code == 2
    assert "Traceback" in cli_stderr(result) and "FormatError" in cli_stderr(result)


def test_backend_crash_exit_1_without_traceback(fake_backend):
    fake_backend(
        """
        def run_bench(quick):
            raise RuntimeError("matrix not positive definite\\nsecond line")
        """
    )
    _assert_one_line_error(
        runner.invoke(cli.app, ["bench"]),
        1,
        "RuntimeError: matrix not positive definite second line",
        "--debug",
    )


def test_backend_summary_json_quiet_and_target(fake_backend, tmp_path):
    fake_backend(
        """
        def run_bench(quick):
            return {"quick": quick, "speedup": 3.5, "passed": quick}
        """
    )
    out = tmp_path / "bench.json"
    result = runner.invoke(cli.app, ["bench", "--quick", "--quiet", "--json", str(out)])
    assert result.exit_code == 0 and result.output == ""
    assert json.loads(out.read_text()) == {"quick": True, "speedup": 3.5, "passed": True}
    result = runner.invoke(cli.app, ["bench"])  # passed = False: target not met
    _assert_one_line_error(result, 1, "target not met")
    assert "speedup: 3.5" in result.stdout


def test_json_to_missing_folder_exits_2(fake_backend, tmp_path):
    fake_backend("def run_bench(quick):\n    return {}\n")
    result = runner.invoke(cli.app, ["bench", "--json", str(tmp_path / "no" / "x.json")])
    _assert_one_line_error(result, 2, "does not exist")


def test_progress_helper():
    seen = []
    with cli.progress("work", total=3, quiet=True) as advance:
        for _ in range(3):
            seen.append(advance())
    with cli.progress("work", total=2) as advance:
        advance()
        advance(1)
    with cli.progress("spinner") as advance:
        advance()
    assert seen == [None, None, None]


# ------------------------------------------------------------------------------------------
# init-session and load_session
# ------------------------------------------------------------------------------------------


def test_init_session_template_loads_after_filling_paths(tmp_path):
    target = tmp_path / "trial.toml"
    result = runner.invoke(cli.app, ["init-session", str(target)])
    assert result.exit_code == 0, result.output
    assert "kinefuse run" in result.output
    text = target.read_text(encoding="utf-8")
    assert text.count("#") > 20  # commented
    for section in (
        "[session]",
        "[imu]",
        "[imu.segments]",
        "[skeleton]",
        "# [camera]",
        "# [reference]",
        "[method]",
    ):
        assert section in text
    with pytest.raises(
        ConfigError, match=r"trial\.toml: \[imu\] path: file 'data/imu.csv' not found"
    ):
        load_session(target)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "imu.csv").write_text("t\n")
    cfg = load_session(target)
    assert cfg.name == "trial" and cfg.method.name == "paper-a"
    assert cfg.imu.path == (tmp_path / "data" / "imu.csv").resolve()
    assert cfg.imu.segments == {"upper_arm_r": "IMU 1", "forearm_r": "IMU 2"}
    assert cfg.out_dir == (tmp_path / "results" / "trial").resolve()
    assert cfg.skeleton.body_height_m == 1.75 and cfg.camera is None and cfg.reference is None


def test_init_session_refuses_overwrite(tmp_path):
    target = tmp_path / "session.toml"
    target.write_text("keep me")
    result = runner.invoke(cli.app, ["init-session", str(target)])
    _assert_one_line_error(result, 2, str(target), "--force")
    assert target.read_text() == "keep me"
    assert runner.invoke(cli.app, ["init-session", str(target), "--force"]).exit_code == 0
    assert "[session]" in target.read_text()


def _session(
    tmp_path: Path, extra: str = "", *, method: str = "imu-only", imu: str = "imu.csv"
) -> Path:
    (tmp_path / "imu.csv").write_text("t\n")
    (tmp_path / "cam.csv").write_text("t\n")
    p = tmp_path / "s.toml"
    p.write_text(
        textwrap.dedent(
            f"""
            [session]
            name = "s"
            [imu]
            format = "csv"
            path = "{imu}"
            [imu.segments]
            forearm_r = "A"
            [skeleton]
            body_height_m = 1.8
            [method]
            name = "{method}"
            """
        )
        + textwrap.dedent(extra),
        encoding="utf-8",
    )
    return p


@pytest.mark.parametrize(
    ("kwargs", "extra", "message"),
    [
        (
            {"imu": "x.csv"},
            "",
            "s.toml: [imu] path: file 'x.csv' not found (looked for ",
        ),
        ({"method": "elm-fir"}, "", "s.toml: [method] name: method 'elm-fir' needs a camera"),
        (
            {"method": "paper-x"},
            "",
            "s.toml: [method] name: unknown method 'paper-x' (did you mean 'paper-a'?)",
        ),
        (
            {},
            "[camera]\nformat = 'kinect'\npath = 'cam.csv'\navailability_treshold = 2\n",
            "[camera] availability_treshold: unknown key (did you mean 'availability_threshold'?)",
        ),
        ({}, "[camera]\npath = 'cam.csv'\n", "s.toml: [camera] format: missing"),
        (
            {"method": "paper-b"},
            "",
            "[method] name: unknown method 'paper-b' (paper B's methods are 'elm-fir'",
        ),
        (
            {},
            "[calibration]\nfacing = 'south'\n",
            's.toml: [calibration] facing: expected "auto" or a horizontal direction [x, y, z]',
        ),
        ({}, "[calibration]\nfacing = [0, 0, 1]\n", "[calibration] facing: expected"),
        (
            {},
            "[reference]\nformat = 'c3d'\npath = 5\n",
            "[reference] path: expected a non-empty string, got 5",
        ),
    ],
)
def test_load_session_errors_name_key_and_fix(tmp_path, kwargs, extra, message):
    p = _session(tmp_path, extra, **kwargs)
    with pytest.raises(ConfigError) as info:
        load_session(p)
    assert message in str(info.value)


def test_missing_relative_path_names_the_path_looked_for(tmp_path):
    p = _session(tmp_path, imu="data/x.csv")
    with pytest.raises(ConfigError) as info:
        load_session(p)
    msg = str(info.value)
    assert f"looked for {tmp_path.resolve() / 'data' / 'x.csv'}" in msg or (
        f"looked for {tmp_path / 'data' / 'x.csv'}" in msg
    )
    assert "relative paths are resolved against the TOML's folder" in msg


def test_load_session_more_errors(tmp_path):
    p = _session(tmp_path)
    text = p.read_text()
    p.write_text(text.replace('forearm_r = "A"', 'forarm_r = "A"'))
    with pytest.raises(
        ConfigError,
        match=r"\[imu.segments\] 'forarm_r': unknown segment \(did you mean 'forearm_r'\?\)",
    ):
        load_session(p)
    p.write_text(text.replace("body_height_m = 1.8", "body_height_m = 180"))
    with pytest.raises(ConfigError, match="not a plausible body height"):
        load_session(p)
    p.write_text(text.replace("body_height_m = 1.8", 'body_height_m = "1.8"'))
    with pytest.raises(ConfigError, match="expected a number"):
        load_session(p)
    p.write_text(text + "\n[method\n")
    with pytest.raises(ConfigError, match="s.toml: not valid TOML"):
        load_session(p)
    p.write_text(text.replace("[skeleton]\nbody_height_m = 1.8\n", ""))
    with pytest.raises(ConfigError, match=r"\[skeleton\]: section missing"):
        load_session(p)


def test_load_session_full(tmp_path):
    extra = """
    [skeleton.lengths]
    forearm_r = 0.26
    [camera]
    format = "kinect"
    path = "cam.csv"
    availability_threshold = 2
    [reference]
    format = "csv"
    path = "cam.csv"
    [method.parameters]
    q = 0.1
    """
    p = _session(tmp_path, method="elm-fir")
    p.write_text(
        p.read_text().replace('[method]\nname = "elm-fir"\n', "")
        + textwrap.dedent(extra)
        + '[method]\nname = "elm-fir"\n'
    )
    cfg = load_session(p)
    assert (
        cfg.camera.availability_threshold == 2.0
        and cfg.camera.path == (tmp_path / "cam.csv").resolve()
    )
    assert cfg.skeleton.lengths_m == {"forearm_r": 0.26} and cfg.reference.format == "csv"
    assert cfg.method.name == "elm-fir"


def test_unknown_format_names_the_formats_not_the_aliases(tmp_path):
    from kinefuse.pipelines.run.streams import load_streams

    p = _session(tmp_path)
    p.write_text(p.read_text().replace('format = "csv"', 'format = "kinect_v3"'))
    with pytest.raises(ConfigError) as info:
        load_streams(load_session(p))
    msg = str(info.value)
    assert "[imu] format: unknown format 'kinect_v3' (did you mean 'kinect_v2'? known" in msg
    assert "xsens_dot" in msg and "asf-amc" not in msg and "gaittoolbox" not in msg


def test_load_session_accepts_the_stream_table(tmp_path):
    """One file for `kinefuse run` and `kinefuse stream` (README, docs/streaming.md): the
    offline loader leaves [stream] to the stream command, and still refuses unknown tables."""
    p = _session(tmp_path, '[stream]\nname_prefix = "x"\n')
    assert load_session(p).method.name == "imu-only"
    p = _session(tmp_path, '[streem]\nname_prefix = "x"\n')
    with pytest.raises(
        ConfigError, match=r"\[top level\] streem: unknown key \(did you mean 'stream'"
    ):
        load_session(p)


# ------------------------------------------------------------------------------------------
# demo and output-overwrite protection
# ------------------------------------------------------------------------------------------


def test_run_refuses_existing_report_before_running(tmp_path, monkeypatch):
    p = _session(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.html").write_text("old")
    monkeypatch.setitem(cli.BACKENDS, "run", ("kinefuse.no_such_module", "run_session"))
    _assert_one_line_error(
        runner.invoke(cli.app, ["run", str(p), "--out", str(out)]), 2, "report.html already exists"
    )
    # with --force it gets as far as the (missing) back-end
    _assert_one_line_error(
        runner.invoke(cli.app, ["run", str(p), "--out", str(out), "--force"]), 1, "not available"
    )


def test_demo_default_folder_never_overwrites(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "kinefuse-demo").mkdir()
    (tmp_path / "kinefuse-demo" / "report.html").write_text("old")
    assert cli._output.fresh_dir("kinefuse-demo") == Path("kinefuse-demo-2")


# ------------------------------------------------------------------------------------------
# the real console script and python -m
# ------------------------------------------------------------------------------------------


def _console_script() -> list[str]:
    exe = Path(sys.executable).parent / "kinefuse"
    if exe.is_file():
        return [str(exe)]
    found = shutil.which("kinefuse")
    return [found] if found else [sys.executable, "-m", "kinefuse"]


def test_console_script_bad_input_subprocess(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "KINEFUSE_DEBUG"}
    r = subprocess.run(
        [*_console_script(), "run", str(tmp_path / "missing.toml")],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert (
        len(lines) == 1 and lines[0].startswith("kinefuse: error: ") and "missing.toml" in lines[0]
    )
    assert "Traceback" not in r.stderr + r.stdout


def test_console_script_warnings_are_one_line_each(shared_data):
    """A reader's warning (a TRC whose header miscounts its frames) reaches the user as one
    `kinefuse: warning:` line, not Python's `file:line: FormatWarning:` and its source line."""
    trc = shared_data / "third_party" / "trc" / "pyomeca_markers.trc"
    env = {k: v for k, v in os.environ.items() if k not in ("KINEFUSE_DEBUG", "PYTHONWARNINGS")}
    r = subprocess.run(
        [*_console_script(), "evaluate", str(trc), "--method", "imu-only"],
        capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip
    assert r.returncode == 2, (r.stdout, r.stderr)  # no IMU in a marker file: an error after it
    # (on a machine whose kernels are not compiled yet, a note on that comes first: not a warning)
    notice = "The filter kernels are not compiled"
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith(notice)]
    assert lines[0].startswith("kinefuse: warning: ") and "NumFrames = 652" in lines[0], lines
    assert lines[1].startswith("kinefuse: error: ") and len(lines) == 2, lines
    assert "FormatWarning" not in r.stderr and ".py:" not in r.stderr


def test_python_dash_m(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "kinefuse", "--version"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0 and r.stdout.startswith("kinefuse ")


def test_bench_quick_runs_the_real_benchmark(tmp_path):
    """`kinefuse bench --quick`: filterpy and kinefuse side by side, targets listed, JSON written."""
    target = tmp_path / "bench.json"
    res = runner.invoke(cli.app, ["bench", "--quick", "--json", str(target)])
    assert res.exit_code in (0, 1), res.output  # 1 = a speed target missed on this machine
    assert "Targets (single core)" in res.output and "filterpy" in res.output
    data = json.loads(target.read_text())
    rows = {(r["case"], r["joints"]) for r in data["results"]["kf_rts"]}
    assert ("KF", 8) in rows and ("RTS", 8) in rows
    assert (res.exit_code == 0) == data["passed"]


# ---- first run on a machine without compiled kernels (issue 15) -------------------------------


def test_first_run_kernels_interprets_small_inputs_and_compiles_for_large(monkeypatch, tmp_path):
    from kinefuse import _kernel_mode
    from kinefuse.cli import offline
    from kinefuse.pipelines import warm_up as warm_up_mod

    small = tmp_path / "imu.csv"
    small.write_bytes(b"x" * 1000)
    calls = []
    monkeypatch.setattr(_kernel_mode, "kernels_cached", lambda: True)
    monkeypatch.setattr(_kernel_mode, "interpret_kernels", lambda: calls.append("interp") or True)
    monkeypatch.setattr(warm_up_mod, "warm_up", lambda report=None: calls.append("compile"))
    assert offline.first_run_kernels([small], quiet=True) == "compiled"
    assert calls == []
    monkeypatch.setattr(_kernel_mode, "kernels_cached", lambda: False)
    assert offline.first_run_kernels([small, tmp_path / "missing"], quiet=True) == "interpreted"
    assert calls == ["interp"]
    monkeypatch.setattr(_kernel_mode, "interpret_kernels", lambda: False)  # kernels loaded here
    assert offline.first_run_kernels([small], quiet=True) == "compiled"
    assert calls == ["interp"]  # no up-front compile for a small input
    monkeypatch.setattr(offline, "INTERPRET_MAX_BYTES", 999)
    assert offline.first_run_kernels([tmp_path], quiet=True) == "compile"  # a folder: 1000 B
    assert calls == ["interp"]  # compiling waits for the command's input checks
    offline.compile_kernels_now(quiet=True)
    assert calls == ["interp", "compile"]


def test_first_kinefuse_run_without_compiled_kernels_runs_interpreted(shared_data, tmp_path):
    """A fresh process with an empty numba cache: `kinefuse run` on the Neura walk runs the
    kernels interpreted (no compile) and writes the same files as the compiled back-end here."""
    from kinefuse.pipelines.run import run_session

    session = Path(__file__).parent / "data" / "sessions" / "neura_walk.toml"
    run_session(session, tmp_path / "compiled")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "empty-cache")}
    proc = subprocess.run(
        [sys.executable, "-m", "kinefuse", "run", str(session), "--out", str(tmp_path / "first")],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "run interpreted" in " ".join(proc.stderr.split())
    assert not list((tmp_path / "empty-cache").rglob("*.nbi"))  # nothing was compiled
    for name in ("neura-walk_joints.csv", "neura-walk_joints.trc", "neura-walk_orientations.sto"):
        assert (tmp_path / "first" / name).read_bytes() == (
            tmp_path / "compiled" / name
        ).read_bytes(), name


def test_run_given_a_recording_or_a_folder_says_how_to_make_a_session(tmp_path):
    rec = tmp_path / "walk.csv"
    rec.write_text("t,acc_x\n0,1\n", encoding="utf-8")
    result = runner.invoke(cli.app, ["run", str(rec)])
    _assert_one_line_error(result, 2, "walk.csv", "not valid TOML", "init-session", "--from")
    result = runner.invoke(cli.app, ["run", str(tmp_path)])
    _assert_one_line_error(result, 2, "a folder, not a session file", "--from")


def test_evaluate_unreadable_recording_fails_before_the_kernel_note(monkeypatch, tmp_path):
    from kinefuse import _kernel_mode

    bad = tmp_path / "rand.bin"
    bad.write_bytes(bytes(range(256)) * 4)
    monkeypatch.setattr(_kernel_mode, "kernels_cached", lambda: False)  # a first run ...
    monkeypatch.setattr(_kernel_mode, "interpret_kernels", lambda: True)  # ... interpreted
    result = runner.invoke(cli.app, ["evaluate", str(bad), "--method", "imu-only"])
    _assert_one_line_error(result, 2, "rand.bin: unsupported format")  # the note not printed


def test_one_sensor_mapped_to_two_segments_is_refused(tmp_path):
    p = _session(tmp_path)
    p.write_text(p.read_text().replace('forearm_r = "A"', 'forearm_r = "A"\nupper_arm_r = "A"'))
    with pytest.raises(
        ConfigError, match=r"sensor 'A' is mapped to 2 segments \(forearm_r, upper_arm_r\)"
    ):
        load_session(p)


def test_evaluate_errors_name_its_options_not_session_keys(shared_data):
    """`kinefuse evaluate` has --body-height, not [skeleton] body_height_m: its errors say so."""
    neura = str(shared_data / "neura_sparse_sample")
    _assert_one_line_error(
        runner.invoke(cli.app, ["evaluate", neura, "-m", "imu-only", "--body-height", "-1"]),
        2,
        "--body-height: expected metres (0.5-2.8), got -1",
    )
    args = ["evaluate", neura, "-m", "paper-a", "--calibration", "reference", "--root", "fixed"]
    line = _assert_one_line_error(runner.invoke(cli.app, args), 2, "give --body-height")
    assert "body_height_m" not in line


def test_evaluate_says_what_a_file_without_imu_holds(shared_data):
    mot = shared_data / "third_party" / "opensim" / "opensim_subject01_walk_IK.mot"
    line = _assert_one_line_error(
        runner.invoke(cli.app, ["evaluate", str(mot), "-m", "camera-only"]), 2, "no IMU data"
    )
    assert "joint angles" in line and "positions only" not in line


def test_a_forced_reader_that_fails_says_what_the_file_looks_like(shared_data):
    trc = shared_data / "third_party" / "trc" / "opensim_subject01_walk1.trc"
    line = _assert_one_line_error(
        runner.invoke(cli.app, ["evaluate", str(trc), "-m", "imu-only", "--format", "c3d"]),
        2,
        "expected a C3D header",
        "first bytes 0x50 0x61 (not a C3D file)",
        "(read as 'c3d', as asked; it looks like 'trc')",
    )
    assert "5061" not in line.replace("0x50 0x61", "")
