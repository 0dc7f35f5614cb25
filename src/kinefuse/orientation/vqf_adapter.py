"""Thin adapters over the ``vqf`` package: batch (:func:`estimate`) and online (:class:`OrientationEstimator`).

Frames and conventions (VQF documentation, "FAQ": *"VQF always outputs quaternions that specify
the orientation of the sensor coordinate system S relative to an east-north-up (ENU) reference
frame"*, scalar-first ``[w x y z]``):

* ``quat9D`` (with magnetometer): sensor -> ENU earth frame, heading from the magnetic field
  (y axis towards magnetic north).
* ``quat6D`` (no magnetometer): sensor -> an earth frame with z up whose heading is arbitrary
  (fixed by the first samples and drifting slowly with the gyro bias).

Both are returned unchanged as kinefuse's ``q_world_from_sensor``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import vqf

from kinefuse._validation import as_float_array, positive_finite
from kinefuse.exceptions import InputError

__all__ = ["METHODS", "OrientationEstimator", "estimate"]

#: Orientation estimation methods known to :func:`estimate`.
METHODS = ("vqf",)


def _imu_array(value, name: str, T: int | None = None) -> np.ndarray:
    a = as_float_array(value, name)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"expected {name} with shape (T, 3), got {a.shape}")
    if T is not None and a.shape[0] != T:
        raise InputError(f"expected {name} with shape (T, 3) = ({T}, 3) like acc, got {a.shape}")
    bad = ~np.all(np.isfinite(a), axis=1)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"expected finite {name} (VQF cannot skip samples), got {a[k]} at sample {k} "
            f"({int(bad.sum())} non-finite rows); fill or cut gaps before estimating orientation"
        )
    return a


def _check_params(params) -> dict:
    if params is None:
        return {}
    if not isinstance(params, Mapping):
        raise InputError(
            f"expected params as a mapping of VQF parameter names, got {type(params).__name__}"
        )
    defaults = vqf.VQF(1.0).params
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise InputError(
            f"unknown VQF parameter(s) {unknown}; expected a subset of {sorted(defaults)}"
        )
    for name, value in params.items():  # VQF's own checks are C++ assertions: they abort Python
        if isinstance(defaults[name], bool):
            if not isinstance(value, (bool, np.bool_)):
                raise InputError(f"VQF parameter {name!r}: expected True or False, got {value!r}")
            continue
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
            raise InputError(f"VQF parameter {name!r}: expected a number, got {value!r}")
        if not math.isfinite(value) or (name in _VQF_POSITIVE and not value > 0):
            need = " > 0" if name in _VQF_POSITIVE else ""
            raise InputError(
                f"VQF parameter {name!r}: expected a finite number{need}, got {value!r}"
            )
    return dict(params)


#: VQF parameters whose value VQF asserts > 0: a C++ assertion, which ends the Python process
#: (vqf 2.x: zero or negative tauAcc or restFilterTau; the others were checked not to abort).
_VQF_POSITIVE = frozenset({"tauAcc", "restFilterTau"})


def estimate(
    acc,
    gyr,
    mag=None,
    *,
    rate_hz: float,
    method: str = "vqf",
    offline: bool = False,
    params: Mapping | None = None,
) -> np.ndarray:
    """Estimate the sensor orientation from raw IMU data (batch).

    Parameters
    ----------
    acc : array_like, shape (T, 3)
        Specific force in the sensor frame, m/s² (gravity included, ~+9.81 on the up axis at rest).
    gyr : array_like, shape (T, 3)
        Angular rate in the sensor frame, rad/s.
    mag : array_like, shape (T, 3), optional
        Magnetic field in the sensor frame, any consistent unit. With it the result is VQF's
        ``quat9D`` (heading referenced to magnetic north); without it ``quat6D`` (arbitrary,
        slowly drifting heading).
    rate_hz : float
        Sampling rate of all three signals, Hz (VQF needs one common rate in batch mode).
    method : {"vqf"}
        Orientation filter. Only VQF is offered; there is no hand-written AHRS in kinefuse.
    offline : bool
        If True use ``vqf.offlineVQF`` (acausal: uses future samples; "offline"), else the causal
        ``vqf.VQF(...).updateBatch``, which equals feeding the samples one by one to
        :class:`OrientationEstimator`.
    params : mapping, optional
        VQF parameters by their VQF names (``tauAcc``, ``tauMag``, ``magDistRejectionEnabled``...),
        passed through unchanged; None = VQF defaults.

    Returns
    -------
    q_world_from_sensor : ndarray, shape (T, 4)
        Unit quaternions, scalar-first ``wxyz``, sensor frame -> ENU earth frame (see the module
        docstring for the heading of the 6D case).

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        Wrong shapes or dtypes, non-finite samples, unknown method or parameter names.

    Notes
    -----
    Implements nothing itself: VQF (D. Laidig and T. Seel, "VQF: Highly Accurate IMU Orientation
    Estimation with Bias Estimation and Magnetic Disturbance Rejection", Information Fusion 91,
    2023). The result is bit-for-bit what ``vqf`` returns for the same contiguous float64 arrays.
    Papers A and B use the orientation of their IMUs' on-board fusion; SPEC §2.2-7.
    """
    if method not in METHODS:
        raise InputError(f"unknown orientation method {method!r}; expected one of {list(METHODS)}")
    acc_a = _imu_array(acc, "acc")
    T = acc_a.shape[0]
    if T == 0:
        raise InputError("expected at least one sample, got acc with shape (0, 3)")
    gyr_a = _imu_array(gyr, "gyr", T)
    mag_a = None if mag is None else _imu_array(mag, "mag", T)
    fs = positive_finite(rate_hz, "rate_hz")
    p = _check_params(params)
    Ts = 1.0 / fs
    if offline:
        out = vqf.offlineVQF(gyr_a, acc_a, mag_a, Ts, p)
    else:
        out = vqf.VQF(Ts, **p).updateBatch(gyr_a, acc_a, mag_a)
    return np.asarray(out["quat6D"] if mag_a is None else out["quat9D"], dtype=np.float64)


class OrientationEstimator:
    """Online (sample-by-sample) orientation estimation: a mutable wrapper around ``vqf.VQF``.

    Parameters
    ----------
    rate_hz : float
        Sampling rate, Hz.
    params : mapping, optional
        VQF parameters by name (see :func:`estimate`).

    Notes
    -----
    Feeding samples one by one gives exactly :func:`estimate` with ``offline=False``. The VQF
    state can be checkpointed with :attr:`state` and restored by assigning it.

    Examples
    --------
    >>> est = OrientationEstimator(100.0)
    >>> q = est.update([0.0, 0.0, 9.81], [0.0, 0.0, 0.0])
    >>> q.shape
    (4,)
    """

    def __init__(self, rate_hz: float, params: Mapping | None = None):
        self.rate_hz = positive_finite(rate_hz, "rate_hz")
        self.params = _check_params(params)
        self._vqf = vqf.VQF(1.0 / self.rate_hz, **self.params)
        self._used_mag = False

    @staticmethod
    def _sample(value, name: str) -> np.ndarray:
        a = as_float_array(value, name)
        if a.shape != (3,):
            raise InputError(f"expected {name} with shape (3,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"expected finite {name}, got {a}")
        return a

    def update(self, acc, gyr, mag=None) -> np.ndarray:
        """Process one sample and return the current orientation.

        Parameters
        ----------
        acc : array_like, shape (3,)
            Specific force, m/s², sensor frame.
        gyr : array_like, shape (3,)
            Angular rate, rad/s, sensor frame.
        mag : array_like, shape (3,), optional
            Magnetic field, any unit. Once given, the 9D quaternion is returned from then on.

        Returns
        -------
        q_world_from_sensor : ndarray, shape (4,)
            ``wxyz``, sensor -> ENU (9D once a magnetometer sample was seen, else 6D).
        """
        a = self._sample(acc, "acc")
        g = self._sample(gyr, "gyr")
        if mag is None:
            self._vqf.update(g, a)
        else:
            self._vqf.update(g, a, self._sample(mag, "mag"))
            self._used_mag = True
        return np.asarray(
            self._vqf.getQuat9D() if self._used_mag else self._vqf.getQuat6D(), dtype=float
        )

    @property
    def bias_rad_s(self) -> np.ndarray:
        """Current gyroscope bias estimate, rad/s, shape (3,)."""
        return np.asarray(self._vqf.getBiasEstimate()[0], dtype=float)

    @property
    def state(self):
        """VQF filter state (a copy); assign a previously read value to restore it."""
        return self._vqf.state

    @state.setter
    def state(self, value) -> None:
        self._vqf.state = value

    def reset(self) -> None:
        """Reset the filter to its initial state (parameters kept)."""
        self._vqf.resetState()
        self._used_mag = False
