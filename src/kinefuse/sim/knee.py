"""Knee secondary rotations
-------------------------
Mocap skeletons often model the knee as a hinge (CMU's ASF tibia has one degree of freedom, and
the project's BVH trials rotate the knee about one axis only). A real knee is not one: biplane
radiography of 39 healthy knees in treadmill walking (J. Biomech. Eng. 142, 2020,
doi:10.1115/1.4047419, PMC7477710) shows a mean range of motion of 67.3° in flexion, **11.5° in
internal/external rotation** (about the tibia's long axis) and **3.7° in ab/adduction**, with
waveforms that differ from the flexion curve; Kefala et al. (Med. Sci. Sports Exerc. 49, 2017)
measure 13.5° of internal/external range in pivoting. Virtual sensors on hinge knees see none of
this: the relative angular rate of thigh and shank lies along one axis, which makes a knee's
centre along its flexion axis unobservable for a functional calibration and the simulator kinder
than real data (``kinefuse experiment realism``, measure (iv)).

:func:`with_knee_secondary` adds the two rotations to each hinge knee of a
:class:`~kinefuse.io.motion.Motion`, in the shank frame (y along the bone, z forward), as the
soft-tissue model of :mod:`kinefuse.sim.soft_tissue` builds its artefact: a random linear mixture
of the joint rotations around the knee,

``θ_IE(t) = G_IE · m_1 · s(t)``, ``θ_AA(t) = G_AA · m_2 · s(t)``,

with ``s(t)`` the stacked rotation vectors (rad, minus their trial mean) of the hip (pelvis to
thigh), the knee (thigh to shank) and the ankle (shank to foot), where those segments exist, and
``m_1, m_2`` the rows of a random matrix of spectral norm <= 1 (singular values uniform in
[0.5, 1]). The mixture ties the rotations to the movement (none when the leg is still) while their
time course is not a copy of the flexion curve (a rotation proportional to flexion would only tilt
the flexion axis). Gains :data:`KNEE_SECONDARY_GAIN` (rad per rad of joint drive) were set so that
the mean ranges of motion (2.5-97.5 percentile span) over the realism check's tuning walks (CMU
02_01 and 02_02, 500 draws each, both knees) equal those means; the shank rotates by ``exp(θ)``
after its mocap orientation, the ankle and foot follow the shank's new direction (the foot keeps
its orientation: the ankle takes up the rotation, as a planted foot does), and the thigh, pelvis
and everything above are unchanged.

Not modelled: tibiofemoral translations (a few mm), and the coupling of these rotations to load.
A knee that is not a hinge in the mocap (off-axis rotation above :data:`HINGE_TOLERANCE_RAD` RMS)
is left as it is.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.io.motion import SEGMENT_AXIS, Motion, _continuous_quat
from kinefuse.sim.noise import norm_bounded_matrix
from kinefuse.sim.soft_tissue import joint_drive

__all__ = ["HINGE_TOLERANCE_RAD", "KNEE_SECONDARY_GAIN", "with_knee_secondary"]

#: Rotation per radian of joint drive: internal/external (about the shank's y axis) and
#: ab/adduction (about its z axis); the module doc gives the sources and how they were set.
KNEE_SECONDARY_GAIN = {"internal_external": 0.50, "ab_adduction": 0.16}

#: A knee whose rotation leaves its main axis by less than this (RMS, rad) counts as a hinge.
HINGE_TOLERANCE_RAD = np.deg2rad(0.5)


def with_knee_secondary(
    motion: Motion, rng: np.random.Generator, scale: float = 1.0
) -> tuple[Motion, dict]:
    """``motion`` with internal/external rotation and ab/adduction added to its hinge knees.

    Parameters
    ----------
    motion : Motion
        The driving motion (ENU).
    rng : numpy.random.Generator
        Source of the mixing matrices (drawn for the left knee, then the right).
    scale : float
        Factor on :data:`KNEE_SECONDARY_GAIN` (0: the motion unchanged).

    Returns
    -------
    motion : Motion
        Shank orientations, ankle and foot positions changed at each hinge knee that has a
        thigh and a shank (and ankle joint); everything else as given.
    truth : dict
        Per knee changed (``"knee_l"``, ``"knee_r"``): the added rotation vector, (T, 3) rad, in
        the shank frame (components y = internal/external, z = ab/adduction).

    Notes
    -----
    Module docstring: the model, its sources and its gains.
    """
    q = motion.q_world_from_segment.copy()
    pos = motion.position_m.copy()
    truth: dict[str, np.ndarray] = {}
    segs = set(motion.segments)
    for side in ("l", "r"):
        thigh, shank, foot = f"thigh_{side}", f"shank_{side}", f"foot_{side}"
        # drawn for every knee, so that the right knee's draw never depends on the left's
        m = _mixing(rng)
        if scale == 0 or not {thigh, shank} <= segs or f"ankle_{side}" not in motion.joints:
            continue
        rot = {s: _rotation(motion, s) for s in ("pelvis", thigh, shank, foot) if s in segs}
        if not _is_hinge(rot[thigh], rot[shank]):
            continue
        drives = [joint_drive(rot[thigh], [rot["pelvis"]])] if "pelvis" in rot else []
        drives.append(joint_drive(rot[shank], [rot[thigh]]))
        if foot in rot:
            drives.append(joint_drive(rot[foot], [rot[shank]]))
        s = np.concatenate(drives, axis=1)
        mix = s @ m[:, : s.shape[1]].T
        theta = np.zeros((len(motion), 3))
        theta[:, 1] = scale * KNEE_SECONDARY_GAIN["internal_external"] * mix[:, 0]
        theta[:, 2] = scale * KNEE_SECONDARY_GAIN["ab_adduction"] * mix[:, 1]
        new_shank = rot[shank] * Rotation.from_rotvec(theta)
        q[:, motion.segment_index(shank)] = _continuous_quat(new_shank.as_quat(scalar_first=True))
        knee, ankle = motion.joint_index(f"knee_{side}"), motion.joint_index(f"ankle_{side}")
        moved = pos[:, knee] + motion.segment_length_m[shank] * new_shank.apply(SEGMENT_AXIS)
        shift = moved - pos[:, ankle]
        pos[:, ankle] = moved
        if f"foot_{side}" in motion.joints:
            pos[:, motion.joint_index(f"foot_{side}")] += shift
        truth[f"knee_{side}"] = theta
    if not truth:
        return motion, truth
    return replace(motion, q_world_from_segment=q, position_m=pos), truth


def _mixing(rng: np.random.Generator) -> np.ndarray:
    """The two mixing rows over the hip, knee and ankle drives (2, 9)."""
    return norm_bounded_matrix(rng, 2, 9)


def _rotation(motion: Motion, segment: str) -> Rotation:
    return Rotation.from_quat(motion.orientation(segment), scalar_first=True)


def _is_hinge(thigh: Rotation, shank: Rotation) -> bool:
    """Whether the knee rotation vectors lie along one axis (off-axis RMS below the tolerance)."""
    rv = (thigh.inv() * shank).as_rotvec()
    sv = np.linalg.svd(rv, compute_uv=False) / np.sqrt(len(rv))
    return bool(sv[1] < HINGE_TOLERANCE_RAD)
