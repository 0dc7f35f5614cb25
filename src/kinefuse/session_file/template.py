"""The commented session template that ``kinefuse init-session`` writes."""

from __future__ import annotations

from collections.abc import Mapping

from kinefuse import methods
from kinefuse.conventions import SEGMENTS
from kinefuse.io import FORMATS
from kinefuse.session_file.config import CALIBRATIONS, CAMERA_METHODS, ROOTS

__all__ = ["session_template"]


_TEMPLATE = """\
# kinefuse session file. Edit the paths and settings, then run:
#     kinefuse run {filename}
# Relative paths are resolved against the folder of this file. Units are SI (m, s, Hz).

[session]
name = "{name}"  # shown in reports
out_dir = "results/{name}"  # output folder; kinefuse refuses to overwrite a report without --force

[imu]
format = "imu_csv"               # reader of the IMU file: one of {formats}
path = "data/imu.csv"            # the IMU recording: a file, a folder for ximu3 / neura / opensense / xsens_dot, or a folder holding one recording
rate_hz = 100.0                  # only used when the file has no time stamps; delete otherwise

[imu.segments]
# canonical segment = sensor name as written in the file
# segments: {segments}
upper_arm_r = "IMU 1"
forearm_r = "IMU 2"

[skeleton]
body_height_m = 1.75             # lengths from body height (Winter 2009 ratios) where not measured
# root: where the chain starts
{roots}
root = "fixed"
root_position_m = [0.0, 0.0, 0.0]  # root = "fixed": the measured root joint (here the shoulder), m

# [skeleton.lengths]             # measured (tape) lengths in m; they win over body height
# upper_arm_r = 0.30
# forearm_r = 0.26

# [skeleton.axes]                # optional: the sensor axis that runs along each segment
# upper_arm_r = "+e1"            # (proximal -> distal); checked against the static pose

[calibration]
# method: what finds each sensor's axis on its segment
{calibrations}
# default: "vision" with a [camera], else "static"
method = "static"
pose = "n"                       # "n": arms hanging, "t": T-pose (static only)
# window_s = 2.0                 # still window length, s; found automatically unless start_s is given
# start_s = 0.0
# heading = "auto"               # 6-D sensors (no magnetometer): "static" aligns their headings
# facing = "auto"                # which way the subject faced in the pose: [x, y, z] (world);
#                                # "auto": from the elbows'/knees' movement (north if none moved)
# flexion_axes = "auto"          # elbow/knee flexion axes: "movement" (default unless facing
#                                # is declared) or "pose" (from the facing)

# Optional: a camera skeleton. Needed by {camera_methods}.
# [camera]
# format = "kinect_v2"
# path = "data/kinect.csv"
# availability_threshold = 2     # tracker confidence below this = joint unavailable
# [camera.reader]                # optional: the reader's own arguments (docs/formats.md),
# time_column = "TimeSpan"       # e.g. an LSL-Kinect recorder CSV's time column, Unix ms
# time_unit = "ms"               # ([imu.reader] and [reference.reader] work the same way)

# Optional: ground truth (optical mocap), used ONLY to evaluate (RMSE tables) unless you ask
# otherwise (calibration method = "reference", root = "reference", align = "rigid"; then
# every table says so).
# [reference]
# format = "c3d"
# path = "data/reference.c3d"
# align = "none"                 # "rigid": Kabsch-align the estimates to it before scoring

[method]
{methods}
name = "paper-a"

[method.parameters]
# method-specific settings; leave empty for the defaults. Examples for paper-a:
# q = 1.0          # process-noise scale (paper A elbow test 1)
# r = 0.01         # measurement-noise variance, m^2
"""


def session_template(name: str = "my-session", filename: str = "session.toml") -> str:
    """The commented session template written by ``kinefuse init-session``.

    Parameters
    ----------
    name : str
        Session name (also used for the default output folder).
    filename : str
        File name mentioned in the header comment.

    Returns
    -------
    str
        TOML text; it loads with :func:`kinefuse.session_file.load_session` once ``[imu] path`` exists.
    """
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in name) or "session"

    def listing(d: Mapping) -> str:
        w = max(len(k) for k in d) + 2
        return "\n".join(f"#   {k + ' ' * (w - len(k))}: {v}" for k, v in d.items())

    rows = {"name": f"{'uses':<14} : what it does"}
    rows.update({m.name: f"{m.uses:<14} : {m.summary}" for m in methods.REGISTRY.values()})
    return _TEMPLATE.format(
        name=safe,
        filename=filename,
        formats=", ".join(sorted(FORMATS)),
        segments=", ".join(SEGMENTS),
        roots=listing(ROOTS),
        calibrations=listing(CALIBRATIONS),
        camera_methods=", ".join(CAMERA_METHODS),
        methods=listing(rows).replace("#   ", "# ", -1),
    )
