"""Orientation accuracy of :func:`kinefuse.orientation.estimate` on BROAD (Laidig et al. 2021).

Run::

    python benchmarks/broad_orientation.py [path/to/broad]

(default path: ``../shared/data/broad`` beside the checkout). For every ``data_mat/*.mat`` trial
it reports the RMSE over the motion phase (``movement == 1``) of

* ``9D``: VQF with magnetometer (causal), total / heading / inclination error, deg;
* ``9D-off``: offline VQF with magnetometer, total error, deg;
* ``6D``: VQF without magnetometer, inclination error only (6D heading is arbitrary), deg.

Error convention = BROAD's own evaluation (``example_code/broad_utils.py`` of dlaidig/broad):
the error quaternion is expressed in the earth frame, ``q_err = q_imu ⊗ q_opt⁻¹``; total error =
its rotation angle; heading error = the angle of its rotation about the vertical
``2·atan(|z/w|)``; inclination error = ``2·acos(sqrt(w² + z²))``. No extra alignment is
applied: ``opt_quat`` is already IMU -> ENU (BROAD SOURCE.md), and VQF's 9D earth frame is ENU.
Samples where the optical reference is NaN are left out (``nanmean``), as in BROAD.
VQF runs with its default parameters (no tuning on BROAD).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.io as sio

from kinefuse.orientation import estimate

DEFAULT_PATH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "broad"


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def orientation_errors_deg(
    q_est: np.ndarray, q_ref: np.ndarray, mask: np.ndarray
) -> dict[str, float]:
    """BROAD's total / heading / inclination RMSE, deg, over ``mask`` (NaN reference rows skipped).

    Parameters
    ----------
    q_est, q_ref : ndarray, shape (T, 4)
        ``q_world_from_sensor`` (``wxyz``, ENU) estimated and reference.
    mask : ndarray of bool, shape (T,)
        Samples to evaluate (BROAD: the motion phases).
    """
    qe = q_est / np.linalg.norm(q_est, axis=1, keepdims=True)
    qr = q_ref / np.linalg.norm(q_ref, axis=1, keepdims=True)
    qr_inv = qr * np.array([1.0, -1.0, -1.0, -1.0])
    d = _qmul(qe, qr_inv)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        total = 2 * np.arccos(np.clip(np.abs(d[:, 0]), 0, 1))
        heading = 2 * np.arctan(np.abs(d[:, 3] / d[:, 0]))
        incl = 2 * np.arccos(np.clip(np.sqrt(d[:, 0] ** 2 + d[:, 3] ** 2), 0, 1))

    def rmse(e):
        return float(np.rad2deg(np.sqrt(np.nanmean(e[mask] ** 2))))

    return {"total": rmse(total), "heading": rmse(heading), "inclination": rmse(incl)}


def evaluate_trial(path: Path) -> dict[str, float]:
    """All figures of one BROAD ``.mat`` trial (see the module docstring)."""
    d = sio.loadmat(path, squeeze_me=True)
    acc, gyr, mag = d["imu_acc"], d["imu_gyr"], d["imu_mag"]
    fs = float(d["sampling_rate"])
    q_ref = d["opt_quat"]
    move = d["movement"].astype(bool)
    e9 = orientation_errors_deg(estimate(acc, gyr, mag, rate_hz=fs), q_ref, move)
    e9off = orientation_errors_deg(estimate(acc, gyr, mag, rate_hz=fs, offline=True), q_ref, move)
    e6 = orientation_errors_deg(estimate(acc, gyr, rate_hz=fs), q_ref, move)
    return {
        "9D_total": e9["total"],
        "9D_heading": e9["heading"],
        "9D_incl": e9["inclination"],
        "9Doff_total": e9off["total"],
        "6D_incl": e6["inclination"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "path", nargs="?", default=str(DEFAULT_PATH), help="BROAD folder (holding data_mat/)"
    )
    args = ap.parse_args(argv)
    folder = Path(args.path)
    files = (
        sorted((folder / "data_mat").glob("*.mat"))
        if (folder / "data_mat").is_dir()
        else sorted(folder.glob("*.mat"))
    )
    if not files:
        print(f"no BROAD .mat files under {folder}", file=sys.stderr)
        return 1
    cols = ["9D_total", "9D_heading", "9D_incl", "9Doff_total", "6D_incl"]
    print("BROAD orientation RMSE over motion phases, deg (VQF defaults; BROAD error convention)")
    print(f"{'trial':44s} " + " ".join(f"{c:>11s}" for c in cols))
    rows = []
    t0 = time.perf_counter()
    for f in files:
        r = evaluate_trial(f)
        rows.append([r[c] for c in cols])
        print(f"{f.stem:44s} " + " ".join(f"{r[c]:11.2f}" for c in cols))
    m = np.mean(rows, axis=0)
    print(f"{'mean over ' + str(len(files)) + ' trials':44s} " + " ".join(f"{v:11.2f}" for v in m))
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
