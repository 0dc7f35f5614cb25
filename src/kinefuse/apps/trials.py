"""An experiment's independent trials, run one after another or through a map the caller gives.

A *trial* is one call ``fn(*args)`` of a function whose result depends on its arguments only
(every virtual sensor is seeded per trial), e.g. one CMU scenario or one UTD-MHAD trial of
paper B. The paper experiments hand their trials to a :data:`TrialMap`: :func:`serial_map` (the
default) runs them here, in order; ``kinefuse experiment --workers N`` / ``--scheduler ADDRESS``
passes a map that runs them on Dask (:func:`kinefuse.batch.trials.dask_trial_map`), the same
cluster path as ``kinefuse batch``. Either way the results come back in the order of the calls,
so the tables are the same.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:  # splits imports this module
    from kinefuse.apps.splits import DataSplit

__all__ = ["ExperimentRun", "TrialMap", "serial_map"]

#: ``map(fn, calls, advance=None) -> [fn(*args) for args in calls]``, results in call order,
#: ``advance()`` called once per finished call; the first exception of a call is raised.
TrialMap = Callable[..., list]


def serial_map(
    fn: Callable[..., Any], calls: Sequence[tuple], advance: Callable[[], None] | None = None
) -> list:
    """Run ``fn(*args)`` for each ``args`` of ``calls`` in this process, in order.

    Parameters
    ----------
    fn : callable
        The trial function.
    calls : sequence of tuple
        Positional arguments of each call.
    advance : callable, optional
        Called after each finished call (progress).

    Returns
    -------
    list
        The results, in the order of ``calls``.

    Examples
    --------
    >>> serial_map(pow, [(2, 3), (3, 2)])
    [8, 9]
    """
    out = []
    for args in calls:
        out.append(fn(*args))
        if advance is not None:
            advance()
    return out


class ExperimentRun(NamedTuple):
    """What a paper experiment runs with (``run_paper_a(run)``, ``run_paper_b(run)``).

    Attributes
    ----------
    data_dir : Path or None
        The shared data folder (``cmu_mocap/``, ``utd_mhad/``, ``neura_sparse_sample/``);
        None: the packaged CMU clip only.
    quick : bool
        The reduced configuration: the packaged clip and two UTD-MHAD trials.
    split : DataSplit
        The declared set of recordings (:mod:`kinefuse.apps.splits`).
    advance : callable
        Progress callback (once per CMU trial, once for UTD-MHAD, once per later step).
    notes : list of str
        Receives the notes printed under the tables.
    trial_map : TrialMap
        Runs the independent trials (default :func:`serial_map`; ``kinefuse experiment
        --workers`` passes a Dask map). The tables do not depend on it.
    """

    data_dir: Path | None
    quick: bool
    split: DataSplit
    advance: Callable[..., None]
    notes: list[str]
    trial_map: TrialMap = serial_map
