"""A set of result files written all at once: staged in a temporary folder, moved into place.

:class:`OutputFolder` is how ``kinefuse run`` writes its results (issue 12): every output is
written into a hidden staging folder on the same file system, and only a complete set is moved
into the output folder. An interrupted or failed run leaves the previous results untouched and
nothing half-written; existing results are replaced only with ``force``; the folder is checked
writable before any processing starts.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

from kinefuse.exceptions import InputError
from kinefuse.io._write import current_umask

__all__ = ["OutputFolder", "check_folder_usable", "check_writable_file", "deferred_interrupts"]

_STAGING_PREFIX = ".kinefuse-partial-"
_PREVIOUS_PREFIX = ".kinefuse-previous-"


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold SIGINT/SIGTERM until the block ends (main thread only), then deliver them.

    Used around the few renames that swap a result set in, so that Ctrl-C cannot leave a mix
    of old and new files.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum, frame):
        caught.append(signum)

    old = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if caught:
            if caught[0] == signal.SIGINT:
                raise KeyboardInterrupt
            os.kill(os.getpid(), caught[0])


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


def _check_dir_writable(folder: Path, what: str) -> None:
    if not folder.is_dir():
        raise InputError(f"{what} {folder}: exists and is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{what} {folder}: folder is not writable (permission denied)")


def check_folder_usable(folder: Path, what: str = "output folder") -> None:
    """Refuse, before any work, an output folder that cannot be created or written.

    An existing ``folder`` must be a writable folder. Otherwise a probe folder is created (and
    removed at once) in its nearest existing parent, as :class:`OutputFolder` will stage there:
    permission checks alone pass for root on file systems that refuse new entries (``/proc``).

    Raises
    ------
    InputError
        The folder (or its nearest existing parent) is a file or not writable, or nothing can
        be created in it; the message names the folder and the system's reason.
    """
    folder = Path(folder)
    anchor = folder if folder.exists() else _nearest_existing(folder.parent)
    _check_dir_writable(anchor, what if anchor == folder else f"{what} {folder}: parent")
    _probe(anchor, f"{what} {folder}")


def _probe(folder: Path, label: str) -> None:
    """Create and remove a folder in ``folder``: an InputError ``label: not writable (why)``
    where the file system refuses (``os.access`` says yes to root on ``/proc``)."""
    try:
        os.rmdir(tempfile.mkdtemp(prefix=_STAGING_PREFIX, dir=folder))
    except OSError as exc:
        raise InputError(f"{label}: not writable ({exc.strerror})") from None


def check_writable_file(
    path: Path, *, force: bool, protect: Iterable = (), what: str = "output"
) -> None:
    """Refuse an output file that is an input, exists without ``force`` or cannot be written.

    Parameters
    ----------
    path : Path
        The file to be written later.
    force : bool
        Allow replacing an existing file (never an input).
    protect : iterable of path
        Input files and folders (and the run's own results): ``path`` may be none of them
        nor lie inside one of those folders.
    what : str
        Label in messages (``"--json"``).

    Raises
    ------
    FileExistsError
        ``path`` exists and ``force`` is False.
    InputError
        ``path`` is an input, a folder, or its folder is missing or not writable (probed by
        creating and removing a folder in it, as :func:`check_folder_usable` does).
    """
    path = Path(path)
    target = path.resolve()
    for p in protect:
        if not p:
            continue
        p = Path(p).resolve()
        if target == p or p in target.parents:
            raise InputError(
                f"{what} {path}: is an input or a result of this run ({p}); refusing to write "
                "over it, even with --force"
            )
    if path.is_dir():
        raise InputError(f"{what} {path}: is a folder, expected a file name")
    if path.exists() and not force:
        raise FileExistsError(
            f"{what} {path}: file exists; pass --force to overwrite it, or choose another file"
        )
    if not path.parent.is_dir():
        raise InputError(f"{what} {path}: folder {path.parent} does not exist")
    _check_dir_writable(path.parent, what)
    _probe(path.parent, f"{what} {path}")
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError(f"{what} {path}: file is not writable (permission denied)")


class OutputFolder:
    """Stage a set of result files and move them into ``folder`` only when complete.

    Parameters
    ----------
    folder : str or Path
        Output folder; created (with its parents) when the set is committed.
    names : iterable of str
        Every file or folder name this kind of run may write into ``folder`` (also those it
        does not write this time, e.g. a report without a reference): any of them that
        exists is previous results.
    force : bool
        Replace previous results. Without it an existing one is a ``FileExistsError``.
    protect : iterable of path
        Inputs of the run: no output may be one of them, even with ``force``.
    what : str
        Label in messages (``"--out"``).

    Raises
    ------
    FileExistsError
        Previous results exist and ``force`` is False (nothing is created).
    InputError
        ``folder`` is a file, an output is an input, or the folder (or the nearest existing
        parent) is not writable: checked at construction, before any processing.

    Notes
    -----
    The staging folder is ``<parent>/.kinefuse-partial-*`` beside a new output folder, or
    ``<folder>/.kinefuse-partial-*`` inside an existing one (same file system, so every move
    is a rename). :meth:`commit` moves a new folder into place with one ``rename``; into an
    existing folder it moves the previous results aside, moves the new ones in and then
    deletes the previous ones, with SIGINT/SIGTERM held for those few renames and a rollback
    on error. Files get the mode the user's umask gives (``mkdtemp`` would give 0700).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> root = pathlib.Path(tempfile.mkdtemp())
    >>> with OutputFolder(root / "out", ["a.txt"], force=False) as stage:
    ...     _ = (stage / "a.txt").write_text("new")
    >>> (root / "out" / "a.txt").read_text()
    'new'
    """

    def __init__(
        self,
        folder,
        names: Iterable[str],
        *,
        force: bool = False,
        protect: Iterable = (),
        what: str = "output folder",
    ):
        self.folder = Path(folder)
        self.names = tuple(dict.fromkeys(names))
        self.force = bool(force)
        self._what = what
        self._committed = False
        self._created: list[Path] = []
        folder = self.folder
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{what} {folder}: exists and is not a folder")
        resolved = folder.resolve()
        for p in protect:
            if not p:
                continue
            p = Path(p).resolve()
            for name in self.names:
                if (resolved / name) == p:
                    raise InputError(
                        f"{what} {folder}: output {name} would overwrite an input of this run "
                        f"({p}); choose another output folder"
                    )
        existing = self.previous()
        if existing and not self.force:
            listed = ", ".join(str(folder / n) for n in existing)
            raise FileExistsError(
                f"{listed} already exist{'s' if len(existing) == 1 else ''} (results of an "
                "earlier run); pass --force to replace them, or choose another --out folder"
            )
        if folder.exists():
            _check_dir_writable(folder, what)
            base = folder
        else:
            anchor = _nearest_existing(folder.parent)
            _check_dir_writable(anchor, what)
            base = folder.parent
            missing = []
            p = base
            while not p.exists():
                missing.append(p)
                p = p.parent
            try:
                base.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise InputError(f"{what} {folder}: cannot create it ({exc.strerror})") from None
            self._created = missing  # deepest first: removed again if nothing is committed
        try:
            self.path = Path(tempfile.mkdtemp(prefix=_STAGING_PREFIX, dir=base))
        except OSError as exc:
            self._remove_created()
            raise InputError(f"{what} {folder}: not writable ({exc.strerror})") from None
        os.chmod(self.path, 0o777 & ~current_umask())

    def previous(self) -> list[str]:
        """Names of previous results present in the folder."""
        return [n for n in self.names if (self.folder / n).exists()]

    def __enter__(self) -> Path:
        return self.path

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()

    def _remove_created(self) -> None:
        for p in self._created:
            with contextlib.suppress(OSError):
                p.rmdir()
        self._created = []

    def discard(self) -> None:
        """Delete the staged files (no-op after :meth:`commit`); previous results stay."""
        if self._committed:
            return
        shutil.rmtree(self.path, ignore_errors=True)
        self._remove_created()

    def commit(self) -> Path:
        """Move the staged set into the folder, replacing previous results; returns the folder."""
        if self._committed:
            return self.folder
        new = sorted(os.listdir(self.path))
        unknown = [n for n in new if n not in self.names]
        if unknown:
            raise RuntimeError(f"staged outputs {unknown} are not declared in names")
        folder = self.folder
        with deferred_interrupts():
            if not folder.exists():
                os.rename(self.path, folder)
            else:
                self._swap_into(folder, new)
            self._committed = True
        self._created = []
        return folder

    def _swap_into(self, folder: Path, new: list[str]) -> None:
        old = self.previous()
        if old and not self.force:  # appeared while processing
            self.discard()
            raise FileExistsError(
                f"{folder / old[0]} appeared while processing; nothing was written (pass "
                "--force to replace it)"
            )
        trash = Path(tempfile.mkdtemp(prefix=_PREVIOUS_PREFIX, dir=folder))
        moved_old: list[str] = []
        moved_new: list[str] = []
        try:
            for n in old:
                os.rename(folder / n, trash / n)
                moved_old.append(n)
            for n in new:
                os.rename(self.path / n, folder / n)
                moved_new.append(n)
        except OSError:
            for n in moved_new:  # roll back: the previous set is restored
                os.rename(folder / n, self.path / n)
            for n in moved_old:
                os.rename(trash / n, folder / n)
            trash.rmdir()
            raise
        os.rmdir(self.path)
        shutil.rmtree(trash, ignore_errors=True)
