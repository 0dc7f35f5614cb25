"""A check of a 6-D pelvis sensor's heading against the hips' movement.

With 6-D orientations the static pose gives every sensor its heading by assuming that all
sensors face the same way on the body; :func:`~kinefuse.kinematics.hinge.limb_headings` then
turns each leg so that its knee's fitted flexion axis is the body's medio-lateral axis, but the
pelvis sensor keeps the assumption. A pelvis sensor worn on the side of the hip, or a belt clip
turned on the body, is then off by that turn, and every pelvis movement since the pose is read
turned by it about the vertical: a posterior pelvic tilt when sitting down reads as lateral
bending of the trunk and as rotation at the hips (on the qmt 6-D full body: the trunk bends
20° sideways while the subject sits still, the right hip reads 38° of external rotation).

The hips tell: each is fitted as :func:`~kinefuse.kinematics.hinge.hinge_frames` fits an elbow
(Laidig, Müller & Seel 2017; the flexion axis fixed in the pelvis and held perpendicular to its
long axis, the thigh's long axis as the second), giving the thigh's heading relative to the
pelvis, which the leg alignment made zero where the assumption holds. A hip moves mostly in
flexion, about one axis, so a heading and the heading half a turn from it fit about equally
well: only the heading modulo 180° is read, and it is not applied (the wrong half would turn a
posterior tilt into an anterior one, silently); a warning names the offset instead.
"""

from __future__ import annotations

import warnings

import numpy as np

from kinefuse.exceptions import NumericalWarning
from kinefuse.io.recording import Recording
from kinefuse.kinematics.calibration_result import Calibration
from kinefuse.kinematics.hinge import (
    MIN_HINGE_RATE_RAD_S,
    _fit_flexion_axis,
    _hinge_orientations,
    _world_rate,
)

__all__ = ["PELVIS_HEADING_WARN_DEG", "pelvis_heading_offset"]

#: Offset, deg (modulo a half turn), between the pelvis sensor's heading and the one its hips'
#: movement implies, beyond which a NumericalWarning says the hip and trunk angles are unreliable.
PELVIS_HEADING_WARN_DEG = 30.0


def pelvis_heading_offset(recording: Recording, calibration: Calibration) -> dict[str, float]:
    """Per hip, the thigh's heading relative to the pelvis implied by the hip's movement, deg.

    Parameters
    ----------
    recording : Recording
        The 6-D orientations the calibration was fitted to.
    calibration : Calibration
        Static, with the legs' headings from their knees (``heading="static"``, flexion axes
        from the movement) and the pelvis calibrated.

    Returns
    -------
    dict of str -> float
        ``hip_l`` / ``hip_r`` -> the offset modulo 180°, in ``[-90, 90)`` deg (0: the pelvis
        sensor faces as the legs do), for each hip whose two segments are calibrated and that
        moved enough (RMS relative rate at least :data:`MIN_HINGE_RATE_RAD_S`).

    Warns
    -----
    NumericalWarning
        The hips' mean offset (modulo 180°) is beyond :data:`PELVIS_HEADING_WARN_DEG`: it names
        it, and that the hip and trunk angles are unreliable.
    """
    out = {}
    if calibration.still is None or "pelvis" not in calibration.axes:
        return out
    for side in "lr":
        thigh = f"thigh_{side}"
        if thigh not in calibration.axes:
            continue
        RA, RB, tk = _hinge_orientations(recording, calibration, f"hip_{side}", None, None)
        if tk.size < 3:
            continue
        wA, wB = _world_rate(RA, tk), _world_rate(RB, tk)
        if float(np.sqrt(np.mean(np.sum((wB - wA) ** 2, axis=1)))) < MIN_HINGE_RATE_RAD_S:
            continue
        axes = calibration.axes["pelvis"], calibration.axes[thigh]
        _, psi, _ = _fit_flexion_axis(RA, RB, wA, wB, *axes, True, perpendicular=True)
        out[f"hip_{side}"] = float((np.degrees(psi) + 90.0) % 180.0 - 90.0)
    if out:
        # axial mean (headings modulo a half turn): the mean of the doubled angles, halved
        mean = 0.5 * float(
            np.degrees(np.angle(np.mean(np.exp(2j * np.radians(list(out.values()))))))
        )
        if abs(mean) > PELVIS_HEADING_WARN_DEG:
            each = ", ".join(f"{j} {v:.0f}" for j, v in out.items())
            warnings.warn(
                f"pelvis heading: the hips' movement puts the thighs {mean:.0f} deg (or "
                f"{mean - np.copysign(180.0, mean):.0f}: a hip's movement cannot tell) about the "
                f"vertical from where the pelvis sensor's heading says ({each} deg); 6-D sensors "
                "take their heading from the pose by assuming that they all face the same way "
                "on the body, which the pelvis sensor apparently does not: the hip and trunk angles, and "
                "hip positions placed from the pelvis, are unreliable (the knee and ankle angles "
                "are not affected). Strap it as the others "
                "(e.g. on the sacrum), or use sensors with magnetometers",
                NumericalWarning,
                stacklevel=2,
            )
    return out
