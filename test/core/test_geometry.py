"""core/geometry.py: the tetrahedron and the difference algorithm (eq. 7) against exact
linear fields and hand-checkable shapes."""
import numpy as np
import pytest

from tetra_gradiometer.core import GeometryError, TetraGeometry, difference_tensor


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
    assert TetraGeometry.regular().positions[1].tolist() == [0.5, 0.0, 0.0]  # default edge 0.5 m


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


def test_baselines_and_their_inverse_by_hand():
    positions = np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 3.0], [1.0, 4.0, 3.0], [1.0, 2.0, 6.0]])
    geometry = TetraGeometry(positions)
    # eq. 6: columns r_2 - r_1, r_3 - r_1, r_4 - r_1 = diag(1, 2, 3)
    np.testing.assert_array_equal(geometry.a, np.diag([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(geometry.a_inv, np.diag([1.0, 0.5, 1.0 / 3.0]), rtol=1e-15)
    np.testing.assert_array_equal(geometry.positions, positions)
    for array in (geometry.positions, geometry.a, geometry.a_inv):
        with pytest.raises(ValueError, match='read-only'):
            array[0, 0] = 0.0


def test_flat_round_trip_and_its_errors():
    regular = TetraGeometry.regular(0.5)
    flat = regular.to_flat()
    assert len(flat) == 12 and all(type(v) is float for v in flat)
    assert flat[3:6] == [0.5, 0.0, 0.0]  # sensor 2 on the x axis, one edge from sensor 1
    np.testing.assert_array_equal(TetraGeometry.from_flat(flat).positions, regular.positions)
    with pytest.raises(GeometryError, match="sensor_positions must be 12 numbers, got \\['a'"):
        TetraGeometry.from_flat(['a'] * 12)
    with pytest.raises(GeometryError, match=r'must be 12 finite floats, got 13 values \(4 sensors x 3'):
        TetraGeometry.from_flat([0.0] * 13)
    with pytest.raises(GeometryError, match='the four sensors must not be coplanar$'):
        TetraGeometry.from_flat([0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0])
    with pytest.raises(ValueError, match=r'sensor positions must have shape \(4, 3\)'):
        TetraGeometry(np.zeros((3, 3)))
    with pytest.raises(GeometryError, match='edge must be positive, got 0'):
        TetraGeometry.regular(0)
