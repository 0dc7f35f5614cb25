"""The validated form of a session file: one frozen dataclass per section.

:class:`SessionConfig` is what :func:`kinefuse.session_file.load_session` returns; the
``[calibration] method`` and ``[skeleton] root`` choices are :data:`CALIBRATIONS` and
:data:`ROOTS`, the ``[method] name`` choices the registry :mod:`kinefuse.methods`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from kinefuse import methods
from kinefuse.exceptions import ConfigError

__all__ = [
    "CALIBRATIONS",
    "CAMERA_METHODS",
    "METHODS",
    "ROOTS",
    "CalibrationConfig",
    "CameraConfig",
    "ImuConfig",
    "MethodConfig",
    "ReferenceConfig",
    "SessionConfig",
    "SECTION_PARAMETERS",
    "SkeletonConfig",
]

#: Processing methods a session can ask for (:func:`kinefuse.methods.names`).
METHODS = methods.names()
#: Methods that cannot run without a ``[camera]`` section.
CAMERA_METHODS = methods.names(needs="camera")
#: ``[calibration] method`` values: what calibrates the sensor-to-segment axes.
CALIBRATIONS = {
    "static": "a still pose (N-pose or T-pose) found in the IMU data; IMUs only",
    "functional": "movement of adjacent segments (joint centres and axes); IMUs only",
    "vision": "the camera joints in a window; needs [camera]",
    "reference": "the reference joints in a window; needs [reference] (then labelled)",
    "none": "no calibration: the configured sensor axes are used",
}
#: ``[skeleton] root`` values: where the chain starts.
ROOTS = {
    "fixed": "a position measured once (root_position_m, default the origin); both arms: the "
    "mid-shoulder point, shoulders from the chest IMU",
    "pelvis": "positions relative to the pelvis; hips from the pelvis IMU",
    "vision": "the camera joints; needs [camera]",
    "reference": "the reference joints; needs [reference]",
}


@dataclass(frozen=True)
class ImuConfig:
    """``[imu]``: the IMU recording.

    Attributes
    ----------
    format : str
        Reader name (see :mod:`kinefuse.io`).
    path : Path
        Absolute path of the recording.
    rate_hz : float or None
        Sampling rate, Hz, when the file has no time stamps (None: from the file).
    segments : dict of str -> str
        Canonical segment name (:data:`kinefuse.conventions.SEGMENTS`) -> sensor name in the file.
    reader : dict
        ``[imu.reader]``: keyword arguments of the format's reader (e.g. ``earth_frame``).
    """

    format: str
    path: Path
    rate_hz: float | None
    segments: dict[str, str]
    reader: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SkeletonConfig:
    """``[skeleton]``: body dimensions.

    Attributes
    ----------
    body_height_m : float or None
        Body height, m, for anthropometric segment lengths (Winter 2009) and the hip joint
        spacing.
    lengths_m : dict of str -> float
        Measured segment lengths, m, by segment name (override the anthropometric ones).
    root : str or None
        :data:`ROOTS` key (None: the default, see :func:`kinefuse.pipelines.process_recording`).
    root_position_m : tuple of float, dict of str -> tuple, or None
        ``root = "fixed"``: the root joint's position (m), or one per chain start.
    axes : dict of str -> str or tuple
        Declared sensor axis along each segment (mounting), e.g. ``thigh_l = "+e1"``.
    """

    body_height_m: float | None
    lengths_m: dict[str, float] = field(default_factory=dict)
    root: str | None = None
    root_position_m: object = None
    axes: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CalibrationConfig:
    """``[calibration]`` (optional): how the sensor-to-segment axes are found.

    Attributes
    ----------
    settings : dict
        ``method`` (:data:`CALIBRATIONS`), ``window_s``, ``start_s``, ``pose`` (``"n"`` /
        ``"t"``), ``facing`` ([x, y, z]), ``heading`` (``"auto"``, ``"none"``, ``"static"``),
        ``flexion_axes`` (``"auto"``, ``"movement"``, ``"pose"``), ``lengths_from_data``
        (bool), ``max_rate_rad_s``, ``max_acc_std_m_s2``, as given.
    """

    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CameraConfig:
    """``[camera]`` (optional): a camera skeleton (Kinect, Azure Kinect, MediaPipe...).

    Attributes
    ----------
    format : str
    path : Path
    availability_threshold : float or None
        Joints whose tracker confidence is below this are treated as unavailable (None: the
        reader's default, e.g. Kinect TrackingState == Tracked).
    reader : dict
        ``[camera.reader]``: keyword arguments of the format's reader, e.g. for a Kinect v2
        recorder CSV ``time_column = "TimeSpan"``, ``time_unit = "ms"``,
        ``confidence_states = {"0" = 0, "0.5" = 1, "1" = 2}``.
    """

    format: str
    path: Path
    availability_threshold: float | None = None
    reader: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ReferenceConfig:
    """``[reference]`` (optional): ground-truth joints (optical mocap) for evaluation only.

    ``align = "rigid"`` asks for a Kabsch rotation + translation of the estimates onto the
    reference before scoring (labelled in every table); default ``"none"``.
    ``reader``: ``[reference.reader]``, keyword arguments of the format's reader (e.g.
    ``length_unit_m`` for a BVH file).
    """

    format: str
    path: Path
    align: str = "none"
    reader: dict = field(default_factory=dict)


@dataclass(frozen=True)
class MethodConfig:
    """``[method]``: which pipeline and its parameters (validated by the pipeline)."""

    name: str
    parameters: dict = field(default_factory=dict)


#: ``[method.parameters]`` names that another section of a session file also sets:
#: ``name -> (section, key)``. :meth:`SessionConfig.processing_parameters` merges them (two
#: different values are an error) and a study's layers treat both spellings as one setting.
SECTION_PARAMETERS = {
    "calibration": ("calibration", "method"),
    "calibration_window_s": ("calibration", "window_s"),
    "calibration_start_s": ("calibration", "start_s"),
    "pose": ("calibration", "pose"),
    "facing": ("calibration", "facing"),
    "heading": ("calibration", "heading"),
    "flexion_axes": ("calibration", "flexion_axes"),
    "measured_lengths": ("calibration", "lengths_from_data"),
    "max_rate_rad_s": ("calibration", "max_rate_rad_s"),
    "max_acc_std_m_s2": ("calibration", "max_acc_std_m_s2"),
    "root": ("skeleton", "root"),
    "root_position_m": ("skeleton", "root_position_m"),
    "axes": ("skeleton", "axes"),
    "align_to_reference": ("reference", "align"),
}


@dataclass(frozen=True)
class SessionConfig:
    """A validated session file.

    Attributes
    ----------
    path : Path
        The TOML file (absolute).
    name : str
        Session name.
    out_dir : Path
        Output folder (absolute).
    imu : ImuConfig
    skeleton : SkeletonConfig
    camera : CameraConfig or None
    reference : ReferenceConfig or None
    method : MethodConfig
    calibration : CalibrationConfig
    """

    path: Path
    name: str
    out_dir: Path
    imu: ImuConfig
    skeleton: SkeletonConfig
    camera: CameraConfig | None
    reference: ReferenceConfig | None
    method: MethodConfig
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def processing_parameters(self) -> dict:
        """``[method.parameters]`` merged with ``[calibration]``, the root and the alignment.

        Raises
        ------
        ConfigError
            The same setting given in two places with different values.
        """
        params = dict(self.method.parameters)
        new = {k: self._section_value(*where) for k, where in SECTION_PARAMETERS.items()}
        for k, v in new.items():
            if v is None:
                continue
            if k in params and params[k] != v:
                raise ConfigError(
                    f"{self.path.name}: {k} given twice ([method.parameters] {k} = "
                    f"{params[k]!r} and {v!r}); keep one"
                )
            params[k] = v
        return params

    def _section_value(self, section: str, key: str):
        """The value ``[section] key`` gave (:data:`SECTION_PARAMETERS`), None if not given."""
        if section == "calibration":
            return self.calibration.settings.get(key)
        if section == "skeleton":
            return getattr(self.skeleton, key) or None
        if self.reference is None or self.reference.align == "none":  # [reference] align
            return None
        return self.reference.align

    @property
    def inputs(self) -> tuple[Path, ...]:
        """The session file and every file or folder it reads (never written over)."""
        streams = (self.imu, self.camera, self.reference)
        return (self.path, *(Path(st.path) for st in streams if st is not None))
