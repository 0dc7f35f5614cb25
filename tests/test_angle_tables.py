"""The joint-angle tables of `kinefuse run` and its report: notes that fit the joints shown."""

import numpy as np
import pytest

from kinefuse.evaluation.angles import angle_extremes_table, range_of_motion_table


def _angles(*joints):
    t = np.linspace(0.0, 1.0, 11)
    return {j: np.stack([30 * t, 5 * t, -5 * t], axis=-1) for j in joints}


def test_ankle_convention_is_noted_only_where_an_ankle_is_shown():
    for make in (angle_extremes_table, range_of_motion_table):
        arm = " ".join(make(_angles("elbow_r")).notes)
        leg = " ".join(make(_angles("knee_l", "ankle_l")).notes)
        assert "dorsiflexion" not in arm and "zero in the calibration pose" in arm
        assert "dorsiflexion" in leg and "zero in the calibration pose" in leg


def test_angle_components_of_an_unknown_joint_is_an_error():
    """'foo' got a limb joint's angle names."""
    from kinefuse.exceptions import InputError
    from kinefuse.kinematics.angles import angle_components

    assert angle_components("trunk")[1] == "lateral_bending"
    with pytest.raises(InputError, match="unknown joint 'foo'"):
        angle_components("foo")
