"""qmt full-body example reader: 16 body-worn IMUs (acc, gyr) in one MATLAB struct file."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import scipy.io

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import finish_recording, make_metadata
from kinefuse.io._names import map_segments
from kinefuse.io._text import check_time
from kinefuse.io.recording import ImuStream, Recording

__all__ = ["read_qmt"]


def read_qmt(
    path, *, sensor_map: Mapping[str, str] | None = None, keep_raw_quat: bool = False
) -> Recording:
    """Read a qmt-style ``.mat``: a time vector ``t`` and one struct per sensor with ``acc``/``gyr``.

    Parameters
    ----------
    path : str or Path
        E.g. ``full_body_example_data.mat``.
    sensor_map : mapping or None
        Struct name -> key overrides; by default names are mapped to canonical segments
        (``upper_arm_right`` -> ``upper_arm_r``, ``lower_leg_left`` -> ``shank_l``,
        ``upper_leg_left`` -> ``thigh_l``, ``hip`` -> ``pelvis``, ``upper_back`` -> ``chest``);
        others (``head``, ``hand_left``, ``lower_back``) keep their own name.
    keep_raw_quat : bool
        Store each struct's ``quat`` in ``metadata["raw_quat"]``. It is never used as
        ``q_world_from_sensor``: its convention is unverified (its angular-rate magnitude
        matches the gyro but its axes do not, so it is not the sensor orientation).

    Returns
    -------
    Recording
        ``imu[key]``: ``acc_m_s2`` (T, 3) m/s², ``gyr_rad_s`` (T, 3) rad/s, sensor frame, no
        orientation; ``t_s`` from ``t`` (s).

    Raises
    ------
    FormatError
        Unreadable file, no ``t``, a struct without ``acc``/``gyr``, wrong shapes, non-monotonic
        ``t``.
    """
    path = Path(path)
    try:
        d = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except Exception as e:
        raise FormatError(
            path, f"expected a MATLAB v5 file of IMU structs, could not read it: {e}"
        ) from None
    if "t" not in d:
        found = sorted(k for k in d if not k.startswith("__"))
        raise FormatError(path, f"missing variable 't' (T,) time in s; found {found}", field="t")
    t = np.asarray(d["t"], dtype=float).reshape(-1)
    t = check_time(path, t, None, "t")
    structs = {k: v for k, v in d.items() if not k.startswith("__") and hasattr(v, "_fieldnames")}
    if not structs:
        raise FormatError(path, "expected at least one struct with fields acc and gyr, found none")
    mapping, notes = map_segments(list(structs), sensor_map)
    imu = {}
    raw_quat = {}
    for name, s in structs.items():
        fields = list(s._fieldnames)
        arr = _acc_gyr(path, name, s, t.size)
        if keep_raw_quat and "quat" in fields:
            raw_quat[mapping[name]] = np.asarray(s.quat, dtype=float)
        imu[mapping[name]] = ImuStream(t_s=t, acc_m_s2=arr["acc"], gyr_rad_s=arr["gyr"], name=name)
    md = make_metadata(
        path,
        "qmt",
        subject=None,
        units_converted=[],
        segment_map=mapping,
        notes=[*notes, "struct field 'quat' not used: convention unverified (see SOURCE.md)"],
    )
    if keep_raw_quat:
        md["raw_quat"] = raw_quat
    return finish_recording(path, md, imu=imu)


def _acc_gyr(path: Path, name: str, s, T: int) -> dict[str, np.ndarray]:
    """Fields ``acc`` and ``gyr`` of struct ``name`` as float64 (T, 3), checked."""
    fields = list(s._fieldnames)
    for f in ("acc", "gyr"):
        if f not in fields:
            raise FormatError(
                path,
                f"struct {name!r}: missing field {f!r}; found {fields}",
                field=f"{name}.{f}",
            )
    arr = {}
    for f in ("acc", "gyr"):
        a = np.asarray(getattr(s, f))
        if a.shape != (T, 3) or not np.issubdtype(a.dtype, np.number):
            raise FormatError(
                path,
                f"expected {name}.{f} numeric with shape ({T}, 3), found {a.shape}",
                field=f"{name}.{f}",
            )
        arr[f] = a.astype(np.float64)
    return arr
