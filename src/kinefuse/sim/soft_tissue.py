"""Soft-tissue artefact (STA)
--------------------------
A body-worn sensor does not follow the bone: skin, fat and muscle let it slide and rotate
relative to the bone, and the motion follows the movement (its frequency content is that of the
movement, so filtering cannot remove it; Leardini et al. 2005, Cappozzo et al. 1996). kinefuse
uses the linear STA model of Dumas, Camomilla, Bonci, Cheze and Cappozzo (J. Biomech. 47, 2014):
the rigid cluster motion relative to the bone is a linear function of the angles of the joints
the segment spans. Here the driving signal ``s(t)`` stacks the rotation vectors (rad) of the
joints at both ends of the segment (the relative rotation to every neighbouring segment of the
motion, minus its trial mean), and

``δθ(t) = A_rot · M_rot s(t)``, ``δp(t) = A_tr · M_tr s(t)`` (segment frame),

with ``M`` random matrices of spectral norm <= 1 (singular values uniform in [0.5, 1], random
directions), so ``|δθ| <= A_rot |s|`` and ``|δp| <= A_tr |s|``: ``A`` is the artefact per radian
of joint motion. The sensor pose is ``R_world_from_sensor = R_world_from_segment · exp(δθ) ·
R_segment_from_sensor`` and its position is the bone point plus ``R_world_from_segment δp``;
gyroscope and accelerometer are exact for that moving pose. Amplitudes :data:`STA_AMPLITUDE`
(per radian of joint excursion, ≈ the peak over a gait cycle whose knee flexes by about 60°),
times ``ImuConfig.soft_tissue_scale``:

* thigh 18 mm, 10° and shank 17 mm, 7°: the rigid marker-cluster STA measured against
  fluoroscopy during gait (Ancillao et al., Hum. Mov. Sci. 2021, CAMS-Knee), within the thigh
  10-30 mm and shank 5-20 mm ranges of Cappozzo et al. (Clin. Biomech. 11, 1996), Leardini et al.
  (Gait Posture 21, 2005, review) and Peters et al. (Gait Posture 31, 2010, review: thigh STA is
  the largest of the lower limb);
* upper arm 20 mm, 8° and forearm 10 mm, 5° [J]: humeral axial rotation is underestimated by
  skin sensors by up to a third of its range (Cutti et al., Gait Posture 21, 2005) and the
  upper-arm cluster moves by centimetres (Blache et al., J. Biomech. 62, 2017); the forearm STA
  is mostly about its long axis (pronation-supination).
* chest, pelvis, feet: none.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kinefuse.io.motion import Motion

__all__ = ["STA_AMPLITUDE", "joint_drive", "neighbours", "sta_kind"]

#: Soft-tissue artefact per radian of joint motion: segment kind -> (translation mm, rotation
#: deg); the module doc gives the sources.
STA_AMPLITUDE = {
    "thigh": (18.0, 10.0),
    "shank": (17.0, 7.0),
    "upper_arm": (20.0, 8.0),
    "forearm": (10.0, 5.0),
}


def sta_kind(segment: str) -> str | None:
    """The :data:`STA_AMPLITUDE` kind of ``segment`` (side suffix dropped), or None."""
    kind = segment.rsplit("_", 1)[0] if segment.endswith(("_l", "_r")) else segment
    return kind if kind in STA_AMPLITUDE else None


def neighbours(motion: Motion, segment: str) -> list[str]:
    """Segments of ``motion`` sharing a joint with ``segment`` (its proximal or distal joint)."""
    prox, dist = motion.segment_joints[segment]
    out = []
    for s in motion.segments:
        if s == segment:
            continue
        p2, d2 = motion.segment_joints[s]
        if (d2 is not None and d2 == prox) or (dist is not None and p2 == dist):
            out.append(s)
    return out


def joint_drive(rot_seg: Rotation, rot_nbs: list[Rotation]) -> np.ndarray:
    """Stacked rotation vectors (rad) of the joints to the neighbours, minus the trial mean, (T, 3m)."""
    cols = []
    for rn in rot_nbs:
        rel = rn.inv() * rot_seg
        cols.append((rel.mean().inv() * rel).as_rotvec())
    return np.concatenate(cols, axis=1) if cols else np.zeros((len(rot_seg), 0))
