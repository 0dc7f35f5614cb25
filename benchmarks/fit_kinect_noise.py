"""Fit the virtual depth camera's noise defaults to the real UTD-MHAD Kinect v1 skeletons.

Run: ``python benchmarks/fit_kinect_noise.py [path/to/shared/data]``. Prints the figures quoted in
:class:`kinefuse.sim.CameraConfig` (``noise_std_m`` and ``bone_length_std``).

Method
------
Jitter (``noise_std_m``)
    Still joints only: the lower-body joints (hips, knees, ankles, feet; UTD joints 13-20) in the
    arm-only actions 1-21, where the subject stands. Each coordinate track (Kinect camera axes x
    lateral, y up, z depth) is smoothed with a Savitzky-Golay filter (window 9 frames = 0.3 s at
    30 Hz, order 2); the residual is the high-pass part. Frames where the smoothed speed exceeds
    0.05 m/s are dropped (residual sway). For white noise of std sigma the residual of this
    linear-phase projection has std ``sigma * sqrt(1 - h_c)`` with ``h_c`` the filter's centre
    tap, so the residual std is divided by ``sqrt(1 - h_c)``. Reported: pooled RMS per axis.
    A second estimator (second differences, ``std(d2) / sqrt(6)``) is printed as a check.
Bone-length variation (``bone_length_std``)
    Per trial and bone (upper arms, forearms, thighs, shanks), std of the bone length over the
    trial divided by its mean; the median over trials is reported separately for bones that move
    (arms in actions 1-21) and bones that are still (legs in actions 1-21), and pooled over all
    27 actions and the eight limb bones (the default). The correlation time is the lag at which
    the autocorrelation of the relative length deviation first drops below 1/e (median).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import scipy.io as sio
from scipy.signal import savgol_coeffs, savgol_filter

RATE_HZ = 30.0
WINDOW, ORDER = 9, 2
STILL_SPEED_M_S = 0.05
STILL_JOINTS = list(range(12, 20))  # 0-based: L/R hip, knee, ankle, foot
ARM_BONES = {
    "upper_arm_l": (4, 5),
    "forearm_l": (5, 6),
    "upper_arm_r": (8, 9),
    "forearm_r": (9, 10),
}
LEG_BONES = {"thigh_l": (12, 13), "shank_l": (13, 14), "thigh_r": (16, 17), "shank_r": (17, 18)}


def main(data: Path) -> None:
    skel_dir = data / "utd_mhad" / "Skeleton"
    files = sorted(skel_dir.glob("a*_s*_t*_skeleton.mat"))
    h_c = savgol_coeffs(WINDOW, ORDER)[WINDOW // 2]
    res_all, d2_all = [], []
    rel_moving, rel_still, rel_all, tau_s = [], [], [], []
    for f in files:
        action = int(f.name.split("_")[0][1:])
        s = sio.loadmat(f)["d_skel"].astype(float)  # (20, 3, T) metres
        for a, b in (*ARM_BONES.values(), *LEG_BONES.values()):
            e = np.linalg.norm(s[a] - s[b], axis=0)
            e = e / e.mean() - 1.0
            rel_all.append(e.std())
            e = e - e.mean()
            if np.any(e != 0):
                ac = np.correlate(e, e, "full")[e.size - 1 :] / (e @ e)
                k = int(np.argmax(ac < np.exp(-1.0)))
                if k > 0:
                    tau_s.append(k / RATE_HZ)
        if action > 21:
            continue
        if s.shape[2] < 2 * WINDOW:
            continue
        x = s[STILL_JOINTS]  # (8, 3, T)
        smooth = savgol_filter(x, WINDOW, ORDER, axis=-1)
        speed = np.linalg.norm(savgol_filter(x, WINDOW, ORDER, deriv=1, axis=-1), axis=1) * RATE_HZ
        still = speed < STILL_SPEED_M_S  # (8, T)
        res = (x - smooth) / np.sqrt(1.0 - h_c)
        res_all.append(res.transpose(0, 2, 1)[still])  # (n, 3)
        d2 = x[..., 2:] - 2 * x[..., 1:-1] + x[..., :-2]
        d2_all.append((d2 / np.sqrt(6.0)).transpose(0, 2, 1)[still[:, 1:-1]])
        for bones, out in ((ARM_BONES, rel_moving), (LEG_BONES, rel_still)):
            for a, b in bones.values():
                length = np.linalg.norm(s[a] - s[b], axis=0)
                out.append(length.std() / length.mean())
    res = np.concatenate(res_all)
    d2 = np.concatenate(d2_all)
    print(f"trials used: actions 1-21, {len(res_all)} trials, {res.shape[0]} still joint-frames")
    print(
        "jitter sigma per camera axis (x lateral, y up, z depth), SG residual [mm]:",
        np.round(1e3 * np.sqrt(np.mean(res**2, axis=0)), 2),
    )
    print(
        "jitter sigma pooled over axes, SG residual [mm]:",
        round(1e3 * float(np.sqrt(np.mean(res**2))), 2),
    )
    print(
        "jitter sigma per axis, second differences [mm]:",
        np.round(1e3 * np.sqrt(np.mean(d2**2, axis=0)), 2),
    )
    print(
        f"relative bone-length std, moving arm bones: median {np.median(rel_moving):.4f}, IQR {np.percentile(rel_moving, 25):.4f}-{np.percentile(rel_moving, 75):.4f}"
    )
    print(
        f"relative bone-length std, all actions and limb bones: median {np.median(rel_all):.4f}; correlation time median {np.median(tau_s):.3f} s"
    )
    print(
        f"relative bone-length std, still leg bones:  median {np.median(rel_still):.4f}, IQR {np.percentile(rel_still, 25):.4f}-{np.percentile(rel_still, 75):.4f}"
    )


if __name__ == "__main__":
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else default)
