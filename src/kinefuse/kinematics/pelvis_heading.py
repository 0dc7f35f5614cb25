"""A 6-D pelvis sensor's heading from the hips' movement.

With 6-D orientations the static pose gives every sensor its heading by assuming that all
sensors face the same way on the body; :func:`~kinefuse.kinematics.hinge.limb_headings` then
turns each leg so that its knee's fitted flexion axis is the body's medio-lateral axis, but the
pelvis sensor keeps the assumption. A pelvis sensor worn on the side of the hip, or a belt clip
turned on the body, is then off by that turn, and every pelvis movement since the pose is read
turned by it about the vertical: a posterior pelvic tilt when sitting down reads as lateral
bending of the trunk and as rotation at the hips (on the qmt 6-D full body: the trunk bends
20° sideways while the subject sits still, the right hip reads 38° of external rotation).

The hips tell, in two ways:

* **rates** -- each hip fitted as :func:`~kinefuse.kinematics.hinge.hinge_frames` fits an elbow
  (Laidig, Müller & Seel 2017: the flexion axis fixed in the pelvis, held perpendicular to its
  long axis; the thigh's long axis), the thigh's heading relative to the pelvis. Precise, but a
  hip moves mostly in flexion, about one axis, so a heading and the heading half a turn from it
  fit about equally well: only the heading modulo 180° is read from it;
* **accelerations** -- the hip centre's acceleration seen from both sensors (Seel, Schauer &
  Raisch 2012; :func:`~kinefuse.kinematics.joint_centre.fit_joint`, the functional
  calibration's model) gives the whole heading, but it absorbs soft-tissue error (tens of
  degrees on real data).

The pelvis is turned by the rate heading whose half turn the acceleration heading chooses,
when the acceleration heading is within :data:`PELVIS_AGREE_DEG` of it; otherwise nothing is
applied and a warning says that the hip and trunk angles are unreliable (applying the wrong
half would turn a posterior pelvic tilt into an anterior one, silently). The pelvis frame is
turned with it, so the still pose reads as before.

References
----------
D. Laidig, P. Müller, T. Seel, "Automatic anatomical calibration for IMU-based elbow angle
measurement in disturbed magnetic fields", Current Directions in Biomedical Engineering
3(2):167-170, 2017.
T. Seel, T. Schauer, J. Raisch, "Joint axis and position estimation from inertial measurement
data by exploiting kinematic constraints", IEEE CCA 2012, 45-49.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from kinefuse.exceptions import InputError, NumericalWarning
from kinefuse.io.recording import Recording
from kinefuse.kinematics.calibration_result import Calibration, oriented_imu, turned_heading
from kinefuse.kinematics.forward import rotation_z
from kinefuse.kinematics.hinge import (
    MIN_HINGE_RATE_RAD_S,
    _fit_flexion_axis,
    _hinge_orientations,
    _world_rate,
)
from kinefuse.kinematics.joint_centre import fit_joint, joint_signals
from kinefuse.kinematics.static import window_orientations

__all__ = ["PELVIS_AGREE_DEG", "PELVIS_WARN_DEG", "pelvis_heading"]

#: Largest angle, deg, between the acceleration heading and the rate heading's nearer half for
#: the pelvis to be turned (the two halves are 180° apart: 45° leaves the acceleration model
#: room for its soft-tissue error, and none for a coin toss).
PELVIS_AGREE_DEG = 45.0

#: The hips' rate heading (modulo 180°), deg, beyond which a turn that cannot be applied is
#: warned about (the hip and trunk angles are then unreliable).
PELVIS_WARN_DEG = 30.0

#: Low-pass of the acceleration model's signals, Hz (the functional calibration's, Winter 2009).
_CUTOFF_HZ = 6.0
#: Least excitation of the hip centre for its acceleration heading, s⁻² (the functional
#: calibration's default).
_MIN_EXCITATION_S2 = 2.0


def _wrap(deg: float) -> float:
    return float((deg + 180.0) % 360.0 - 180.0)


def _rate_headings(recording, calibration) -> dict[str, float]:
    """Per hip that moved: the pelvis turn its rates imply, modulo 180° in [-90, 90), deg."""
    out = {}
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
        # the thigh's world turned by psi = the pelvis's turned by -psi
        out[f"hip_{side}"] = float((-np.degrees(psi) + 90.0) % 180.0 - 90.0)
    return out


def _acc_headings(recording, calibration, hips) -> dict[str, float]:
    """Per hip in ``hips``: the pelvis turn the hip centre's accelerations imply, deg."""

    def turned(s):  # the sensor's orientations with its calibrated heading applied
        psi = calibration.world_heading_deg.get(s, 0.0)
        return turned_heading(oriented_imu(recording, s, "pelvis heading"), psi)

    pelvis = turned("pelvis")
    if pelvis.acc_m_s2 is None or pelvis.gyr_rad_s is None:
        return {}
    t = pelvis.t_s
    try:
        A = joint_signals(pelvis, "pelvis", t, _CUTOFF_HZ)
    except InputError:  # too few valid samples: the accelerations do not tell
        return {}
    n_eff = min(1.0, 2.0 * _CUTOFF_HZ * float(np.median(np.diff(t))))
    out = {}
    for j in hips:
        thigh = f"thigh_{j[-1]}"
        st = turned(thigh)
        if st.acc_m_s2 is None or st.gyr_rad_s is None:
            continue
        try:
            B = joint_signals(st, thigh, t, _CUTOFF_HZ)
            fit, _ = fit_joint(j, "pelvis", thigh, A, B, _MIN_EXCITATION_S2, n_eff, "vector")
        except InputError:  # too little movement: this hip does not tell
            continue
        out[j] = _wrap(fit.heading_deg)  # Rz(psi) turns the pelvis's world onto the thigh's
    return out


def _axial_mean(deg) -> float:
    """Mean of angles modulo 180°, deg in [-90, 90)."""
    return 0.5 * float(np.degrees(np.angle(np.mean(np.exp(2j * np.radians(list(deg)))))))


def pelvis_heading(recording: Recording, calibration: Calibration) -> Calibration:
    """``calibration`` with the pelvis sensor's heading turned as its hips' movement says.

    Parameters
    ----------
    recording : Recording
        The 6-D orientations (and the accelerations and rates) the calibration was fitted to.
    calibration : Calibration
        Static, with the legs' headings from their knees (``heading="static"``, flexion axes
        from the movement) and the pelvis calibrated.

    Returns
    -------
    Calibration
        ``world_heading_deg["pelvis"]`` turned and the pelvis frame turned with it (the pose
        reads as before); ``pelvis_heading_deg``: the turn and both hips' estimates. The input
        unchanged where no hip moved enough.

    Warns
    -----
    NumericalWarning
        The hips' rate heading is beyond :data:`PELVIS_WARN_DEG` (modulo 180°) and the
        acceleration heading does not choose its half (:data:`PELVIS_AGREE_DEG`): nothing
        applied, the hip and trunk angles unreliable.
    """
    if calibration.still is None or "pelvis" not in calibration.axes:
        return calibration
    rates = _rate_headings(recording, calibration)
    if not rates:
        return calibration
    m = _axial_mean(rates.values())
    acc = _acc_headings(recording, calibration, rates)
    a = (
        float(np.degrees(np.angle(np.mean(np.exp(1j * np.radians(list(acc.values())))))))
        if acc
        else None
    )
    pick = None
    if a is not None:
        pick = min((m, _wrap(m + 180.0)), key=lambda c: abs(_wrap(c - a)))
        if abs(_wrap(pick - a)) > PELVIS_AGREE_DEG:
            pick = None
    if pick is None:
        if abs(m) > PELVIS_WARN_DEG:
            each = ", ".join(f"{j} {v:.0f}" for j, v in rates.items())
            warnings.warn(
                f"pelvis heading: the hips' movement turns the pelvis sensor's heading by {m:.0f} "
                f"or {_wrap(m + 180.0):.0f} deg ({each}), and their accelerations "
                + ("cannot tell which" if a is None else f"say {a:.0f}")
                + ": not applied. 6-D sensors take their heading from the pose by assuming that "
                "they all face the same way on the body, which the pelvis sensor apparently does "
                "not: the hip and trunk angles, and hip positions placed from the pelvis, are "
                "unreliable (the knee and ankle angles are not affected). Strap it as the others "
                "(e.g. on the sacrum), or use sensors with magnetometers",
                NumericalWarning,
                stacklevel=2,
            )
        return calibration
    _, R_mean = window_orientations({"pelvis": oriented_imu(recording, "pelvis", "pelvis")},
                                    calibration.still)  # fmt: skip
    R = R_mean["pelvis"]  # the raw orientation in the pose: the frame keeps its pose there
    frames = dict(calibration.frames)
    frames["pelvis"] = R.T @ rotation_z(-np.radians(pick)) @ R @ frames["pelvis"]
    heading = dict(calibration.world_heading_deg)
    heading["pelvis"] = _wrap(heading.get("pelvis", 0.0) + pick)
    found = {"turn": pick, "rates": rates, "accelerations": acc}
    return replace(calibration, frames=frames, world_heading_deg=heading, pelvis_heading_deg=found)
