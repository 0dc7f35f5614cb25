"""Mutable real-time wrapper around any kinefuse filter (layer 3 of the filter API, STYLE.md)."""

from __future__ import annotations

import copy

import numpy as np

from kinefuse.exceptions import InputError

__all__ = ["OnlineFilter"]

_CHECKPOINT_VERSION = 1


class OnlineFilter:
    """Hold ``(filter, state)`` and advance it one measurement at a time.

    Works with any filter object exposing ``init(batch_shape)`` and
    ``step(state, z) -> (state, out)`` (KalmanFilter, and the EM-KF / UFIR / integrated / IMM
    filters of :mod:`kinefuse.filters`). The filter object is immutable configuration; only the
    state changes.

    Parameters
    ----------
    filter : object with ``init`` and ``step``
        The (frozen) filter configuration.
    state : filter state, optional
        State to start from (e.g. ``filter.init((n_joints,), mean=...)`` or the state returned
        by ``filter.filter`` on a history). Without it, the first :meth:`update` calls
        ``filter.init(batch_shape=z.shape[:-1])``.

    Examples
    --------
    >>> import numpy as np
    >>> from kinefuse.filters import KalmanFilter
    >>> from kinefuse.models import constant_velocity
    >>> online = OnlineFilter(KalmanFilter(constant_velocity(1 / 30, q=1.0, r=0.01)))
    >>> out = online.update(np.array([0.1, 0.2, 1.0]))      # one sample, ENU m
    >>> out.position
    array([0.1, 0.2, 1. ])
    >>> saved = online.checkpoint()
    >>> out2 = online.update(np.array([0.11, 0.2, 1.0]))
    >>> online.restore(saved)                                # back to before out2
    """

    def __init__(self, filter, state=None):
        if not (
            callable(getattr(filter, "init", None)) and callable(getattr(filter, "step", None))
        ):
            raise InputError(
                f"expected a filter object with init(batch_shape) and step(state, z), got {type(filter).__name__}"
            )
        self._filter = filter
        self._state = state
        self._n_updates = 0

    @property
    def filter(self):
        """The wrapped filter configuration (read-only)."""
        return self._filter

    @property
    def state(self):
        """Current filter state (None before the first update when none was given)."""
        return self._state

    @property
    def n_updates(self) -> int:
        """Number of :meth:`update` calls since construction or the last :meth:`restore`/:meth:`reset`."""
        return self._n_updates

    def update(self, z):
        """Advance by one time slice.

        Parameters
        ----------
        z : array_like of float, shape (..., n_z)
            Measurement at this step (batch shape fixed by the first call or by the state);
            a row containing NaN is missing (predict only). For the :class:`IMM`, one row per
            model: shape ``(..., M, n_z)`` (its ``step_measurement_shape``).

        Returns
        -------
        out
            The filter's per-step output (for :class:`KalmanFilter`: a FilterResult without
            the time axis).
        """
        if self._state is None:
            arr = np.asarray(z)
            # trailing axes of one element's measurement: (n_z,), or (M, n_z) for the IMM
            event = tuple(getattr(self._filter, "step_measurement_shape", (None,)))
            if arr.ndim < len(event):
                names = ", ".join("n_z" if e is None else str(e) for e in event)
                raise InputError(f"expected z with shape (..., {names}), got {arr.shape}")
            self._state = self._filter.init(batch_shape=arr.shape[: arr.ndim - len(event)])
        state, out = self._filter.step(self._state, z)
        self._state = state
        self._n_updates += 1
        return out

    def reset(self, state=None) -> None:
        """Drop the current state (re-initialise lazily on the next update, or use ``state``)."""
        self._state = state
        self._n_updates = 0

    def checkpoint(self) -> dict:
        """Snapshot of the mutable part: a dict with a deep copy of the state.

        The dict holds only the state (NumPy arrays, ints) and bookkeeping, never the filter
        configuration; restore it into an ``OnlineFilter`` of the same filter configuration.
        It can be stored with e.g. :func:`pickle` or by saving the arrays.

        Returns
        -------
        dict
            ``{"version", "filter_type", "n_updates", "state"}``.
        """
        return {
            "version": _CHECKPOINT_VERSION,
            "filter_type": type(self._filter).__name__,
            "n_updates": self._n_updates,
            "state": copy.deepcopy(self._state),
        }

    def restore(self, checkpoint: dict) -> None:
        """Return to a state saved by :meth:`checkpoint` (the checkpoint stays reusable).

        Raises
        ------
        ValueError
            If ``checkpoint`` is not a checkpoint dict or was made with another filter type.
        """
        if (
            not isinstance(checkpoint, dict)
            or "state" not in checkpoint
            or "filter_type" not in checkpoint
        ):
            raise InputError(
                f"expected a checkpoint dict from OnlineFilter.checkpoint(), got {type(checkpoint).__name__}"
            )
        if checkpoint.get("version") != _CHECKPOINT_VERSION:
            raise InputError(
                f"expected checkpoint version {_CHECKPOINT_VERSION}, got {checkpoint.get('version')!r}"
            )
        expected = type(self._filter).__name__
        if checkpoint["filter_type"] != expected:
            raise InputError(
                f"expected a checkpoint of a {expected}, got one of a {checkpoint['filter_type']}"
            )
        self._state = copy.deepcopy(checkpoint["state"])
        self._n_updates = int(checkpoint.get("n_updates", 0))
