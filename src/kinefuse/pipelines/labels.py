"""Table labels of the pipelines' methods and the method lists of the papers' tables.

Used by the session outputs (:mod:`kinefuse.pipelines.run`) and by the apps that print the
papers' tables (:mod:`kinefuse.apps.demo`, :mod:`kinefuse.apps.experiments`).
"""

from __future__ import annotations

from kinefuse.pipelines.vision_assisted import METHODS

__all__ = ["BASELINE_METHODS", "PAPER_A_LABELS", "PAPER_B_LABELS", "paper_b_methods"]

#: Paper A method names of :func:`kinefuse.pipelines.upper_limb` -> table labels (paper A's).
PAPER_A_LABELS = {"kf": "KF", "fir": "FIR", "em-kf-fir": "EM-KF/FIR"}
#: Paper B method names of :func:`kinefuse.pipelines.vision_assisted` -> table labels.
PAPER_B_LABELS = {
    "elm-fir": "ELM/FIR",
    "elm-kf": "ELM/KF",
    "imu-only": "IMU only",
    "camera-only": "camera only",
    "camera-gapfill": "camera gap-fill",
    "offset-interp": "offset interp",
    "offset-hold": "offset hold",
    "kinefuse": "kinefuse",
}
#: The simple baselines every paper-B table shows (:mod:`kinefuse.pipelines.vision_assisted`).
BASELINE_METHODS = ("camera-gapfill", "offset-interp", "offset-hold")


def paper_b_methods(include_kinefuse: bool = True) -> tuple[str, ...]:
    """Paper B methods available in this installation, in table order: paper B's, the simple
    baselines (:data:`BASELINE_METHODS`), then ``"kinefuse"``."""
    names = ["elm-fir", "elm-kf", "imu-only", "camera-only", *BASELINE_METHODS]
    if include_kinefuse and "kinefuse" in METHODS:
        names.append("kinefuse")
    return tuple(n for n in names if n in METHODS)
