"""The live loop of the online engine: pull every input, feed the engine, push its outputs.

:func:`run_loop` is transport-agnostic (any input with ``pull``/``feed``/``refresh_clock``/
``close``/``lost``, any outlet with ``push``/``close``); :func:`~.runner.run_stream` runs it on
LSL inlets.
"""

from __future__ import annotations

import gc
import logging
import time
from collections import deque
from typing import NamedTuple

import numpy as np

from kinefuse.streaming.interrupt import sigint_as_flag

__all__ = ["LoopResult", "run_loop"]

log = logging.getLogger("kinefuse.streaming")


class LoopResult(NamedTuple):
    """Outcome of :func:`run_loop`."""

    #: Ctrl-C ended the loop.
    interrupted: bool
    #: Per timed output, s: start of the pull that returned the sample completing its frame ->
    #: output pushed.
    latency_s: np.ndarray
    #: Outputs pushed.
    outputs: int
    #: Outputs of the start-up backlog (not timed).
    catch_up_outputs: int


class _Loop:
    """The state of one :func:`run_loop`: counts, latencies, start-up catch-up, timers."""

    def __init__(self, engine, inputs, outlet, clock, on_output):
        self.engine, self.inputs, self.outlet = engine, inputs, outlet
        self.clock, self.on_output = clock, on_output
        self.latencies: deque = deque(maxlen=200_000)
        self.n_out = 0
        self.caught_up = False
        self.n_catch_up = 0
        self.last_data = None
        self.next_status = 0.0
        self.next_reattach = 0.0

    def push(self, outs, t_pull) -> None:
        for o in outs:
            if self.outlet is not None:
                self.outlet.push(o)
            if t_pull is not None:
                self.latencies.append(time.perf_counter() - t_pull)
            self.n_out += 1
            if self.on_output is not None:
                self.on_output(o)

    def pass_once(self) -> bool:
        """Pull every live input once and process what is ready; True if any sample came."""
        engine, clock = self.engine, self.clock
        got = False
        for inp in self.inputs:
            if inp.lost:
                continue
            t_pull = time.perf_counter()
            data, ts = inp.pull()
            if len(ts):
                got = True
                inp.feed(engine, data, ts, clock())
                if self.caught_up:  # live: the frame these samples complete goes out now
                    self.push(engine.poll(clock()), t_pull)
        if not self.caught_up:
            # start-up: the samples buffered while the streams were connected are all read
            # before any frame is processed (a frame never goes out without IMU samples that
            # had already arrived); these outputs are not timed
            outs = engine.poll(clock())
            self.n_catch_up += len(outs)
            self.push(outs, None)
            self.caught_up = not got
        else:
            self.push(engine.poll(clock()), None)  # frames released by max latency / staleness
        return got

    def housekeeping(self, mono: float, got: bool, status, reattach) -> None:
        """Clock offsets, reattaching lost inputs (every 0.5 s), status (every 0.25 s)."""
        if got:
            self.last_data = mono
        for inp in self.inputs:
            if not inp.lost:
                inp.refresh_clock()
        if reattach is not None and mono >= self.next_reattach:
            self.next_reattach = mono + 0.5
            for inp in self.inputs:
                if inp.lost:
                    reattach(inp)
        if status is not None and mono >= self.next_status:
            self.next_status = mono + 0.25
            status(self.engine, self.latencies)

    def close(self) -> None:
        """Flush the engine's pending frames, then close inputs and outlet."""
        try:
            self.push(self.engine.flush(self.clock()), None)
        finally:
            for inp in self.inputs:
                inp.close()
            if self.outlet is not None:
                self.outlet.close()


def _stop(mono, start, last_data, duration_s, idle_timeout_s, stop_event) -> bool:
    if duration_s is not None and mono - start >= duration_s:
        return True
    if idle_timeout_s is not None and last_data is not None and mono - last_data >= idle_timeout_s:
        return True
    return stop_event is not None and stop_event.is_set()


def run_loop(engine, inputs, outlet, *, clock, duration_s=None, idle_timeout_s=None, stop_event=None,
             on_output=None, status=None, reattach=None) -> LoopResult:  # fmt: skip
    """Pull every input, feed the engine, push its outputs, until a stop condition.

    Parameters
    ----------
    engine : Engine
    inputs : list of :class:`~kinefuse.streaming.lsl.Input`-like objects
        ``pull() -> (data, ts)``, ``feed(engine, data, ts, now)``, ``refresh_clock()``,
        ``close()``, ``lost``.
    outlet : object with ``push(output)`` and ``close()``, or None
    clock : callable
        Current time on the samples' clock (``pylsl.local_clock``).
    duration_s, idle_timeout_s : float, optional
        Stop after this wall time / after this long without any input sample (once some
        arrived).
    stop_event : threading.Event, optional
    on_output : callable, optional
        Called with every :class:`EngineOutput` after it was pushed.
    status : callable, optional
        Called about 4 times a second with ``(engine, latencies_s)``.
    reattach : callable, optional
        Called with a lost input every 0.5 s until it returns True.

    Returns
    -------
    LoopResult

    Notes
    -----
    Live, every input is polled in turn and the engine right after each input that returned
    samples, so a frame goes out as soon as its last sample is in. At start-up the samples
    buffered while the streams were being connected are first read from every input before
    any frame is processed (until a loop pass finds nothing new); those outputs are counted
    as ``catch_up_outputs`` and not timed (they measure the connection time, not the
    processing). Outputs released by ``max_latency_s`` / staleness are not timed either.

    Ctrl-C (SIGINT) ends the loop; pending frames are then processed (:meth:`Engine.flush`)
    and pushed, and inputs and outlet are closed. In the main thread the signal is taken
    between two loop passes (a handler sets a flag; the previous handler is restored before
    the flush), so a frame the engine has processed is never lost to an interrupt inside a
    pass; elsewhere a KeyboardInterrupt ends the loop as it comes. A process that ignores
    SIGINT (started in the background) keeps ignoring it.
    """
    start = time.monotonic()
    loop = _Loop(engine, inputs, outlet, clock, on_output)
    interrupted = False
    gc.collect()
    gc.freeze()  # set-up objects out of the collector's way: short collections in the loop
    try:
        with sigint_as_flag() as sigint:  # the previous handler is back before the flush
            try:
                while not sigint:
                    got = loop.pass_once()
                    mono = time.monotonic()
                    loop.housekeeping(mono, got, status, reattach)
                    if _stop(mono, start, loop.last_data, duration_s, idle_timeout_s, stop_event):
                        break
                    if not got:
                        time.sleep(0.0005)
                interrupted = bool(sigint)
            except KeyboardInterrupt:
                interrupted = True
    finally:
        if interrupted:
            log.warning("interrupted (Ctrl-C): flushing pending frames and closing streams")
        gc.unfreeze()
        loop.close()
    return LoopResult(interrupted, np.asarray(loop.latencies), loop.n_out, loop.n_catch_up)
