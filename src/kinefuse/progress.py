"""Progress bars for long work: one rich bar on stderr, or nothing when quiet.

Bottom layer (imports no other kinefuse module): the pipelines, the apps and the CLI all show
progress through :func:`progress`, so nothing below the CLI imports :mod:`kinefuse.cli`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from rich import progress as bars
from rich.console import Console
from rich.markup import escape

__all__ = ["progress"]


def _stderr() -> Console:
    return Console(stderr=True, highlight=False, soft_wrap=True)


@contextlib.contextmanager
def progress(
    description: str, total: float | None = None, *, quiet: bool = False
) -> Iterator[Callable[..., None]]:
    """A rich progress bar on stderr for long work; yields ``advance(n=1)``.

    Parameters
    ----------
    description : str
        Shown left of the bar.
    total : float, optional
        Number of steps (None: an indeterminate spinner).
    quiet : bool
        Show nothing (``advance`` is a no-op).

    Yields
    ------
    callable
        ``advance(n=1)``: n more steps done; ``advance.describe(text)`` replaces the
        description (e.g. the stage a long step is in).

    Examples
    --------
    >>> with progress("Filtering joints", total=3, quiet=True) as advance:
    ...     for _ in range(3):
    ...         advance()
    """
    if quiet:
        yield _Advance(None, None)
        return
    columns = [bars.SpinnerColumn(), bars.TextColumn("{task.description}"), bars.BarColumn()]
    if total is not None:
        columns.append(bars.MofNCompleteColumn())
    columns.append(bars.TimeElapsedColumn())
    with bars.Progress(*columns, console=_stderr(), transient=True) as bar:
        task = bar.add_task(escape(description), total=total)  # text, not markup (a name)
        yield _Advance(bar, task)


class _Advance:
    """``advance(n=1)`` and ``advance.describe(text)`` of one bar (no-ops without a bar)."""

    def __init__(self, bar, task):
        self._bar, self._task = bar, task

    def __call__(self, n: float = 1) -> None:
        if self._bar is not None:
            self._bar.advance(self._task, n)

    def describe(self, text: str) -> None:
        if self._bar is not None:
            self._bar.update(self._task, description=escape(text))
