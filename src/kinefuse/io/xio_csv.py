"""x-io Technologies' plain IMU CSV (as in x-io's Gait-Tracking and Oscillatory-Motion-Tracking examples).

One file, one sensor, a header and comma-separated rows::

    Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),...

optionally ``Magnetometer X/Y/Z (...)``. Units are read from the parentheses (time s/ms/us, gyro
deg/s or rad/s, acceleration g or m/s²). This is not the x-IMU3 log folder layout
(:mod:`kinefuse.io.ximu3`, ``Timestamp (us)`` in ``Inertial.csv``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import DEG2RAD, G, finish_recording, make_metadata
from kinefuse.io._text import Table, check_time, read_table, read_text, unit_triplet
from kinefuse.io.recording import ImuStream, Recording

__all__ = ["is_xio_csv", "read_xio_csv"]

_TIME = re.compile(r"^time\s*\((s|ms|us|µs)\)$", re.IGNORECASE)
_TIME_FACTOR = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
_GYR_FACTOR = {"deg/s": DEG2RAD, "°/s": DEG2RAD, "dps": DEG2RAD, "rad/s": 1.0}
_ACC_FACTOR = {"g": G, "m/s^2": 1.0, "m/s²": 1.0, "m/s2": 1.0}


def is_xio_csv(columns) -> bool:
    """True for a header ``Time (<unit>), Gyroscope X (...), ..., Accelerometer X (...)``."""
    cols = [c.strip() for c in columns]
    return (
        bool(cols)
        and _TIME.match(cols[0]) is not None
        and any(c.lower().startswith("gyroscope x") for c in cols)
        and any(c.lower().startswith("accelerometer x") for c in cols)
    )


def read_xio_csv(path, *, segment: str = "imu") -> Recording:
    """Read an x-io plain IMU CSV (one sensor) into a :class:`Recording`.

    Parameters
    ----------
    path : str or Path
        The ``.csv`` file.
    segment : str
        Key of the stream in ``Recording.imu`` (the file does not say where the sensor was
        worn); default ``"imu"``.

    Returns
    -------
    Recording
        ``imu[segment]``: ``gyr_rad_s`` (T, 3), ``acc_m_s2`` (T, 3) (sensor frame, gravity
        included), ``mag`` when present; no orientation. Time from the ``Time`` column, s.
        Rows that repeat the previous row exactly (same time, same values: a logging
        artefact in x-io's example files) are dropped; their count is
        ``metadata["duplicate_rows_dropped"]``.

    Raises
    ------
    FormatError
        Not an x-io CSV header, unknown units, non-numeric fields, truncated lines, two rows
        with the same time but different values, decreasing time.
    """
    path = Path(path)
    tab = _table(path)
    tcol = tab.columns[0]
    t = tab.floats(tcol, allow_empty=False) * _TIME_FACTOR[_TIME.match(tcol).group(1).lower()]
    gyr, gu, acc, au = _gyr_acc(tab)
    has_mag = any(c.lower().startswith("magnetometer x") for c in tab.columns)
    mag = unit_triplet(tab, "Magnetometer")[0] if has_mag else None
    data = np.column_stack([t, gyr, acc] + ([mag] if mag is not None else []))
    same_t = np.concatenate([[False], np.diff(t) == 0])
    dup = same_t & np.concatenate([[False], np.all(data[1:] == data[:-1], axis=1)])
    if np.any(same_t & ~dup):
        i = int(np.flatnonzero(same_t & ~dup)[0])
        raise tab.error_at(
            i, f"expected one row per time, found two different rows at time {t[i]!r}", tcol
        )
    keep = ~dup
    t = check_time(path, t[keep], tab.lines[keep], tcol)
    units = [f"gyr {gu} -> rad/s"] if _GYR_FACTOR[gu] != 1.0 else []
    units += [f"acc {au} -> m/s^2"] if _ACC_FACTOR[au] != 1.0 else []
    stream = ImuStream(
        t_s=t,
        acc_m_s2=acc[keep] * _ACC_FACTOR[au],
        gyr_rad_s=gyr[keep] * _GYR_FACTOR[gu],
        mag=None if mag is None else mag[keep],
        name=path.stem,
    )
    md = make_metadata(
        path,
        "xio_csv",
        units_converted=units,
        segment_map={path.stem: segment},
        duplicate_rows_dropped=int(dup.sum()),
        notes=[f"{int(dup.sum())} exact duplicate rows dropped"] if dup.any() else [],
    )
    return finish_recording(path, md, imu={segment: stream})


def _table(path: Path) -> Table:
    """The file as a table, after checking that its header is x-io's."""
    first = next((ln for ln in read_text(path).splitlines() if ln.strip()), "")
    if not is_xio_csv(first.split(",")):
        raise FormatError(
            path,
            "expected an x-io CSV header 'Time (s),Gyroscope X (deg/s),...,Accelerometer X (g),...', "
            f"found {first[:80]!r}",
            line=1,
        )
    tab = read_table(path, delimiter=",")
    if not is_xio_csv(tab.columns):
        raise tab.header_error(
            "expected an x-io CSV header 'Time (s),Gyroscope X (deg/s),...,Accelerometer X (g),...', "
            f"found {tab.columns[:4]}"
        )
    return tab


def _gyr_acc(tab: Table):
    """(gyr, its unit, acc, its unit), the units checked against the known factors."""
    gyr, gu = unit_triplet(tab, "Gyroscope")
    acc, au = unit_triplet(tab, "Accelerometer")
    if gu not in _GYR_FACTOR or au not in _ACC_FACTOR:
        bad, known = (
            ("Gyroscope", sorted(_GYR_FACTOR))
            if gu not in _GYR_FACTOR
            else ("Accelerometer", sorted(_ACC_FACTOR))
        )
        raise tab.header_error(
            f"unknown unit {(gu if bad == 'Gyroscope' else au)!r} of {bad} X/Y/Z; kinefuse reads {known}"
        )
    return gyr, gu, acc, au
