"""Fields and the difference algorithm against independent truth."""
import numpy as np
import pytest

from tetra_gradiometer.core import (GeometryError, TetraGeometry, difference_tensor, dipole_field,
                                    dipole_gradient)


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


def test_difference_tensor_is_exact_for_a_linear_field():
    rng = np.random.default_rng(3)
    geometry = TetraGeometry(rng.normal(0, 0.4, (4, 3)), max_condition=1e4)
    gradients = rng.normal(0, 1e-7, (5, 3, 3))  # any matrix, even asymmetric
    b0 = rng.normal(0, 5e-5, (5, 3))
    fields = b0[:, None, :] + np.einsum('nij,sj->nsi', gradients, geometry.positions)
    np.testing.assert_allclose(difference_tensor(fields, geometry), gradients, rtol=1e-9, atol=1e-18)


def test_regular_tetrahedron_has_equal_edges():
    positions = TetraGeometry.regular(0.7).positions
    edges = [np.linalg.norm(positions[i] - positions[j]) for i in range(4) for j in range(i + 1, 4)]
    np.testing.assert_allclose(edges, 0.7, rtol=1e-12)


def test_degenerate_geometry_is_refused_naming_condition_number():
    flat = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-6]]
    with pytest.raises(GeometryError, match='condition number'):
        TetraGeometry(flat)
    with pytest.raises(GeometryError, match='12 floats'):
        TetraGeometry.from_flat([0.0] * 11)


@pytest.mark.parametrize('bad, message', [
    (np.full((3, 4, 3), np.nan), 'non-finite'),
    (np.zeros((3, 3, 3)), r'shape \(N, 4, 3\)'),
])
def test_bad_fields_raise_clear_errors(bad, message):
    with pytest.raises(ValueError, match=message):
        difference_tensor(bad, TetraGeometry.regular())


def test_dipole_at_a_sensor_raises():
    with pytest.raises(ValueError, match='coincides'):
        dipole_field([[1.0, 2.0, 3.0]], [1.0, 0.0, 0.0], [1.0, 2.0, 3.0])
