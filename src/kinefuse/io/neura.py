"""Reader for the Neura sparse / gaittoolbox exports: Xsens IMU CSVs + Vicon joint-centre CSV.

Format (``gait-tech/gaittoolbox`` ``data/sample``; ``../shared/data/neura_sparse_sample/SOURCE.md``)::

    <root>/imu/<Subj>-<Trial>-<Sensor>.csv    // header lines, then ori_1..4 (wxyz, world),
                                              acc_1..3 (m/s², sensor), gyr_1..3 (rad/s, sensor),
                                              mag_1..3 (normalised a.u.)
    <root>/vicon/<Subj>-<Trial>.csv           // header lines (fs, posUnit=m), then PELV, LFEP/RFEP
                                              (hips), LFEO/RFEO (knees), LTIO/RTIO (ankles),
                                              LTOE/RTOE (toes) _1.._3 in m, and qRPV, qLTH/qRTH,
                                              qLSK/qRSK, qLFT/qRFT _1.._4 (wxyz)

Frames: the IMU orientations were already rotated ("yaw fix") into the common world frame of the
Vicon data (z up; x, y are the lab axes, not east/north). Both are therefore labelled
``frame="vicon"``; no conversion is applied. Units are already SI.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from kinefuse.exceptions import FormatError
from kinefuse.io._checks import zero_is_missing
from kinefuse.io._names import PLUG_IN_GAIT_JOINTS
from kinefuse.io._text import header_number
from kinefuse.io.recording import ImuStream, JointStream, Recording

__all__ = ["IMU_SEGMENTS", "VICON_JOINTS", "VICON_SEGMENTS", "read_neura"]

#: Xsens sensor name -> kinefuse segment key. ``LowLeg2`` is on the shank; ``LowLeg`` sits just
#: above the ankle (gaittoolbox docs), kept under a non-canonical key.
IMU_SEGMENTS = {
    "Pelvis": "pelvis",
    "L_UpLeg": "thigh_l",
    "R_UpLeg": "thigh_r",
    "L_LowLeg2": "shank_l",
    "R_LowLeg2": "shank_r",
    "L_LowLeg": "shank_distal_l",
    "R_LowLeg": "shank_distal_r",
    "L_Foot": "foot_l",
    "R_Foot": "foot_r",
}

#: Vicon (Plug-in-Gait-style) point -> canonical joint. ``foot_*`` is the toe point (LTOE/RTOE).
VICON_JOINTS = {"PELV": "pelvis", **PLUG_IN_GAIT_JOINTS, "LTOE": "foot_l", "RTOE": "foot_r"}
_REQUIRED_JOINTS = ("PELV", "LFEP", "RFEP", "LFEO", "RFEO", "LTIO", "RTIO")

#: Vicon segment orientation -> canonical segment.
VICON_SEGMENTS = {
    "qRPV": "pelvis",
    "qLTH": "thigh_l",
    "qRTH": "thigh_r",
    "qLSK": "shank_l",
    "qRSK": "shank_r",
    "qLFT": "foot_l",
    "qRFT": "foot_r",
}


def _read_table(path: Path) -> tuple[dict[str, str], list[str], np.ndarray]:
    """``//`` header key=value pairs, column names and the float table of one CSV."""
    try:
        text = path.read_text()
    except OSError as e:
        raise FormatError(path, f"cannot read file: {e.strerror or e}") from None
    meta: dict[str, str] = {}
    cols: list[str] | None = None
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("//"):
            for key, val in re.findall(r"(\w+)=(\S+)", s):
                meta[key] = val
            continue
        fields = [f.strip() for f in s.split(",")]
        if cols is None:
            cols = fields
            if len(set(cols)) != len(cols):
                raise FormatError(path, f"duplicate column names in header {cols}", line=lineno)
            continue
        if len(fields) != len(cols):
            raise FormatError(
                path, f"expected {len(cols)} comma-separated values, got {len(fields)}", line=lineno
            )
        row = []
        for name, f in zip(cols, fields, strict=True):
            try:
                row.append(float(f))
            except ValueError:
                raise FormatError(
                    path, f"expected a number, got {f!r}", line=lineno, field=name
                ) from None
        rows.append(row)
    if cols is None:
        raise FormatError(path, "expected a header line with column names, got none")
    if not rows:
        raise FormatError(path, "expected at least one data row, got none")
    data = np.array(rows, dtype=float)
    if "nSamples" in meta:
        n = header_number(path, meta["nSamples"], "nSamples", cast=int, what="an integer")
        if n != data.shape[0]:
            raise FormatError(
                path, f"header says nSamples={n}, got {data.shape[0]} data rows", field="nSamples"
            )
    return meta, cols, data


def _rate(path: Path, meta: dict[str, str]) -> float:
    if "fs" not in meta:
        raise FormatError(path, "expected a '// fs=<Hz>' header line, got none", field="fs")
    fs = header_number(path, meta["fs"], "fs", what="a sampling rate in Hz")
    if not np.isfinite(fs) or fs <= 0:
        raise FormatError(path, f"expected a positive sampling rate, got {fs}", field="fs")
    return fs


def _columns(path: Path, cols: list[str], data: np.ndarray, prefix: str, n: int, *, required: bool):
    names = [f"{prefix}_{k}" for k in range(1, n + 1)]
    missing = [c for c in names if c not in cols]
    if missing:
        if required or len(missing) < n:
            raise FormatError(
                path, f"expected columns {names}, missing {missing}", field=missing[0]
            )
        return None
    return np.ascontiguousarray(data[:, [cols.index(c) for c in names]])


def _unit_quaternions(path: Path, q: np.ndarray, prefix: str) -> np.ndarray:
    n = np.linalg.norm(q, axis=1)
    bad = np.isfinite(n) & (np.abs(n - 1.0) > 1e-2)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise FormatError(
            path,
            f"expected unit quaternions (w,x,y,z), got norm {n[k]:.4g} in data row {k + 1}",
            field=f"{prefix}_1",
        )
    return q / n[:, None]


def _resolve(path: Path, trial: str | None) -> tuple[Path, str]:
    """Dataset root and trial name (``S02-Trial-Walk-1``) from a folder or one of its files."""
    if path.is_dir():
        root = path
        if not (root / "vicon").is_dir() or not (root / "imu").is_dir():
            raise FormatError(
                path, "expected a Neura/gaittoolbox folder with 'imu/' and 'vicon/' subfolders"
            )
        trials = sorted(p.stem for p in (root / "vicon").glob("*.csv"))
        if trial is None:
            if len(trials) != 1:
                raise FormatError(path, f"expected one trial or trial=..., found trials {trials}")
            trial = trials[0]
        elif trial not in trials:
            raise FormatError(path, f"unknown trial {trial!r}; found {trials}")
        return root, trial
    if not path.is_file():
        raise FormatError(path, "no such file or folder")
    root = path.parent.parent
    if path.parent.name == "vicon":
        return root, path.stem
    if path.parent.name == "imu":
        for sensor in sorted(IMU_SEGMENTS, key=len, reverse=True):
            if path.stem.endswith("-" + sensor):
                return root, path.stem[: -len(sensor) - 1]
        raise FormatError(
            path,
            f"expected an IMU file named <trial>-<sensor>.csv with sensor in {sorted(IMU_SEGMENTS)}",
        )
    raise FormatError(
        path, "expected the dataset folder, or a CSV inside its 'vicon/' or 'imu/' folder"
    )


def _vicon(vpath: Path, vcols, v: np.ndarray, t: np.ndarray):
    """Vicon joint centres (:data:`VICON_JOINTS`) and segment orientations of the trial."""
    jnames, jpos = [], []
    for code, joint in VICON_JOINTS.items():
        p = _columns(vpath, vcols, v, code, 3, required=code in _REQUIRED_JOINTS)
        if p is not None:
            jnames.append(joint)
            jpos.append(p)
    jp = np.stack(jpos, axis=1)
    reference = JointStream(
        t_s=t, position_m=jp, available=~zero_is_missing(jp), joints=tuple(jnames), frame="vicon"
    )
    ref_ori = {}
    for code, seg in VICON_SEGMENTS.items():
        q = _columns(vpath, vcols, v, code, 4, required=False)
        if q is not None:
            ref_ori[seg] = ImuStream(
                t_s=t,
                q_world_from_sensor=_unit_quaternions(vpath, q, code),
                name=code,
                frame="vicon",
            )
    return reference, ref_ori


def _imus(root: Path, trial: str, vpath: Path, fs: float, t: np.ndarray):
    """The trial's IMU streams by segment (same rate and length as the Vicon file), and names."""
    T = t.size
    imu = {}
    sensor_names = {}
    for sensor, seg in IMU_SEGMENTS.items():
        ipath = root / "imu" / f"{trial}-{sensor}.csv"
        if not ipath.is_file():
            continue
        imeta, icols, d = _read_table(ipath)
        ifs = _rate(ipath, imeta)
        if abs(ifs - fs) > 1e-9 or d.shape[0] != T:
            raise FormatError(
                ipath,
                f"expected {T} samples at {fs} Hz like {vpath.name}, got {d.shape[0]} at {ifs} Hz",
                field="fs",
            )
        q = _unit_quaternions(ipath, _columns(ipath, icols, d, "ori", 4, required=True), "ori")
        imu[seg] = ImuStream(
            t_s=t,
            q_world_from_sensor=q,
            acc_m_s2=_columns(ipath, icols, d, "acc", 3, required=False),
            gyr_rad_s=_columns(ipath, icols, d, "gyr", 3, required=False),
            mag=_columns(ipath, icols, d, "mag", 3, required=False),
            name=sensor,
            frame="vicon",
        )
        sensor_names[seg] = sensor
    if not imu:
        raise FormatError(root / "imu", f"expected IMU files {trial}-<sensor>.csv, found none")
    return imu, sensor_names


def read_neura(path, *, trial: str | None = None) -> Recording:
    """Read one Neura sparse (gaittoolbox) trial: Xsens IMUs + Vicon joint centres.

    Parameters
    ----------
    path : str or Path
        The dataset folder (holding ``imu/`` and ``vicon/``), or the trial's Vicon CSV, or one of
        its IMU CSVs.
    trial : str, optional
        Trial name, e.g. ``"S02-Trial-Walk-1"``, when the folder holds several.

    Returns
    -------
    Recording
        ``imu``: one :class:`ImuStream` per sensor found (keys :data:`IMU_SEGMENTS`: ``pelvis``,
        ``thigh_l/r``, ``shank_l/r`` (= LowLeg2), ``shank_distal_l/r`` (= LowLeg), ``foot_l/r``)
        with ``q_world_from_sensor`` (T, 4) wxyz, ``acc_m_s2`` (T, 3) m/s², ``gyr_rad_s`` (T, 3)
        rad/s, ``mag`` (T, 3) normalised a.u.; ``reference``: Vicon joints
        (:data:`VICON_JOINTS`), (T, J, 3) in m; ``reference_orientation``: Vicon segment
        orientations (:data:`VICON_SEGMENTS`). All on ``t_s = arange(T) / fs`` (100 Hz), all in
        ``frame="vicon"`` (z up, shared by IMUs and Vicon; see the module docstring).

    Raises
    ------
    kinefuse.exceptions.FormatError
        Missing files or columns, non-numeric values (file, line and field named), mismatching
        sample counts or rates between files, non-unit quaternions.
    """
    root, trial = _resolve(Path(path), trial)
    vpath = root / "vicon" / f"{trial}.csv"
    if not vpath.is_file():
        raise FormatError(vpath, "expected the trial's Vicon file, not found")
    vmeta, vcols, v = _read_table(vpath)
    fs = _rate(vpath, vmeta)
    unit = vmeta.get("posUnit", "m")
    if unit != "m":
        raise FormatError(
            vpath, f"expected positions in metres (posUnit=m), got posUnit={unit}", field="posUnit"
        )
    t = np.arange(v.shape[0]) / fs
    reference, ref_ori = _vicon(vpath, vcols, v, t)
    imu, sensor_names = _imus(root, trial, vpath, fs, t)
    subject, _, act = trial.partition("-")
    return Recording(
        imu=imu,
        reference=reference,
        reference_orientation=ref_ori,
        metadata={
            "subject": subject,
            "trial": act or trial,
            "source": str(vpath),
            "format": "neura",
            "units_converted": False,
            "rate_hz": fs,
            "sensor_names": sensor_names,
            "frame_note": "IMU orientations yaw-fixed into the Vicon world frame (z up); shared frame 'vicon'",
            "raw_frame_range": vmeta.get("idx"),
        },
    )
