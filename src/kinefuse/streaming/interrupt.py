"""Ctrl-C taken at a safe point: :func:`sigint_as_flag`.

A live loop that pushes samples must not be cut between a push and its bookkeeping (a frame
processed but never sent, a sample sent but not counted). Inside :func:`sigint_as_flag`, SIGINT
only sets a flag that the loop reads between two steps.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["sigint_as_flag"]


@contextmanager
def sigint_as_flag() -> Iterator[list]:
    """Within the block, Ctrl-C (SIGINT) appends ``True`` to the yielded list instead of
    raising :class:`KeyboardInterrupt`; the previous handler is restored on leaving.

    Only in the main thread (Python delivers signals there): elsewhere the list stays empty and a
    KeyboardInterrupt comes as usual. A process that ignores SIGINT (started in the background)
    keeps ignoring it. A handler not installed from Python is restored as Python's default.
    """
    flag: list = []
    main = threading.current_thread() is threading.main_thread()
    main = main and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN
    previous = signal.signal(signal.SIGINT, lambda *_: flag.append(True)) if main else None
    try:
        yield flag
    finally:
        if main:
            signal.signal(
                signal.SIGINT, signal.default_int_handler if previous is None else previous
            )
