"""BROAD reader: one IMU (acc/gyr/mag) with OptiTrack orientation and position ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import finish_recording, make_metadata
from kinefuse.io.recording import ImuStream, JointStream, Recording

__all__ = ["read_broad"]

_REQUIRED = {
    "imu_gyr": "(N, 3) rad/s",
    "imu_acc": "(N, 3) m/s^2",
    "imu_mag": "(N, 3) uT",
    "opt_quat": "(N, 4) w,x,y,z IMU -> ENU",
    "opt_pos": "(N, 3) m",
    "sampling_rate": "scalar Hz",
}


def read_broad(path, *, sensor_name: str = "imu") -> Recording:
    """Read one BROAD trial ``.mat`` (Laidig et al. 2021).

    Parameters
    ----------
    path : str or Path
        ``data_mat/<NN>_<description>.mat``.
    sensor_name : str
        Key of the IMU and of its reference (the IMU sits on a hand-moved box, not a body
        segment, so no canonical segment applies).

    Returns
    -------
    Recording
        ``imu[sensor_name]``: ``acc_m_s2`` (N, 3) m/s², ``gyr_rad_s`` (N, 3) rad/s, ``mag``
        (N, 3) µT, sensor frame, no on-board orientation. ``reference_orientation[sensor_name]``:
        OptiTrack ``q_world_from_sensor`` (N, 4) wxyz, IMU -> ENU, NaN rows at marker dropouts.
        ``reference``: the box position (N, 1, 3) in m, ENU, joint name ``sensor_name``.
        Times ``t = n / sampling_rate`` (285.714 Hz). ``metadata["movement"]`` (N,) bool marks
        the motion phases to use for error metrics; ``metadata["info"]`` is the trial text.

    Raises
    ------
    FormatError
        Unreadable file, missing variable, wrong shape.
    """
    path = Path(path)
    d, fs, arrays = _load(path)
    n = arrays["imu_gyr"].shape[0]
    t = np.arange(n) / fs
    imu = ImuStream(
        t_s=t,
        acc_m_s2=arrays["imu_acc"],
        gyr_rad_s=arrays["imu_gyr"],
        mag=arrays["imu_mag"],
        name=sensor_name,
    )
    q = arrays["opt_quat"].copy()
    q[~np.all(np.isfinite(q), axis=1)] = np.nan
    ref_q = ImuStream(t_s=t, q_world_from_sensor=q, name="optitrack", frame="ENU")
    pos = arrays["opt_pos"][:, None, :]
    ref = JointStream(t_s=t, position_m=pos, joints=(sensor_name,), frame="ENU")
    movement = np.asarray(d.get("movement", np.ones(n)), dtype=bool).reshape(-1)
    md = make_metadata(
        path,
        "broad",
        subject=None,
        units_converted=[],
        trial=path.stem,
        info=str(d.get("info", "")),
        rate_hz=fs,
        movement=movement,
        segment_map={"imu": sensor_name},
        optical_valid_fraction=float(np.isfinite(q).all(axis=1).mean()),
        notes=["rigid box moved by hand, not a body-worn sensor", "mag in uT"],
    )
    return finish_recording(
        path, md, imu={sensor_name: imu}, reference=ref, reference_orientation={sensor_name: ref_q}
    )


def _load(path: Path):
    """(the .mat variables, sampling rate, the arrays of :data:`_REQUIRED` as float64, checked)."""
    try:
        d = scipy.io.loadmat(path, squeeze_me=True)
    except Exception as e:
        raise FormatError(
            path, f"expected a BROAD MATLAB v5 file, could not read it: {e}"
        ) from None
    for k, what in _REQUIRED.items():
        if k not in d:
            found = sorted(x for x in d if not x.startswith("__"))
            raise FormatError(path, f"missing variable {k!r} {what}; found {found}", field=k)
    fs = float(np.asarray(d["sampling_rate"], dtype=float).reshape(-1)[0])
    if not np.isfinite(fs) or fs <= 0:
        raise FormatError(
            path, f"expected a positive sampling_rate, found {fs}", field="sampling_rate"
        )
    arrays = {}
    n = np.asarray(d["imu_gyr"]).shape[0]
    for k, tail in (
        ("imu_gyr", 3),
        ("imu_acc", 3),
        ("imu_mag", 3),
        ("opt_quat", 4),
        ("opt_pos", 3),
    ):
        a = np.asarray(d[k])
        if a.ndim != 2 or a.shape != (n, tail) or not np.issubdtype(a.dtype, np.number):
            raise FormatError(
                path,
                f"expected {k} numeric with shape ({n}, {tail}), found {a.shape} {a.dtype}",
                field=k,
            )
        arrays[k] = a.astype(np.float64)
    return d, fs, arrays
