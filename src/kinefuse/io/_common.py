"""Old import path of the io helpers, kept for code outside :mod:`kinefuse.io` that still uses it.

The helpers now live one idea per module: :mod:`~kinefuse.io._text` (tables, time columns,
JSON), :mod:`~kinefuse.io._names` (canonical names), :mod:`~kinefuse.io._checks` (metadata,
zero rule, unit checks) and :mod:`~kinefuse.io._write` (safe writes). New code imports from
those; this module only re-exports them.
"""

from __future__ import annotations

from kinefuse.io._checks import DEG2RAD, ZERO_RULE, G, check_units, make_metadata, zero_is_missing
from kinefuse.io._names import (
    KINECT_LIMB_JOINTS,
    PLUG_IN_GAIT_JOINTS,
    canonical_joint,
    canonical_segment,
    map_joints,
    map_segments,
)
from kinefuse.io._text import TIME_COLUMNS, Table, check_time, read_table, table_time
from kinefuse.io._write import current_umask, fmt_float, write_text_safely

__all__ = [
    "DEG2RAD",
    "G",
    "KINECT_LIMB_JOINTS",
    "PLUG_IN_GAIT_JOINTS",
    "TIME_COLUMNS",
    "ZERO_RULE",
    "Table",
    "canonical_joint",
    "canonical_segment",
    "check_time",
    "check_units",
    "current_umask",
    "fmt_float",
    "make_metadata",
    "map_joints",
    "map_segments",
    "read_table",
    "table_time",
    "write_text_safely",
    "zero_is_missing",
]
