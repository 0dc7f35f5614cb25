"""``kinefuse batch``: a whole study (many recordings x methods) on dask.distributed.

:func:`load_study` / :func:`study_from_sessions` build a :class:`Study`; :func:`run_study`
runs it on a LocalCluster (default) or an existing Dask cluster and writes one tidy table
(:mod:`kinefuse.batch.table`, Parquet + CSV), every recording's ``kinefuse run`` outputs and a
study report. Needs the ``batch`` extra (``pip install 'kinefuse[batch]'``: distributed, pyarrow);
:func:`missing_packages` says which of them are absent. Importing this package does not import
them.
"""

from __future__ import annotations

import importlib.util

from kinefuse.batch.runner import compare_workers, run_study
from kinefuse.batch.study import Study, Task, load_study, study_from_sessions

__all__ = [
    "Study",
    "Task",
    "compare_workers",
    "load_study",
    "missing_packages",
    "run_study",
    "study_from_sessions",
]

#: Import name -> distribution name of the ``batch`` extra.
BATCH_PACKAGES = {"distributed": "distributed", "pyarrow": "pyarrow"}


def missing_packages() -> list[str]:
    """Distributions of the ``batch`` extra that are not installed."""
    return [dist for mod, dist in BATCH_PACKAGES.items() if importlib.util.find_spec(mod) is None]
