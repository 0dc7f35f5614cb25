"""End-to-end pipelines: paper A's upper limb (Sun 2024) and paper B's vision-assisted fusion (Xu 2023).

Thin over :mod:`kinefuse.filters`, :mod:`kinefuse.learning` and :mod:`kinefuse.kinematics`.
"""

from kinefuse.pipelines._outages import SOURCE_NONE, OutageEpisode
from kinefuse.pipelines.fusion_context import FusionResult
from kinefuse.pipelines.upper_limb import (
    UPPER_LIMB_METHODS,
    UpperLimbResult,
    upper_limb,
    upper_limb_from_recording,
)
from kinefuse.pipelines.vision_assisted import METHODS, register_method, vision_assisted
from kinefuse.pipelines.vision_params import VisionParams
from kinefuse.pipelines.vision_recording import RecordingFusion, vision_assisted_from_recording

__all__ = [
    "METHODS",
    "SOURCE_NONE",
    "UPPER_LIMB_METHODS",
    "FusionResult",
    "OutageEpisode",
    "RecordingFusion",
    "UpperLimbResult",
    "VisionParams",
    "register_method",
    "upper_limb",
    "upper_limb_from_recording",
    "vision_assisted",
    "vision_assisted_from_recording",
]
