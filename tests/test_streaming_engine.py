"""Online engine (no LSL): equality with the offline causal computation, faults, checkpoints."""

from __future__ import annotations

import os
import pickle
import signal

import numpy as np
import pytest

from kinefuse.conventions import SOURCE_CAMERA, SOURCE_FUSED, SOURCE_IMU
from kinefuse.kinematics import full_body
from kinefuse.streaming.engine import Engine, EngineConfig
from kinefuse.streaming.engine_types import FLAG_CAMERA_MISSING, FLAG_FORCED, FLAG_IMU_STALE
from kinefuse.streaming.offline import offline_causal
from kinefuse.streaming.processors import (
    SOURCE_PREDICT,
    IntegratedProcessor,
    KalmanFusionProcessor,
)
from kinefuse.streaming.runner import run_loop

TOL = 1e-9
PROCESSORS = {
    "kf-fusion": lambda: KalmanFusionProcessor(1 / 30),
    "paper-a": lambda: IntegratedProcessor(1 / 30),
    "kf-fusion-lag5": lambda: KalmanFusionProcessor(1 / 30, lag=5),
}


@pytest.fixture(scope="module")
def rec():
    from kinefuse.streaming.replay import demo_recording

    return demo_recording(stop_s=4.0, seed=3)


def make_config(rec, **kw):
    return EngineConfig(
        full_body(height_m=1.75), camera_joints=rec.vision.joints, record=True, **kw
    )


def events(rec, *, imu_delay_s=0.0, drop=None, cam_shift=None):
    """Arrival-ordered sample events ``(arrival, order, kind, key, t, payload)``.

    ``drop(kind, key, t) -> bool`` removes samples; ``cam_shift(t) -> dt`` shifts camera stamps
    (a clock jump: frames still arrive at their true time).
    """
    ev = []
    for seg, st in rec.imu.items():
        for k in range(len(st)):
            t = float(st.t_s[k])
            if drop and drop("imu", seg, t):
                continue
            ev.append((t + imu_delay_s, 0, "imu", seg, t, st.q_world_from_sensor[k]))
    v = rec.vision
    for k in range(len(v)):
        t = float(v.t_s[k])
        if drop and drop("camera", "camera", t):
            continue
        ts = t + (cam_shift(t) if cam_shift else 0.0)
        ev.append((t, 1, "camera", "camera", ts, (v.position_m[k], v.available[k])))
    ev.sort(key=lambda e: (e[0], e[1]))
    return ev


def feed(engine, ev, flush=True):
    outs = []
    for arrival, _o, kind, key, t, payload in ev:
        if kind == "imu":
            engine.push_imu(key, t, payload, now=arrival)
        else:
            engine.push_camera(t, payload[0], payload[1], now=arrival)
        outs += engine.poll(arrival)
    if flush:
        outs += engine.flush()
    return outs


def offline_of(engine, make_processor, frame_times=None):
    cfg = engine.config
    imu = {}
    for s in cfg.segments:
        acc = engine.accepted["imu"][s]
        imu[s] = (np.array([a[0] for a in acc]), np.array([a[1] for a in acc]).reshape(-1, 4))
    cam = engine.accepted["camera"]
    camera = (
        np.array([c[0] for c in cam]),
        np.array([c[1] for c in cam]),
        np.array([c[2] for c in cam]),
    )
    if frame_times is None:
        frame_times = [f[0] for f in engine.accepted["frames"]]
    return offline_causal(cfg, make_processor(), imu, camera, frame_times=frame_times)


def assert_equal_offline(outs, off):
    pos = np.stack([o.position_m for o in outs])
    cov = np.stack([o.cov_m2 for o in outs])
    np.testing.assert_array_equal([o.t_s for o in outs], off.t_s)
    np.testing.assert_array_equal(np.isnan(pos), np.isnan(off.position_m))
    np.testing.assert_allclose(pos, off.position_m, atol=TOL, rtol=0)
    np.testing.assert_allclose(cov, off.cov_m2, atol=TOL, rtol=0)
    np.testing.assert_array_equal(np.stack([o.source for o in outs]), off.source)
    np.testing.assert_array_equal(np.stack([o.imu_status for o in outs]), off.imu_status)
    # the same per-frame code: the same flags (offline never forces a frame)
    flags = np.stack([o.flags for o in outs]) & ~np.uint8(FLAG_FORCED)
    np.testing.assert_array_equal(flags, off.flags)


@pytest.mark.parametrize("name", list(PROCESSORS))
def test_engine_equals_offline_causal(rec, name):
    eng = Engine(make_config(rec), PROCESSORS[name]())
    outs = feed(eng, events(rec, imu_delay_s=0.004))
    assert len(outs) == len(rec.vision)  # one output per camera frame, in order
    np.testing.assert_array_equal([o.t_s for o in outs], rec.vision.t_s)
    assert [o.index for o in outs] == list(range(len(outs)))
    assert eng.counters["forced_frames"] == 0 and eng.counters["synthesized_frames"] == 0
    # offline with its own frame rule (camera frames) equals the engine
    assert_equal_offline(outs, offline_of(eng, PROCESSORS[name], frame_times=None))


def test_sources_of_kf_fusion(rec):
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    outs = feed(eng, events(rec))
    src = np.stack([o.source for o in outs])
    j = rec.vision.joints
    avail = rec.vision.available[:, [j.index(n) for n in eng.config.joints]]
    assert np.all(src[avail] == SOURCE_FUSED)
    assert np.all(src[~avail] == SOURCE_IMU)  # IMU chain always valid here
    assert np.all(np.isfinite(np.stack([o.std_m for o in outs])))


def test_paused_imu_stream(rec):
    """forearm_r silent for 2 s: outputs continue, wrist_r flagged stale, nothing misaligned."""
    t0 = float(rec.vision.t_s[0])
    a, b = t0 + 1.0, t0 + 3.0

    def drop(kind, key, t):
        return kind == "imu" and key == "forearm_r" and a <= t < b

    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    outs = feed(eng, events(rec, drop=drop))
    t = np.array([o.t_s for o in outs])
    np.testing.assert_array_equal(t, rec.vision.t_s)  # every camera frame, on time
    jw, je = eng.config.joints.index("wrist_r"), eng.config.joints.index("elbow_r")
    flags = np.stack([o.flags for o in outs])
    src = np.stack([o.source for o in outs])
    stale = (t > a + eng.config.stale_after_s) & (t < b)
    assert np.all(flags[stale, jw] & FLAG_IMU_STALE)
    assert not np.any(flags[:, je] & FLAG_IMU_STALE)  # elbow_r hangs on upper_arm_r only
    assert np.all(np.isin(src[stale, jw], [SOURCE_CAMERA, SOURCE_PREDICT]))
    assert np.all(src[t > b + 0.05, jw] != SOURCE_PREDICT)
    kinds = [(e.kind, e.stream) for e in eng.events]
    assert ("stream_stale", "imu:forearm_r") in kinds and ("resumed", "imu:forearm_r") in kinds
    assert eng.counters["forced_frames"] > 0  # waited max_latency before giving up on it
    assert_equal_offline(outs, offline_of(eng, lambda: KalmanFusionProcessor(1 / 30)))


def test_paused_camera_synthesizes_frames(rec):
    t0 = float(rec.vision.t_s[0])
    a, b = t0 + 1.0, t0 + 3.0
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    outs = feed(eng, events(rec, drop=lambda kind, key, t: kind == "camera" and a <= t < b))
    t = np.array([o.t_s for o in outs])
    assert np.all(np.diff(t) > 0)
    gap = (t >= a) & (t < b)
    assert gap.sum() >= 55  # ~60 frames at 30 Hz; the last ones wait for the resumed camera
    np.testing.assert_allclose(np.diff(t[gap]), 1 / 30, atol=1e-9)
    flags = np.stack([o.flags for o in outs])
    assert np.all(flags[gap] & FLAG_CAMERA_MISSING)
    assert np.all(np.stack([o.source for o in outs])[gap] == SOURCE_IMU)
    assert eng.counters["camera_stale"] == 1 and eng.counters["resumed"] == 1
    assert_equal_offline(outs, offline_of(eng, lambda: KalmanFusionProcessor(1 / 30)))


def test_camera_clock_jump_is_a_gap(rec):
    """+500 ms jump of the camera clock: detected, reported, hole filled, never misaligned."""
    tj = float(rec.vision.t_s[60])
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    outs = feed(eng, events(rec, cam_shift=lambda t: 0.5 if t >= tj else 0.0))
    assert eng.counters["time_jump"] == 1
    assert any(e.kind == "time_jump" and e.stream == "camera" for e in eng.events)
    t = np.array([o.t_s for o in outs])
    assert np.all(np.diff(t) > 0) and np.max(np.diff(t)) < 1.5 / 30
    synth = np.array([bool(o.flags[0] & FLAG_CAMERA_MISSING) for o in outs])
    assert synth.sum() == 15  # the hole: 0.5 s of frames at 30 Hz
    # offline with its own hole rule equals the engine
    assert_equal_offline(
        outs, offline_of(eng, lambda: KalmanFusionProcessor(1 / 30), frame_times=None)
    )


def test_imu_clock_jump_not_interpolated(rec):
    tj = float(rec.vision.t_s[0]) + 2.0
    st = rec.imu["shank_l"]
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    ev = [e for e in events(rec) if not (e[3] == "shank_l")]
    for k in range(len(st)):  # shank_l stamps jump forward by 0.5 s at tj
        t = float(st.t_s[k])
        ev.append(
            (t, 0, "imu", "shank_l", t + (0.5 if t >= tj else 0.0), st.q_world_from_sensor[k])
        )
    ev.sort(key=lambda e: (e[0], e[1]))
    outs = feed(eng, ev)
    assert any(e.kind == "time_jump" and e.stream == "imu:shank_l" for e in eng.events)
    ja = eng.config.joints.index("ankle_l")
    t = np.array([o.t_s for o in outs])
    stat = np.stack([o.imu_status for o in outs])[:, ja]
    inside = (t > tj) & (t < tj + 0.5)
    assert np.all(stat[inside] > 0)  # held then stale inside the gap, never interpolated
    assert_equal_offline(outs, offline_of(eng, lambda: KalmanFusionProcessor(1 / 30)))


def test_duplicates_dropped_and_counted(rec):
    ev = events(rec)
    ref = feed(Engine(make_config(rec), KalmanFusionProcessor(1 / 30)), ev)
    dup = []
    for k, e in enumerate(ev):
        dup.append(e)
        if k % 7 == 0:
            dup.append((e[0] + 1e-4, *e[1:]))  # same timestamp, arrives again a bit later
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    outs = feed(eng, dup)
    assert eng.counters["duplicate"] + eng.counters["late"] == len(dup) - len(ev)
    assert eng.counters["duplicate"] > 0
    np.testing.assert_array_equal(
        np.stack([o.position_m for o in outs]), np.stack([o.position_m for o in ref])
    )


def test_out_of_order_reordered_or_dropped(rec):
    ev = events(rec, imu_delay_s=0.002)
    swapped = sorted(  # every 37th IMU sample arrives 15 ms late: after its successor
        (
            (e[0] + 0.015 if e[2] == "imu" and k % 37 == 0 else e[0], *e[1:])
            for k, e in enumerate(ev)
        ),
        key=lambda e: (e[0], e[1]),
    )
    late_t = float(rec.imu["chest"].t_s[5])
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30))
    outs = feed(eng, swapped, flush=False)
    n_before = eng.counters["late"]
    assert eng.push_imu("chest", late_t, rec.imu["chest"].q_world_from_sensor[5]) is False
    assert eng.counters["late"] == n_before + 1
    outs += eng.flush()
    assert eng.counters["reordered"] > 0
    t = [o.t_s for o in outs]
    np.testing.assert_array_equal(t, rec.vision.t_s)


@pytest.mark.parametrize("name", list(PROCESSORS))
def test_checkpoint_restore_continues_identically(rec, name):
    ev = events(rec, imu_delay_s=0.003)
    full = feed(Engine(make_config(rec), PROCESSORS[name]()), ev)
    half = len(ev) // 2
    eng = Engine(make_config(rec), PROCESSORS[name]())
    first = feed(eng, ev[:half], flush=False)
    blob = pickle.dumps(eng.checkpoint())
    eng2 = Engine(make_config(rec), PROCESSORS[name]())
    eng2.restore(pickle.loads(blob))
    second = feed(eng2, ev[half:])
    outs = first + second
    assert len(outs) == len(full)
    for a, b in zip(outs, full, strict=True):
        assert a.t_s == b.t_s and a.index == b.index
        np.testing.assert_array_equal(a.position_m, b.position_m)
        np.testing.assert_array_equal(a.cov_m2, b.cov_m2)
        np.testing.assert_array_equal(a.source, b.source)


def test_raw_imu_samples_use_vqf(rec):
    from kinefuse.orientation import estimate

    cfg = make_config(rec)
    eng_raw = Engine(cfg, KalmanFusionProcessor(1 / 30))
    eng_q = Engine(cfg, KalmanFusionProcessor(1 / 30))
    q_est = {s: estimate(st.acc_m_s2, st.gyr_rad_s, rate_hz=100.0) for s, st in rec.imu.items()}
    ev = events(rec)
    outs_raw, outs_q = [], []
    idx = {s: 0 for s in rec.imu}
    for arrival, _o, kind, key, t, payload in ev:
        if kind == "imu":
            k = idx[key]
            idx[key] += 1
            st = rec.imu[key]
            eng_raw.push_imu(key, t, acc=st.acc_m_s2[k], gyr=st.gyr_rad_s[k], now=arrival)
            eng_q.push_imu(key, t, q_est[key][k], now=arrival)
        else:
            eng_raw.push_camera(t, *payload, now=arrival)
            eng_q.push_camera(t, *payload, now=arrival)
        outs_raw += eng_raw.poll(arrival)
        outs_q += eng_q.poll(arrival)
    assert len(outs_raw) == len(outs_q) > 0
    for a, b in zip(outs_raw, outs_q, strict=True):
        np.testing.assert_allclose(a.position_m, b.position_m, atol=1e-12, rtol=0)


def test_no_camera_outputs_on_grid(rec):
    cfg = EngineConfig(full_body(height_m=1.75), camera=False, output_rate_hz=25.0, record=True)
    eng = Engine(cfg, IntegratedProcessor(1 / 25))
    ev = [e for e in events(rec) if e[2] == "imu"]
    outs = feed(eng, ev, flush=False)
    t = np.array([o.t_s for o in outs])
    np.testing.assert_allclose(np.diff(t), 1 / 25, atol=1e-9)
    assert t[0] == float(rec.imu["chest"].t_s[0]) and len(outs) >= 95
    off = offline_of(eng, lambda: IntegratedProcessor(1 / 25))
    assert_equal_offline(outs, off)


def test_no_camera_all_streams_stale_stops_at_the_clock(rec):
    """Without a camera, once every IMU stream is stale the frames go on at the output rate up
    to the clock, predicted, and stop there: poll used to synthesize frames without end (a
    live IMU-only stream hung once its sender stopped: --idle-timeout never came)."""
    cfg = EngineConfig(full_body(height_m=1.75), camera=False, output_rate_hz=25.0)
    eng = Engine(cfg, IntegratedProcessor(1 / 25))
    ev = [e for e in events(rec) if e[2] == "imu"]
    outs = feed(eng, ev, flush=False)
    last = max(b.last_t for b in eng._seg_list)
    more = eng.poll(last + 2.0)  # 2 s after the last sample, every stream stale
    t = np.array([o.t_s for o in outs + more])
    assert t[-1] <= last + 2.0 and len(more) <= 2.0 * 25 + 1
    np.testing.assert_allclose(np.diff(t), 1 / 25, atol=1e-9)
    stale = np.array([o.t_s > last + cfg.stale_after_s for o in more])
    assert stale.any() and all(
        np.all(o.source == SOURCE_PREDICT) for o, s in zip(more, stale, strict=True) if s
    )
    assert eng.poll(last + 2.0) == []  # nothing new at the same clock


@pytest.mark.parametrize("path", ["compiled", "grouped"])
def test_kf_fusion_matches_information_form(rng, path):
    """Oracle: a textbook stacked-measurement KF (numpy) per joint; three joints whose sensor
    cases differ within frames. Both code paths of the processor: the one-call compiled step
    and the grouped per-case fallback."""
    from kinefuse.models import constant_velocity

    dt, q, ri, rc = 1 / 30, 0.05, 4e-4, 9e-4
    T, J = 60, 3
    z_imu = np.cumsum(rng.normal(0, 0.01, (T, J, 3)), axis=0)
    z_cam = z_imu + rng.normal(0, 0.02, (T, J, 3))
    avail = rng.random((T, J)) > 0.3
    z_imu[10:14, 0] = np.nan
    z_imu[20:30, 2] = np.nan
    avail[25:28, 2] = False  # nothing at all: predict only
    proc = KalmanFusionProcessor(dt, q, ri, rc)
    if path == "grouped":
        proc._fast = None
    pos, cov, src = proc.run(np.arange(T) * dt, z_imu, z_cam, avail)
    m = constant_velocity(dt, q=q, r=1.0)
    F, Q, H = m.F, m.Q, m.H
    for j in range(J):
        x = None
        for k in range(T):
            rows, zs, rs = [], [], []
            if np.all(np.isfinite(z_imu[k, j])):
                rows.append(H), zs.append(z_imu[k, j]), rs.append(ri)
            if avail[k, j]:
                rows.append(H), zs.append(z_cam[k, j]), rs.append(rc)
            if x is None:  # first measurement initialises (positions, zero velocity)
                zc = (zs[0] / rs[0] + (zs[1] / rs[1] if len(zs) > 1 else 0)) / sum(
                    1 / r for r in rs
                )
                r_eq = 1 / sum(1 / r for r in rs)
                x = H.T @ zc
                P = H.T @ (r_eq * np.eye(3)) @ H + np.diag([0, 1, 0, 1, 0, 1.0])
            else:
                x, P = F @ x, F @ P @ F.T + Q
                if rows:
                    Hs = np.vstack(rows)
                    Rs = np.diag(np.repeat(rs, 3))
                    S = Hs @ P @ Hs.T + Rs
                    K = P @ Hs.T @ np.linalg.inv(S)
                    x = x + K @ (np.concatenate(zs) - Hs @ x)
                    IKH = np.eye(6) - K @ Hs
                    P = IKH @ P @ IKH.T + K @ Rs @ K.T
            np.testing.assert_allclose(pos[k, j], H @ x, atol=1e-9)
            np.testing.assert_allclose(cov[k, j], H @ P @ H.T, atol=1e-9)
    assert src[12, 0] in (SOURCE_CAMERA, SOURCE_PREDICT)
    assert src[26, 2] == SOURCE_PREDICT and src[22, 2] == SOURCE_CAMERA
    assert src[5, 1] in (SOURCE_FUSED, SOURCE_IMU)


class _ChunkInput:
    """A loop input handing out ``items`` (``events(rec)``) 25 at a time; a KeyboardInterrupt
    on pull number ``interrupt_at`` + 1 (never by default)."""

    lost = False

    def __init__(self, items, interrupt_at=None):
        self.items, self.interrupt_at = items, interrupt_at
        self.closed = False
        self.calls = 0

    def pull(self):
        self.calls += 1
        if self.interrupt_at is not None and self.calls > self.interrupt_at:
            raise KeyboardInterrupt
        chunk, self.items = self.items[:25], self.items[25:]
        return chunk, [e[4] for e in chunk]

    def feed(self, engine, data, ts, now):
        for e in data:
            if e[2] == "imu":
                engine.push_imu(e[3], e[4], e[5])
            else:
                engine.push_camera(e[4], *e[5])

    def refresh_clock(self):
        pass

    def close(self):
        self.closed = True


class _ListOutlet:
    """A loop outlet keeping what it is pushed; with ``sigint_at``, sends this process one
    SIGINT from inside that push (the main thread receives it there)."""

    def __init__(self, sigint_at=None):
        self.pushed, self.closed, self.sigint_at = [], False, sigint_at

    def push(self, o):
        if len(self.pushed) == self.sigint_at:
            self.sigint_at = None
            os.kill(os.getpid(), signal.SIGINT)
        self.pushed.append(o)

    def close(self):
        self.closed = True


def test_run_loop_ctrl_c_flushes_and_closes(rec):
    """KeyboardInterrupt in the loop: pending frames and the lagged outputs are pushed, inputs
    and outlet closed."""
    ev = events(rec)
    inp, outlet = _ChunkInput(ev, interrupt_at=40), _ListOutlet()
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30, lag=3))
    res = run_loop(eng, [inp], outlet, clock=lambda: eng._data_now)
    assert res.interrupted and inp.closed and outlet.closed
    n_cam = sum(1 for e in ev[: 40 * 25] if e[2] == "camera")
    assert len(outlet.pushed) == eng.counters["frames"] == n_cam  # nothing held back
    assert [o.index for o in outlet.pushed] == list(range(n_cam))


def test_run_loop_sigint_inside_a_pass_loses_no_frame(rec):
    """SIGINT while an output is being pushed (the engine has counted its frame): the loop
    takes it between passes, so that output and every pending frame are still pushed. Raised
    as a KeyboardInterrupt inside the push, that output was lost (outputs = frames - 1: the
    race tests/test_lsl.py::test_sigint_flushes_and_closes met once under load)."""
    inp, outlet = _ChunkInput(events(rec)), _ListOutlet(sigint_at=10)
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30, lag=3))
    # Python's own handler, as in a terminal (a background job, CI's, starts with SIG_IGN)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        res = run_loop(eng, [inp], outlet, clock=lambda: eng._data_now)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, before)
    assert res.interrupted and inp.closed and outlet.closed
    assert len(outlet.pushed) == eng.counters["frames"] > 10
    assert [o.index for o in outlet.pushed] == list(range(len(outlet.pushed)))


def test_run_loop_keeps_an_ignored_sigint_ignored(rec):
    """A process started with SIGINT ignored (nohup, a background job): the loop does not take
    it over; the stream runs to its end."""
    inp, outlet = _ChunkInput(events(rec)), _ListOutlet(sigint_at=10)
    eng = Engine(make_config(rec), KalmanFusionProcessor(1 / 30, lag=3))
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        res = run_loop(eng, [inp], outlet, clock=lambda: eng._data_now, idle_timeout_s=0.2)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
    assert not res.interrupted and len(outlet.pushed) == eng.counters["frames"] > 20


def test_replay_waits_for_every_reader_or_a_grace_after_the_first():
    """A consumer that reads only some streams (IMU-only capture, no camera) must not hold the
    replay for the whole --wait-for-consumers: after the first reader, CONSUMER_GRACE_S more."""
    from kinefuse.streaming.replay import CONSUMER_GRACE_S, wait_for_consumers

    class Clock:
        t = 0.0

        def __call__(self):
            return self.t

        def sleep(self, dt):
            self.t += dt

    class Outlet:
        def __init__(self, from_t):
            self.from_t = from_t

        def have_consumers(self):
            return clock.t >= self.from_t

    clock = Clock()
    some = [Outlet(1.0), Outlet(1.0), Outlet(np.inf)]  # the camera is never read
    assert wait_for_consumers(some, 60.0, clock=clock, sleep=clock.sleep) is False
    assert clock.t == pytest.approx(1.0 + CONSUMER_GRACE_S, abs=0.02)  # not 60 s
    clock.t = 0.0
    every = [Outlet(1.0), Outlet(1.5)]
    assert wait_for_consumers(every, 60.0, clock=clock, sleep=clock.sleep) is True
    assert clock.t == pytest.approx(1.5, abs=0.02)
    clock.t = 0.0
    assert wait_for_consumers([Outlet(np.inf)], 5.0, clock=clock, sleep=clock.sleep) is False
    assert clock.t == pytest.approx(5.0, abs=0.02)  # nobody: the whole timeout
