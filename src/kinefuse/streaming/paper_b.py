"""Paper B (Xu 2023) as a per-frame processor: the causal ELM/FIR (or ELM/KF) pipeline online.

:class:`VisionAssistedProcessor` steps :class:`kinefuse.pipelines.paper_b.PaperBCore`, the same
core the batch pipeline :func:`kinefuse.pipelines.vision_assisted` (``causal=True``) runs over a
whole series: here one frame per :meth:`~VisionAssistedProcessor.step`. The processor adds the
engine's protocol (validation per frame, checkpoints, warm-up) and nothing of the method.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np

from kinefuse._validation import positive_finite
from kinefuse.exceptions import InputError
from kinefuse.pipelines.paper_b import PAPER_B_METHODS, PaperBCore, PaperBState
from kinefuse.pipelines.vision_assisted import vision_assisted
from kinefuse.pipelines.vision_params import VisionParams
from kinefuse.streaming.processors import _check_series

__all__ = ["VisionAssistedProcessor"]

_CHECKPOINT_VERSION = 2


class VisionAssistedProcessor:
    """Paper B's causal pipeline (ELM/FIR or ELM/KF) per frame, all joints batched.

    Parameters
    ----------
    method : {"elm-fir", "elm-kf"}
        As in :func:`kinefuse.pipelines.vision_assisted`: UFIRs (paper B) or KFs (its
        comparator) for FIR-1..3.
    params : VisionParams, optional
        Pipeline settings (default ``VisionParams()``). ``fixed_lag`` must be 0: the processor
        reproduces the causal, undelayed output.
    dt_s : float
        Frame interval, s (default 1/30).
    joints : int or sequence of str, optional
        Number of joints, or their names; fixes J at construction. Default: J taken from the
        first frame.

    Attributes
    ----------
    lag_frames : int
        0 (outputs are not delayed).
    core : PaperBCore
        The method (configuration).
    state : PaperBState or None
        Its state (None before the first frame when J is not fixed).
    last_mu : ndarray, shape (J, 2)
        IMM model probabilities (IMU, camera) after the last step.

    Notes
    -----
    Each frame is :meth:`PaperBCore.advance` over a block of one frame (the pipeline is in
    :mod:`kinefuse.pipelines.paper_b`). Per frame: FIR-1, FIR-2 and the IMM over all joints,
    plus, per joint in an outage, one FIR-3 step and two ELM evaluations; at an outage onset
    the joint's ELMs are trained and FIR-3 is run over the window (O(W), once per episode).
    ``step`` repeated equals :func:`vision_assisted` (``causal=True``; positions and
    covariances to rounding, sources exactly; tested to 1e-9): both run the same code, on
    blocks of one frame and of the whole series.
    """

    lag_frames = 0

    def __init__(
        self,
        method: str = "elm-fir",
        params: VisionParams | None = None,
        dt_s: float = 1 / 30,
        joints: int | Sequence[str] | None = None,
    ):
        if method not in PAPER_B_METHODS:
            raise InputError(f"expected method in {tuple(PAPER_B_METHODS)}, got {method!r}")
        if params is None:
            params = VisionParams()
        elif not isinstance(params, VisionParams):
            raise InputError(f"expected params as a VisionParams, got {type(params).__name__}")
        if params.fixed_lag != 0:
            raise InputError(
                f"expected params.fixed_lag = 0 (the processor gives the undelayed causal output), "
                f"got {params.fixed_lag}"
            )
        self.method = method
        self.params = params
        self.dt_s = positive_finite(dt_s, "dt_s")
        self.joints, self.n_joints = _joint_names(joints)
        self.core = PaperBCore(method, params, self.dt_s)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the initial state (sized now if J is known, else on the first frame)."""
        self._allocate(self.n_joints)

    def _allocate(self, J: int | None) -> None:
        self.state: PaperBState | None = None if J is None else self.core.init(J)
        self.last_mu = None if J is None else np.full((J, 2), np.nan)

    @property
    def frames(self) -> int:
        """Frames processed since the start (or the last reset)."""
        return 0 if self.state is None else self.state.k

    @property
    def episodes(self) -> tuple:
        """Per joint, the :class:`~kinefuse.pipelines.OutageEpisode` s so far (a running one
        ends at :attr:`frames`, not recovered: what the batch pipeline reports at that length)."""
        return () if self.state is None else self.state.episodes()

    @property
    def _episodes(self) -> list:
        # read by kinefuse.apps.bench_engine (episode count per frame, for the onset timings)
        s = self.state
        if s is None:
            return []
        return [[*c, *([] if o is None else [o])] for c, o in zip(s.closed, s.open, strict=True)]

    def checkpoint(self) -> dict:
        """Pickle-able snapshot of the mutable state (filter states, history, trained ELMs)."""
        return {
            "version": _CHECKPOINT_VERSION,
            "type": type(self).__name__,
            "method": self.method,
            "state": copy.deepcopy((self.state, self.last_mu)),
        }

    def restore(self, checkpoint: dict) -> None:
        """Return to a snapshot from :meth:`checkpoint` (same method and parameters)."""
        got = checkpoint if isinstance(checkpoint, dict) else {"type": type(checkpoint).__name__}
        for key, want, text in (
            ("type", type(self).__name__, "a checkpoint of a {}"),
            ("version", _CHECKPOINT_VERSION, "checkpoint version {}"),
            ("method", self.method, "a checkpoint of method {!r}"),
        ):
            if got.get(key) != want:
                raise InputError(f"expected {text.format(want)}, got {got.get(key)!r}")
        state, mu = copy.deepcopy(checkpoint["state"])
        if state is None:
            self.reset()
            return
        if self.n_joints is not None and state.n_joints != self.n_joints:
            raise InputError(
                f"expected a checkpoint for {self.n_joints} joints, got {state.n_joints}"
            )
        self.state, self.last_mu = state, mu

    # ------------------------------------------------------------------ per frame
    def step(self, t_s, z_imu, z_cam, available):
        """Process one frame.

        Parameters
        ----------
        t_s : float
            Frame time, s (unused: fixed-rate models; kept for the protocol).
        z_imu : array_like, shape (J, 3)
            IMU-chain joint positions, m; NaN rows = no IMU measurement.
        z_cam : array_like, shape (J, 3)
            Camera joint positions, m; ignored where ``available`` is False or not finite.
        available : array_like of bool, shape (J,)

        Returns
        -------
        position : ndarray, shape (J, 3)
            m; NaN where there is no estimate.
        cov : ndarray, shape (J, 3, 3)
            m².
        source : ndarray of int8, shape (J,)
            ``SOURCE_FUSED``, ``SOURCE_BRIDGED``, ``SOURCE_IMU``, ``SOURCE_PREDICTED``
            (neither the chain nor the camera measured the joint), or -1 (no estimate).
        """
        zi = np.asarray(z_imu, dtype=np.float64)
        zc = np.asarray(z_cam, dtype=np.float64)
        av = np.asarray(available, dtype=bool)
        if self.state is None:
            if zi.ndim != 2:
                raise InputError(f"expected z_imu with shape (J, 3), got {zi.shape}")
            self._allocate(zi.shape[0])
        J = self.state.n_joints
        if zi.shape != (J, 3) or zc.shape != (J, 3) or av.shape != (J,):
            raise InputError(
                f"expected z_imu, z_cam (J, 3) and available (J,) with J = {J}, got "
                f"{zi.shape}, {zc.shape}, {av.shape}"
            )
        # (the ELMs' small-sample warning is silenced where they are fitted: PaperBCore._onset)
        out = self.core.advance(self.state, zi[:, None], zc[:, None], av[:, None])
        self.last_mu = out.imm.mu[:, 0]
        return out.position[:, 0], out.cov[:, 0], out.source[:, 0]

    def warm_up(self) -> None:
        """Run every compiled path once on a throwaway copy (state of ``self`` untouched).

        The first call of a numba kernel in a process loads (or compiles) its machine code,
        which takes tens of milliseconds: call this before a real-time run so that the first
        frames and the first outage onset do not pay it.
        """
        n = self.core.n_min + self.params.horizon + 5
        t = np.arange(n + 2 * self.params.horizon) * self.dt_s
        zi = np.stack([np.sin(t), np.cos(0.7 * t), 0.1 * t], axis=-1)[:, None, :]
        zc = zi + 0.01
        av = np.ones((t.size, 1), bool)
        av[n : n + 3] = False
        tmp = VisionAssistedProcessor(self.method, self.params, self.dt_s, 1)
        for k in range(t.size):
            tmp.step(t[k], zi[k], zc[k], av[k])

    # ------------------------------------------------------------------ series
    def flush(self) -> list:
        """Nothing is held back (no lag): ``[]``."""
        return []

    def run(self, t_s, z_imu, z_cam, available):
        """:func:`vision_assisted` with ``causal=True`` over ``(T, J, ...)`` series, as the
        processor protocol's ``run``: ``(position, cov, source)``; the online state is not
        touched. A joint without any finite IMU sample (which the batch pipeline refuses) is
        run through :meth:`step` on a fresh copy of the processor instead.
        """
        t, zi, zc, av = _check_series(t_s, z_imu, z_cam, available)
        if self.n_joints is not None and zi.shape[1] != self.n_joints:
            raise InputError(f"expected {self.n_joints} joints, got {zi.shape[1]}")
        if np.all(np.any(np.all(np.isfinite(zi), axis=-1), axis=0)):
            r = vision_assisted(zi, zc, av, self.dt_s, self.method, causal=True, params=self.params)
            return r.position, r.cov, r.source
        fresh = VisionAssistedProcessor(self.method, self.params, self.dt_s, zi.shape[1])
        outs = [fresh.step(t[k], zi[k], zc[k], av[k]) for k in range(t.size)]
        return tuple(np.stack([o[i] for o in outs]) for i in range(3))


def _joint_names(joints) -> tuple[tuple[str, ...] | None, int | None]:
    """``(names, J)`` from a joint count or names (``(None, None)``: J from the first frame)."""
    if joints is None:
        return None, None
    if isinstance(joints, (int, np.integer)) and not isinstance(joints, bool):
        if joints < 1:
            raise InputError(f"expected joints >= 1, got {joints}")
        return tuple(f"joint_{j}" for j in range(int(joints))), int(joints)
    if isinstance(joints, str):
        raise InputError(f"expected joints as a sequence of names, got {joints!r}")
    names = tuple(str(j) for j in joints)
    if not names:
        raise InputError("expected at least one joint")
    return names, len(names)
