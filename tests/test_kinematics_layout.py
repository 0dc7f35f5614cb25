"""The modules split by idea keep their public names, and the shared helpers agree with oracles."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinefuse._validation import as_float, readonly_array
from kinefuse.exceptions import InputError
from kinefuse.kinematics.forward import rotation_z
from kinefuse.sim.noise import gauss_markov


def test_old_import_paths_still_resolve():
    from kinefuse.kinematics import calibration, functional
    from kinefuse.sim import imu

    for name in calibration.__all__:
        assert hasattr(calibration, name), name
    for name in functional.__all__:
        assert hasattr(functional, name), name
    for name in imu.__all__:
        assert hasattr(imu, name), name


@pytest.mark.parametrize("psi", [0.0, 0.3, -2.0, np.pi])
def test_rotation_z_matches_scipy(psi):
    expected = Rotation.from_rotvec([0.0, 0.0, psi]).as_matrix()
    np.testing.assert_allclose(rotation_z(psi), expected, atol=1e-15)


def test_gauss_markov_draws_even_when_silent():
    # a zero std still consumes its draws, so later draws do not shift
    a, b = np.random.default_rng(1), np.random.default_rng(1)
    assert not np.any(gauss_markov(a, 5, 2, 0.0, 1.0, 0.1))
    b.standard_normal((5, 2))
    assert a.standard_normal() == b.standard_normal()


def test_validation_helpers():
    assert as_float("2.5", "unused") == 2.5
    with pytest.raises(InputError, match="not a number here"):
        as_float("x", "not a number here")
    r = readonly_array([1, 2])
    assert r.dtype == np.float64 and not r.flags.writeable
