"""core/fields.py: the dipole field and gradient against the textbook and a numerical derivative."""
import numpy as np
import pytest

from tetra_gradiometer.core import dipole_field, dipole_gradient
from tetra_gradiometer.core.fields import uniform_field


def _random_dipole_points(rng, n=20):
    moment = rng.normal(0, 1e5, 3)
    source = rng.normal(0, 5, 3)
    directions = rng.normal(size=(n, 3))
    points = source + directions / np.linalg.norm(directions, axis=1)[:, None] * rng.uniform(5, 60, (n, 1))
    return moment, source, points


def test_dipole_on_axis_field_matches_textbook():
    # On the moment's axis at distance r: B = mu0/(4 pi) * 2 m / r^3, along m.
    b = dipole_field([[0.0, 0.0, 10.0]], [0.0, 0.0, 1e4], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(b[0], [0.0, 0.0, 1e-7 * 2 * 1e4 / 1000.0], rtol=1e-12)


def test_dipole_gradient_matches_numerical_derivative_of_field():
    rng = np.random.default_rng(1)
    moment, source, points = _random_dipole_points(rng)
    analytic = dipole_gradient(points, moment, source)
    step = 1e-4
    numeric = np.empty_like(analytic)
    for j in range(3):
        offset = np.zeros(3)
        offset[j] = step
        numeric[:, :, j] = (dipole_field(points + offset, moment, source)
                            - dipole_field(points - offset, moment, source)) / (2 * step)
    scale = np.abs(analytic).max(axis=(1, 2))[:, None, None]
    np.testing.assert_array_less(np.abs(numeric - analytic) / scale, 1e-7)


def test_dipole_gradient_is_symmetric_and_traceless():
    rng = np.random.default_rng(2)
    moment, source, points = _random_dipole_points(rng)
    g = dipole_gradient(points, moment, source)
    scale = np.abs(g).max()
    np.testing.assert_allclose(g, np.swapaxes(g, 1, 2), atol=1e-12 * scale)
    np.testing.assert_allclose(np.trace(g, axis1=1, axis2=2), 0.0, atol=1e-12 * scale)


def test_dipole_at_a_sensor_raises():
    with pytest.raises(ValueError, match='coincides'):
        dipole_field([[1.0, 2.0, 3.0]], [1.0, 0.0, 0.0], [1.0, 2.0, 3.0])


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match=r'dipole moment must have shape \(3,\)'):
        dipole_field([[1.0, 2.0, 3.0]], [1.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r'dipole moment must have shape \(3,\)'):
        dipole_gradient([[1.0, 2.0, 3.0]], [1.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r'dipole position must have shape \(3,\)'):
        dipole_field([[1.0, 2.0, 3.0]], [1.0, 0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ValueError, match=r'points must have shape \(N, 3\)'):
        dipole_gradient([1.0, 2.0, 3.0, 4.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0])


def test_uniform_field_repeats_the_field():
    out = uniform_field(3, [1e-5, -2e-5, 4e-5])
    np.testing.assert_array_equal(out, [[1e-5, -2e-5, 4e-5]] * 3)
    out[0, 0] = 0.0  # a copy, writable
    with pytest.raises(ValueError, match=r'uniform field must have shape \(3,\)'):
        uniform_field(2, [1.0, 2.0])
