"""The declared sets of recordings of the paper experiments and the data they load.

:data:`TUNING_SET` is the only set anything in kinefuse was developed or chosen on;
:data:`REPORT_SET` (the default) is what the tables report on (issue 11). The loaders here are
shared by :mod:`kinefuse.apps.paper_a` and :mod:`kinefuse.apps.paper_b`: CMU motions (or the
packaged clip), UTD-MHAD trial pairs and the UTD-MHAD wrist chain with its simulated outage.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kinefuse.apps._common import imu_only_output
from kinefuse.apps.trials import TrialMap, serial_map
from kinefuse.data import DEMO_TRIAL, demo_motion
from kinefuse.exceptions import InputError
from kinefuse.io import load
from kinefuse.io.cmu import load_motion_asf_amc

__all__ = [
    "REPORT_SET",
    "SEED",
    "SPLITS",
    "TUNING_SET",
    "UTD_ACTIONS",
    "UTD_HIDDEN",
    "DataSplit",
    "as_run",
    "cmu_motions",
    "default_data_dir",
    "utd_hidden",
    "utd_recording",
    "utd_trials",
    "utd_wrist_chain",
    "each_utd_trial",
]

#: Seed of every virtual sensor of the paper experiments (offset per scenario).
SEED = 2023

#: UTD-MHAD actions with the IMU on the right wrist used for the real-data checks.
UTD_ACTIONS = (1, 5, 9, 10, 12, 14)


@dataclass(frozen=True)
class DataSplit:
    """A declared set of recordings (issue 11: tune on one set, report on another).

    Attributes
    ----------
    name : str
        ``"tuning"`` or ``"report"``.
    cmu_trials : tuple of str
        CMU trials (``SS_TT``) driving the virtual scenarios (long enough to train the ELMs).
    utd_subjects : tuple of int
        UTD-MHAD subjects (trial 1 of :data:`UTD_ACTIONS`).
    neura : bool
        Whether the Neura walk belongs to the set (it is evaluation-only: report set).
    reduced_from : str
        Empty for a declared set; for what a run used instead of one (``--quick``, or data
        missing: :func:`as_run`), the declared set's name.
    """

    name: str
    cmu_trials: tuple[str, ...]
    utd_subjects: tuple[int, ...]
    neura: bool
    reduced_from: str = ""

    def describe(self) -> str:
        """One line naming the recordings of the set."""
        cmu = f"CMU {', '.join(self.cmu_trials)}"
        if self.cmu_trials == (DEMO_TRIAL,):
            cmu += " (the packaged clip: CMU subject 02, whose trials are the tuning set's)"
        parts = [cmu]
        if self.utd_subjects:
            actions = UTD_ACTIONS[:2] if self.name == "quick" else UTD_ACTIONS
            parts.append(
                f"UTD-MHAD subjects {', '.join(map(str, self.utd_subjects))} (trial 1"
                + (f", actions {', '.join(map(str, actions))})" if self.reduced_from else ")")
            )
        if self.neura:
            parts.append("Neura walk")
        head = f"{self.name} set"
        if self.reduced_from:
            head += f" (not the {self.reduced_from} set)"
        return f"{head}: " + "; ".join(parts)


def as_run(split: DataSplit, data_dir, quick: bool) -> DataSplit:
    """The recordings a run of ``split`` uses: ``split`` itself, or, with ``quick`` or its data
    missing from ``data_dir``, a set named ``"quick"`` or ``"reduced"`` that says what runs
    instead (the packaged CMU clip, fewer or no UTD-MHAD trials), so that no table claims the
    declared set."""
    root = None if data_dir is None else Path(data_dir)

    def has(sub: str) -> bool:
        return root is not None and (root / sub).is_dir()

    cmu_full = not quick and has("cmu_mocap/asfamc")
    if cmu_full and has("utd_mhad") and (has("neura_sparse_sample") or not split.neura):
        return split
    return DataSplit(
        "quick" if quick else "reduced",
        split.cmu_trials if cmu_full else (DEMO_TRIAL,),
        (split.utd_subjects[:1] if quick else split.utd_subjects) if has("utd_mhad") else (),
        split.neura and has("neura_sparse_sample"),
        reduced_from=split.name,
    )


#: The only recordings anything in kinefuse was developed or chosen on (CMU subject 02,
#: UTD-MHAD subjects 1-3).
TUNING_SET = DataSplit("tuning", ("02_05", "02_07", "02_10"), (1, 2, 3), False)

#: The recordings the tables report on; nothing is chosen by looking at them (CMU subject 03,
#: UTD-MHAD subjects 4-6, the Neura walk).
REPORT_SET = DataSplit("report", ("03_03", "03_04"), (4, 5, 6), True)

#: ``kinefuse experiment --set`` choices.
SPLITS = {"tuning": TUNING_SET, "report": REPORT_SET}


def default_data_dir() -> Path | None:
    """``../shared/data`` if it exists (the checkout's neighbour), else None."""
    p = Path("..") / "shared" / "data"
    return p if p.is_dir() else None


def cmu_motions(data_dir: Path | None, trials: Sequence[str], quick: bool, notes: list[str]):
    """``(name, Motion)`` pairs: CMU trials from ``data_dir/cmu_mocap``, else the packaged clip."""
    root = None if data_dir is None else Path(data_dir) / "cmu_mocap" / "asfamc"
    if quick or root is None or not root.is_dir():
        if root is None or not root.is_dir():
            notes.append("CMU: no data_dir/cmu_mocap; the packaged clip 02_08 only")
        return [(DEMO_TRIAL, demo_motion())]

    out = []
    for name in trials:
        subj = name.split("_")[0]
        amc = root / subj / f"{name}.amc"
        if amc.is_file():
            out.append((name, load_motion_asf_amc(amc, root / subj / f"{subj}.asf")))
    if not out:
        raise InputError(f"{root}: none of the CMU trials {list(trials)} found")
    return out


def utd_trials(data_dir: Path, quick: bool, split: DataSplit) -> list[tuple[Path, Path]]:
    """``(inertial, skeleton)`` file pairs of the set's UTD-MHAD trials (trial 1 of each action)."""
    root = Path(data_dir) / "utd_mhad"
    pairs = []
    subjects = split.utd_subjects[:1] if quick else split.utd_subjects
    actions = UTD_ACTIONS[:2] if quick else UTD_ACTIONS
    for a in actions:
        for s in subjects:
            i = root / "Inertial" / f"a{a}_s{s}_t1_inertial.mat"
            k = root / "Skeleton" / f"a{a}_s{s}_t1_skeleton.mat"
            if i.is_file() and k.is_file():
                pairs.append((i, k))
    return pairs


#: Paper-B UTD-MHAD protocol: the Kinect wrist is hidden from 55 % of each trial for 25 % of it.
UTD_HIDDEN = (0.55, 0.25)


def utd_recording(inertial: Path, skeleton: Path):
    """One UTD-MHAD trial as loaded (inertial + Kinect skeleton)."""
    return load((inertial, skeleton))


def utd_hidden(t: np.ndarray, t_cam: np.ndarray, hidden=UTD_HIDDEN) -> np.ndarray:
    """Rows of ``t`` inside the simulated outage ``[t_cam[a], t_cam[a + L])`` (fractions of T)."""
    T = t_cam.size
    a = int(hidden[0] * T)
    b = a + int(hidden[1] * T)
    hi = t_cam[b] if b < T else np.inf
    return (t >= t_cam[a]) & (t < hi)


def utd_wrist_chain(rec, hidden: tuple[float, float] | None = None):
    """Real UTD-MHAD trial: wrist chain (Kinect elbow + forearm IMU) and Kinect wrist at 30 Hz.

    ``hidden = (start, length)`` (fractions of the trial): the Kinect wrist is unavailable
    there to everything that calibrates (axis, camera rotation, forearm length) and to the
    returned camera; the reference keeps it. None: calibration over the whole trial.
    Returns ``t, chain, reference, camera, origin`` (wrist, (T, 3); origin = Kinect
    spine_shoulder), the hidden mask ``(T,)`` and the orientations of the segments that move
    the wrist (``(T, S, 3, 3)``, :meth:`SessionOutput.segment_rotations`).
    """
    v = rec.vision
    cam = v
    if hidden is not None:
        av = v.available.copy()
        av[utd_hidden(v.t_s, v.t_s, hidden), v.index("wrist_r")] = False
        cam = replace(v, available=av)
    rec = replace(rec, vision=cam, reference=v)
    out = imu_only_output(rec, 100.0)
    j = out.joints.index("wrist_r")
    sc = v.position("spine_shoulder")
    ok = np.all(np.isfinite(sc), axis=1)
    origin = np.stack([np.interp(out.t_s, v.t_s[ok], sc[ok, k]) for k in range(3)], -1)
    hide = (
        np.zeros(out.t_s.size, dtype=bool) if hidden is None else utd_hidden(out.t_s, v.t_s, hidden)
    )
    camera = np.where(hide[:, None], np.nan, out.camera[:, j])
    rots = out.segment_rotations(["wrist_r"])[:, 0]
    return out.t_s, out.chain[:, j], out.reference[:, j], camera, origin, hide, rots


class _Skipped(NamedTuple):
    """A UTD-MHAD trial that was skipped, and why (a note)."""

    note: str


def _utd_trial(make: Callable, inertial: Path, skeleton: Path, name: str):
    """``make(recording, name)`` on one UTD-MHAD trial, or :class:`_Skipped` on an InputError."""
    try:
        return make(utd_recording(inertial, skeleton), name)
    except InputError as exc:
        return _Skipped(f"UTD-MHAD {inertial.name}: skipped ({exc})")


def each_utd_trial(
    data_dir: Path,
    quick: bool,
    split: DataSplit,
    notes: list[str],
    make: Callable,
    trial_map: TrialMap = serial_map,
) -> list:
    """``make(recording, name)`` for each UTD-MHAD trial of the set (:func:`utd_trials`); a trial
    whose loading or ``make`` raises :class:`InputError` is skipped with a note.

    The trials run through ``trial_map`` (:mod:`kinefuse.apps.trials`: here, or on Dask), each
    loading its own files; results and notes keep the order of the trials.
    """
    calls = [
        (make, inertial, skeleton, inertial.name.replace("_inertial.mat", ""))
        for inertial, skeleton in utd_trials(data_dir, quick, split)
    ]
    out = []
    for r in trial_map(_utd_trial, calls):
        if isinstance(r, _Skipped):
            notes.append(r.note)
        else:
            out.append(r)
    return out
