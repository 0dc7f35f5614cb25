"""`kinefuse replay` and `kinefuse stream` end to end, at the command line.

Network safety (as in test_lsl.py): every process that loads pylsl is a child started with the
``lsl_env`` environment (conftest.py), whose ``LSLAPICFG`` points at a fresh machine-local
configuration before liblsl loads; the pytest process never imports pylsl (bad input is
rejected before LSL is touched, checked below). Every child has a hard timeout and is killed in
``finally``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import LSL_PRELUDE, cli_stderr, ctrl_c_default
from kinefuse import cli

CHILD_TIMEOUT_S = 150
KINEFUSE = [sys.executable, "-m", "kinefuse"]  # src/kinefuse/__main__.py

runner = CliRunner()


def _one_line_error(stderr: str, *needles: str) -> str:
    # liblsl's own "Logging to <file>" notice (the test configuration logs to a file) aside
    lines = [ln for ln in stderr.splitlines() if ln.strip() and "loguru.cpp" not in ln]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("kinefuse: error: ") and "Traceback" not in stderr, stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def _start(args, env, log_dir, name, **kw):
    out = open(log_dir / f"{name}.out", "w", encoding="utf-8")  # closed by _stop
    err = open(log_dir / f"{name}.err", "w", encoding="utf-8")
    proc = subprocess.Popen(args, env=env, stdout=out, stderr=err, text=True, **kw)
    proc.files = (out, err)
    return proc


def _stop(proc) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)
    for f in proc.files:
        f.close()


def _text(log_dir, name) -> str:
    return "".join(
        f"--- {name}.{ext}\n" + (log_dir / f"{name}.{ext}").read_text(encoding="utf-8")[-3000:]
        for ext in ("out", "err")
    )


def _skip_if_no_lsl(log_dir) -> None:
    out = (log_dir / "reader.out").read_text(encoding="utf-8")
    if "SKIP:" in out:
        pytest.skip("pylsl cannot load liblsl: " + out.split("SKIP:", 1)[1].strip())


# A reader of PREFIX_fused: pulls until the test writes a line to its stdin (the stream process
# has ended), then drains what is still in flight, and saves the rows and timestamps.
_READER = LSL_PRELUDE + textwrap.dedent("""
    import select, time
    import numpy as np
    name, target = sys.argv[1] + "_fused", sys.argv[2]
    found = pylsl.resolve_byprop("name", name, 1, 120)
    assert found, f"{name} not found"
    inlet = pylsl.StreamInlet(found[0])
    inlet.open_stream(30)
    rows, stamps = [], []
    done_at, last_data = None, time.monotonic()
    deadline = time.monotonic() + 140
    while time.monotonic() < deadline:
        d, t = inlet.pull_chunk(timeout=0.2)
        if t:
            rows += d
            stamps += t
            last_data = time.monotonic()
        if done_at is None and select.select([sys.stdin], [], [], 0)[0]:
            sys.stdin.readline()
            done_at = time.monotonic()
        if done_at is not None and not t and time.monotonic() - max(done_at, last_data) > 1.5:
            break
    inlet.close_stream()
    np.savez(target, rows=np.array(rows, float).reshape(len(rows), -1), stamps=np.array(stamps))
    print("RESULT:" + json.dumps({"received": len(rows), "drained": done_at is not None}))
""")


def test_cli_replay_stream_loopback_60s(lsl_env, tmp_path):
    """`kinefuse replay demo` (60 s, 5x) -> `kinefuse stream` -> a reader: nothing lost, and the
    live outputs equal the causal batch computation on the recorded inputs.

    ``KINEFUSE_LOOPBACK_RATE=1`` replays at real time (60 s of wall time instead of 12 s)."""
    from kinefuse.streaming import offline_causal
    from kinefuse.streaming.runner import build_engine, stream_config

    rate = float(os.environ.get("KINEFUSE_LOOPBACK_RATE", "5"))
    timeout_s = CHILD_TIMEOUT_S + 60.0 / rate

    env, prefix = lsl_env["env"], lsl_env["prefix"]
    session = tmp_path / "live.toml"
    session.write_text(
        textwrap.dedent(f"""
        [stream]
        name_prefix = "{prefix}"
        max_latency_s = 1.0       # 5x replay on a loaded 2-core machine: nothing is forced
        stale_after_s = 1.0
        resolve_timeout_s = 30
        """),
        encoding="utf-8",
    )
    out, summary_json, replay_json = tmp_path / "live", tmp_path / "s.json", tmp_path / "r.json"
    replay_args = [
        *KINEFUSE,
        "replay",
        "demo",
        "--loop",
        "--duration",
        "60",
        "--rate",
        str(rate),
        "--prefix",
        prefix,
        "--wait-for-consumers",
        "60",
        "--json",
        str(replay_json),
    ]
    stream_args = [*KINEFUSE, "stream", str(session), "--idle-timeout", "2", "--out", str(out),
                   "--record-inputs", "--no-status", "--wait-for-reader", "30",
                   "--json", str(summary_json)]  # fmt: skip
    reader_args = [sys.executable, "-c", _READER, prefix, str(tmp_path / "reader.npz")]
    procs = {}
    try:
        procs["replay"] = _start(replay_args, env, tmp_path, "replay")
        procs["stream"] = _start(stream_args, env, tmp_path, "stream")
        procs["reader"] = _start(reader_args, env, tmp_path, "reader", stdin=subprocess.PIPE)
        t_end = time.monotonic() + timeout_s
        for name in ("stream", "replay"):
            try:
                procs[name].wait(max(1.0, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                _skip_if_no_lsl(tmp_path)
                pytest.fail(f"{name} did not finish:\n" + _text(tmp_path, name))
        reader = procs["reader"]
        if reader.poll() is None:
            reader.stdin.write("done\n")
            reader.stdin.flush()
        reader.wait(max(1.0, t_end - time.monotonic()))
    finally:
        for p in procs.values():
            _stop(p)
    _skip_if_no_lsl(tmp_path)
    for name, p in procs.items():
        assert p.returncode == 0, f"{name} exited {p.returncode}:\n" + _text(tmp_path, name)
    assert "kinefuse stream" in (tmp_path / "stream.out").read_text(encoding="utf-8")  # table
    assert "samples pushed" in (tmp_path / "replay.out").read_text(encoding="utf-8")

    rep = json.loads(replay_json.read_text(encoding="utf-8"))
    res = json.loads(summary_json.read_text(encoding="utf-8"))
    got = np.load(tmp_path / "reader.npz")
    rec = np.load(out.with_suffix(".npz"))
    assert (
        json.loads(out.with_suffix(".json").read_text(encoding="utf-8"))["outputs"]
        == res["outputs"]
    )
    assert rep["recording_s"] == pytest.approx(60.0) and not rep["interrupted"]
    assert res["missing"] == [] and not res["interrupted"]

    # every output reached the reader once, in order, stamped with its frame time
    frame_t, stamps = rec["frame_t"], got["stamps"]
    assert res["outputs"] == res["frames"] == len(frame_t) == len(stamps) > 1500
    assert np.all(np.diff(stamps) > 0)
    assert np.array_equal(stamps, frame_t) and np.array_equal(rec["t_s"], frame_t)

    # nothing lost on the way in: every pushed sample was accepted
    segments = [str(s) for s in rec["segments"]]
    for seg in segments:
        assert len(rec[f"imu_{seg}_t"]) == rep["samples"][f"{prefix}_imu_{seg}"], seg
    assert len(rec["camera_t"]) == rep["samples"][f"{prefix}_camera"]
    assert set(rep["samples"]) == {f"{prefix}_imu_{s}" for s in segments} | {f"{prefix}_camera"}
    c = res["counters"]
    assert c["late"] == c["duplicate"] == c["forced_frames"] == 0, c

    # the live outputs equal the causal batch computation on the recorded inputs
    cam_rate, imu_rates = (
        float(rec["camera_rate_hz"]),
        dict(zip(segments, rec["imu_rate_hz"], strict=True)),
    )
    assert cam_rate == pytest.approx(30 * rate) and all(
        r == pytest.approx(100 * rate) for r in imu_rates.values()
    )
    engine = build_engine(stream_config(session), camera=True, camera_rate_hz=cam_rate,
                          imu_rate_hz=imu_rates)  # fmt: skip
    cfg = engine.config
    assert tuple(rec["camera_joints"]) == cfg.camera_joints and tuple(rec["joints"]) == cfg.joints
    imu = {s: (rec[f"imu_{s}_t"], rec[f"imu_{s}_q"]) for s in segments}
    camera = (rec["camera_t"], rec["camera_position_m"], rec["camera_available"])
    off = offline_causal(cfg, engine.processor, imu, camera, frame_times=frame_t)
    assert np.array_equal(off.synthesized, rec["frame_synthesized"])
    rows = got["rows"].reshape(len(stamps), len(cfg.joints), 8)
    std = np.sqrt(np.diagonal(off.cov_m2, axis1=-2, axis2=-1))
    for live, batch in ((rows[..., :3], off.position_m), (rows[..., 3:6], std)):
        assert np.array_equal(np.isnan(live), np.isnan(batch))
        assert np.nanmax(np.abs(live - batch)) <= 1e-9
    assert np.array_equal(rows[..., 6].astype(int), off.source)
    assert np.array_equal(rec["position_m"], rows[..., :3], equal_nan=True)  # the --out file
    assert len(np.unique(off.source)) > 1  # camera outages: more than one source was used
    assert "pylsl" not in sys.modules


def test_cli_stream_accepts_offline_session(lsl_env, tmp_path):
    """An offline session from `kinefuse init-session` (paper A: static calibration, a fixed
    shoulder) is refused before LSL, naming what the online engine would ignore; without them
    it is accepted, and with no streams around it ends with exit 2 and one line: the IMU
    streams were not found within the timeout, and what LSL sees instead."""
    session = tmp_path / "trial.toml"
    assert runner.invoke(cli.app, ["init-session", str(session)]).exit_code == 0
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "imu.csv").write_text("t\n", encoding="utf-8")
    result = runner.invoke(cli.app, ["stream", str(session), "--no-status"])
    assert result.exit_code == 2, result.output
    _one_line_error(cli_stderr(result), "trial.toml: kinefuse stream cannot honour",
                    "calibration 'static'", "root 'fixed'", "kinefuse run")  # fmt: skip
    assert "pylsl" not in sys.modules
    text = session.read_text(encoding="utf-8")
    text = text.replace('root = "fixed"', "").replace('method = "static"', 'method = "none"')
    session.write_text(text.replace("root_position_m = [0.0, 0.0, 0.0]", ""), encoding="utf-8")
    proc = subprocess.run(
        [*KINEFUSE, "stream", str(session), "--duration", "1", "--resolve-timeout", "1",
         "--no-status"],
        env=lsl_env["env"], capture_output=True, text=True, timeout=CHILD_TIMEOUT_S,
    )  # fmt: skip
    if proc.returncode == 1 and "Lab Streaming Layer is not available" in proc.stderr:
        pytest.skip("pylsl cannot load liblsl: " + proc.stderr.strip())
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    # the session's name is the prefix; it has no [camera], so only IMU streams are looked for
    _one_line_error(proc.stderr, "no IMU stream found within 1 s", "'trial_imu_", "visible")


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["replay", "missing.csv"], ["RECORDING missing.csv: file not found"]),
        (["replay", "rand.bin"], ["rand.bin: unsupported format"]),  # before "Publishing"
        (["replay", "demo", "--rate", "0"], ["--rate", "> 0"]),
        (["replay", "demo", "--duration", "-1"], ["--duration", "> 0"]),
        (["replay", "demo", "--format", "nope"], ["--format: unknown reader 'nope'"]),
        # an IMU with acc/gyr only: --no-raw would publish nothing (refused, no "Publishing")
        (["replay", "raw.csv", "--no-raw"], ["--no-raw", "IMU 'thigh_r' has no orientation"]),
        (
            ["stream", "bad.toml"],
            ["bad.toml: [stream] bogus: unknown key (allowed keys: name_prefix, imu_streams,"],
        ),
        (
            ["stream", "typo.toml"],
            ["typo.toml: [stream] name_prefx: unknown key (did you mean 'name_prefix'?)"],
        ),
        (["stream", "notab.toml"], ["notab.toml: [stream]: expected a table, got int"]),
        (["stream", "broken.toml"], ["broken.toml: not valid TOML"]),
        (["stream", "missing.toml"], ["missing.toml: file not found"]),
        (["stream", "s.toml", "--out", "existing"], ["existing.npz already exists", "--force"]),
        (
            ["stream", "s.toml", "--out", "/proc/kf-live/out"],
            ["--out /proc/kf-live", "not writable"],
        ),
        (["stream", "s.toml", "--out", "existing.npz/sub/out"], ["existing.npz", "not a folder"]),
        (["stream", "s.toml", "--record-inputs"], ["--record-inputs needs --out"]),
        (
            ["stream", "s.toml", "--chain", "c.json"],
            ["--chain c.json: SESSION.toml s.toml is a streaming session", "[stream] table"],
        ),
        (["stream", "s.toml", "--idle-timeout", "0"], ["--idle-timeout", "> 0"]),
        (["stream", "s.toml", "--view", "--view-port", "70000"], ["--view-port", "[0, 65535]"]),
    ],
)
def test_cli_stream_replay_bad_input_exits_2_before_lsl(args, needles, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "s.toml").write_text('[stream]\nname_prefix = "kftest_unused"\n')
    (tmp_path / "bad.toml").write_text('[stream]\nname_prefix = "x"\nbogus = 1\n')
    (tmp_path / "typo.toml").write_text('[stream]\nname_prefx = "x"\n')
    (tmp_path / "notab.toml").write_text("stream = 1\n")
    (tmp_path / "broken.toml").write_text("[stream\n")
    (tmp_path / "existing.npz").write_bytes(b"keep me")
    (tmp_path / "rand.bin").write_bytes(bytes(range(256)) * 4)
    rows = "".join(f"{k / 100:.2f},thigh_r,0,0,9.81,0,0,0\n" for k in range(3))
    (tmp_path / "raw.csv").write_text(
        "# kinefuse-imu-csv 1\nt_s,sensor,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z\n" + rows
    )
    result = runner.invoke(cli.app, args)
    assert result.exit_code == 2, (result.output, cli_stderr(result))
    _one_line_error(cli_stderr(result), *needles)
    assert (tmp_path / "existing.npz").read_bytes() == b"keep me"
    assert not (tmp_path / "existing.json").exists()
    assert "pylsl" not in sys.modules  # rejected before LSL was touched


@pytest.mark.parametrize(
    ("command", "options"),
    [
        ("replay", ["--rate", "--prefix", "--loop", "--duration", "--no-raw", "--format",
                    "--wait-for-consumers", "--quiet", "--json", "_imu_", "_camera", "MoCap"]),
        ("stream", ["--duration", "--idle-timeout", "--resolve-timeout", "--out", "--force",
                    "--record-inputs", "--wait-for-reader", "--no-status", "--quiet", "--json",
                    "_fused", "--view", "--view-port", "127.0.0.1"]),
    ],
)  # fmt: skip
def test_cli_stream_replay_help(command, options):
    result = runner.invoke(cli.app, [command, "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    for option in options:
        assert option in result.output, option


def test_cli_stream_help_lists_every_published_channel():
    """The help names each channel family of the fused and joint-angle outlets as the code
    builds them (kinefuse.streaming.lsl), and every joint that has angles."""
    from kinefuse.kinematics.angles import JOINTS
    from kinefuse.streaming.lsl import angle_channels, output_channels

    result = runner.invoke(cli.app, ["stream", "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    fused = [label for label, *_ in output_channels(["JOINT"]) if label[-2:] not in ("_y", "_z")]
    assert fused == ["JOINT_x", "JOINT_std_x", "JOINT_source", "JOINT_flags"]
    for label in fused:
        assert label in text, label
    for joint in dict.fromkeys(j.removesuffix("_l").removesuffix("_r") for j in JOINTS):
        assert joint in text, joint
        first, *others = [label for label, *_ in angle_channels([joint])]
        assert (first if joint == "trunk" else first.replace(joint, "JOINT")) in text, first
        for label in others:
            assert label.removeprefix(joint) in text, label


def _view_url(log_dir, proc, timeout_s: float) -> str | None:
    """The live view's address from the stream's stderr (None if it ends or times out)."""
    import re

    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end and proc.poll() is None:
        m = re.search(
            r"live view at (http://127\.0\.0\.1:\d+/)",
            (log_dir / "stream.err").read_text(encoding="utf-8"),
        )
        if m:
            return m.group(1)
        time.sleep(0.2)
    return None


def test_cli_stream_view_in_chromium(lsl_env, tmp_path):
    """`kinefuse stream --view` during a loopback replay: two pages in headless Chromium
    receive and draw frames, one is closed mid-stream, and the stream loses, repeats or
    forces no sample meanwhile; Ctrl-C ends the replay, and the stream still gets every sample
    the replay counts."""
    from _chromium import browser, canvas_stats, color_fraction

    env, prefix = lsl_env["env"], lsl_env["prefix"]
    session = tmp_path / "live.toml"
    session.write_text(
        f'[stream]\nname_prefix = "{prefix}"\nmax_latency_s = 1.0\nstale_after_s = 1.0\n'
        "resolve_timeout_s = 30\n",
        encoding="utf-8",
    )
    out, summary_json, replay_json = tmp_path / "live", tmp_path / "s.json", tmp_path / "r.json"
    replay_args = [*KINEFUSE, "replay", "demo", "--loop", "--duration", "60", "--rate", "2",
                   "--prefix", prefix, "--wait-for-consumers", "60", "--json", str(replay_json)]  # fmt: skip
    stream_args = [*KINEFUSE, "stream", str(session), "--idle-timeout", "2", "--out", str(out),
                   "--record-inputs", "--no-status", "--view", "--json", str(summary_json)]  # fmt: skip
    procs = {}
    seen = {}
    # the browser starts before the streams, and the replay lasts up to 30 s: a cold Chromium
    # start (seen taking longer than 10 s in CI), or the pages' steps on a machine busy with the
    # other test worker (a 10 s replay ended before the second page saw 10 more frames), must
    # not outlast the stream they are to watch. Once the pages are checked, Ctrl-C ends it.
    with browser() as (ctx, log):
        first, second = ctx.new_page(), ctx.new_page()
        try:
            procs["replay"] = _start(
                replay_args, env, tmp_path, "replay", preexec_fn=ctrl_c_default
            )
            procs["stream"] = _start(stream_args, env, tmp_path, "stream")
            url = _view_url(tmp_path, procs["stream"], CHILD_TIMEOUT_S)
            if url is None:
                _skip_if_no_lsl_stream(tmp_path)
                pytest.fail("no live view address:\n" + _text(tmp_path, "stream"))
            assert url.startswith("http://127.0.0.1:")
            t0 = time.monotonic()
            first.goto(url)
            first.wait_for_function("window.kfViewer && kfViewer.frames > 0", timeout=5_000)
            seen["first_frame_s"] = time.monotonic() - t0
            second.goto(url)
            second.wait_for_function("kfViewer.frames > 0", timeout=5_000)
            first.wait_for_function("kfViewer.framesDrawn > 5", timeout=5_000)
            shot = first.locator("#kf-viewer").screenshot(path=tmp_path / "live_view.png")
            seen["first"] = first.evaluate("kfViewer.frames")
            seen["sources"] = first.locator("#kf-joint-sources td").all_inner_texts()
            seen["latency"] = first.locator("#kf-latency").inner_text()
            first.close()  # one viewer leaves mid-stream
            n2 = second.evaluate("kfViewer.frames")
            second.wait_for_function(f"kfViewer.frames > {n2 + 10}", timeout=10_000)
            seen["second"] = second.evaluate("kfViewer.frames")
            canvas2 = second.locator("#kf-viewer canvas").screenshot()
            print(f"\nlive view screenshot: {tmp_path / 'live_view.png'}; first frame after "
                  f"{seen['first_frame_s']:.2f} s; frames seen {seen['first']} / {seen['second']}")  # fmt: skip
            procs["replay"].send_signal(signal.SIGINT)  # the stream ends 2 s after its last input
            for name in ("stream", "replay"):
                procs[name].wait(CHILD_TIMEOUT_S)
        finally:
            for p in procs.values():
                _stop(p)
    for name, p in procs.items():
        assert p.returncode == 0, f"{name} exited {p.returncode}:\n" + _text(tmp_path, name)
    assert log["errors"] == [] and log["blocked"] == []
    for png in (shot, canvas2):  # the skeleton's bones (not only the floor grid) are drawn
        stats = canvas_stats(png)
        assert stats["non_white"] > 0.02 and color_fraction(stats["pixels"], "#332288") > 2e-4
    joints_sources = seen["sources"][1::2]
    assert joints_sources and all(s != "–" for s in joints_sources), seen["sources"]
    assert seen["latency"].endswith("ms)"), seen["latency"]

    rep = json.loads(replay_json.read_text(encoding="utf-8"))
    res = json.loads(summary_json.read_text(encoding="utf-8"))
    rec = np.load(out.with_suffix(".npz"))
    c = res["counters"]
    assert c["late"] == c["duplicate"] == c["forced_frames"] == 0, c
    assert res["outputs"] == res["frames"] == len(rec["frame_t"]) and not res["missing"]
    assert rep["interrupted"] or rep["recording_s"] == 60.0, rep  # Ctrl-C, unless it had ended
    segments = [str(s) for s in rec["segments"]]
    for seg in segments:  # every pushed sample was accepted while the pages were open
        assert len(rec[f"imu_{seg}_t"]) == rep["samples"][f"{prefix}_imu_{seg}"], seg
    assert len(rec["camera_t"]) == rep["samples"][f"{prefix}_camera"]
    assert res["view"]["published"] == res["outputs"]
    assert res["view_url"] == url


def _skip_if_no_lsl_stream(log_dir) -> None:
    err = (log_dir / "stream.err").read_text(encoding="utf-8")
    if "Lab Streaming Layer is not available" in err:
        pytest.skip("pylsl cannot load liblsl: " + err.strip()[-300:])
