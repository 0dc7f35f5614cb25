"""Outage-bridging study: ``"kinefuse"`` against paper B's methods on three scenarios.

Run from the repository root::

    python benchmarks/fusion_study.py [cmu] [utd] [neura] [--causal] [--report]

On the declared tuning set (:data:`kinefuse.apps.splits.TUNING_SET`: CMU subject 02,
UTD-MHAD subjects 1-3) by default, the only set to develop on; ``--report`` runs the report set
(CMU subject 03, UTD-MHAD subjects 4-6; the Neura walk belongs to it), never to choose anything.

Prints, per scenario and method, per joint RMSE along x/y/z and 3-D, and the error at CDF 0.9,
inside the camera outages and overall, pooled over the scenario's trials. The simple baselines
(``offset-interp`` offline, ``offset-hold`` causal, ``camera-gapfill``) run beside the fusions.
Calibration never sees a hidden sample (``tests/test_leakage.py``).

Scenarios
---------
cmu
    The set's CMU trials (arm-dominant and walking) drive 9 virtual IMUs (ICM-20948 error
    model, AHRS heading drift, 2° mounting error) and a virtual Kinect (UTD-MHAD-fitted jitter
    and bone-length variation, ENU), :func:`kinefuse.sim.virtual_recording`. The chain
    (SPEC §2.2, chest origin) uses axes and lengths from :func:`kinefuse.kinematics.calibrate`
    (vision, first 2 s) and shoulder/hip offsets in the chest-IMU frame averaged over the same
    window. Everything is chest-relative (joint − spine_shoulder), as in paper B. Outages: per
    joint, independent renewal process, visible Exp(mean 4 s), hidden U[0.5, 2] s, none in the
    first 2 s; eight joints (elbows, wrists, knees, ankles). Scored against the mocap truth.
utd
    UTD-MHAD actions 1-21, the set's subjects (trial 1): the real wrist IMU (acc+gyr, 50 Hz) gives the
    forearm orientation (VQF 6D, :func:`kinefuse.orientation.estimate`); the axis and the
    IMU-world -> Kinect rotation come from :func:`kinefuse.kinematics.calibrate` (vision,
    ``align="rotation"``) on the camera-seen frames; the chain wrist is Kinect elbow + forearm
    length x direction. The Kinect wrist is hidden in one window of 25 % of the trial placed in
    its second half; scored against the hidden Kinect wrist.
neura (evaluation only; never used to choose anything)
    Real Xsens thigh/shank orientations; roots = Vicon hip centres; chain knees/ankles with
    axes and lengths calibrated against Vicon over the first 2 s (reference-to-IMU frames are
    shared). Virtual camera = Vicon knee/ankle + white 2 cm noise per axis, 30 Hz, with 1.5 s
    outages per joint (visible Exp(mean 3 s)). Scored against Vicon.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

from kinefuse.apps.splits import REPORT_SET, TUNING_SET
from kinefuse.evaluation.metrics import error_at
from kinefuse.io.cmu import load_motion_asf_amc
from kinefuse.io.neura import read_neura
from kinefuse.io.recording import ImuStream, JointStream, Recording
from kinefuse.io.utd_mhad import read_utd_mhad
from kinefuse.kinematics import (
    as_rotation_matrices,
    calibrate,
    forward_kinematics,
    full_body,
    lower_body,
    upper_limb,
)
from kinefuse.orientation import estimate
from kinefuse.orientation.resample import slerp_resample
from kinefuse.pipelines import vision_assisted
from kinefuse.pipelines.features import imu_features
from kinefuse.pipelines.kinefuse_fusion import kinefuse_fusion
from kinefuse.sim import CameraConfig, virtual_recording

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
JOINTS8 = ("elbow_l", "elbow_r", "wrist_l", "wrist_r", "knee_l", "knee_r", "ankle_l", "ankle_r")
CAL_S = 2.0


# ----------------------------------------------------------------------------- outages
def renewal_outages(T, J, dt, rng, *, visible_mean_s=4.0, hidden_s=(0.5, 2.0), free_s=CAL_S):
    """Per-joint availability (T, J): alternating Exp(visible) / U(hidden) periods."""
    av = np.ones((T, J), dtype=bool)
    for j in range(J):
        t = free_s + rng.exponential(visible_mean_s)
        while t < T * dt:
            d = rng.uniform(*hidden_s)
            a, b = int(round(t / dt)), int(round((t + d) / dt))
            av[a : min(b, T), j] = False
            t += d + max(rng.exponential(visible_mean_s), 0.3)
    return av


# ----------------------------------------------------------------------------- scenarios
def _rot(stream, t):
    return as_rotation_matrices(slerp_resample(stream.t_s, stream.q_world_from_sensor, t))


def cmu_trial(name: str, seed: int = 0) -> dict:
    motion = load_motion_asf_amc(DATA / "cmu_mocap" / "asfamc" / name[:2] / f"{name}.amc")
    cam = CameraConfig(occlusion_rate_per_min=0.0, dropout_rate_per_min=0.0)
    rec = virtual_recording(motion, camera=cam, seed=seed)
    v, ref = rec.vision, rec.reference
    t = v.t_s
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(rec, full_body(height_m=1.7), "vision", window_s=CAL_S, align="none")
    sk = cal.apply(full_body(height_m=1.7))
    ori = {s: _rot(rec.imu[s], t) for s in (*sk.segments, "chest")}
    win = t < t[0] + CAL_S
    ss = v.position("spine_shoulder")
    offs = {
        j: np.nanmean(np.einsum("tji,tj->ti", ori["chest"][win], (v.position(j) - ss)[win]), 0)
        for j in ("shoulder_l", "shoulder_r", "hip_l", "hip_r")
    }
    sk = sk.with_offsets(offs)
    pos = forward_kinematics(sk, ori, np.zeros((t.size, 3)))
    z_imu = np.stack([pos[j] for j in JOINTS8], 1)
    z_cam = np.stack([v.position(j) - ss for j in JOINTS8], 1)
    truth = np.stack([ref.position(j) - ref.position("spine_shoulder") for j in JOINTS8], 1)
    dt = float(np.median(np.diff(t)))
    rng = np.random.default_rng([seed, 7, int(name.replace("_", ""))])
    av = renewal_outages(t.size, len(JOINTS8), dt, rng) & np.all(np.isfinite(z_cam), -1)
    feats = imu_features(rec, sk, JOINTS8, t)
    return dict(
        name=name,
        z_imu=z_imu,
        z_cam=z_cam,
        truth=truth,
        available=av,
        dt=dt,
        features=feats,
        joints=JOINTS8,
        parents=[-1, -1, 0, 1, -1, -1, 4, 5],
    )


def utd_trial(action: int, subject: int, trial: int = 1, seed: int = 0) -> dict | None:
    p = DATA / "utd_mhad" / "Inertial" / f"a{action}_s{subject}_t{trial}_inertial.mat"
    if not p.is_file():
        return None
    return utd_inputs(read_utd_mhad(p), action, subject, trial, seed)


def utd_inputs(rec, action: int, subject: int, trial: int = 1, seed: int = 0) -> dict:
    """The UTD-MHAD scenario of one loaded trial (calibration on camera-seen frames only)."""
    imu = rec.imu["forearm_r"]
    q = estimate(imu.acc_m_s2, imu.gyr_rad_s, rate_hz=imu.rate_hz)
    rec.imu["forearm_r"] = ImuStream(
        t_s=imu.t_s,
        q_world_from_sensor=q,
        acc_m_s2=imu.acc_m_s2,
        gyr_rad_s=imu.gyr_rad_s,
        name=imu.name,
    )
    v = rec.vision
    t = v.t_s
    T = t.size
    dt = float(np.median(np.diff(t)))
    rng = np.random.default_rng([seed, 11, action, subject, trial])
    L = max(int(round(0.25 * T)), 3)
    a = int(rng.integers(int(0.45 * T), max(int(0.75 * T) - L, int(0.45 * T)) + 1))
    av = np.ones((T, 1), dtype=bool)
    av[a : a + L, 0] = False
    # calibration (forearm axis + IMU-world -> Kinect rotation) on the camera-seen frames only

    seen_v = JointStream(
        t_s=t,
        position_m=v.position_m,
        available=v.available & av[:, [0] * 20] | (np.arange(20)[None] != v.index("wrist_r")),
        joints=v.joints,
        frame=v.frame,
    )
    rec_seen = Recording(imu=rec.imu, vision=seen_v)
    sk = upper_limb("r", lengths={"upper_arm_r": 0.3, "forearm_r": 0.25})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(
            rec_seen, sk, "vision", window_s=1e9, align="rotation", segments=["forearm_r"]
        )
    Rc = cal.R_world_from_camera
    R = _rot(rec.imu["forearm_r"], t)
    d = np.einsum("ji,tjk,k->ti", Rc, R, cal.axes["forearm_r"])  # camera-frame direction
    elbow = v.position("elbow_r")
    wrist = v.position("wrist_r")
    length = np.nanmedian(np.linalg.norm((wrist - elbow)[av[:, 0]], axis=-1))
    z_imu = (elbow + length * d)[:, None]
    z_cam = wrist[:, None]
    feats = imu_features(
        {"forearm_r": rec.imu["forearm_r"]}, sk, ["wrist_r"], t, R_world_from_camera=Rc
    )
    return dict(
        name=f"a{action}_s{subject}_t{trial}",
        z_imu=z_imu,
        z_cam=z_cam,
        truth=z_cam.copy(),
        available=av,
        dt=dt,
        features=feats,
        joints=("wrist_r",),
        parents=None,
    )


def neura_trial(seed: int = 0) -> dict:
    rec = read_neura(DATA / "neura_sparse_sample")
    ref = rec.reference
    t_all = ref.t_s
    t = np.arange(t_all[0], t_all[-1], 1 / 30.0)
    joints = ("knee_l", "knee_r", "ankle_l", "ankle_r")
    sk0 = lower_body(
        lengths={"thigh_l": 0.4, "thigh_r": 0.4, "shank_l": 0.4, "shank_r": 0.4},
        hip_offsets={"hip_l": (np.nan,) * 3, "hip_r": (np.nan,) * 3},
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(rec, sk0, "reference", window_s=CAL_S, align="none")
    sk = cal.apply(sk0)
    ori = {s: _rot(rec.imu[s], t) for s in sk.segments}
    interp = lambda j: np.stack([np.interp(t, t_all, ref.position(j)[:, a]) for a in range(3)], 1)  # noqa: E731
    pos = forward_kinematics(sk, ori, {"hip_l": interp("hip_l"), "hip_r": interp("hip_r")})
    truth = np.stack([interp(j) for j in joints], 1)
    z_imu = np.stack([pos[j] for j in joints], 1)
    rng = np.random.default_rng([seed, 13])
    z_cam = truth + rng.normal(0.0, 0.02, truth.shape)
    dt = 1 / 30.0
    av = renewal_outages(t.size, len(joints), dt, rng, visible_mean_s=3.0, hidden_s=(1.5, 1.5))
    feats = imu_features(rec, sk, joints, t)
    return dict(
        name="neura",
        z_imu=z_imu,
        z_cam=z_cam,
        truth=truth,
        available=av,
        dt=dt,
        features=feats,
        joints=joints,
        parents=[-1, -1, 0, 1],
    )


# ----------------------------------------------------------------------------- methods
def run_method(method: str, tr: dict, causal: bool) -> np.ndarray:
    zi, zc, av, dt = tr["z_imu"], tr["z_cam"], tr["available"], tr["dt"]
    zc = np.where(av[..., None], zc, np.nan)
    if method == "kinefuse":
        return kinefuse_fusion(zi, zc, av, dt, causal=causal, features=tr["features"]).position
    if method == "kinefuse-nofeat":
        return kinefuse_fusion(zi, zc, av, dt, causal=causal, parents=tr["parents"]).position
    if method == "chain":
        return zi.copy()
    if method == "bias-exp":  # exponential bias tracker (tau 1 s), camera where seen
        a = dt / 1.0
        out = zi.copy()
        for j in range(zi.shape[1]):
            b = np.zeros(3)
            for t in range(zi.shape[0]):
                if av[t, j]:
                    b = b + a * (zc[t, j] - zi[t, j] - b)
                    out[t, j] = zc[t, j]
                else:
                    out[t, j] = zi[t, j] + b
        return out

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return vision_assisted(zi, zc, av, dt, method=method, causal=causal).position


# ----------------------------------------------------------------------------- tables
def table(title, trials, results, methods):
    print(f"\n=== {title} ===  (cm; 'in' = inside outages, 'all' = every sample)")
    joints = trials[0]["joints"]
    head = f"{'method':<16}{'joint':<9}" + "".join(
        f"{h:>7}" for h in ("in x", "in y", "in z", "in 3D", "in p90", "all 3D", "all p90", "n_in")
    )
    print(head)
    summary = {}
    for m in methods:
        for j, jn in enumerate([*joints, "ALL"]):
            E, M = [], []
            for tr, est in zip(trials, results[m], strict=True):
                sl = slice(None) if jn == "ALL" else slice(j, j + 1)
                e = (est[:, sl] - tr["truth"][:, sl]).reshape(-1, 3)
                E.append(e)
                M.append((~tr["available"][:, sl]).reshape(-1))
            E, M = np.concatenate(E), np.concatenate(M)
            ok = np.all(np.isfinite(E), 1)
            rin = np.sqrt(np.mean(E[M & ok] ** 2, 0)) * 100
            r3 = np.sqrt(np.mean(np.sum(E[M & ok] ** 2, 1))) * 100
            ra = np.sqrt(np.mean(np.sum(E[ok] ** 2, 1))) * 100
            p_in = float(error_at(E[M & ok], np.zeros_like(E[M & ok]), p=0.9)) * 100
            p_all = float(error_at(E[ok], np.zeros_like(E[ok]), p=0.9)) * 100
            if jn == "ALL" or len(joints) > 1:
                print(
                    f"{m:<16}{jn:<9}"
                    + "".join(f"{x:7.2f}" for x in (*rin, r3, p_in, ra, p_all))
                    + f"{int((M & ok).sum()):7d}"
                )
            if jn == "ALL":
                ro = np.sqrt(np.mean(np.sum(E[~M & ok] ** 2, 1))) * 100
                summary[m] = (r3, ra, ro)
    print(f"\n{'summary':<16}{'in 3D':>8}{'all 3D':>8}{'out 3D':>8}")
    for m, (a, b, c) in summary.items():
        print(f"{m:<16}{a:8.2f}{b:8.2f}{c:8.2f}")
    return summary


def _trim(tr):
    """Keep the samples where the chain exists (IMU and camera timelines differ at the ends)."""
    ok = np.all(np.isfinite(tr["z_imu"]), axis=(1, 2)) & np.all(
        np.isfinite(tr["features"]), axis=(1, 2)
    )
    idx = np.flatnonzero(ok)
    sl = slice(idx[0], idx[-1] + 1)
    return {k: (v[sl] if isinstance(v, np.ndarray) and v.ndim >= 2 else v) for k, v in tr.items()}


def study(name, trials, causal):
    trials = [_trim(tr) for tr in trials]
    methods = [
        "kinefuse",
        "kinefuse-nofeat",
        "elm-fir",
        "elm-kf",
        "imu-only",
        "camera-only",
        "camera-gapfill",
        "offset-interp",
        "offset-hold",
        "chain",
        "bias-exp",
    ]
    if causal:  # methods that read the future
        for m in ("camera-only", "camera-gapfill", "offset-interp"):
            methods.remove(m)
    results = {m: [] for m in methods}
    t0 = time.time()
    for tr in trials:
        for m in methods:
            results[m].append(run_method(m, tr, causal))
    print(
        f"\n[{name}: {len(trials)} trials, {'causal' if causal else 'offline'}, "
        f"{time.time() - t0:.1f} s]"
    )
    return table(f"{name} ({'causal' if causal else 'offline'})", trials, results, methods)


def main(argv):
    causal = "--causal" in argv
    split = REPORT_SET if "--report" in argv else TUNING_SET
    print(split.describe())
    which = [a for a in argv if not a.startswith("--")] or ["cmu", "utd"]
    if "cmu" in which:
        trials = [cmu_trial(n) for n in split.cmu_trials]
        study(f"CMU-virtual full body, {split.name} set", trials, causal)
    if "utd" in which:
        trials = [
            tr
            for a in range(1, 22)
            for s in split.utd_subjects
            if (tr := utd_trial(a, s)) is not None
        ]
        study(f"UTD-MHAD real wrist, {split.name} set", trials, causal)
    if "neura" in which and split.neura:
        study("Neura walk (evaluation only)", [neura_trial()], causal)


if __name__ == "__main__":
    main(sys.argv[1:])
