"""IMU chain on the Neura walk: Xsens thigh/shank orientations + Vicon hip centres -> knees, ankles.

Run::

    python examples/neura_chain.py [path/to/neura_sparse_sample]

Calibration = the first second against the Vicon joint centres (segment axis in each sensor
frame and segment length); IMUs and Vicon share a world frame (SOURCE.md), so no alignment.
Prints the 3-D RMSE per joint and the papers' metric (mean of the per-axis RMSEs), cm.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from kinefuse.io.neura import read_neura
from kinefuse.kinematics import Skeleton, calibrate, chain_positions

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "neura_sparse_sample"


def main(argv: list[str] | None = None) -> dict[str, tuple[float, float]]:
    args = sys.argv[1:] if argv is None else argv
    rec = read_neura(args[0] if args else DEFAULT)
    sk = Skeleton.from_joint_stream(rec.reference, "lower_body", window_s=1.0)
    cal = calibrate(rec, sk, "reference", window_s=1.0)
    est = chain_positions(rec, sk, cal, root=("hip_l", "hip_r"))
    out = {}
    print(f"{'joint':8s} {'3-D RMSE':>9s} {'mean-axes':>9s}  (cm, whole walk, {len(est)} samples)")
    for j in ("knee_l", "knee_r", "ankle_l", "ankle_r"):
        e = est.position(j) - rec.reference.position(j)
        r3 = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
        ra = float(np.mean(np.sqrt(np.mean(e**2, axis=0))))
        out[j] = (r3, ra)
        print(f"{j:8s} {100 * r3:9.2f} {100 * ra:9.2f}")
    m3, ma = np.mean([v[0] for v in out.values()]), np.mean([v[1] for v in out.values()])
    print(f"{'mean':8s} {100 * m3:9.2f} {100 * ma:9.2f}")
    return out


if __name__ == "__main__":
    main()
