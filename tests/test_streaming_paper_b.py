"""Paper B online (VisionAssistedProcessor): step == vision_assisted(causal=True), engine, checkpoints."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_FUSED, SOURCE_IMU, SOURCE_PREDICTED
from kinefuse.exceptions import InputError
from kinefuse.kinematics import full_body
from kinefuse.pipelines import VisionParams, vision_assisted
from kinefuse.streaming.engine import Engine, EngineConfig
from kinefuse.streaming.offline import offline_causal
from kinefuse.streaming.paper_b import VisionAssistedProcessor
from kinefuse.streaming.processors import Processor

DT = 1 / 30
TOL = 1e-9


def make_scenario(seed: int = 5, T: int = 1200, J: int = 5):
    """Smooth 3-D joints; IMU = truth + offset + noise; camera outages of several kinds.

    Joint 0: outage at the very start, then a long one; joint 1: back-to-back outages (gap
    < N, one episode) and one a few frames after the recovery; joint 2: random dropouts of
    single frames (short available runs); joint 3: sparse camera (available in bursts), so the
    training window spans far more than W frames; joint 4: IMU rows missing, never-ending outage.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    truth = np.zeros((T, J, 3))
    for j in range(J):
        for k in range(3):
            f = rng.uniform(0.05, 0.3, 3)
            ph = rng.uniform(0, 2 * np.pi, 3)
            a = rng.uniform(0.05, 0.2, 3)
            truth[:, j, k] = (a * np.sin(2 * np.pi * f * t[:, None] + ph)).sum(axis=1)
    offset = rng.choice([-0.06, 0.06], (1, J, 3)) + 0.01 * np.sin(t / 7)[:, None, None]
    z_imu = truth + offset + rng.normal(0, 0.01, (T, J, 3))
    z_cam = truth + rng.normal(0, 0.02, (T, J, 3))
    av = np.ones((T, J), dtype=bool)
    av[:30, 0] = False
    av[500:620, 0] = False
    av[300:320, 1] = False
    av[325:360, 1] = False  # 5 available frames in between: merged
    av[380:400, 1] = False  # 20 frames after the episode ended: a new one
    av[:, 2] = rng.random(T) > 0.1
    av[:, 3] = (np.arange(T) % 90) < 30
    z_imu[700:730, 4] = np.nan
    av[1100:, 4] = False
    z_cam[~av] = np.nan
    return z_imu, z_cam, av


@pytest.fixture(scope="module")
def scenario():
    return make_scenario()


def stepped(proc, z_imu, z_cam, av):
    outs = [proc.step(k * DT, z_imu[k], z_cam[k], av[k]) for k in range(z_imu.shape[0])]
    return tuple(np.stack([o[i] for o in outs]) for i in range(3))


def assert_matches(got, res):
    pos, cov, src = got
    np.testing.assert_array_equal(src, res.source)
    np.testing.assert_array_equal(np.isnan(pos), np.isnan(res.position))
    np.testing.assert_allclose(pos, res.position, atol=TOL, rtol=0)
    np.testing.assert_array_equal(np.isnan(cov), np.isnan(res.cov))
    np.testing.assert_allclose(cov, res.cov, atol=TOL, rtol=0)


PARAMS = {
    "default": VisionParams(),
    "short-window": VisionParams(train_window=120, min_train=40),
    "fir3-input": VisionParams(
        train_window=300, linear_skip=True, alpha=1e-3, elm2_input="fir3_out", clip_factor=1.0
    ),
    "elm2-skipped": VisionParams(train_window=240, min_train=60, horizon=12),
}


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
@pytest.mark.parametrize("name", list(PARAMS))
def test_step_equals_batch_causal(scenario, method, name):
    z_imu, z_cam, av = scenario
    params = PARAMS[name]
    res = vision_assisted(z_imu, z_cam, av, DT, method, causal=True, params=params)
    proc = VisionAssistedProcessor(method, params, DT, joints=z_imu.shape[1])
    assert_matches(stepped(proc, z_imu, z_cam, av), res)
    # same episodes (typed, every field), same training decisions
    assert proc.episodes == res.episodes


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
def test_no_input_is_predicted_not_bridged(scenario, method):
    """Inside an outage, frames without the IMU chain (a stale or dropped IMU) are backed by no
    input: source PREDICTED (never available), online, causal and offline alike; a chain gap
    while the camera sees the joint stays fused (the camera measured it)."""
    z_imu, z_cam, av = (a.copy() for a in scenario)
    z_imu[540:560, 0] = np.nan  # joint 0's camera outage is 500:620
    proc = VisionAssistedProcessor(method, PARAMS["default"], DT, joints=z_imu.shape[1])
    got = stepped(proc, z_imu, z_cam, av)
    for res in (vision_assisted(z_imu, z_cam, av, DT, method, causal=c) for c in (True, False)):
        src = res.source
        assert np.all(src[540:560, 0] == SOURCE_PREDICTED)
        assert np.all(np.isfinite(res.position[540:560, 0]))  # an estimate, labelled honestly
        assert np.all(src[505:540, 0] == SOURCE_BRIDGED) and np.all(
            src[560:620, 0] == SOURCE_BRIDGED
        )
        assert np.all(src[700:730, 4] == SOURCE_FUSED)  # chain gap in view
        assert np.sum(src == SOURCE_PREDICTED) == 20
    np.testing.assert_array_equal(
        got[2], vision_assisted(z_imu, z_cam, av, DT, method, causal=True).source
    )


@pytest.mark.parametrize("causal", [True, False])
def test_batch_form_in_blocks_equals_one_block(scenario, monkeypatch, causal):
    """The batch form advances the core in blocks of BATCH_BLOCK_FRAMES (bounded memory on long
    recordings); blocks that cut through outages, onsets and recoveries give the one-block
    result (same episodes, positions to 1e-9 m), offline (RTS over the joined IMM) too."""
    from kinefuse.pipelines import paper_b

    z_imu, z_cam, av = scenario
    kw = {"causal": causal, "params": PARAMS["default"]}
    whole = vision_assisted(z_imu, z_cam, av, DT, "elm-fir", **kw)
    monkeypatch.setattr(paper_b, "BATCH_BLOCK_FRAMES", 97)  # 13 blocks, the last one short
    blocks = vision_assisted(z_imu, z_cam, av, DT, "elm-fir", **kw)
    assert blocks.episodes == whole.episodes
    assert_matches((blocks.position, blocks.cov, blocks.source), whole)
    np.testing.assert_allclose(blocks.mu, whole.mu, atol=TOL, rtol=0)


def test_scenario_covers_every_rule(scenario):
    z_imu, z_cam, av = scenario
    res = vision_assisted(z_imu, z_cam, av, DT, "elm-fir", causal=True, params=PARAMS["default"])
    eps = res.episodes
    assert eps[0][0].start == 0 and eps[0][0].mode == "imu-fallback"
    assert any(e.mode == "bridged" and not e.elm2_skipped for ep in eps for e in ep)
    assert eps[1][0].stop > 360  # back-to-back outages merged
    assert not eps[4][-1].recovered
    src = res.source
    assert {SOURCE_FUSED, SOURCE_BRIDGED, SOURCE_IMU} <= set(np.unique(src).tolist())
    r2 = vision_assisted(
        z_imu, z_cam, av, DT, "elm-fir", causal=True, params=PARAMS["elm2-skipped"]
    )
    assert any(e.elm2_skipped and e.mode == "bridged" for ep in r2.episodes for e in ep)
    # joint 3's training window spans more than the initial history capacity
    proc = VisionAssistedProcessor("elm-fir", PARAMS["short-window"], DT)
    cap0 = 2 * PARAMS["short-window"].train_window + 64
    stepped(proc, z_imu, z_cam, av)
    assert proc.state.history.capacity > cap0


def test_run_is_the_batch_pipeline_and_protocol(scenario):
    z_imu, z_cam, av = scenario
    proc = VisionAssistedProcessor("elm-fir", joints=5)
    assert isinstance(proc, Processor) and proc.lag_frames == 0 and proc.flush() == []
    t = np.arange(z_imu.shape[0]) * DT
    pos, cov, src = proc.run(t, z_imu, z_cam, av)
    res = vision_assisted(z_imu, z_cam, av, DT, "elm-fir", causal=True)
    np.testing.assert_array_equal(pos, res.position)
    np.testing.assert_array_equal(src, res.source)
    assert proc.frames == 0  # online state untouched


def test_run_without_any_imu_sample_for_a_joint_steps(scenario):
    z_imu, z_cam, av = (a[:300].copy() for a in scenario)
    z_imu[:, 1] = np.nan
    proc = VisionAssistedProcessor("elm-fir")
    pos, cov, src = proc.run(np.arange(300) * DT, z_imu, z_cam, av)
    ref = stepped(VisionAssistedProcessor("elm-fir"), z_imu, z_cam, av)
    np.testing.assert_array_equal(pos, ref[0])
    np.testing.assert_array_equal(src, ref[2])
    assert np.all(np.isfinite(pos[av[:, 1], 1]))  # camera-only model of the IMM


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
@pytest.mark.parametrize("cut", [515, 560, 650])  # in an episode (after training), in recovery
def test_checkpoint_restore_continues_identically(scenario, method, cut):
    z_imu, z_cam, av = scenario
    params = PARAMS["short-window"]
    full = stepped(VisionAssistedProcessor(method, params), z_imu, z_cam, av)
    proc = VisionAssistedProcessor(method, params)
    first = stepped(proc, z_imu[:cut], z_cam[:cut], av[:cut])
    blob = pickle.dumps(proc.checkpoint())
    proc.step(0.0, z_imu[cut], z_cam[cut], av[cut])  # the snapshot is independent of later steps
    other = VisionAssistedProcessor(method, params)
    other.restore(pickle.loads(blob))
    second = stepped(other, z_imu[cut:], z_cam[cut:], av[cut:])
    for a, b, f in zip(first, second, full, strict=True):
        np.testing.assert_array_equal(np.concatenate([a, b]), f)
    other.reset()
    np.testing.assert_array_equal(stepped(other, z_imu, z_cam, av)[0], full[0])


def test_restore_checks(scenario):
    proc = VisionAssistedProcessor("elm-fir")
    with pytest.raises(InputError, match="method"):
        VisionAssistedProcessor("elm-kf").restore(proc.checkpoint())
    with pytest.raises(InputError, match="checkpoint of a VisionAssistedProcessor"):
        proc.restore({"type": "KalmanFusionProcessor"})
    fresh = VisionAssistedProcessor("elm-fir")
    fresh.restore(proc.checkpoint())  # before the first frame
    assert fresh.state is None


def test_bad_arguments():
    with pytest.raises(InputError, match="method"):
        VisionAssistedProcessor("imu-only")
    with pytest.raises(InputError, match="fixed_lag"):
        VisionAssistedProcessor(params=VisionParams(fixed_lag=5))
    with pytest.raises(InputError, match="VisionParams"):
        VisionAssistedProcessor(params={"q": 1})
    with pytest.raises(InputError, match="dt_s"):
        VisionAssistedProcessor(dt_s=0)
    proc = VisionAssistedProcessor(joints=("a", "b"))
    with pytest.raises(InputError, match=r"J = 2"):
        proc.step(0.0, np.zeros((3, 3)), np.zeros((3, 3)), np.ones(3, bool))


# ------------------------------------------------------------------------------ engine
@pytest.fixture(scope="module")
def rec():
    from kinefuse.data import demo_motion
    from kinefuse.sim import virtual_recording

    return virtual_recording(demo_motion(), seed=3)


def _events(rec, imu_delay_s=0.004):
    ev = []
    for seg, st in rec.imu.items():
        for k in range(len(st)):
            t = float(st.t_s[k])
            ev.append((t + imu_delay_s, 0, "imu", seg, t, st.q_world_from_sensor[k]))
    v = rec.vision
    for k in range(len(v)):
        t = float(v.t_s[k])
        ev.append((t, 1, "camera", None, t, (v.position_m[k], v.available[k])))
    ev.sort(key=lambda e: (e[0], e[1]))
    return ev


def _feed(engine, ev):
    outs = []
    for arrival, _o, kind, key, t, payload in ev:
        if kind == "imu":
            engine.push_imu(key, t, payload, now=arrival)
        else:
            engine.push_camera(t, payload[0], payload[1], now=arrival)
        outs += engine.poll(arrival)
    return outs + engine.flush()


@pytest.mark.parametrize("method", ["elm-fir", "elm-kf"])
def test_engine_equals_offline_causal_on_virtual_clip(rec, method):
    params = VisionParams(train_window=300)
    cfg = EngineConfig(full_body(height_m=1.75), camera_joints=rec.vision.joints, record=True)
    eng = Engine(cfg, VisionAssistedProcessor(method, params, joints=cfg.joints))
    outs = _feed(eng, _events(rec))
    assert len(outs) == len(rec.vision) and eng.counters["forced_frames"] == 0
    acc = eng.accepted
    imu = {s: (np.array([a[0] for a in acc["imu"][s]]), np.array([a[1] for a in acc["imu"][s]]))
           for s in cfg.segments}  # fmt: skip
    cam = tuple(np.array([c[i] for c in acc["camera"]]) for i in range(3))
    off = offline_causal(cfg, VisionAssistedProcessor(method, params), imu, cam)
    pos = np.stack([o.position_m for o in outs])
    cov = np.stack([o.cov_m2 for o in outs])
    src = np.stack([o.source for o in outs])
    np.testing.assert_array_equal(src, off.source)
    np.testing.assert_array_equal(np.isnan(pos), np.isnan(off.position_m))
    # the trained ELM bridge (a least-squares solve) amplifies the rounding of the two paths'
    # summation orders to ~1e-9 m on this clip (realistic virtual sensors): 1e-8 m = 10 nm
    np.testing.assert_allclose(pos, off.position_m, atol=10 * TOL, rtol=0)
    np.testing.assert_allclose(cov, off.cov_m2, atol=10 * TOL, rtol=0)
    # the clip exercises the camera path, the IMU fallback and a trained bridge
    assert {SOURCE_FUSED, SOURCE_BRIDGED, SOURCE_IMU} <= set(np.unique(src).tolist())
    # and the processor's step equals the batch pipeline on the engine's own inputs
    res = vision_assisted(
        off.z_imu, off.z_cam, off.available, DT, method, causal=True, params=params
    )
    proc = VisionAssistedProcessor(method, params)
    assert_matches(stepped(proc, off.z_imu, off.z_cam, off.available), res)


def test_engine_checkpoint_with_trained_bridge(rec):
    params = VisionParams(train_window=300)
    cfg = EngineConfig(full_body(height_m=1.75), camera_joints=rec.vision.joints)
    ev = _events(rec, 0.003)
    full = _feed(Engine(cfg, VisionAssistedProcessor("elm-fir", params)), ev)
    # cut inside the bridged episode of the clip
    src = np.stack([o.source for o in full])
    k = int(np.flatnonzero((src == SOURCE_BRIDGED).any(axis=1))[5])
    t_cut = full[k].t_s
    half = next(i for i, e in enumerate(ev) if e[0] > t_cut + 0.01)
    eng = Engine(cfg, VisionAssistedProcessor("elm-fir", params))
    first = []
    for arrival, _o, kind, key, t, payload in ev[:half]:
        if kind == "imu":
            eng.push_imu(key, t, payload, now=arrival)
        else:
            eng.push_camera(t, payload[0], payload[1], now=arrival)
        first += eng.poll(arrival)
    assert any(b is not None for b in eng.processor.state.bridges)
    eng2 = Engine(cfg, VisionAssistedProcessor("elm-fir", params))
    eng2.restore(pickle.loads(pickle.dumps(eng.checkpoint())))
    outs = first + _feed(eng2, ev[half:])
    assert len(outs) == len(full)
    for a, b in zip(outs, full, strict=True):
        np.testing.assert_array_equal(a.position_m, b.position_m)
        np.testing.assert_array_equal(a.cov_m2, b.cov_m2)
        np.testing.assert_array_equal(a.source, b.source)
