"""IMU-only live capture: the chain `kinefuse run` calibrated (chain.json) run by the online engine."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kinefuse.exceptions import ConfigError, InputError
from kinefuse.pipelines.run import process_recording, run_session
from kinefuse.pipelines.run.chain_file import CHAIN_FILE, read_chain
from kinefuse.pipelines.run.streams import load_streams
from kinefuse.session_file import load_session
from kinefuse.session_file.from_recording import filled_template, sketch_recording
from kinefuse.streaming.config import stream_config_from_session
from kinefuse.streaming.engine_types import IMU_FRESH
from kinefuse.streaming.offline import offline_causal
from kinefuse.streaming.runner import build_engine

pytestmark = pytest.mark.filterwarnings("ignore:.*has no online form:UserWarning")


@pytest.fixture(scope="module")
def calibrated(shared_data, tmp_path_factory):
    """The x-IMU3 lower body as `kinefuse init-session --from` fills it (pelvis root, static
    calibration, IMU only), run once."""
    d = tmp_path_factory.mktemp("chain")
    p = d / "xl.toml"
    sketch = sketch_recording(shared_data / "xio_imu_mocap_lower_body", d)
    p.write_text(filled_template("xl", p.name, sketch), encoding="utf-8")
    run_session(p, d / "out")
    return p, d / "out" / CHAIN_FILE


@pytest.fixture(scope="module")
def live_and_offline(calibrated):
    """kinefuse run's computation (process_recording) and the online engine's on the same
    orientation samples and frame times, with chain.json."""
    session, chain_path = calibrated
    cfg = load_session(session)
    rec, _ = load_streams(cfg, strict_units=True)
    out = process_recording(rec, "imu-only", cfg.processing_parameters(),
                            lengths=cfg.skeleton.lengths_m, body_height_m=cfg.skeleton.body_height_m)  # fmt: skip
    chain = read_chain(chain_path)
    scfg = stream_config_from_session(cfg, chain)
    rates = {s: 1.0 / float(np.median(np.diff(rec.imu[s].t_s))) for s in rec.imu}
    engine = build_engine(scfg, camera=False, camera_rate_hz=30.0, imu_rate_hz=rates)
    imu = {s: (st.t_s, st.q_world_from_sensor) for s, st in rec.imu.items()}
    off = offline_causal(engine.config, engine.processor, imu, None, frame_times=out.t_s)
    return out, chain, scfg, engine, off


def test_the_live_chain_is_the_offline_chain(live_and_offline):
    """Oracle: kinefuse run's own chain (static calibration, pelvis root, hips from the pelvis
    IMU). The online engine on the same orientation samples and frame times, with chain.json,
    gives the same joint positions wherever it had a fresh sample (held or stale samples, e.g.
    at dropped packets, are the engine's own rule, not a chain difference)."""
    out, chain, scfg, _, off = live_and_offline
    assert chain == json.loads(json.dumps(out.chain_description))  # the file is that chain
    assert scfg.camera_stream == "" and scfg.joints == out.joints
    fresh = off.imu_status == IMU_FRESH
    assert fresh.mean() > 0.95
    both = fresh & np.all(np.isfinite(out.chain), axis=-1)
    np.testing.assert_allclose(off.z_imu[both], out.chain[both], atol=1e-9, rtol=0)
    assert np.ptp(out.chain[both][:, 2]) > 0.1  # the legs moved: not a trivial comparison


def test_the_live_joint_angles_are_the_offline_angles(live_and_offline):
    """Oracle: kinefuse run's ISB joint angles (process_recording's, which its _angles.csv
    rounds to 1e-4 deg). chain.json carries the calibrated segment frames; the engine turns
    the orientations at each frame into the same knee, hip and ankle angles (the feet serve
    the ankle angles only: not in the chain, read for the angles) wherever every segment
    of the joint had a fresh sample. The tolerance, 1e-6 deg, is rounding through one SLERP
    and one Euler decomposition (~1e-13 rad) with a wide margin; an angle computed from
    another frame or timeline is off by degrees."""
    out, chain, _, engine, off = live_and_offline
    legs = {f"{part}_{side}" for part in ("thigh", "shank", "foot") for side in "lr"}
    assert set(chain["segment_frames"]) == legs | {"pelvis"}
    joints = engine.config.angle_joints
    assert joints == ("knee_l", "knee_r", "hip_l", "hip_r", "ankle_l", "ankle_r")
    fresh = np.all(off.imu_status == IMU_FRESH, axis=1)  # every segment (the hips' pelvis too)
    assert fresh.mean() > 0.95
    checked = 0
    for a, j in enumerate(joints):
        want = out.angles[j]
        ok = fresh & np.all(np.isfinite(want), axis=1)
        np.testing.assert_allclose(off.angles_deg[ok, a], want[ok], atol=1e-6, rtol=0)
        checked += int(ok.sum())
    knee = off.angles_deg[:, 0, 0]
    assert np.nanmax(knee) > 90  # the recording squats and kneels: not a trivial comparison
    assert checked > 1000


def test_chain_file_errors_and_refusals(calibrated, tmp_path):
    session, chain_path = calibrated
    with pytest.raises(InputError, match="file not found"):
        read_chain(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "other"}', encoding="utf-8")
    with pytest.raises(InputError, match="written by kinefuse run"):
        read_chain(bad)
    d = json.loads(chain_path.read_text(encoding="utf-8"))
    del d["segments"][0]["axis_sensor"]
    bad.write_text(json.dumps(d), encoding="utf-8")
    with pytest.raises(InputError, match="malformed chain description"):
        read_chain(bad)
    d = json.loads(chain_path.read_text(encoding="utf-8"))
    d["segment_frames"]["thigh_l"] = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]  # a reflection
    bad.write_text(json.dumps(d), encoding="utf-8")
    with pytest.raises(InputError, match=r"segment_frames\['thigh_l'\]: expected a 3 x 3 rotation"):
        read_chain(bad)
    cfg = load_session(session)
    with pytest.raises(ConfigError, match="kinefuse stream xl.toml --chain"):
        stream_config_from_session(cfg)  # static calibration, pelvis root: needs the chain
    chain = read_chain(chain_path)
    one_leg = {**chain, "segments": [s for s in chain["segments"] if s["name"].endswith("_l")]}
    with pytest.raises(ConfigError, match=r"shank_r, thigh_r \(not in the chain file\)"):
        stream_config_from_session(cfg, one_leg)
    with pytest.raises(ConfigError, match="runs without a camera"):
        build_engine(stream_config_from_session(cfg, chain), camera=True, camera_rate_hz=30.0,
                     imu_rate_hz=100.0)  # fmt: skip
