"""``kinefuse bench``: the filter rows — kinefuse's filters and smoother next to filterpy's.

Microseconds per joint-step (median of repeats, this thread's CPU time) of ``KalmanFilter.filter``
and ``rts_smooth`` against filterpy's predict/update loop and ``rts_smoother``; the online
``step`` / ``OnlineFilter.update`` against one filterpy predict/update; UFIR, EM-KF and the
integrated EM-KF/FIR filter; and a second process's import + first call. filterpy (the peer, an
optional dependency: the ``bench`` extra) is imported where it is used.
"""

from __future__ import annotations

import functools
import importlib
import json
import subprocess
import sys
import time
import warnings

import numpy as np

import kinefuse.filters as kf_mod
from kinefuse.filters import KalmanFilter, OnlineFilter, rts_smooth
from kinefuse.filters._base import initial_covariance
from kinefuse.models import constant_velocity

__all__ = [
    "DT_S",
    "KF_OUTPUTS",
    "PAPER_TABLE6_US",
    "Q_PAPER",
    "R_PAPER",
    "UFIR_HORIZONS",
    "UFIR_NO_COV",
    "filterpy_filter",
    "kf_rts_rows",
    "make_data",
    "measure",
    "measure_interleaved",
    "paper_model",
    "online_rows",
    "other_filter_rows",
    "second_process_time",
]

#: What the KF rows ask for: the outputs filterpy's loop stores (x and P per step). ``KF*`` rows
#: time every output (position, innovation, NIS, observed flags as well).
KF_OUTPUTS = ("mean", "cov")

#: UFIR horizons timed; the O(1) claim is checked over these.
UFIR_HORIZONS = (10, 40, 200)

#: UFIR outputs without the covariance (its closed form on horizons with gaps is the costlier part).
UFIR_NO_COV = ("mean", "position", "observed", "innovation")

#: Paper A (Sun 2024) Table 6, MATLAB, per step (one joint): KF 0.037 ms, FIR 0.237 ms, EM-KF/FIR 7.954 ms.
PAPER_TABLE6_US = {"KF": 37.0, "UFIR(N=20)": 237.0, "integrated": 7954.0}

DT_S = 1 / 30

Q_PAPER = 1.0

R_PAPER = 0.01


def paper_model():
    """Paper A's elbow test-1 model: constant velocity, dt = 1/30 s, q = 1, R = 0.01 I."""
    return constant_velocity(DT_S, q=Q_PAPER, r=R_PAPER)


def make_data(
    n_joints: int, n_steps: int, seed: int = 0, missing: float = 0.02, own_gaps: bool = False
) -> np.ndarray:
    """Random-walk joint positions with 1 cm noise and a few missing rows, ``(n_joints, T, 3)`` m.

    The missing rows are frames lost for every joint (a camera dropout), or with ``own_gaps``
    drawn for each joint on its own (occlusions).
    """
    rng = np.random.default_rng(seed)
    vel = np.cumsum(rng.normal(scale=0.05, size=(n_joints, n_steps, 3)), axis=1) * DT_S
    z = np.cumsum(vel, axis=1) + rng.normal(scale=0.01, size=(n_joints, n_steps, 3))
    if own_gaps:
        z[rng.random((n_joints, n_steps)) < missing] = np.nan
    else:
        z[:, rng.random(n_steps) < missing] = np.nan
    z[:, 0] = np.where(np.isnan(z[:, 0]), 0.0, z[:, 0])
    return z


def measure(fn, repeats: int) -> tuple[float, float]:
    """Median (CPU seconds, wall seconds) of ``repeats`` calls (after one warm-up call)."""
    return measure_interleaved({"fn": fn}, repeats)["fn"]


def measure_interleaved(calls: dict, repeats: int, warm_up: bool = True) -> dict:
    """Median ``(CPU seconds, wall seconds)`` per call of each of ``calls`` (label -> callable),
    timed in interleaved rounds: every round calls each once (after one warm-up call each,
    unless the caller made it: ``warm_up=False``).

    Rows that are compared with each other (a filter and its peer, UFIR horizons) then see the
    same phases of a shared machine, instead of one burst each. Within a round each row is
    called twice in a row and the second call is timed: a call inherits the memory and cache
    state its predecessor leaves, and on this project's 2-core VM a UFIR call right after the
    integrated filter's took 0.01 µs a joint-step more (a fifth of its time), charged to
    whichever row came next. Timed after itself, each row measures its own steady state (one
    row alone is called once a round: its predecessor is itself).
    """
    for fn in calls.values() if warm_up else ():
        fn()
    times = {label: ([], []) for label in calls}
    for _ in range(repeats):
        for label, fn in calls.items():
            if len(calls) > 1:  # untimed: the timed call follows this row's own (docstring)
                fn()
            w0, c0 = time.perf_counter(), time.thread_time()
            fn()
            times[label][0].append(time.thread_time() - c0)
            times[label][1].append(time.perf_counter() - w0)
    return {k: (float(np.median(c)), float(np.median(w))) for k, (c, w) in times.items()}


def filterpy_filter(model, z):
    """filterpy predict/update loop over ``z (n_joints, T, 3)``; returns means, covs lists."""
    from filterpy.kalman import KalmanFilter as FKF

    out = []
    for zj in z:
        kf = FKF(dim_x=model.n_x, dim_z=model.n_z)
        kf.F, kf.H, kf.Q, kf.R = model.F.copy(), model.H.copy(), model.Q.copy(), model.R.copy()
        kf.x = np.zeros((model.n_x, 1))
        kf.x[0::2, 0] = zj[0]
        kf.P = initial_covariance(model)
        xs = np.empty((len(zj), model.n_x))
        Ps = np.empty((len(zj), model.n_x, model.n_x))
        for t in range(len(zj)):
            kf.predict()
            if not np.isnan(zj[t, 0]):
                kf.update(zj[t].reshape(-1, 1))
            xs[t] = kf.x[:, 0]
            Ps[t] = kf.P
        out.append((xs, Ps))
    return out


def _filterpy_rts(model, filtered):
    from filterpy.kalman import rts_smoother

    for xs, Ps in filtered:
        n = len(xs)
        rts_smoother(xs, Ps, [model.F] * n, [model.Q] * n)


def kf_rts_rows(quick: bool) -> list[dict]:
    """KF (outputs mean + cov, and every output) and RTS per joint-step, next to filterpy."""
    model = paper_model()
    kf = KalmanFilter(model)
    n_steps_target = 2_000 if quick else 20_000
    budget = 40_000 if quick else 400_000  # joint-steps per kinefuse call for big batches
    fp_steps = 300 if quick else 2_000
    repeats = 3 if quick else 7
    rows = []
    for n_joints in (1, 8, 64, 1024):
        T = int(min(n_steps_target, max(100, budget // n_joints)))
        z = make_data(n_joints, T, seed=n_joints)
        n_js = n_joints * T
        _, res = kf.filter(z, outputs=KF_OUTPUTS + ("observed",))
        kf_cpu, kf_wall = measure(lambda z=z: kf.filter(z, outputs=KF_OUTPUTS), repeats)
        kfa_cpu, kfa_wall = measure(lambda z=z: kf.filter(z), repeats)
        rts_cpu, rts_wall = measure(lambda res=res: rts_smooth(model, res, position=False), repeats)
        fp_j = min(n_joints, 2)
        fp_T = min(T, fp_steps)
        zf = z[:fp_j, :fp_T]
        fp_cpu, fp_wall = measure(lambda zf=zf: filterpy_filter(model, zf), max(1, repeats // 2))
        filtered = filterpy_filter(model, zf)
        fpr_cpu, fpr_wall = measure(
            lambda f=filtered: _filterpy_rts(model, f), max(1, repeats // 2)
        )
        fp_js = fp_j * fp_T
        for name, cpu, wall, pcpu, pwall in (
            ("KF", kf_cpu, kf_wall, fp_cpu, fp_wall),
            ("KF*", kfa_cpu, kfa_wall, fp_cpu, fp_wall),
            ("RTS", rts_cpu, rts_wall, fpr_cpu, fpr_wall),
        ):
            us = cpu / n_js * 1e6
            peer = pcpu / fp_js * 1e6
            rows.append(
                {
                    "case": name,
                    "joints": n_joints,
                    "steps": T,
                    "kinefuse_us": us,
                    "kinefuse_wall_us": wall / n_js * 1e6,
                    "peer": "filterpy",
                    "peer_joints": fp_j,
                    "peer_steps": fp_T,
                    "peer_us": peer,
                    "peer_wall_us": pwall / fp_js * 1e6,
                    "speedup": peer / us,
                }
            )
    return rows


def online_rows(quick: bool) -> list[dict]:
    """One ``step`` / ``OnlineFilter.update`` call for all joints, next to filterpy per joint."""
    from filterpy.kalman import KalmanFilter as FKF

    model = paper_model()
    kf = KalmanFilter(model)
    n = 300 if quick else 3_000
    rows = []
    for n_joints in (1, 8):
        z = make_data(n_joints, n, seed=3)
        zt = [np.ascontiguousarray(z[:, t]) for t in range(n)]

        def run_step(zt=zt, n_joints=n_joints):
            st = kf.init((n_joints,))
            for zz in zt:
                st, _ = kf.step(st, zz)

        def run_online(zt=zt):
            o = OnlineFilter(kf)
            for zz in zt:
                o.update(zz)

        fkf = FKF(dim_x=6, dim_z=3)
        fkf.F, fkf.H, fkf.Q, fkf.R = model.F.copy(), model.H.copy(), model.Q.copy(), model.R.copy()
        zs1 = [z[0, t].reshape(-1, 1) for t in range(n)]

        def run_fp(zs1=zs1, fkf=fkf):
            for zz in zs1:
                fkf.predict()
                if not np.isnan(zz[0, 0]):
                    fkf.update(zz)

        t = measure_interleaved(
            {"step": run_step, "online": run_online, "fp": run_fp}, 3 if quick else 9
        )
        step_cpu, onl_cpu, fp_cpu = t["step"][0], t["online"][0], t["fp"][0]
        fp_us = fp_cpu / n * 1e6  # one joint per call
        for name, cpu in (("KF.step", step_cpu), ("OnlineFilter.update", onl_cpu)):
            us_call = cpu / n * 1e6
            rows.append(
                {
                    "case": name,
                    "joints": n_joints,
                    "us_per_call": us_call,
                    "filterpy_us_per_joint_step": fp_us,
                    "speedup_vs_filterpy_per_joint": fp_us * n_joints / us_call,
                }
            )
    return rows


_MODULE_OF = {
    "UFIRFilter": "kinefuse.filters.ufir",
    "EMKalmanFilter": "kinefuse.filters.em_kalman",
    "IntegratedFilter": "kinefuse.filters.integrated",
}


def _find_filter_class(kf_mod, cls_name: str):
    """``kinefuse.filters.<cls_name>``, else from its module if present; None if unavailable."""
    cls = getattr(kf_mod, cls_name, None)
    if cls is not None:
        return cls

    try:
        return getattr(importlib.import_module(_MODULE_OF[cls_name]), cls_name, None)
    except Exception:
        return None


def other_filter_rows(quick: bool) -> list[dict]:
    """UFIR, EM-KF and the integrated filter per joint-step (8 joints).

    The targets compare these rows with each other (UFIR horizons, EM-KF iteration counts), so
    the repeats are interleaved: round r times every filter once before round r + 1, and each
    row is the median of its rounds; a slow phase of a shared machine then falls on every row
    alike instead of on whichever row was being timed.
    """
    model = paper_model()
    T = 2_000 if quick else 20_000
    z = make_data(8, T, seed=8)
    z_own = make_data(8, T, seed=8, own_gaps=True)  # the covariance is not shared between joints
    repeats = 3 if quick else 9
    specs = [("UFIRFilter", f"UFIR(N={N})", {"horizon": N}) for N in UFIR_HORIZONS]
    specs += [("UFIRFilter", f"UFIR(N={N}) no cov", {"horizon": N}) for N in UFIR_HORIZONS]
    specs += [("UFIRFilter", f"UFIR(N={N}) own gaps", {"horizon": N}) for N in UFIR_HORIZONS]
    specs += [("EMKalmanFilter", f"EM-KF(n_iter={n})", {"n_iter": n}) for n in (1, 3, 10)]
    specs.append(
        (
            "IntegratedFilter",
            "integrated",
            {"horizon": 20, "threshold1": 2.0, "threshold2": 2.0, "n_em_iter": 3},
        )
    )
    rows, calls = [], {}
    for cls_name, label, kwargs in specs:
        row = {"case": label, "joints": 8, "steps": T}
        rows.append(row)
        cls = _find_filter_class(kf_mod, cls_name)
        if cls is None:
            row["skipped"] = f"kinefuse.filters.{cls_name} not available yet"
            continue
        try:
            filt = cls(model, **kwargs)
            kw = {"outputs": UFIR_NO_COV} if label.endswith("no cov") else {}
            call = functools.partial(filt.filter, z_own if "own gaps" in label else z, **kw)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                call()  # warm-up (and the error, if any)
        except Exception as exc:
            row["skipped"] = f"{type(exc).__name__}: {exc}"
            continue
        calls[label] = call
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        times = measure_interleaved(calls, repeats, warm_up=False)  # each called above
    for row in rows:
        if row["case"] in times:
            cpu, wall = times[row["case"]]
            row["kinefuse_us"] = cpu / z[..., 0].size * 1e6
            row["kinefuse_wall_us"] = wall / z[..., 0].size * 1e6
    return rows


_SECOND_PROCESS = r"""
import json, time
t0 = time.perf_counter()
import numpy as np
from kinefuse.filters import KalmanFilter, rts_smooth
from kinefuse.models import constant_velocity
t1 = time.perf_counter()
m = constant_velocity(1 / 30, q=1.0, r=0.01)
z = np.cumsum(np.random.default_rng(0).normal(size=(8, 500, 3)), axis=1) * 0.01
_, res = KalmanFilter(m).filter(z)
st, _ = KalmanFilter(m).step(KalmanFilter(m).init((8,)), z[:, 0])
rts_smooth(m, res)
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1}))
"""


def second_process_time() -> dict:
    """Import + first KF/step/RTS call in a fresh interpreter (numba cache warm after run 1)."""
    out = {}
    for attempt in ("cold_or_warm", "warm"):
        w0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-c", _SECOND_PROCESS], capture_output=True, text=True, check=False
        )
        total = time.perf_counter() - w0
        if proc.returncode != 0:
            return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"}
        d = json.loads(proc.stdout.strip().splitlines()[-1])
        d["process_total_s"] = total
        out[attempt] = d
    return out["warm"] | {"first_run": out["cold_or_warm"]}
