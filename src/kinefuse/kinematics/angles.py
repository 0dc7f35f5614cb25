"""Joint angles from segment orientations, ISB conventions (Wu et al. 2002, 2005).

Segment frames follow the ISB recommendation: X anterior, Y superior (distal -> proximal along
the segment), Z to the right, on both sides. The joint rotation is the distal segment in the
proximal one, ``R = R_proximalᵀ R_distal``, decomposed as the joint coordinate system of
Grood & Suntay (1983): ``R = R_Z(α) R_X(β) R_Y(γ)`` (flexion about the proximal segment's
medio-lateral axis Z, then the floating axis X, then the distal segment's long axis Y).

- Wu, G. et al. (2002). ISB recommendation on definitions of joint coordinate system of various
  joints for the reporting of human joint motion - part I: ankle, hip, and spine. J Biomech 35.
- Wu, G. et al. (2005). ISB recommendation ... part II: shoulder, elbow, wrist and hand.
  J Biomech 38.
- Grood, E. S. & Suntay, W. J. (1983). A joint coordinate system for the clinical description
  of three-dimensional motions: application to the knee. J Biomech Eng 105.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse._validation import names_arg
from kinefuse.exceptions import InputError
from kinefuse.kinematics.forward import as_rotation_matrices

__all__ = ["JOINTS", "JOINT_ANGLE_COMPONENTS", "angle_components", "angle_words", "joint_angles"]

#: The three angles of every limb joint, in the order returned (degrees).
JOINT_ANGLE_COMPONENTS = ("flexion", "adduction", "internal_rotation")

#: The three angles of the midline joint ``trunk`` (the chest in the pelvis), in the order
#: returned: ISB's spine (Wu et al. 2002), OpenSim's ``lumbar_extension`` (sign flipped),
#: ``lumbar_bending``, ``lumbar_rotation``.
TRUNK_ANGLE_COMPONENTS = ("flexion", "lateral_bending", "axial_rotation")

#: Joint -> (proximal segment, distal segment, sign of flexion relative to +α about Z).
#: With Z to the right, +α moves the distal segment's end anteriorly: elbow and hip flexion,
#: but knee *extension*, so the knee's sign is −1 (ISB: knee flexion positive). At the ankle
#: +α turns the foot's anterior axis (the toes) up: dorsiflexion, positive as in ISB (Wu et
#: al. 2002: the tibia's Z is the dorsi/plantarflexion axis). The shoulder is the humerus in
#: the thorax (the chest IMU's segment), with the sequence of the other joints: the
#: coordinates OpenSim's models and OpenSense report (``arm_flex``, ``arm_add``, ``arm_rot``).
#: Wu et al. (2005) recommend Y-X-Y for the thorax-humerus instead; that sequence is singular
#: with the arm hanging (the N-pose, where this one reads zero), this one with the arm
#: horizontal to the side (adduction ±90°, the T-pose), where flexion and internal rotation are
#: not defined: near it they are ill-conditioned, and on it flexion takes the whole turn about
#: the vertical and internal rotation reads 0.
JOINTS = {
    **{f"shoulder_{s}": ("chest", f"upper_arm_{s}", 1.0) for s in "lr"},
    **{f"elbow_{s}": (f"upper_arm_{s}", f"forearm_{s}", 1.0) for s in "lr"},
    **{f"knee_{s}": (f"thigh_{s}", f"shank_{s}", -1.0) for s in "lr"},
    **{f"hip_{s}": ("pelvis", f"thigh_{s}", 1.0) for s in "lr"},
    **{f"ankle_{s}": (f"shank_{s}", f"foot_{s}", 1.0) for s in "lr"},
    "trunk": ("pelvis", "chest", -1.0),
}
#: The trunk (the chest IMU's segment in the pelvis IMU's) bends forward when the chest's
#: superior axis tilts anteriorly: −α, so its sign is −1 (flexion positive). It is on the
#: midline: its other two angles are not mirrored but read by the right-hand rule about ISB's
#: axes, as OpenSim's lumbar coordinates: lateral bending positive to the right, axial rotation
#: positive to the left (the chest turning towards the left, seen from above).


def angle_components(joint: str) -> tuple[str, str, str]:
    """The names of ``joint``'s three angles, in the order :func:`joint_angles` returns them:
    :data:`TRUNK_ANGLE_COMPONENTS` for ``"trunk"``, else :data:`JOINT_ANGLE_COMPONENTS`.
    ``joint``: a joint of :data:`JOINTS` or its kind without the side (``"knee"``); anything
    else is an error (it got a limb joint's names)."""
    if joint not in JOINTS and f"{joint}_l" not in JOINTS:
        kinds = sorted({j.rsplit("_", 1)[0] if j[-2:] in ("_l", "_r") else j for j in JOINTS})
        raise InputError(
            f"unknown joint {joint!r}; expected one of {sorted(JOINTS)} or a kind {kinds}"
        )
    return TRUNK_ANGLE_COMPONENTS if joint == "trunk" else JOINT_ANGLE_COMPONENTS


def angle_words(joint: str) -> tuple[str, str, str]:
    """:func:`angle_components` as words for tables and messages ("internal rotation")."""
    return tuple(c.replace("_", " ") for c in angle_components(joint))


def joint_angles(
    orientations: Mapping[str, object], joints: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """Flexion, adduction and internal rotation of shoulders, elbows, knees, hips and ankles,
    and flexion, lateral bending and axial rotation of the trunk, degrees.

    Parameters
    ----------
    orientations : mapping of str -> array_like
        ``R_world_from_segment`` of ISB segment frames (X anterior, Y superior, Z right) per
        segment, ``(..., T, 3, 3)`` matrices or ``(..., T, 4)`` ``wxyz`` quaternions, e.g. from
        :func:`kinefuse.kinematics.segment_orientations`. NaN rows give NaN angles.
    joints : sequence of str, optional
        Joints of :data:`JOINTS` (``shoulder_r``, ``elbow_r``, ``knee_l``, ``hip_r``...).
        Default: every joint whose two segments are in ``orientations``.

    Returns
    -------
    dict of str -> ndarray, shape (..., T, 3)
        Per joint ``[flexion, adduction, internal_rotation]`` (:data:`JOINT_ANGLE_COMPONENTS`;
        the trunk's: :data:`TRUNK_ANGLE_COMPONENTS`, signs at :data:`JOINTS`), deg. Signs
        (ISB, both sides): flexion positive (elbow and knee bent, shoulder and hip with the arm
        or thigh forward, ankle dorsiflexed: toes up); adduction positive (distal segment
        towards the midline; at the elbow this is varus); internal rotation positive (at the
        elbow this is pronation). Zero in the calibration pose of
        :func:`kinefuse.kinematics.calibrate` (``"static"``).

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        An unknown joint, or a joint whose segments are missing.

    Notes
    -----
    ``R = R_pᵀ R_d = R_Z(α) R_X(β) R_Y(γ)`` (intrinsic Z-X-Y, SciPy ``"ZXY"``); flexion
    ``= s α`` with the sign ``s`` of :data:`JOINTS`, adduction ``= β`` (right) or ``−β`` (left),
    internal rotation ``= γ`` (right) or ``−γ`` (left), so that both sides read alike; the
    trunk's lateral bending ``= β`` and axial rotation ``= γ``. The decomposition is singular
    at ``β = ±90°``: never reached by a healthy knee or elbow; at the shoulder, the arm
    horizontal to the side (see :data:`JOINTS`; there ``γ`` is set to 0 and ``α`` takes the
    whole turn, without SciPy's gimbal-lock warning).
    """
    if not isinstance(orientations, Mapping):
        raise InputError(
            f"expected orientations as a mapping segment -> (..., T, 3, 3), got {type(orientations).__name__}"
        )
    joints = names_arg(joints, "joints")
    if joints is None:
        joints = [j for j, (p, d, _) in JOINTS.items() if p in orientations and d in orientations]
    out = {}
    for j in joints:
        if j not in JOINTS:
            raise InputError(f"unknown joint {j!r}; expected one of {sorted(JOINTS)}")
        prox, dist, sign = JOINTS[j]
        lack = [s for s in (prox, dist) if s not in orientations]
        if lack:
            raise InputError(
                f"joint {j!r} needs the orientations of {prox!r} and {dist!r}; missing {lack}"
            )
        Rp = as_rotation_matrices(orientations[prox], f"orientations[{prox!r}]")
        Rd = as_rotation_matrices(orientations[dist], f"orientations[{dist!r}]")
        if Rp.shape != Rd.shape:
            raise InputError(
                f"joint {j!r}: {prox!r} orientations {Rp.shape[:-2]} and {dist!r} "
                f"{Rd.shape[:-2]} are not on the same timeline"
            )
        R = np.einsum("...ji,...jk->...ik", Rp, Rd).reshape(-1, 3, 3)
        ang = np.full((R.shape[0], 3), np.nan)
        ok = np.all(np.isfinite(R), axis=(1, 2))
        if np.any(ok):
            with warnings.catch_warnings():  # β = ±90°: documented above
                warnings.filterwarnings("ignore", "Gimbal lock detected", UserWarning)
                ang[ok] = Rotation.from_matrix(R[ok]).as_euler("ZXY", degrees=True)
        side = -1.0 if j.endswith("_l") else 1.0  # the right side and the midline as computed
        ang *= np.array([sign, side, side])
        out[j] = ang.reshape(*Rp.shape[:-2], 3)
    return out
