"""6-D sensors live: the engine finds each sensor's heading again from the calibration pose.

The qmt arm (raw acc + gyr, VQF 6-D: a heading per sensor) calibrated by `kinefuse run` from its
still N-pose writes a chain.json with ``"heading": {"from": "pose"}``. Oracles: kinefuse run's own
chain (its calibration aligned the headings with the static pose and the elbow's hinge fit), a
closed form (turning every sensor's world frame by its own angle turns the output by the
reference sensor's angle only), and the engine fed sample by sample (= its batch form).
"""

from __future__ import annotations

import io
import json
from types import SimpleNamespace

import numpy as np
import pytest
from rich.console import Console
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import InputError
from kinefuse.io import ImuStream
from kinefuse.kinematics.static import pose_headings, relative_yaw
from kinefuse.pipelines.run import process_recording, run_session
from kinefuse.pipelines.run.chain_file import CHAIN_FILE, read_chain
from kinefuse.pipelines.run.streams import load_streams
from kinefuse.session_file import load_session
from kinefuse.streaming.config import stream_config_from_session
from kinefuse.streaming.engine import Engine
from kinefuse.streaming.engine_types import IMU_FRESH
from kinefuse.streaming.offline import offline_causal
from kinefuse.streaming.runner import _status_printer, build_engine

pytestmark = pytest.mark.filterwarnings("ignore:.*has no online form:UserWarning")


@pytest.fixture(scope="module")
def arm(shared_data, tmp_path_factory):
    """kinefuse run on the qmt right arm (6-D), its chain.json and the engine it configures."""
    d = tmp_path_factory.mktemp("heading")
    mat = shared_data / "qmt_full_body_example" / "full_body_example_data.mat"
    session = d / "arm.toml"
    session.write_text(
        f'[session]\nname = "arm"\n[imu]\nformat = "qmt"\npath = "{mat.as_posix()}"\n'
        '[imu.segments]\nupper_arm_r = "upper_arm_right"\nforearm_r = "forearm_right"\n'
        '[skeleton]\nroot = "fixed"\nroot_position_m = [0.0, 0.0, 1.40]\n'
        "[skeleton.lengths]\nupper_arm_r = 0.30\nforearm_r = 0.26\n"
        '[skeleton.axes]\nupper_arm_r = "-e1"\nforearm_r = "-e1"\n'
        '[calibration]\nmethod = "static"\nwindow_s = 1.0\n[method]\nname = "imu-only"\n',
        encoding="utf-8",
    )
    run_session(session, d / "out")
    cfg = load_session(session)
    rec, _ = load_streams(cfg, strict_units=True)
    out = process_recording(rec, "imu-only", cfg.processing_parameters(),
                            lengths=cfg.skeleton.lengths_m)  # fmt: skip
    chain = read_chain(d / "out" / CHAIN_FILE)
    rates = {s: 1.0 / float(np.median(np.diff(st.t_s))) for s, st in rec.imu.items()}
    engine = build_engine(stream_config_from_session(cfg, chain), camera=False,
                          camera_rate_hz=30.0, imu_rate_hz=rates, record=True)  # fmt: skip
    imu = {s: (st.t_s, st.q_world_from_sensor) for s, st in rec.imu.items()}  # VQF 6-D
    return out, chain, engine, imu


def test_a_6d_chain_finds_its_headings_from_the_pose(arm):
    out, chain, engine, imu = arm
    assert chain == json.loads(json.dumps(out.chain_description))
    h = chain["heading"]
    assert (h["from"], h["window_s"], h["reference"]) == ("pose", 1.0, "upper_arm_r")
    # the frames' headings in the pose, relative to the upper arm's, as the calibration left them
    assert h["pose_yaw_deg"]["upper_arm_r"] == 0.0 and abs(h["pose_yaw_deg"]["forearm_r"]) < 5.0
    assert engine.config.heading_pose_s == 1.0
    every = slice(None, None, 5)  # 2000 of the 10000 samples: the oracle, at a fifth the cost
    off = offline_causal(engine.config, engine.processor, imu, None, frame_times=out.t_s[every])
    assert (off.imu_status == IMU_FRESH).mean() > 0.99
    # kinefuse run aligned the headings with the pose, then refined the forearm's with the
    # elbow's hinge fit; with the frames' relative headings in the pose that the calibration
    # left (pose_yaw_deg) the engine finds the same turns: the same chain, to rounding
    np.testing.assert_allclose(off.z_imu, out.chain[every], atol=1e-9, rtol=0)
    assert np.ptp(out.chain[every, 1, 2]) > 0.3  # the wrist moved


def test_turning_each_sensor_turns_the_output_by_the_reference_only(arm):
    """Closed form: sensor k's world turned by δ_k about the vertical (a new power-up of 6-D
    sensors); the pose gives ψ_k + δ_ref − δ_k, so the output turns by δ_ref about the root."""
    out, _, engine, imu = arm
    cfg = engine.config
    t = out.t_s[::5]
    base = offline_causal(cfg, engine.processor, imu, None, frame_times=t)
    delta = {"upper_arm_r": 1.1, "forearm_r": -2.3}
    turned = {}
    for s, (ts, q) in imu.items():
        r = Rotation.from_euler("z", delta[s]) * Rotation.from_quat(q, scalar_first=True)
        turned[s] = (ts, r.as_quat(scalar_first=True))
    res = offline_causal(cfg, engine.processor, turned, None, frame_times=t)
    root = np.array(cfg.root_position_m)
    Rz = Rotation.from_euler("z", delta[cfg.segments[0]]).as_matrix()
    np.testing.assert_allclose(res.z_imu - root, (base.z_imu - root) @ Rz.T, atol=1e-9)


def test_the_engine_waits_for_the_pose_then_equals_its_batch_form(arm):
    out, _, engine, imu = arm
    events = sorted((float(t), s, k) for s, (ts, _) in imu.items() for k, t in enumerate(ts))
    outputs = []
    for t, s, k in events:
        engine.push_imu(s, t, imu[s][1][k], now=t)
        got = engine.poll(t)
        if got and not outputs:
            # the first frames come once the pose (1 s still, found within its first 1.25 s
            # of data) has been seen: nothing before
            assert t >= imu[s][0][0] + 1.0
        outputs += got
    outputs += engine.flush(events[-1][0] + 1.0)
    assert [e.kind for e in engine.events].count("heading") == 1
    t_out = np.array([o.t_s for o in outputs])
    live = np.array([o.position_m for o in outputs])
    off = offline_causal(engine.config, engine.processor, imu, None, frame_times=t_out)
    assert t_out.size > 0.9 * 30.0 * (out.t_s[-1] - out.t_s[0])  # every frame, at 30 Hz
    np.testing.assert_allclose(live, off.position_m, atol=1e-9, rtol=0)
    # --record-inputs keeps the samples as received: re-run offline, they give the same frames
    rec = {s: (np.array([t for t, _ in v]), np.array([q for _, q in v]))
           for s, v in engine.accepted["imu"].items()}  # fmt: skip
    again = offline_causal(engine.config, engine.processor, rec, None, frame_times=t_out)
    np.testing.assert_allclose(again.position_m, live, atol=1e-9, rtol=0)


def test_a_malformed_heading_is_refused(arm, tmp_path):
    _, chain, _, _ = arm
    for bad in ({"from": "magnetometer", "window_s": 1.0, "reference": "upper_arm_r"},
                {"from": "pose", "window_s": 0, "reference": "upper_arm_r"},
                {"from": "pose", "window_s": 1.0},
                {"from": "pose", "window_s": 1.0, "reference": "upper_arm_r",
                 "pose_yaw_deg": {"forearm_r": "north"}}, "pose"):  # fmt: skip
        p = tmp_path / "c.json"
        p.write_text(json.dumps(dict(chain, heading=bad)), encoding="utf-8")
        with pytest.raises(InputError, match=r"heading: expected"):
            read_chain(p)


def test_the_live_status_says_to_hold_the_pose(arm):
    """Until the pose is found nothing comes out: the terminal status says why."""
    _, _, engine, _ = arm
    fresh = Engine(engine.config, engine.processor)
    console = Console(file=io.StringIO(), width=120, force_terminal=False)
    live, show = _status_printer(console, SimpleNamespace(output_stream_name="arm_fused"))
    try:
        show(fresh, [])
    finally:
        live.stop()
    text = console.file.getvalue()
    assert "hold the calibration pose: stand still for 1 s" in text, text


def test_the_turns_keep_the_pose_headings_the_calibration_left():
    """Closed form: still sensors with arbitrary orientations and frames; the turns make each
    segment frame's heading relative to the reference's equal the one given (the calibration's
    pose_yaw), 0 by default."""
    rng = np.random.default_rng(3)
    t = np.arange(300) / 100.0
    names = ("pelvis", "thigh_l", "shank_l")
    R = {s: Rotation.random(random_state=rng) for s in names}
    frames = {s: Rotation.random(random_state=rng).as_matrix() for s in names}
    imus = {s: ImuStream(t_s=t, q_world_from_sensor=np.tile(R[s].as_quat(scalar_first=True), (t.size, 1)))
            for s in names}  # fmt: skip
    for keep in ({}, {"thigh_l": 0.4, "shank_l": -2.0}):
        still, psi = pose_headings(imus, frames, 2.0, max_rate_rad_s=0.1, max_acc_std_m_s2=0.2,
                                   pose_yaw_rad=keep)  # fmt: skip
        assert still.still and psi["pelvis"] == 0.0
        S = {s: Rotation.from_euler("z", psi[s]).as_matrix() @ R[s].as_matrix() @ frames[s]
             for s in names}  # fmt: skip
        for s in names[1:]:
            assert relative_yaw(S["pelvis"], S[s]) == pytest.approx(keep.get(s, 0.0), abs=1e-12)
