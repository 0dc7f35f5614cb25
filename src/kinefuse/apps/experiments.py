"""``kinefuse experiment paper-a|paper-b|neura-imu-only|realism``: the experiments, one entry point.

``paper-a`` (Sun 2024 §4.2-4.4)
    KF, FIR and EM-KF/FIR on the arm chain with paper A's four Q/R settings
    (:mod:`kinefuse.apps.paper_a`).
``paper-b`` (Xu 2023 §4.2)
    ELM/FIR vs ELM/KF, the simple baselines and ``kinefuse`` (offline and causal) on the eight
    joints, overall and inside camera outages (:mod:`kinefuse.apps.paper_b`, tables in
    :mod:`kinefuse.apps.paper_b_tables`).
``neura-imu-only`` (issue 10)
    The Neura walk from its IMUs alone: functional calibration from the walk, tape-measure
    lengths, Vicon hips as the declared root; Vicon scores only
    (:mod:`kinefuse.apps.neura_imu_only`).
``realism``
    The virtual sensors next to real ones (:mod:`kinefuse.apps.realism`).

The paper experiments pool the samples of all scenarios of a data set before computing the RMSE,
and run on a declared set of recordings (:mod:`kinefuse.apps.splits`): :data:`REPORT_SET`
(default) or :data:`TUNING_SET` (the only one anything is developed or chosen on); every table
names it. No calibration, alignment, length, noise fit or learned correction sees a sample that
the evaluation hides (outage-blind; tested per protocol in ``tests/test_leakage.py``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

from kinefuse.apps.neura_imu_only import run_neura_imu_only
from kinefuse.apps.paper_a import PAPER_A_TESTS, run_paper_a
from kinefuse.apps.paper_b import run_paper_b
from kinefuse.apps.realism import run_realism
from kinefuse.apps.splits import (
    REPORT_SET,
    SPLITS,
    TUNING_SET,
    UTD_ACTIONS,
    DataSplit,
    as_run,
    default_data_dir,
)
from kinefuse.apps.trials import ExperimentRun, TrialMap, serial_map
from kinefuse.exceptions import InputError
from kinefuse.progress import progress

__all__ = [
    "EXPERIMENTS",
    "PAPER_A_TESTS",
    "REPORT_SET",
    "SPLITS",
    "TRIAL_EXPERIMENTS",
    "TUNING_SET",
    "UTD_ACTIONS",
    "DataSplit",
    "run_experiment",
]

#: Experiments this module runs.
EXPERIMENTS = ("paper-a", "paper-b", "neura-imu-only", "realism")

_QUICK_ENV = "KINEFUSE_EXPERIMENT_QUICK"


def _neura_imu_only(run: ExperimentRun) -> dict:  # one recording, evaluation only
    return run_neura_imu_only(run.data_dir, run.advance, run.notes)


def _realism(run: ExperimentRun) -> dict:  # its own declared sets (realism.TUNING/REPORT)
    return run_realism(run.data_dir, run.quick, run.advance, run.notes)


#: Experiments made of independent trials (:mod:`kinefuse.apps.trials`): the ones that can run
#: on Dask (``kinefuse experiment --workers`` / ``--scheduler``).
TRIAL_EXPERIMENTS = ("paper-a", "paper-b")


def _runner(name: str, quick: bool, split: DataSplit) -> tuple[Callable, int]:
    """The experiment's function ``(ExperimentRun) -> dict`` and its number of progress steps."""
    n_cmu = 1 if quick else len(split.cmu_trials)
    return {
        "neura-imu-only": (_neura_imu_only, 2),
        "paper-a": (run_paper_a, n_cmu + 1 + (8 if quick else 12)),
        "realism": (_realism, 12),
        "paper-b": (run_paper_b, n_cmu + 2),
    }[name]


def _check_data(name: str, data_dir, explicit: bool, quick: bool) -> None:
    """A full (not --quick) paper experiment on a ``--data`` folder holding none of its data
    sets is an error (it would silently run the packaged clip alone)."""
    if quick or not explicit:
        return
    root = Path(data_dir)
    if not any((root / sub).is_dir() for sub in ("cmu_mocap", "utd_mhad")):
        raise InputError(
            f"--data {data_dir}: holds neither cmu_mocap/ nor utd_mhad/, the recordings of "
            f"{name}; give the shared data folder, or --quick for the packaged CMU clip alone"
        )


def _data_set(split: DataSplit) -> dict:
    return {
        "cmu_trials": list(split.cmu_trials),
        "utd_subjects": list(split.utd_subjects),
        "neura": split.neura,
    }


def run_experiment(
    name: str,
    data_dir=None,
    *,
    quick: bool | None = None,
    quiet: bool = False,
    split: str = "report",
    trial_map: TrialMap | None = None,
) -> dict:
    """Back-end of ``kinefuse experiment``: reproduce paper A's or paper B's experiment.

    Parameters
    ----------
    name : {"paper-a", "paper-b", "neura-imu-only", "realism"}
        Which experiment (see the module docstring).
    data_dir : str or Path, optional
        The shared data folder (``cmu_mocap/``, ``utd_mhad/``, ``neura_sparse_sample/``).
        Default ``../shared/data`` when it exists, else the packaged CMU clip only.
    quick : bool, optional
        Reduced configuration (packaged clip, two UTD-MHAD trials; seconds instead of minutes).
        Default from the environment variable ``KINEFUSE_EXPERIMENT_QUICK`` (``1`` = quick).
    quiet : bool
        No progress bar.
    split : {"report", "tuning"}
        Which declared set of recordings (:data:`REPORT_SET`, default; :data:`TUNING_SET`,
        the only one to develop on) for ``paper-a`` and ``paper-b``; every table title names
        it. ``neura-imu-only`` ignores it (the Neura walk, evaluation only).
    trial_map : TrialMap, optional
        How the trials of ``paper-a`` and ``paper-b`` (:data:`TRIAL_EXPERIMENTS`) run
        (:mod:`kinefuse.apps.trials`): default here, in order; ``kinefuse experiment
        --workers/--scheduler`` passes a Dask map (:func:`kinefuse.batch.trials.dask_trial_map`).
        The numbers do not depend on it. Refused for the other experiments.

    Returns
    -------
    dict
        ``tables`` (ResultTable list, printed by the CLI), ``results`` (nested dict of every
        number, for ``--json``), ``targets`` (paper-b: kinefuse vs the baselines), ``notes``,
        ``quick``, ``data_dir``, ``split``, ``data_set`` (its recordings), ``wall_time_s``.

    Raises
    ------
    InputError
        Unknown experiment or split, missing data folder, or a ``trial_map`` for an experiment
        that is not made of trials.
    """
    if name not in EXPERIMENTS:
        raise InputError(f"unknown experiment {name!r}; expected one of {', '.join(EXPERIMENTS)}")
    if trial_map is not None and name not in TRIAL_EXPERIMENTS:
        raise InputError(
            f"--workers/--scheduler: {name} is not split into trials; only "
            f"{' and '.join(TRIAL_EXPERIMENTS)} run on Dask"
        )
    if split not in SPLITS:
        raise InputError(f"unknown set {split!r}; expected one of {', '.join(SPLITS)}")
    chosen = SPLITS[split]
    if quick is None:
        quick = os.environ.get(_QUICK_ENV, "") not in ("", "0")
    explicit = data_dir is not None
    if data_dir is None:
        data_dir = default_data_dir()
    elif not Path(data_dir).is_dir():
        raise InputError(f"data folder {data_dir} not found")
    data_dir = None if data_dir is None else Path(data_dir)
    if name == "neura-imu-only" and data_dir is None:
        raise InputError("neura-imu-only: needs --data (the folder with neura_sparse_sample/)")
    notes: list[str] = []
    t0 = time.perf_counter()
    paper = name in ("paper-a", "paper-b")  # neura-imu-only: the Neura walk, evaluation only
    if paper:
        _check_data(name, data_dir, explicit, bool(quick))
        chosen = as_run(chosen, data_dir, bool(quick))  # what runs: every table names it
        if chosen.reduced_from:
            notes.append(f"{name}: {chosen.describe()}; these figures are not the {split} set's")
    run, n_steps = _runner(name, bool(quick), chosen)
    title = f"Experiment {name}" + (f" ({chosen.name} set)" if paper else "")
    with progress(title, total=n_steps, quiet=quiet) as advance:
        out = run(
            ExperimentRun(data_dir, bool(quick), chosen, advance, notes, trial_map or serial_map)
        )
    out.update(
        notes=notes,
        quick=bool(quick),
        split=chosen.name if paper else None,
        data_set=_data_set(chosen) if paper else None,
        data_dir=None if data_dir is None else str(data_dir),
        wall_time_s=time.perf_counter() - t0,
    )
    return out
