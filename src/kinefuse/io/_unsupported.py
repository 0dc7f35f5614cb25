"""What an unreadable file looks like: the "unsupported format" message of :func:`kinefuse.io.load`.

Private module. :func:`unsupported_message` names what the file appears to be (from its
extension, first bytes, columns or variables) and what kinefuse reads instead, so a user learns
which export to make rather than that "the format could not be detected".
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from pathlib import Path

import scipy  # scipy.io loads on first use (SciPy imports its subpackages lazily)

__all__ = ["looks_like", "unsupported_message"]

_BY_EXTENSION = {
    ".mvn": "an Xsens MVN Analyze recording (binary); export it to MVNX (.mvnx) in MVN Analyze",
    ".mtb": "an Xsens MT Manager binary log; export it as text (.txt) in MT Manager",
    ".osim": "an OpenSim model, not a recording",
    ".xlsx": "an Excel workbook; save the sheet as CSV",
    ".xls": "an Excel workbook; save the sheet as CSV",
    ".fbx": "an FBX animation; export it as BVH",
    ".xdf": "an LSL XDF recording; load its streams with pyxdf and build a Recording",
    ".mkv": "an Azure Kinect video recording; run the Body Tracking SDK and export its JSON",
    ".mp4": "a video; run a pose estimator (e.g. MediaPipe Pose) and export the landmarks",
    ".avi": "a video; run a pose estimator (e.g. MediaPipe Pose) and export the landmarks",
    ".mov": "a video; run a pose estimator (e.g. MediaPipe Pose) and export the landmarks",
    ".npy": "a NumPy array file (no time base or names); build a Recording in Python",
    ".npz": "a NumPy archive (no declared layout); build a Recording in Python",
    ".h5": "an HDF5 file (no declared layout); build a Recording in Python",
    ".hdf5": "an HDF5 file (no declared layout); build a Recording in Python",
    ".pkl": "a Python pickle (not read: unpickling runs code)",
    ".zip": "a compressed archive; extract it first",
    ".gz": "a compressed archive; extract it first",
    ".tar": "an archive; extract it first",
    ".7z": "a compressed archive; extract it first",
    ".log": "a log file",
    ".md": "a Markdown document",
    ".pdf": "a PDF document",
}


def _readable_files(folder: Path, detect, limit: int = 50) -> list[tuple[str, str]]:
    """(name, format) of the first ``limit`` entries of ``folder`` that ``detect`` recognises
    (hidden ones left out, as the loader leaves them)."""
    out = []
    for p in sorted(p for p in folder.iterdir() if not p.name.startswith("."))[:limit]:
        try:  # sub-folders by layout only: no recursion into their own messages
            fmt = detect(p)
        except (ValueError, OSError):
            continue
        if fmt:
            out.append((p.name + ("/" if p.is_dir() else ""), fmt))
    return out


def _inside(folder: Path, detect) -> str:
    """``"; its sub-folder d/ holds files kinefuse reads (fmt), e.g. d/x; pass one of them"``
    for the first sub-folder (of 10) holding recordings, else ``""`` (a dataset's top folder)."""
    if detect is None:
        return ""
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and p.name[0] != ".")[:10]:
        readable = _readable_files(sub, detect)
        if readable:
            fmts = ", ".join(sorted({fmt for _n, fmt in readable}))
            return (
                f"; its sub-folder {sub.name}/ holds files kinefuse reads ({fmts}), e.g. "
                f"{sub.name}/{readable[0][0]}; pass one of them"
            )
    return ""


def _head(path: Path, n: int = 8192) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError:
        return b""


def _columns(text: str) -> list[str]:
    for ln in text.splitlines():
        s = ln.strip()
        if s and not s.startswith(("#", "//")):
            sep = "\t" if "\t" in s else ("," if "," in s else (";" if ";" in s else None))
            return [c.strip() for c in (s.split(sep) if sep else s.split())]
    return []


def looks_like(path, detect=None) -> str:
    """A short description of what ``path`` appears to be (never raises).

    ``detect(p) -> format or None`` recognises the entries of a folder (the registry's
    detection, passed in so that this module does not import the registry).
    """
    path = Path(path)
    if path.is_dir():
        kinds = Counter(p.suffix.lower() or "(no extension)" for p in path.iterdir() if p.is_file())
        if not kinds:
            return "a folder without files kinefuse recognises (pass one file or a sensor folder)"
        top = ", ".join(f"{n} {ext}" for ext, n in kinds.most_common(4))
        readable = _readable_files(path, detect) if detect is not None else []
        if readable:
            shown = ", ".join(f"{name}: {fmt}" for name, fmt in readable[:4])
            more = f" and {len(readable) - 4} more" if len(readable) > 4 else ""
            return (
                f"a folder ({top}) that is not one recording; kinefuse reads what is in it one "
                f"at a time ({shown}{more}); pass one of them"
            )
        return f"a folder of files kinefuse does not recognise ({top}){_inside(path, detect)}"
    ext = path.suffix.lower()
    raw = _head(path)
    if not raw.strip():
        return "an empty file"
    text = raw.decode("utf-8", errors="replace")
    low = text.lower()
    if ext in _BY_EXTENSION:
        return _BY_EXTENSION[ext]
    if "<opensimdocument" in low:
        return "an OpenSim setup or model XML, not a recording"
    if "no_of_frames" in low and "marker_names" in low:
        return "a Qualisys TSV export; export C3D from QTM instead"
    if ext == ".mat":
        try:
            names = [n for n, _s, _c in scipy.io.whosmat(path)]
        except Exception:
            names = None
        if names is not None:
            return f"a MATLAB file with variables {names[:8]} (no known dataset layout)"
        return "a MATLAB file of a version scipy cannot list (v7.3/HDF5?)"
    if ext == ".json":
        return "a JSON file without Azure Kinect 'bodies' or MediaPipe landmarks"
    if b"\x00" in raw or text.count("\ufffd") > len(text) // 20:
        return f"a binary file ({ext or 'no extension'})"
    cols = _columns(text)
    if len(cols) > 1:
        shown = ", ".join(repr(c) for c in cols[:6]) + (", ..." if len(cols) > 6 else "")
        return f"a text table whose columns ({shown}) match no known layout"
    return f"a text file without a recognisable header ({ext or 'no extension'})"


def unsupported_message(path, formats: Mapping[str, str], detect=None) -> str:
    """``"unsupported format: this looks like X; kinefuse reads: a, b, ..."`` for ``path``: the
    reader names only (their descriptions: ``kinefuse.io.FORMATS``, docs/formats.md), so that
    the message stays one readable line."""
    return (
        f"unsupported format: this looks like {looks_like(path, detect)}; kinefuse reads: "
        f"{', '.join(sorted(formats))} (docs/formats.md describes each). To read it as one of "
        "them anyway: --format NAME (Python: format=NAME)"
    )
