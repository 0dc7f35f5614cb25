"""Paper A's online form (streaming IntegratedProcessor) equals its batch form (upper_limb)."""

from __future__ import annotations

import numpy as np

from kinefuse.conventions import MODE_PREDICT
from kinefuse.pipelines.upper_limb import upper_limb
from kinefuse.streaming.processors import SOURCE_PREDICT, IntegratedProcessor

DT = 1 / 30
TOL = 1e-12


def _chain(T=150, seed=0):
    rng = np.random.default_rng(seed)
    z = np.cumsum(0.01 * rng.standard_normal((T, 2, 3)), axis=0) + np.array([0.3, 0.5, 1.2])
    z[40:46, 1] = np.nan  # the wrist chain missing for a while
    z[90, 0] = np.nan
    return z


def test_integrated_processor_equals_upper_limb_batch_and_stepped():
    z = _chain()
    T, J, _ = z.shape
    ref = upper_limb(z[:, 0], z[:, 1], DT, "em-kf-fir", q=0.1, r=0.01)
    proc = IntegratedProcessor(DT, q=0.1, r=0.01)
    t = np.arange(T) * DT
    no_cam = np.full_like(z, np.nan)
    avail = np.zeros((T, J), bool)
    pos, cov, source = proc.run(t, z, no_cam, avail)
    np.testing.assert_allclose(pos, ref.position, atol=TOL, rtol=0)
    np.testing.assert_allclose(cov, ref.cov, atol=TOL, rtol=0)
    np.testing.assert_array_equal(source == SOURCE_PREDICT, ref.mode == MODE_PREDICT)
    stepped = [proc.step(t[k], z[k], no_cam[k], avail[k]) for k in range(T)]
    np.testing.assert_allclose(np.stack([s[0] for s in stepped]), ref.position, atol=TOL, rtol=0)
    np.testing.assert_allclose(np.stack([s[1] for s in stepped]), ref.cov, atol=TOL, rtol=0)
