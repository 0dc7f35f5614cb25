"""An experiment's trials on Dask: the map behind ``kinefuse experiment --workers/--scheduler``.

:func:`dask_trial_map` turns a ``distributed.Client`` into a trial map of
:mod:`kinefuse.apps.trials` (``map(fn, calls, advance=None)``, results in call order);
:func:`trial_cluster` opens the same clusters as ``kinefuse batch`` (:func:`kinefuse.batch.runner.connect`:
a LocalCluster on 127.0.0.1 with single-threaded numba workers sharing one on-disk numba cache,
or an existing scheduler) and closes them afterwards. A worker that dies has its trials
re-run by Dask on the others; a trial that raises stops the experiment with that error (the
other trials are cancelled). Needs the ``batch`` extra.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from kinefuse.batch import runner

__all__ = ["dask_trial_map", "trial_cluster"]


def dask_trial_map(client) -> Callable[..., list]:
    """A trial map that runs each call as one Dask task on ``client``'s cluster.

    Parameters
    ----------
    client : distributed.Client
        The cluster's client (the caller owns it).

    Returns
    -------
    callable
        ``map(fn, calls, advance=None) -> list``: ``fn(*args)`` for each ``args`` of ``calls``
        as a task (``pure=False``: a call is never merged with an equal one), ``advance()``
        once per finished task, the results in the order of ``calls``. The first task that
        raises has its exception re-raised here after the unfinished tasks are cancelled.
    """
    from distributed import as_completed

    def trial_map(
        fn: Callable[..., Any], calls: Sequence[tuple], advance: Callable[[], None] | None = None
    ) -> list:
        futures = [client.submit(fn, *args, pure=False) for args in calls]
        try:
            for fut in as_completed(futures):
                if fut.status == "error":
                    fut.result()  # raises the trial's own exception
                if advance is not None:
                    advance()
            return client.gather(futures)
        finally:
            client.cancel([f for f in futures if not f.done()])

    return trial_map


@contextlib.contextmanager
def trial_cluster(
    scheduler: str | None = None, workers: int | None = None
) -> Iterator[tuple[Callable[..., list], str]]:
    """Open a cluster for an experiment's trials; yield ``(trial map, where it runs)``.

    Parameters
    ----------
    scheduler : str, optional
        An existing scheduler's address (default: ``DASK_SCHEDULER_ADDRESS``, else a
        LocalCluster).
    workers : int, optional
        LocalCluster size (default: the number of cores).

    Yields
    ------
    tuple
        :func:`dask_trial_map` of the cluster's client and a one-line description
        (``"LocalCluster, 2 workers on 127.0.0.1"`` or ``"scheduler tcp://..."``).
    """
    client, cluster, where = runner.connect(scheduler, workers, dashboard=False)
    try:
        yield dask_trial_map(client), where
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
