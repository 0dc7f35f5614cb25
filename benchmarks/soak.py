"""Soak test of every filter: ``python benchmarks/soak.py [--joint-steps N] [--json FILE]``.

Runs ``N`` joint-steps (default 10^7) through each of kinefuse's filters (KF, EM-KF, UFIR,
EM-KF/FIR, IMM) on random constant-velocity trajectories with random outages (NaN episodes
of 0.1-3 s) and outliers (1 m spikes), in chunks whose state is carried over (split and
resume), and checks at every sample: the mean is finite once the joint was observed, the
covariance is finite, symmetric and positive semi-definite. Prints one row per filter (the
worst values seen and the throughput) and exits 1 if any check failed.

Issue 12: "10^7 joint-steps through every filter with random outages and outliers - no NaN,
covariance PSD throughout".
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings

import numpy as np

from kinefuse.filters import IMM, EMKalmanFilter, IntegratedFilter, KalmanFilter, UFIRFilter
from kinefuse.models import constant_velocity

RATE_HZ = 30.0


def _trajectories(rng, B: int, T: int, start: np.ndarray) -> np.ndarray:
    """Constant-velocity-like joint paths, m: (B, T, 3), continuing from ``start`` (B, 3)."""
    acc = rng.normal(scale=0.5, size=(B, T, 3))
    vel = np.cumsum(acc, axis=1) / RATE_HZ
    vel -= vel.mean(axis=1, keepdims=True)  # bounded drift
    return start[:, None, :] + np.cumsum(vel, axis=1) / RATE_HZ


def _corrupt(rng, z: np.ndarray, noise_m: float) -> np.ndarray:
    """Measurement noise, outage episodes (NaN) and outliers."""
    B, T, _ = z.shape
    z = z + rng.normal(scale=noise_m, size=z.shape)
    for b in range(B):
        for _ in range(rng.poisson(T / RATE_HZ / 10.0)):  # one outage per 10 s on average
            k = rng.integers(T)
            z[b, k : k + int(rng.uniform(0.1, 3.0) * RATE_HZ)] = np.nan
    spikes = rng.random((B, T)) < 2e-3
    z[spikes] += rng.normal(scale=1.0, size=(int(spikes.sum()), 3))
    return z


class _Checks:
    def __init__(self):
        self.nan_means = 0
        self.bad_cov = 0
        self.worst_asym = 0.0
        self.worst_eig = np.inf  # smallest eigenvalue / largest diagonal entry

    def add(self, mean, cov, seen):
        """``mean (B, T, n)``, ``cov (B, T, n, n)``, ``seen (B, T)`` (observed at least once)."""
        m, P = mean[seen], cov[seen]
        self.nan_means += int(np.sum(~np.all(np.isfinite(m), axis=-1)))
        finite = np.all(np.isfinite(P), axis=(-2, -1))
        self.bad_cov += int(np.sum(~finite))
        P = P[finite]
        if P.size == 0:
            return
        scale = np.max(np.abs(np.diagonal(P, axis1=-2, axis2=-1)), axis=-1)
        asym = np.max(np.abs(P - np.swapaxes(P, -1, -2)), axis=(-2, -1)) / scale
        eig = np.linalg.eigvalsh(0.5 * (P + np.swapaxes(P, -1, -2)))[:, 0] / scale
        self.worst_asym = max(self.worst_asym, float(asym.max()))
        self.worst_eig = min(self.worst_eig, float(eig.min()))
        self.bad_cov += int(np.sum((asym > 1e-9) | (eig < -1e-9)))

    @property
    def ok(self) -> bool:
        return self.nan_means == 0 and self.bad_cov == 0


def _soak(name: str, flt, n_steps: int, batch: int, chunk: int, seed: int, imm: bool) -> dict:
    rng = np.random.default_rng(seed)
    n_chunks = max(1, int(np.ceil(n_steps / (batch * chunk))))
    state = None
    start = np.zeros((batch, 3))
    seen = np.zeros(batch, bool)
    checks = _Checks()
    t_filter = 0.0
    n_warn = 0  # NumericalWarnings (e.g. the EM covariance floor of SPEC §5.4 binding)
    for _ in range(n_chunks):
        truth = _trajectories(rng, batch, chunk, start)
        start = truth[:, -1]
        z = _corrupt(rng, truth, 0.01)
        if imm:  # IMU chain (drifting) and camera (noisier, own outages) of the same joint
            z_cam = _corrupt(rng, truth, 0.03)
            z = np.stack([z, z_cam], axis=-2)
            obs = np.any(np.all(np.isfinite(z), axis=-1), axis=-1)
        else:
            obs = np.all(np.isfinite(z), axis=-1)
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            state, res = flt.filter(z, state=state)
        t_filter += time.perf_counter() - t0
        n_warn += len(caught)
        seen_t = seen[:, None] | (np.cumsum(obs, axis=1) > 0)
        seen = seen_t[:, -1]
        checks.add(res.mean, res.cov, seen_t)
    steps = n_chunks * batch * chunk
    return {
        "filter": name,
        "joint_steps": steps,
        "nan_means": checks.nan_means,
        "bad_covariances": checks.bad_cov,
        "worst_relative_asymmetry": checks.worst_asym,
        "worst_relative_min_eigenvalue": checks.worst_eig,
        "numerical_warnings": n_warn,
        "filter_time_s": t_filter,
        "joint_steps_per_s": steps / t_filter if t_filter > 0 else float("nan"),
        "passed": checks.ok,
    }


def _filters():
    dt = 1.0 / RATE_HZ
    m = constant_velocity(dt, 0.5, 1e-4)
    m_cam = constant_velocity(dt, 0.5, 9e-4)
    return [
        ("KF", KalmanFilter(m), False),
        ("EM-KF", EMKalmanFilter(m), False),
        ("UFIR(N=20)", UFIRFilter(m, horizon=20), False),
        ("EM-KF/FIR(N=20)", IntegratedFilter(m, horizon=20), False),
        ("IMM(IMU, camera)", IMM(m, m_cam), True),
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--joint-steps", type=float, default=1e7, help="per filter (default 1e7)")
    ap.add_argument("--batch", type=int, default=200, help="joints filtered together")
    ap.add_argument("--chunk", type=int, default=2500, help="samples per resumed chunk")
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    rows = []
    for i, (name, flt, imm) in enumerate(_filters()):
        flt.filter(np.zeros((1, 30, 2, 3) if imm else (1, 30, 3)))  # compile outside the timing
        row = _soak(name, flt, int(args.joint_steps), args.batch, args.chunk, args.seed + i, imm)
        rows.append(row)
        print(
            f"{name:18s} {row['joint_steps']:>10d} joint-steps  NaN means {row['nan_means']}  "
            f"bad covariances {row['bad_covariances']}  max asym {row['worst_relative_asymmetry']:.1e}  "
            f"min eig/diag {row['worst_relative_min_eigenvalue']:.1e}  "
            f"{row['joint_steps_per_s'] / 1e6:.2f} M joint-steps/s  "
            f"warnings {row['numerical_warnings']}  "
            f"{'PASS' if row['passed'] else 'FAIL'}",
            flush=True,
        )
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=2)
    passed = all(r["passed"] for r in rows)
    print(f"soak: {'PASSED' if passed else 'FAILED'}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
