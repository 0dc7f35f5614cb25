"""Both arms (or arms and legs) from IMUs alone: the shoulders hang from the trunk IMU.

Closed-form oracle: a synthetic upper body (chest, upper arms, forearms) still in the N-pose,
then the trunk turns and leans while the arms swing and the elbows flex. With a fixed root at
the mid-shoulder point, each shoulder is that point ± half the shoulder joint spacing (0.189 x
body height, OpenSim's full-body model) along the trunk's right axis, each elbow and wrist follows along its
segment, and the live engine running the chain.json `kinefuse run` wrote gives the same joints.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse.exceptions import ConfigError
from kinefuse.io import ImuStream, Recording, write_imu_csv
from kinefuse.kinematics.skeleton import ANTHROPOMETRIC_RATIOS
from kinefuse.pipelines.run import process_recording, run_session
from kinefuse.pipelines.run.chain_file import CHAIN_FILE, read_chain
from kinefuse.pipelines.run.streams import load_streams
from kinefuse.session_file import load_session
from kinefuse.streaming.config import stream_config_from_session
from kinefuse.streaming.engine_types import IMU_FRESH
from kinefuse.streaming.offline import offline_causal
from kinefuse.streaming.runner import build_engine

pytestmark = pytest.mark.filterwarnings("ignore:.*has no online form:UserWarning")

FS = 100.0
H = 1.75
ROOT = np.array([0.2, -0.1, 1.4])
MOUNTS = {
    "chest": Rotation.from_euler("xyz", [5, -20, 100], degrees=True),
    "upper_arm_l": Rotation.from_euler("xyz", [10, 80, -30], degrees=True),
    "upper_arm_r": Rotation.from_euler("xyz", [-60, 15, 40], degrees=True),
    "forearm_l": Rotation.from_euler("xyz", [-40, 20, 65], degrees=True),
    "forearm_r": Rotation.from_euler("xyz", [30, -50, -10], degrees=True),
}


def _upper_body(T: int = 800):
    """Segment orientations (world from segment; identity = N-pose facing north) and the
    recording whose sensors carry them through ``MOUNTS``."""
    t = np.arange(T) / FS
    m = np.clip(t - 2.5, 0.0, None)  # still for 2.5 s (the default window: 2 s)
    trunk = Rotation.from_euler(
        "zx", np.stack([35.0 * np.sin(0.8 * m), -20.0 * (1 - np.cos(0.6 * m))], 1), degrees=True
    )
    seg = {"chest": trunk}
    for side, k in (("l", 1.0), ("r", 1.4)):
        # shoulder flexion (the arm swings forward) and elbow flexion, both about the right
        # axis, from the pose (zero at the end of the still part)
        sh = Rotation.from_euler("x", 30.0 * np.sin(1.1 * k * m)[:, None], degrees=True)
        el = Rotation.from_euler("x", 55.0 * (1 - np.cos(1.4 * k * m))[:, None], degrees=True)
        seg[f"upper_arm_{side}"] = trunk * sh
        seg[f"forearm_{side}"] = trunk * sh * el
    imu = {
        s: ImuStream(t_s=t, q_world_from_sensor=(R * MOUNTS[s]).as_quat(scalar_first=True), name=s)
        for s, R in seg.items()
    }
    return seg, Recording(imu=imu)


def _expected(seg) -> dict[str, np.ndarray]:
    """The joints in closed form (lengths from body height, arms hanging in the pose)."""
    half = 0.5 * ANTHROPOMETRIC_RATIOS["shoulder_joint_spacing"] * H
    down = np.array([0.0, 0.0, -1.0])
    out = {}
    for side, sign in (("l", -1.0), ("r", 1.0)):
        shoulder = ROOT + seg["chest"].apply(np.array([sign * half, 0.0, 0.0]))
        elbow = shoulder + ANTHROPOMETRIC_RATIOS["upper_arm"] * H * seg[f"upper_arm_{side}"].apply(
            down
        )
        out[f"elbow_{side}"] = elbow
        out[f"wrist_{side}"] = elbow + ANTHROPOMETRIC_RATIOS["forearm"] * H * seg[
            f"forearm_{side}"
        ].apply(down)
    return out


# the subject's facing declared (north): the pose frames are then exact; estimated from the
# elbows' movement ("auto") it is off by a few hundredths of a degree (a weak prior of the fit)
PARAMS = {"root": "fixed", "root_position_m": ROOT.tolist(), "calibration": "static",
          "facing": [0.0, 1.0, 0.0]}  # fmt: skip


def test_shoulders_hang_from_the_chest_imu():
    seg, rec = _upper_body()
    out = process_recording(rec, "imu-only", dict(PARAMS), body_height_m=H)
    want = _expected(seg)
    for k, j in enumerate(out.joints):
        # exact data, SLERP at the sensors' own times: only the calibration's least squares
        np.testing.assert_allclose(out.chain[:, k], want[j], atol=1e-6, err_msg=j)
    # in the pose the elbows are a shoulder joint spacing apart, along the right axis (east)
    jl, jr = out.joints.index("elbow_l"), out.joints.index("elbow_r")
    np.testing.assert_allclose(out.chain[0, jr] - out.chain[0, jl], [0.189 * H, 0, 0], atol=1e-9)
    assert np.ptp(out.chain[:, jr, 1] - out.chain[:, jl, 1]) > 0.12  # the trunk turned with them
    assert "shoulders from the chest IMU" in out.root
    assert out.frame.endswith("relative to the mid-shoulder point") is False  # ROOT is not 0
    assert any("± 0.165 m along the chest right axis" in n for n in out.notes), out.notes


def test_without_a_chest_imu_the_pelvis_carries_the_shoulders():
    seg, rec = _upper_body()
    imu = dict(rec.imu)
    imu["pelvis"] = imu.pop("chest")  # the same trunk motion, read from a pelvis IMU
    out = process_recording(Recording(imu=imu), "imu-only", dict(PARAMS), body_height_m=H)
    want = _expected(seg)
    np.testing.assert_allclose(
        out.chain[:, out.joints.index("elbow_l")], want["elbow_l"], atol=1e-6
    )
    assert any("taken as rigid with the pelvis" in n for n in out.notes)


def test_two_arms_without_a_trunk_imu_are_refused_before_any_work():
    _, rec = _upper_body(T=50)
    imu = {s: st for s, st in rec.imu.items() if s != "chest"}
    with pytest.raises(
        ConfigError,
        match=r"the shoulders \['shoulder_l', 'shoulder_r'\] are placed from the chest IMU.*map 'chest'",
    ):
        process_recording(Recording(imu=imu), "imu-only", dict(PARAMS), body_height_m=H)
    # a measured position per shoulder needs no trunk IMU
    per_joint = dict(
        PARAMS, root_position_m={"shoulder_l": [0, 0, 1.4], "shoulder_r": [0.4, 0, 1.4]}
    )
    out = process_recording(Recording(imu=imu), "imu-only", per_joint, body_height_m=H)
    assert "fixed shoulder_l at [0, 0, 1.4] m" in out.root


def _run_session(tmp_path, rec, root: str):
    """kinefuse run on ``rec`` written as the generic IMU CSV (static pose, facing north,
    body height H); returns chain.json, the session, and kinefuse run's computation."""
    write_imu_csv(tmp_path / "imu.csv", rec)
    lines = "\n".join(f'{s} = "{s}"' for s in rec.imu)
    session = tmp_path / "s.toml"
    session.write_text(
        f'[session]\nname = "s"\n[imu]\nformat = "imu_csv"\npath = "imu.csv"\n'
        f"[imu.segments]\n{lines}\n[skeleton]\nbody_height_m = {H}\n{root}\n"
        '[calibration]\nmethod = "static"\nfacing = [0.0, 1.0, 0.0]\n[method]\nname = "imu-only"\n',
        encoding="utf-8",
    )
    run_session(session, tmp_path / "out")
    chain = read_chain(tmp_path / "out" / CHAIN_FILE)
    cfg = load_session(session)
    rec2, _ = load_streams(cfg, strict_units=True)
    out = process_recording(rec2, "imu-only", cfg.processing_parameters(),
                            body_height_m=cfg.skeleton.body_height_m)  # fmt: skip
    assert chain == json.loads(json.dumps(out.chain_description))
    return chain, cfg, rec2, out


def _assert_live_is_offline(chain, cfg, rec, out) -> None:
    """The online engine with chain.json, on the same samples and frame times, gives
    kinefuse run's chain wherever it had a fresh sample."""
    engine = build_engine(stream_config_from_session(cfg, chain), camera=False,
                          camera_rate_hz=30.0, imu_rate_hz=FS)  # fmt: skip
    imu = {s: (st.t_s, st.q_world_from_sensor) for s, st in rec.imu.items()}
    off = offline_causal(engine.config, engine.processor, imu, None, frame_times=out.t_s)
    fresh = off.imu_status == IMU_FRESH
    assert fresh.mean() > 0.95
    np.testing.assert_allclose(off.z_imu[fresh], out.chain[fresh], atol=1e-9, rtol=0)


def test_the_live_chain_places_the_shoulders_as_kinefuse_run(tmp_path):
    """Oracle: kinefuse run's chain on the same samples (as tests/test_stream_chain.py for the
    hips): chain.json carries the shoulders as offsets in the chest sensor's frame."""
    seg, rec = _upper_body()
    chain, cfg, rec2, out = _run_session(
        tmp_path, rec, f'root = "fixed"\nroot_position_m = {ROOT.tolist()}'
    )
    assert chain["root"] == "spine_shoulder" and chain["root_segment"] == "chest"
    assert set(chain["offsets_m"]) == {"shoulder_l", "shoulder_r"}
    _assert_live_is_offline(chain, cfg, rec2, out)
    k = out.joints.index("wrist_r")
    np.testing.assert_allclose(out.chain[:, k], _expected(seg)["wrist_r"], atol=1e-6)


def _full_body(T: int = 800):
    """The upper body of :func:`_upper_body` on a pelvis that turns less than the chest, with
    legs swinging from it (hip and knee flexion about the right axis)."""
    seg, _ = _upper_body(T)
    t = np.arange(T) / FS
    m = np.clip(t - 2.5, 0.0, None)
    pelvis = Rotation.from_euler("z", 15.0 * np.sin(0.8 * m)[:, None], degrees=True)
    seg["pelvis"] = pelvis
    for side, k in (("l", 1.0), ("r", -1.3)):
        hip = Rotation.from_euler("x", 25.0 * np.sin(1.2 * k * m)[:, None], degrees=True)
        knee = Rotation.from_euler("x", -40.0 * (1 - np.cos(1.2 * k * m))[:, None], degrees=True)
        seg[f"thigh_{side}"] = pelvis * hip
        seg[f"shank_{side}"] = pelvis * hip * knee
    mounts = dict(MOUNTS, pelvis=Rotation.from_euler("xyz", [0, 10, -70], degrees=True))
    for i, s in enumerate(("thigh_l", "thigh_r", "shank_l", "shank_r")):
        mounts[s] = Rotation.from_euler("xyz", [20 * i, -35, 50 + 40 * i], degrees=True)
    imu = {
        s: ImuStream(t_s=t, q_world_from_sensor=(R * mounts[s]).as_quat(scalar_first=True), name=s)
        for s, R in seg.items()
    }
    return seg, Recording(imu=imu)


def test_full_body_shoulders_on_the_chest_hips_on_the_pelvis_live_too(tmp_path):
    """Pelvis root: the hips hang from the pelvis IMU, the shoulders 0.288 H up the chest from
    the mid-hip point (closed form); chain.json carries both (offset_segments: the chest) and
    the live engine gives the same joints."""
    seg, rec = _full_body()
    chain, cfg, rec2, out = _run_session(tmp_path, rec, 'root = "pelvis"')
    assert chain["root_segment"] == "pelvis"
    assert chain["offset_segments"] == {"shoulder_l": "chest", "shoulder_r": "chest"}
    down = np.array([0.0, 0.0, -1.0])
    r = ANTHROPOMETRIC_RATIOS
    for side, sign in (("l", -1.0), ("r", 1.0)):
        shoulder = seg["chest"].apply(
            [sign * 0.5 * r["shoulder_joint_spacing"] * H, 0.0, r["chest_to_hip"] * H]
        )
        elbow = shoulder + r["upper_arm"] * H * seg[f"upper_arm_{side}"].apply(down)
        hip = seg["pelvis"].apply([sign * 0.5 * r["hip_joint_spacing"] * H, 0.0, 0.0])
        knee = hip + r["thigh"] * H * seg[f"thigh_{side}"].apply(down)
        for j, want in ((f"elbow_{side}", elbow), (f"knee_{side}", knee)):
            np.testing.assert_allclose(
                out.chain[:, out.joints.index(j)], want, atol=1e-6, err_msg=j
            )
    _assert_live_is_offline(chain, cfg, rec2, out)


def test_reference_calibration_places_the_shoulders_from_the_reference_trunk_frame(shared_data):
    """MVNX with both arms, calibrated on its reference (asked), root fixed: the chest frame
    comes from the reference's shoulders and hips, not from the T8 sensor taken as
    right-front-up (which points its x mostly down there and put every arm joint 0.25 m off).
    The shoulder spacing is still the anthropometric one (0.189 x 1.75 m = 0.33 m; the file's
    shoulders are 0.32 m apart): a few centimetres at most."""
    from kinefuse.pipelines.run.evaluate import evaluate_recording

    path = shared_data / "third_party" / "xsens" / "blender-mvnx-io_test_mocap.mvnx"
    ev = evaluate_recording(
        path, "imu-only", calibration="reference", root="fixed", body_height_m=1.75
    )
    assert "calibrated on reference" in ev.methods[0]
    arms = [i for i, j in enumerate(ev.joints) if j.startswith(("elbow", "wrist"))]
    assert len(arms) == 4
    assert np.all(ev.rmse_3d[0, arms] < 0.05)
