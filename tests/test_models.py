"""constant_velocity / LinearGaussianModel: values, structure, validation."""

from __future__ import annotations

import numpy as np
import pytest

from kinefuse.models import LinearGaussianModel, constant_velocity


def test_constant_velocity_matrices_3d():
    dt, q, r = 1 / 30, 0.18, 0.02
    m = constant_velocity(dt, q, r)
    assert (m.n_x, m.n_z) == (6, 3) and m.dt_s == dt and m.axis_blocks
    F_axis = np.array([[1.0, dt], [0.0, 1.0]])
    Q_axis = q * np.array([[dt**2 / 4, dt / 2], [dt / 2, 1.0]])  # paper A Eq. 30 closed form
    for a in range(3):
        s = slice(2 * a, 2 * a + 2)
        np.testing.assert_array_equal(m.F[s, s], F_axis)
        np.testing.assert_allclose(m.Q[s, s], Q_axis, rtol=1e-15, atol=0)
        assert np.linalg.matrix_rank(m.Q[s, s]) == 1
        g = np.array([dt / 2, 1.0])
        np.testing.assert_allclose(m.Q[s, s], q * np.outer(g, g), rtol=1e-15)
        # = white-noise-acceleration model with sigma_a^2 = q / dt^2 (SPEC §1)
        wna = (q / dt**2) * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        np.testing.assert_allclose(m.Q[s, s], wna, rtol=1e-12)
    H = np.zeros((3, 6))
    H[0, 0] = H[1, 2] = H[2, 4] = 1.0
    np.testing.assert_array_equal(m.H, H)
    np.testing.assert_array_equal(m.R, r * np.eye(3))
    off = ~np.kron(np.eye(3), np.ones((2, 2))).astype(bool)
    assert not np.any(m.F[off]) and not np.any(m.Q[off])
    assert np.linalg.eigvalsh(m.Q).min() > -1e-15


def test_constant_velocity_2d_and_full_r():
    m2 = constant_velocity(0.1, 1.0, 0.5, n_axes=2)
    assert m2.F.shape == (4, 4) and m2.H.shape == (2, 4) and m2.R.shape == (2, 2)
    np.testing.assert_array_equal(m2.H, [[1, 0, 0, 0], [0, 0, 1, 0]])
    R = np.array([[0.02, 0.005, 0.0], [0.005, 0.03, 0.001], [0.0, 0.001, 0.01]])
    m = constant_velocity(1 / 30, 1.0, R)
    np.testing.assert_array_equal(m.R, R)
    assert not m.axis_blocks
    assert constant_velocity(1 / 30, 1.0, np.diag([0.1, 0.2, 0.3])).axis_blocks


def test_model_is_immutable():
    m = constant_velocity(1 / 30, 1.0, 0.01)
    with pytest.raises(ValueError):
        m.F[0, 0] = 2.0
    with pytest.raises(AttributeError):
        m.dt_s = 0.5
    m2 = m.replace(R=0.5 * np.eye(3))
    assert m2.R[0, 0] == 0.5 and m.R[0, 0] == 0.01


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dt_s": np.nan}, r"expected dt_s finite and > 0, got nan"),
        ({"dt_s": np.inf}, r"expected dt_s finite and > 0, got inf"),
        ({"dt_s": -0.1}, r"expected dt_s finite and > 0, got -0.1"),
        ({"dt_s": "fast"}, r"expected dt_s as a positive number, got 'fast'"),
        ({"q": -1.0}, r"expected q finite and >= 0, got -1.0"),
        ({"q": np.nan}, r"expected q finite and >= 0, got nan"),
        ({"r": -0.01}, r"expected r finite and > 0, got -0.01"),
        ({"r": 0.0}, r"expected r finite and > 0, got 0.0"),
        (
            {"r": np.array([[0.01, 0.02, 0], [0.02, 0.01, 0], [0, 0, 0.01]])},
            r"expected R positive definite, got smallest eigenvalue -0.01",
        ),
        (
            {"r": np.array([[0.01, 0.005, 0], [0.0, 0.01, 0], [0, 0, 0.01]])},
            r"expected R symmetric, got max",
        ),
        ({"r": np.eye(2) * 0.01}, r"expected r as a scalar or shape \(3, 3\), got \(2, 2\)"),
        ({"r": np.ones(3) * 0.01}, r"expected r as a scalar or shape \(3, 3\), got \(3,\)"),
        ({"n_axes": 4}, r"expected n_axes 2 or 3, got 4"),
        ({"n_axes": 1}, r"expected n_axes 2 or 3, got 1"),
        ({"n_axes": True}, r"expected n_axes 2 or 3, got True"),
    ],
)
def test_constant_velocity_bad_input(kwargs, match):
    args = {"dt_s": 1 / 30, "q": 1.0, "r": 0.01, "n_axes": 3}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        constant_velocity(**args)


def test_linear_gaussian_model_bad_shapes():
    with pytest.raises(ValueError, match=r"expected F with shape \(n_x, n_x\), got \(2, 3\)"):
        LinearGaussianModel(F=np.ones((2, 3)), H=np.ones((1, 2)), Q=np.eye(2), R=np.eye(1))
    with pytest.raises(ValueError, match=r"expected H with shape \(n_z, 2\), got \(1, 3\)"):
        LinearGaussianModel(F=np.eye(2), H=np.ones((1, 3)), Q=np.eye(2), R=np.eye(1))
    with pytest.raises(ValueError, match=r"expected Q with shape \(2, 2\), got \(3, 3\)"):
        LinearGaussianModel(F=np.eye(2), H=np.ones((1, 2)), Q=np.eye(3), R=np.eye(1))
    with pytest.raises(ValueError, match=r"expected Q positive semi-definite"):
        LinearGaussianModel(F=np.eye(2), H=np.ones((1, 2)), Q=-np.eye(2), R=np.eye(1))


# issue 12 case 10: text is not a number (float("1") used to accept q="1")
@pytest.mark.parametrize(
    "kw",
    [
        {"q": "1"},
        {"q": b"1"},
        {"q": True},
        {"r": "1"},
        {"r": np.array(["0.1"])},
        {"dt_s": "0.1"},
    ],
)
def test_constant_velocity_refuses_text_and_bools(kw):
    from kinefuse.exceptions import InputError

    args = {"dt_s": 0.1, "q": 0.1, "r": 0.01, **kw}
    with pytest.raises(InputError, match="expected"):
        constant_velocity(**args)
