"""Readers and writers of real recording formats, one :class:`Recording` container, alignment.

Entry point: :func:`load` (format detected from content, extension and folder layout; see
:data:`FORMATS` and ``docs/formats.md``). Reader and writer functions are re-exported lazily,
so ``import kinefuse.io`` stays cheap and optional dependencies (``ezc3d``) are imported only
when used.
"""

from __future__ import annotations

from kinefuse._lazy import lazy_exports
from kinefuse.io._registry import _REGISTRY, FORMATS, detect_format, load
from kinefuse.io.recording import ImuStream, JointStream, Recording

_LAZY = {
    "read_utd_mhad": "utd_mhad",
    "read_opensense": "opensense",
    "read_qmt": "qmt",
    "read_ximu3": "ximu3",
    "read_broad": "broad",
    "read_c3d": "c3d",
    "read_trc": "trc",
    "write_trc": "trc",
    "write_mot": "mot",
    "read_kinect_v2_csv": "kinect_v2",
    "read_azure_kinect_json": "azure_kinect",
    "read_mediapipe": "mediapipe",
    "read_generic_csv": "generic_csv",
    "read_imu_csv": "generic_csv",
    "read_joint_csv": "generic_csv",
    "write_imu_csv": "generic_csv",
    "write_joint_csv": "generic_csv",
    "resample_coverage": "align",
    "resample_orientation": "align",
    "resample_positions": "align",
    "resample_recording": "align",
    "common_timeline": "align",
    "estimate_clock_offset": "align",
    "ClockOffset": "align",
    "check_units": "_checks",
    # other engineers' readers (resolved when their modules are present)
    "read_neura": "neura",
    "read_asf_amc": "cmu",
    "read_bvh": "bvh",
    "read_opensim_table": "opensim",
    "read_opensense_sto": "opensim",
    "write_opensense_sto": "opensim",
    "read_mvnx": "mvnx",
    "read_xsens_dot": "xsens_dot",
    "read_xio_csv": "xio_csv",
}

# every registered reader is exported too (a new format needs no line here)
_LAZY |= {spec.function: spec.module for spec in _REGISTRY.values() if spec.function not in _LAZY}

__all__ = ["FORMATS", "ImuStream", "JointStream", "Recording", "detect_format", "load", *_LAZY]


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
