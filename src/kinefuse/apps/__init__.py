"""Applications built on the library: the papers' experiments, the demo, the benchmark.

One layer above :mod:`kinefuse.streaming` and :mod:`kinefuse.pipelines` (and below
:mod:`kinefuse.cli`, which calls each one's back-end function):

============================  ===========================================================
module                        what it holds
============================  ===========================================================
:mod:`~.experiments`          ``kinefuse experiment NAME``: :func:`run_experiment`
:mod:`~.splits`               the declared sets of recordings (tuning / report) and loaders
:mod:`~.paper_a`              paper A's experiment (Sun 2024 Tables 4-6)
:mod:`~.paper_b`              paper B's experiment (Xu 2023 Tables 3-5)
:mod:`~.paper_b_tables`       paper B's summary, in-view, CDF-claim and target tables
:mod:`~.neura_imu_only`       the Neura walk from its IMUs alone
:mod:`~.realism`              virtual sensors next to real ones
:mod:`~.demo`                 ``kinefuse demo``: both papers on packaged data, a report
:mod:`~.bench`                ``kinefuse bench`` (rows in :mod:`~.bench_filters`,
                              :mod:`~.bench_engine`)
============================  ===========================================================

Importing this package imports none of them (``kinefuse demo`` must be able to switch the
kernels to interpreted mode before they are imported; see :mod:`kinefuse._compile`).
"""
