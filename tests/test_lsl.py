"""LSL adapters, replay and the live runner.

Network safety: every test that loads liblsl does so in a child process whose environment has
``LSLAPICFG`` pointing at a machine-local configuration written by the ``lsl_env`` fixture
(conftest.py) *before* the child imports pylsl (liblsl reads its configuration once per
process). The parent process never imports pylsl. Each test uses its own ``[lab] SessionID``
and stream names, so runs of other engineers on this machine cannot interfere. Every child has
a hard timeout.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from conftest import LSL_PRELUDE as _PRELUDE
from kinefuse.streaming.config import (
    LOCAL_SETTINGS,
    LSL_CONFIG_ENV,
    check_lsl_config,
    ensure_local_lsl_config,
    local_lsl_config_text,
    parse_lsl_config,
)

CHILD_TIMEOUT_S = 120


def _child(code: str, env: dict, timeout: float = CHILD_TIMEOUT_S, wrapper=()):
    return subprocess.run(
        [*wrapper, sys.executable, "-c", code],
        env=env, capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip


def _code(body: str) -> str:
    return _PRELUDE + textwrap.dedent(body)


def _result(proc):
    out = proc.stdout
    if "SKIP:" in out:
        pytest.skip("pylsl cannot load liblsl: " + out.split("SKIP:", 1)[1].strip())
    assert proc.returncode == 0, (
        f"child failed ({proc.returncode}):\n{out[-3000:]}\n{proc.stderr[-3000:]}"
    )
    line = [ln for ln in out.splitlines() if ln.startswith("RESULT:")]
    assert line, f"no result from the child:\n{out[-3000:]}\n{proc.stderr[-3000:]}"
    return json.loads(line[-1][len("RESULT:") :])


# ------------------------------------------------------------------------------ configuration
def test_local_config_text_has_the_machine_local_keys():
    text = local_lsl_config_text("kinefuse-x")
    for (section, key), value in LOCAL_SETTINGS.items():
        assert re.search(rf"\[{section}\][^\[]*\n{key} = {re.escape(value)}\n", text), (
            section,
            key,
        )
    assert "SessionID = kinefuse-x" in text and "KnownPeers = {127.0.0.1}" in text
    with pytest.raises(ValueError, match="session_id"):
        local_lsl_config_text("bad id with spaces")


def test_ensure_local_lsl_config_sets_env(tmp_path, monkeypatch):
    monkeypatch.delenv(LSL_CONFIG_ENV, raising=False)
    path = ensure_local_lsl_config(tmp_path, session_id="kinefuse-t")
    assert os.environ[LSL_CONFIG_ENV] == str(path) and path.parent == tmp_path
    info = check_lsl_config(path)
    assert info["local"], info["problems"]
    assert parse_lsl_config(path)[("multicast", "ResolveScope")] == "machine"
    # a user setting is respected, with a warning when it is not machine-local
    other = tmp_path / "lan.cfg"
    other.write_text("[multicast]\nResolveScope = site\n", encoding="utf-8")
    monkeypatch.setenv(LSL_CONFIG_ENV, str(other))
    with pytest.warns(UserWarning, match="not a machine-local"):
        assert ensure_local_lsl_config(tmp_path) == other
    assert not check_lsl_config(other)["local"]


def test_importing_kinefuse_streaming_does_not_load_pylsl(lsl_env):
    code = textwrap.dedent("""
    import sys, json
    import kinefuse.streaming, kinefuse.streaming.lsl, kinefuse.streaming.replay, kinefuse.streaming.runner
    print("RESULT:" + json.dumps({"pylsl": "pylsl" in sys.modules}))
    """)
    assert _result(_child(code, lsl_env["env"])) == {"pylsl": False}


def test_lsl_config_in_effect_and_traffic_stays_local(lsl_env):
    code = _code("""
    from kinefuse.streaming.lsl import make_outlet, resolve, Input
    out = make_outlet(os.environ["KINEFUSE_TEST_PREFIX"] + "_probe", "IMU",
                      [("qw", "1", "Orientation"), ("qx", "1", "Orientation"),
                       ("qy", "1", "Orientation"), ("qz", "1", "Orientation")], 100.0, source_id="probe")
    inp = Input.open("imu", "chest", os.environ["KINEFUSE_TEST_PREFIX"] + "_probe", timeout_s=10)
    inp.refresh_clock(first=True)
    import time
    for k in range(20):
        out.push_sample([1.0, 0.0, 0.0, 0.0], pylsl.local_clock())
    got, t_end = 0, time.monotonic() + 10
    while got < 20 and time.monotonic() < t_end:
        data, ts = inp.pull(); got += len(ts); time.sleep(0.01)
    inp.close()
    print("RESULT:" + json.dumps({"got": got, "info": pylsl.library_info(), "offset": inp.offset_s}))
    """)
    wrapper = ()
    trace = lsl_env["cfg"].parent / "strace.txt"
    if shutil.which("strace"):
        wrapper = ("strace", "-f", "-qq", "-e", "trace=connect,sendto,sendmsg", "-o", str(trace))
    res = _result(_child(code, lsl_env["env"], wrapper=wrapper))
    assert res["got"] == 20 and abs(res["offset"]) < 0.01
    log = lsl_env["log"].read_text(encoding="utf-8")
    assert f"Configuration loaded from {lsl_env['cfg']}" in log  # liblsl read our file
    if wrapper:  # every IPv4 destination is this machine (loopback) or unspecified
        addrs = set(re.findall(r'inet_addr\("([0-9.]+)"\)', trace.read_text()))
        assert addrs and all(a.startswith("127.") or a == "0.0.0.0" for a in addrs), addrs
        assert "AF_INET6" not in trace.read_text()


# ------------------------------------------------------------------------------ loopback
_LOOPBACK = (
    _PRELUDE
    + """
import threading, time
import numpy as np
from kinefuse.streaming import run_replay, run_stream, StreamConfig, offline_causal
from kinefuse.streaming.replay import demo_recording
prefix = os.environ["KINEFUSE_TEST_PREFIX"]
rec = demo_recording(stop_s=DATA_S, seed=1)
rep, res = {}, {}
replay = threading.Thread(target=lambda: rep.update(
    run_replay(rec, rate=5.0, name_prefix=prefix, wait_for_consumers_s=40)))
replay.start()
cfg = StreamConfig(name_prefix=prefix, max_latency_s=1.0, stale_after_s=1.0, resolve_timeout_s=20)
runner = threading.Thread(target=lambda: res.update(run_stream(
    cfg, status=False, idle_timeout_s=1.5, wait_for_reader_s=30, record=True, return_engine=True)))
runner.start()
found = pylsl.resolve_byprop("name", prefix + "_fused", 1, 30)
inlet = pylsl.StreamInlet(found[0]); inlet.open_stream(10)
rows, stamps = [], []
deadline = time.monotonic() + 90
while time.monotonic() < deadline:
    d, t = inlet.pull_chunk(timeout=0.2)
    rows += d; stamps += t
    if not runner.is_alive() and not t:
        break
runner.join(10); replay.join(10)
eng = res["engine"]
cfgE = eng.config
imu = {s: (np.array([a[0] for a in eng.accepted["imu"][s]]), np.array([a[1] for a in eng.accepted["imu"][s]]))
       for s in cfgE.segments}
cam = eng.accepted["camera"]
camera = (np.array([c[0] for c in cam]), np.array([c[1] for c in cam]), np.array([c[2] for c in cam]))
frames = [f[0] for f in eng.accepted["frames"]]
off = offline_causal(cfgE, eng.processor, imu, camera, frame_times=frames)
G = np.array(rows).reshape(len(rows), len(cfgE.joints), 8)
stamps = np.array(stamps)
n = min(len(stamps), len(frames))
same_nan = bool(np.array_equal(np.isnan(G[..., :3]), np.isnan(off.position_m[:len(G)])))
print("RESULT:" + json.dumps({
    "received": len(rows), "outputs": res["outputs"], "frames": len(frames),
    "camera_frames_sent": len(rec.vision), "camera_frames_accepted": len(cam),
    "camera_in_outputs": int(np.isin(camera[0], stamps).sum()),
    "in_order": bool(np.all(np.diff(stamps) > 0)),
    "stamps_equal_frames": bool(len(stamps) == len(frames) and np.array_equal(stamps, frames)),
    "max_pos_diff": float(np.nanmax(np.abs(G[..., :3] - off.position_m[:len(G)]))),
    "max_std_diff": float(np.nanmax(np.abs(G[..., 3:6] - np.sqrt(np.diagonal(off.cov_m2, axis1=-2, axis2=-1))[:len(G)]))),
    "same_nan": same_nan,
    "source_equal": bool(np.array_equal(G[..., 6].astype(int), off.source[:len(G)])),
    "imu_samples": {s: len(eng.accepted["imu"][s]) for s in cfgE.segments},
    "imu_sent": {s: len(st) for s, st in rec.imu.items()},
    "counters": res["counters"], "latency_ms": res["latency_ms"], "missing": res["missing"],
}))
"""
)


def test_loopback_replay_engine_outlet_equals_offline(lsl_env):
    """12 s of the virtual full-body recording at 5x: replay -> run_stream -> outlet -> reader."""
    proc = _child(_LOOPBACK.replace("DATA_S", "12.0"), lsl_env["env"])
    r = _result(proc)
    assert r["missing"] == []
    assert r["imu_samples"] == r["imu_sent"]  # nothing lost on the way in
    assert r["camera_frames_accepted"] == r["camera_frames_sent"]
    assert r["received"] == r["outputs"] == r["frames"]  # every output arrived once
    assert r["in_order"] and r["stamps_equal_frames"]
    assert r["camera_in_outputs"] == r["camera_frames_sent"]  # every camera frame got its output
    assert r["same_nan"] and r["source_equal"]
    assert r["max_pos_diff"] <= 1e-9 and r["max_std_diff"] <= 1e-9
    assert r["counters"]["late"] == 0 and r["counters"]["duplicate"] == 0


def test_inlet_reattaches_to_recreated_stream(lsl_env):
    code = _code("""
    import time
    from kinefuse.streaming.lsl import make_outlet, Input, IMU_CHANNELS
    name = os.environ["KINEFUSE_TEST_PREFIX"] + "_re"
    def outlet():
        return make_outlet(name, "IMU", list(IMU_CHANNELS), 100.0, source_id=name + "@src")
    def pull_until(inp, n, timeout):
        got, end = [], time.monotonic() + timeout
        while len(got) < n and time.monotonic() < end:
            d, t = inp.pull(); got += list(d[:, 0]) if len(t) else []; time.sleep(0.01)
        return got
    a = outlet()
    inp = Input.open("imu", "chest", name, timeout_s=10)
    for k in range(5):
        a.push_sample([1.0, 0, 0, 0], pylsl.local_clock())
    first = pull_until(inp, 5, 10)
    del a                                     # the sender stops ...
    time.sleep(0.5)
    b = outlet()                              # ... and restarts: same name and source id
    end = time.monotonic() + 20
    second = []
    while not second and time.monotonic() < end:
        b.push_sample([-1.0, 0, 0, 0], pylsl.local_clock())
        second = [v for v in pull_until(inp, 1, 0.2) if v == -1.0]
    inp.close()
    print("RESULT:" + json.dumps({"first": len(first), "second": len(second)}))
    """)
    r = _result(_child(code, lsl_env["env"]))
    assert r["first"] == 5 and r["second"] >= 1


def test_sigint_flushes_and_closes(lsl_env):
    # A child inherits an ignored or blocked SIGINT from its parent (Python then keeps it
    # ignored), which would make this test depend on what earlier tests did to the pytest
    # process: the child states its disposition and restores Python's default Ctrl-C.
    code = _code("""
    import faulthandler, signal, threading
    status = open("/proc/self/status").read().splitlines()
    print("SIGNALS:", signal.getsignal(signal.SIGINT),
          [l for l in status if l.startswith(("SigBlk", "SigIgn"))], file=sys.stderr, flush=True)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.default_int_handler)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    from kinefuse.streaming import run_replay, run_stream, StreamConfig
    from kinefuse.streaming.replay import demo_recording
    prefix = os.environ["KINEFUSE_TEST_PREFIX"]
    stop = threading.Event()
    rec = demo_recording(stop_s=3.0)
    threading.Thread(target=run_replay, args=(rec,), daemon=True,
                     kwargs=dict(rate=1.0, name_prefix=prefix, loop=True, stop_event=stop,
                                 wait_for_consumers_s=30)).start()
    cfg = StreamConfig(name_prefix=prefix, lag=3, resolve_timeout_s=20)
    def first(o):
        if o.index == 0:
            print("READY", flush=True)
    import kinefuse.streaming.runner as R
    orig = R.run_loop
    def loop(*a, **k):
        k["on_output"] = (lambda f: (lambda o: (f(o), first(o))))(k["on_output"])
        return orig(*a, **k)
    R.run_loop = loop
    s = run_stream(cfg, status=False, duration_s=60)
    stop.set()
    print("RESULT:" + json.dumps({k: s[k] for k in ("outputs", "frames", "interrupted")}))
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], env=lsl_env["env"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        t_end = time.monotonic() + 60
        lines = []
        while time.monotonic() < t_end:
            line = proc.stdout.readline()
            lines.append(line)
            if line.startswith("SKIP:"):
                proc.wait(10)
                pytest.skip(line)
            if line.startswith("READY") or not line:
                break
        assert lines and lines[-1].startswith("READY"), "".join(lines) + proc.stderr.read()
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGUSR1)  # the child's stacks, for the failure message
            time.sleep(1.0)
            proc.kill()
            out, err = proc.communicate(timeout=10)
            pytest.fail(f"no exit 30 s after SIGINT; child's stderr:\n{err[-6000:]}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    res = _result(
        subprocess.CompletedProcess(proc.args, proc.returncode, "".join(lines) + out, err)
    )
    assert res["interrupted"] is True
    assert res["outputs"] == res["frames"] > 10  # the 3 frames held by the lag were flushed too


def test_lost_and_timed_out_inlets_are_handled(lsl_env):
    """pylsl's LostError / TimeoutError (in pylsl.util) end as a 'lost' input, not a crash."""
    code = _code(
        """
        from kinefuse.streaming.lsl import Input
        class Lost:
            def samples_available(self):
                return 0                  # a lost stream shows nothing: found by the periodic full pull
            def pull_chunk(self, **kw):
                raise pylsl.util.LostError("the stream has been lost.")
            def time_correction(self, timeout):
                raise pylsl.util.TimeoutError("timeout")
        inp = Input.__new__(Input)
        inp.__dict__.update(inlet=Lost(), lost=False, name="x", n_samples=0, offset_s=0.0,
                            refresh_s=1.0, _next_refresh=0.0)
        data, ts = inp.pull()
        inp.clock = "manual"
        inp.refresh_clock(first=True)  # a time_correction timeout keeps the old offset
        print("RESULT:" + json.dumps({"lost": inp.lost, "n": len(ts)}))
        """
    )
    assert _result(_child(code, lsl_env["env"])) == {"lost": True, "n": 0}


def test_stream_that_goes_away_before_it_is_opened(lsl_env):
    """A stream resolved but gone when the inlets subscribe: an IMU stream -> reported missing
    (its joints predict-only), the run goes on; the camera -> a clear InputError."""
    code = _code("""
    import threading
    import kinefuse.streaming.lsl as L
    from kinefuse.exceptions import InputError
    from kinefuse.streaming import run_replay, run_stream, StreamConfig
    from kinefuse.streaming.replay import demo_recording
    prefix = os.environ["KINEFUSE_TEST_PREFIX"]
    stop = threading.Event()
    threading.Thread(target=run_replay, args=(demo_recording(stop_s=3.0),), daemon=True,
                     kwargs=dict(name_prefix=prefix, loop=True, stop_event=stop)).start()
    orig = L.Input.open.__func__
    gone = {"key": "shank_r"}
    def open_(cls, kind, key, name, **kw):
        if key == gone["key"]:
            raise pylsl.util.TimeoutError("the operation failed due to a timeout.")
        return orig(cls, kind, key, name, **kw)
    L.Input.open = classmethod(open_)
    cfg = StreamConfig(name_prefix=prefix, resolve_timeout_s=20)
    s = run_stream(cfg, status=False, duration_s=2.0)
    gone["key"] = "camera"
    try:
        run_stream(cfg, status=False, duration_s=2.0)
        err = None
    except InputError as exc:
        err = str(exc)
    stop.set()
    print("RESULT:" + json.dumps({"missing": s["missing"], "outputs": s["outputs"], "err": err}))
    """)
    r = _result(_child(code, lsl_env["env"]))
    assert r["missing"] == [f"{lsl_env['prefix']}_imu_shank_r"] and r["outputs"] > 10
    assert r["err"] is not None and "went away before it could be opened" in r["err"]


def test_wrong_prefix_error_names_the_streams_lsl_sees(lsl_env):
    """A session whose prefix matches no stream: the error lists what LSL sees on this machine
    and the prefix of its IMU streams (e.g. `kinefuse replay`'s default `kinefuse`)."""
    code = _code("""
    from kinefuse.exceptions import InputError
    from kinefuse.streaming import StreamConfig
    from kinefuse.streaming.lsl import IMU_CHANNELS, IMU_TYPE, make_outlet
    from kinefuse.streaming.runner import _resolve_inputs
    prefix = os.environ["KINEFUSE_TEST_PREFIX"]
    outlet = make_outlet(f"{prefix}_imu_thigh_l", IMU_TYPE, IMU_CHANNELS, 100.0)
    cfg = StreamConfig(name_prefix=prefix + "x", camera_stream="", resolve_timeout_s=1.0)
    try:
        _resolve_inputs(cfg)
        err = None
    except InputError as exc:
        err = str(exc)
    print("RESULT:" + json.dumps({"err": err}))
    """)
    err = _result(_child(code, lsl_env["env"]))["err"]
    p = lsl_env["prefix"]
    assert err.startswith(f"no IMU stream found within 1 s (looked for ['{p}x_imu_chest'"), err
    assert f"visible: {p}_imu_thigh_l" in err and f"prefix '{p}'" in err
    assert f"kinefuse replay --prefix {p}x" in err
