"""``kinefuse run`` and ``kinefuse evaluate``: a user's own recording, end to end.

:func:`run_session` processes the recording a session TOML describes
(:func:`kinefuse.session_file.load_session`): it loads the IMU file and the optional camera and
reference, maps sensors to segments, estimates missing orientations from raw data, builds the
skeleton, calibrates, runs the method, writes the joint positions as CSV (with per-sample source,
filter branch and standard deviation) and TRC (OpenSim), the joint angles as CSV and ``.mot``
(where the calibration gives segment frames), an HTML report, and, with a reference in the
output's frame, the metrics. :func:`evaluate_recording` runs one method on any loadable recording that has a
reference and returns the per-joint tables. :func:`process_recording` is the shared core.

One module per idea: :mod:`~kinefuse.pipelines.run.streams` (loading the files, unit checks),
:mod:`~kinefuse.pipelines.run.parameters` (the parameters below and the plan),
:mod:`~kinefuse.pipelines.run.chain` (orientations, skeleton, roots),
:mod:`~kinefuse.pipelines.run.timeline` (output timeline, coverage),
:mod:`~kinefuse.pipelines.run.calibration`, :mod:`~kinefuse.pipelines.run.process` (the
method), :mod:`~kinefuse.pipelines.run.write` (the files), :mod:`~kinefuse.pipelines.run.evaluate`.

Method parameters (``[method.parameters]`` of the session file; all optional)
-----------------------------------------------------------------------------
``calibration``
    ``"static"``, ``"functional"``, ``"vision"``, ``"reference"`` or ``"none"`` (default:
    ``"vision"`` with a camera, else ``"static"``; the reference only when asked). The session
    file's ``[calibration] method`` sets it.
``calibration_window_s``, ``calibration_start_s``
    Calibration window, s (default 2 s; static calibration searches the earliest still window
    unless the start is given). ``[calibration] window_s`` / ``start_s``.
``pose``, ``facing``, ``heading``, ``max_rate_rad_s``, ``max_acc_std_m_s2``
    Static calibration: ``"n"`` (default) or ``"t"``; the subject's facing in the IMU world
    frame (default north); ``"auto"`` (default: align 6-D sensors' headings at the pose),
    ``"none"`` or ``"static"``; the stillness thresholds
    (:func:`kinefuse.kinematics.find_still_window`).
``flexion_axes``
    Static calibration: the flexion axes of elbows and knees from the movement (``"movement"``,
    :func:`kinefuse.kinematics.hinge.hinge_frames`) or from ``facing`` (``"pose"``); ``"auto"``
    (default): from the movement when the headings are aligned at the pose (6-D sensors).
``align``
    Camera/reference frame alignment of the calibration: ``"auto"`` (default), ``"none"``,
    ``"heading"``, ``"rotation"``.
``root``, ``root_position_m``
    Where the chain's root joints (shoulders, hips, or the proximal joint of any segment
    without a mapped parent) are: ``"fixed"`` (``root_position_m`` [x, y, z] m, or one per
    root joint; default the origin), ``"pelvis"`` (hips from the pelvis IMU, mid-hip origin),
    ``"vision"`` (``"camera"``) or ``"reference"``. Default: the camera if there is one, else
    ``"pelvis"`` for leg chains with a pelvis IMU, else ``"fixed"``. ``[skeleton] root``.
``axes``
    Declared sensor axis along each segment (``[skeleton.axes]``): the sensor axes without
    calibration, the check of the static pose otherwise.
``align_to_reference``
    ``"none"`` (default) or ``"rigid"``: Kabsch-align the estimates to the reference before
    scoring (labelled). ``[reference] align``.
``rate_hz``
    Output/filter rate, Hz (default 30 for ``paper-a`` and the camera methods, else the root
    stream's own timeline; without a root stream, the first IMU's, made uniform over its span
    where that IMU dropped packets).
``filter``
    ``imu-only`` only: ``"none"`` (default), ``"kf"``, ``"fir"``, ``"em-kf"``, ``"em-kf-fir"``;
    ``paper-a`` uses ``"em-kf-fir"`` unless told otherwise.
``q``, ``r``, ``horizon``, ``threshold1``, ``threshold2``, ``n_em_iter``
    Paper A filter settings (:func:`kinefuse.pipelines.upper_limb`); ``q`` and ``r`` may be
    one number or a table per joint or joint kind (``{knee = 0.1, ankle = 0.2}``).
``q``, ``r_imu``, ``r_cam``, ``horizon``, ``n_hidden``, ``train_window``, ...
    Paper B settings (:class:`kinefuse.pipelines.VisionParams`) for ``elm-fir``, ``elm-kf``,
    ``imu-only`` / ``camera-only`` with a camera, and ``kinefuse``.
``measured_lengths``
    Use the segment lengths measured in the calibration window (``[calibration]
    lengths_from_data``; default true for ``"vision"``, false otherwise: the reference gives
    lengths only when asked). Explicit ``[skeleton.lengths]`` always win; ``body_height_m``
    (Winter 2009 ratios) fills the rest.
``orientation_params``
    VQF parameters for sensors without an orientation (:func:`kinefuse.orientation.estimate`).
``estimate_orientation``
    ``"auto"`` (default: estimate sensor orientations from acc + gyr with VQF only when no
    mapped sensor has one in the file), ``true`` (for every sensor without one) or ``false``
    (never); an estimate is always reported as a warning.
``strict_units``
    Default true: magnitudes that look like wrong units (acc in g, gyro in deg/s, positions in
    mm; :func:`kinefuse.io.check_units`) are an error instead of a warning.
"""

from kinefuse.pipelines.run.chain import SEGMENT_JOINTS, build_chain
from kinefuse.pipelines.run.evaluate import evaluate_recording
from kinefuse.pipelines.run.output import SessionOutput
from kinefuse.pipelines.run.process import process_recording
from kinefuse.pipelines.run.streams import FORMAT_ALIASES, load_streams
from kinefuse.pipelines.run.timeline import (
    COVERAGE_WARN_FRACTION,
    IMU_MAX_GAP_S,
    ROOT_MAX_GAP_S,
    apply_coverage,
    coverage_counts,
    coverage_table,
)
from kinefuse.pipelines.run.write import RunResult, output_paths, run_session

__all__ = [
    "COVERAGE_WARN_FRACTION",
    "FORMAT_ALIASES",
    "IMU_MAX_GAP_S",
    "ROOT_MAX_GAP_S",
    "SEGMENT_JOINTS",
    "RunResult",
    "SessionOutput",
    "apply_coverage",
    "build_chain",
    "coverage_counts",
    "coverage_table",
    "evaluate_recording",
    "load_streams",
    "output_paths",
    "process_recording",
    "run_session",
]
