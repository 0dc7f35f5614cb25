"""``kinefuse warm-up``'s steps: the filter kernels' and the pipelines' own compiled kernels.

:mod:`kinefuse.filters.warm_up` compiles the filters; the ``"kinefuse"`` fusion has kernels of
its own (:mod:`kinefuse.pipelines._kinefuse_kernels`: its KF and RTS, the noise fit's moment
sums, the outage bridge's scores; about 8 s cold on this project's 2-core machine), which this
module adds as one more step. Importing it imports the kernel modules (``kinefuse.cli`` imports
it only for ``kinefuse warm-up`` and a first run on a large input, after the interpreted-mode
decision of :mod:`kinefuse._compile`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from kinefuse.filters import warm_up as _filters
from kinefuse.pipelines.kinefuse_fusion import kinefuse_fusion

__all__ = ["WARM_UP_STEPS", "warm_up"]


def _kinefuse_fusion() -> None:
    """Offline and causal (fixed-lag) fusion of two joints with two outages: every kernel of the
    fusion, in the specialisations a run uses (float64, C-contiguous)."""
    rng = np.random.default_rng(0)
    z_imu = np.cumsum(rng.normal(0.0, 0.01, (300, 2, 3)), axis=0)
    z_cam = z_imu + rng.normal(0.0, 0.01, z_imu.shape)
    available = np.ones((300, 2), dtype=bool)
    available[100:140] = available[200:230] = False
    kinefuse_fusion(z_imu, z_cam, available, 1 / 30)
    kinefuse_fusion(z_imu, z_cam, available, 1 / 30, causal=True, lag=3)


#: ``(what, function)``: the filters' warm-up steps, then the fusion's.
WARM_UP_STEPS: tuple[tuple[str, Callable[[], None]], ...] = (
    *_filters.WARM_UP_STEPS,
    ("kinefuse fusion (its KF and RTS, noise fit, outage bridge)", _kinefuse_fusion),
)


def warm_up(report: Callable[[str], None] | None = None) -> list[tuple[str, float]]:
    """Compile or load every kernel a ``kinefuse run`` may use (:data:`WARM_UP_STEPS`); returns
    ``(step, seconds)`` per step. ``report``: as :func:`kinefuse.filters.warm_up.warm_up`."""
    return _filters.warm_up(report, WARM_UP_STEPS)
