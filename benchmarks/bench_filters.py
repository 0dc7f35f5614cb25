"""Filter benchmark vs filterpy: ``python benchmarks/bench_filters.py [--quick] [--json FILE]``.

The same as ``kinefuse bench``; the code lives in :mod:`kinefuse.apps.bench`.
"""

from kinefuse.apps.bench import main

if __name__ == "__main__":
    raise SystemExit(main())
