"""`kinefuse run` never loses a user's file (issue 12, cases 5-9): atomic result sets,
``--force`` the only way to replace anything, ``--json`` never over an input, outputs checked
writable before any processing, files with the user's umask, Ctrl-C at any time."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import test_session_run as _base
from conftest import ctrl_c_default
from kinefuse import cli
from kinefuse.exceptions import InputError
from kinefuse.io import read_joint_csv
from kinefuse.pipelines.run import run_session
from kinefuse.pipelines.run import write as session_mod  # run_session reads load_streams here

_err, _good, runner = _base._err, _base._good, _base.runner
synthetic_files = _base.synthetic_files  # the module-scoped fixture of the synthetic session

RESULTS = ("synthetic_joints.csv", "synthetic_joints.trc", "report.html", "metrics.json")


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` (relative path -> content)."""
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _no_processing(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("processing started although the outputs were not checked first")

    monkeypatch.setattr(session_mod, "load_streams", boom)


def _complete(folder: Path) -> bool:
    names = {p.name for p in folder.iterdir()}
    if not set(RESULTS) | {"figures"} <= names:
        return False
    rec = read_joint_csv(folder / "synthetic_joints.csv")
    return len(rec.vision) > 0 and (folder / "report.html").read_text().rstrip().endswith("</html>")


def _staging_left(root: Path) -> list[Path]:
    return [p for p in root.rglob(".kinefuse-*")]


@pytest.fixture(scope="module")
def previous(synthetic_files, tmp_path_factory):
    """A complete earlier result set (in-process run) to copy into each test."""
    out = tmp_path_factory.mktemp("previous") / "out"
    run_session(_good(synthetic_files), out)
    return _snapshot(out)


def _restore(snapshot: dict[str, bytes], folder: Path) -> None:
    for rel, data in snapshot.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(data)


# ------------------------------------------------------------------------------------ case 5
def test_json_never_targets_an_input_file(synthetic_files, tmp_path, monkeypatch):
    p = _good(synthetic_files)
    before = p.read_bytes()
    _no_processing(monkeypatch)
    for target in (p, synthetic_files / "imu.csv", synthetic_files / "truth.csv"):
        for extra in ([], ["--force"]):
            res = runner.invoke(
                cli.app,
                ["run", str(p), "--out", str(tmp_path / "o"), "--json", str(target)] + extra,
            )
            assert res.exit_code == 2, (res.output, _err(res))
            assert "is an input or a result of this run" in _err(res)
    assert p.read_bytes() == before
    assert not (tmp_path / "o").exists()
    # nor one of the run's own results (it would replace the joints CSV after writing it)
    out = tmp_path / "o"
    for name in ("synthetic_joints.csv", "metrics.json", "figures/x.json"):
        res = runner.invoke(cli.app, ["run", str(p), "--out", str(out), "--json", str(out / name)])
        assert res.exit_code == 2 and "result of this run" in _err(res), _err(res)


def test_json_never_overwrites_without_force(synthetic_files, tmp_path, monkeypatch):
    p = _good(synthetic_files)
    js = tmp_path / "summary.json"
    js.write_text("mine")
    with monkeypatch.context() as m:
        _no_processing(m)
        res = runner.invoke(
            cli.app, ["run", str(p), "--out", str(tmp_path / "o"), "--json", str(js)]
        )
        assert res.exit_code == 2 and "--force" in _err(res), (res.output, _err(res))
        assert js.read_text() == "mine" and not (tmp_path / "o").exists()
    res = runner.invoke(
        cli.app, ["run", str(p), "--out", str(tmp_path / "o"), "--json", str(js), "--force", "-q"]
    )
    assert res.exit_code == 0, (res.output, _err(res))
    assert js.read_text().startswith("{")


def test_json_of_other_commands_needs_force(tmp_path):
    js = tmp_path / "x.json"
    js.write_text("mine")
    res = runner.invoke(cli.app, ["evaluate", str(js), "--method", "paper-a", "--json", str(js)])
    assert res.exit_code == 2 and "input" in _err(res)
    res = runner.invoke(cli.app, ["bench", "--quick", "--json", str(js)])
    assert res.exit_code == 2 and "--force" in _err(res)
    assert js.read_text() == "mine"


def test_json_and_template_in_a_folder_that_refuses_files_are_exit_2_before_work(monkeypatch):
    """``/proc`` refuses new files even to root, whose permission checks all pass: `--json`
    there, or an init-session template, is one line and exit 2 before any work (the bench and
    the template writer must not be reached)."""
    from kinefuse.cli import offline

    monkeypatch.setattr(offline, "backend", lambda name: pytest.fail(f"{name} ran"))
    for args, label in (
        (["bench", "--quick", "--json", "/proc/kf.json"], "--json /proc/kf.json"),
        (["init-session", "/proc/kf.toml"], "PATH /proc/kf.toml"),
    ):
        res = runner.invoke(cli.app, args)
        err = [ln for ln in _err(res).splitlines() if ln.strip()]
        assert res.exit_code == 2 and len(err) == 1, (args, res.exit_code, err)
        assert f"{label}: not writable" in err[0], err


# ------------------------------------------------------------------------------------ case 6
@pytest.mark.parametrize("present", ["metrics.json", "figures", "synthetic_joints.trc"])
def test_any_earlier_result_needs_force(synthetic_files, tmp_path, monkeypatch, present):
    out = tmp_path / "out"
    out.mkdir()
    if present == "figures":
        (out / "figures").mkdir()
        (out / "figures" / "summary_rmse.png").write_bytes(b"old")
    else:
        (out / present).write_text("old")
    (out / "notes.txt").write_text("the user's own file")
    before = _snapshot(out)
    _no_processing(monkeypatch)
    res = runner.invoke(cli.app, ["run", str(_good(synthetic_files)), "--out", str(out)])
    assert res.exit_code == 2, (res.output, _err(res))
    assert present in _err(res) and "--force" in _err(res)
    assert _snapshot(out) == before


def test_force_replaces_the_whole_set_and_keeps_other_files(synthetic_files, tmp_path, previous):
    out = tmp_path / "out"
    _restore(previous, out)
    (out / "figures" / "stale.png").write_bytes(b"from an older run")
    (out / "notes.txt").write_text("the user's own file")
    run_session(_good(synthetic_files), out, force=True)
    assert _complete(out)
    assert not (out / "figures" / "stale.png").exists()  # a new set, not a mix
    assert (out / "notes.txt").read_text() == "the user's own file"
    assert _staging_left(tmp_path) == []


# ------------------------------------------------------------------------------------ case 7
@pytest.mark.parametrize("where", ["write_report", "write_trc"])
def test_failure_while_writing_leaves_previous_results(
    synthetic_files,
    tmp_path,
    previous,
    monkeypatch,
    where,
):
    out = tmp_path / "out"
    _restore(previous, out)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(session_mod, where, interrupted)  # the writer run_session calls
    with pytest.raises(KeyboardInterrupt):
        run_session(_good(synthetic_files), out, force=True)
    assert _snapshot(out) == previous
    assert _staging_left(tmp_path) == []
    # a fresh folder: nothing at all is left behind
    with pytest.raises(KeyboardInterrupt):
        run_session(_good(synthetic_files), tmp_path / "new" / "out")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("delay_s", [1.0, 3.0, 5.0])
def test_sigint_leaves_previous_or_complete_new_results(
    synthetic_files,
    tmp_path,
    previous,
    delay_s,
):
    out = tmp_path / "out"
    _restore(previous, out)
    # cli is the package src/kinefuse/cli/: parents[2] is src
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).parents[2])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "kinefuse", "run", str(_good(synthetic_files)), "--out", str(out),
         "--force", "-q"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, preexec_fn=ctrl_c_default,
    )  # fmt: skip
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    now = _snapshot(out)
    assert now == previous or (_complete(out) and now != previous), sorted(now)
    # the signal arrived (not ignored as in a background job): an interrupt (130; -SIGINT before
    # Python's handler exists), or a run that had finished
    interrupted = proc.returncode in (130, -signal.SIGINT)
    assert interrupted or (proc.returncode == 0 and now != previous), (proc.returncode, err)
    if delay_s == 1.0:  # a run takes several seconds: the first second is always interrupted
        assert interrupted, (proc.returncode, err)
    assert _staging_left(tmp_path) == []


# ------------------------------------------------------------------------------------ case 8
def test_unwritable_output_folder_is_exit_2_before_processing(
    synthetic_files,
    tmp_path,
    monkeypatch,
):
    _no_processing(monkeypatch)
    p = _good(synthetic_files)
    for out in ("/proc/kinefuse-out", "/proc/self/kinefuse-out/sub"):
        res = runner.invoke(cli.app, ["run", str(p), "--out", out])
        assert res.exit_code == 2, (res.output, _err(res))
        assert "not writable" in _err(res) or "cannot create" in _err(res), _err(res)
    # a folder the process may not write (root would ignore a chmod, so ask os.access)
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(
        os,
        "access",
        lambda path, mode: real(path, mode) and not (Path(path) == ro and mode & os.W_OK),
    )
    res = runner.invoke(cli.app, ["run", str(p), "--out", str(ro)])
    assert res.exit_code == 2 and "not writable" in _err(res), _err(res)
    file_out = tmp_path / "afile"
    file_out.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        run_session(p, file_out / "sub")


# ------------------------------------------------------------------------------------ case 9
@pytest.mark.parametrize("umask", [0o027])  # not the usual 022: the mode follows it
def test_outputs_get_the_users_umask(synthetic_files, tmp_path, umask):
    old = os.umask(umask)
    try:
        out = tmp_path / "out"
        run_session(_good(synthetic_files), out)
    finally:
        os.umask(old)
    want_file, want_dir = 0o666 & ~umask, 0o777 & ~umask
    for p in [out, *out.rglob("*")]:
        mode = p.stat().st_mode & 0o777
        assert mode == (want_dir if p.is_dir() else want_file), (p, oct(mode))


def test_ctrl_c_during_the_swap_is_held_until_the_new_set_is_in(tmp_path, monkeypatch):
    from kinefuse.io.output_folder import OutputFolder

    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    (out / "c.txt").write_text("old c, not written by the new run")
    stage = OutputFolder(out, ["a.txt", "b.txt", "c.txt"], force=True)
    (stage.path / "a.txt").write_text("new a")
    (stage.path / "b.txt").write_text("new b")
    real = os.rename
    calls = []

    def rename_then_ctrl_c(src, dst):
        if not calls:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of the swap
        calls.append(dst)
        return real(src, dst)

    monkeypatch.setattr(os, "rename", rename_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        stage.commit()
    assert len(calls) == 4  # 2 old out, 2 new in: all done before the interrupt
    assert {p.name: p.read_text() for p in out.iterdir()} == {"a.txt": "new a", "b.txt": "new b"}


def test_run_names_its_stages_as_it_goes(synthetic_files, tmp_path):
    """`kinefuse run` shows the stage on its progress bar (a long recording takes minutes)."""
    stages: list[str] = []
    run_session(_good(synthetic_files), tmp_path / "o", stage=stages.append)
    assert [s.split(" ")[0] for s in stages] == ["reading", "calibrating,", "writing", "writing"]
    assert stages[-1] == "writing the report"
    assert ".toml" not in stages[0]  # the recording's files, not the session's
