"""Packaged demo data: one short CMU mocap trial (subject 02, trial 08, swordplay, 12.5 s).

Attribution and terms: ``CMU_ATTRIBUTION.md`` in this folder ("The data used in this project was
obtained from mocap.cs.cmu.edu. The database was created with funding from NSF EIA-0196217.").
"""

from __future__ import annotations

from importlib.resources import as_file, files
from pathlib import Path

from kinefuse.io.cmu import load_motion_asf_amc

__all__ = ["DEMO_TRIAL", "demo_motion", "demo_paths"]

#: The packaged trial: CMU subject 02, trial 08 ("swordplay", 1500 frames at 120 Hz).
DEMO_TRIAL = "02_08"


def demo_paths() -> tuple[Path, Path]:
    """Paths of the packaged ``(amc, asf)`` files."""
    root = files(__name__)
    with as_file(root / f"{DEMO_TRIAL}.amc") as amc, as_file(root / "02.asf") as asf:
        return Path(amc), Path(asf)


def demo_motion(start_s: float | None = None, stop_s: float | None = None):
    """The packaged CMU trial as a :class:`~kinefuse.io.motion.Motion`.

    Parameters
    ----------
    start_s, stop_s : float, optional
        Keep only ``start_s <= t_s < stop_s`` (s; default the whole 12.5 s trial).

    Returns
    -------
    Motion
        120 Hz; ``q_world_from_segment (T, 12, 4)``, ``position_m (T, 22, 3)`` in metres, ENU.
    """
    amc, asf = demo_paths()
    motion = load_motion_asf_amc(amc, asf)
    if start_s is not None or stop_s is not None:
        motion = motion.window(
            -float("inf") if start_s is None else start_s,
            float("inf") if stop_s is None else stop_s,
        )
    return motion
