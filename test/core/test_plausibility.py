"""core/plausibility.py: the physical bounds, checked against hand-built cases whose verdict is
known (a reading of 1 T, an edge of 5 mm, k = 1e308, a NaN position)."""
import numpy as np
import pytest

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.core.plausibility import (
    MAX_FIELD_T,
    check_parameters,
    check_positions_match,
    plausible_reading,
    plausible_readings,
    plausible_sets,
)
from tetra_gradiometer.errors import GeometryError, InputError


def test_plausible_sets_drops_each_bad_set_once_with_its_reason():
    fields = np.full((6, 4, 3), 2e-5)
    fields[1, 2, 0] = np.nan                   # non-finite
    fields[2, 3] = [1.0, 0.0, 0.0]             # 1 T
    fields[3, 0] = [0.0, 0.0, -np.inf]         # non-finite (also "large": counted once)
    fields[4, 1] = [0.6e-3, 0.6e-3, 0.6e-3]    # each component < 1e-3 T but |B| = 1.04e-3 T
    keep, dropped = plausible_sets(fields)
    assert keep.tolist() == [True, False, False, False, False, True]
    assert (dropped.non_finite, dropped.field_magnitude, dropped.total) == (2, 2, 4)
    assert dropped.text() == f'2 non-finite, 2 with |B| > {MAX_FIELD_T:g} T'
    # Per reading, with a stricter bound where a node asks for one (never a looser one).
    readings = plausible_readings(fields[4])
    assert readings.tolist() == [True, False, True, True]
    assert plausible_readings(np.array([0.0, 0.0, 6e-5]), max_field_t=5e-5) == np.False_
    assert plausible_readings(np.array([0.0, 0.0, 2e-3]), max_field_t=1.0) == np.False_


@pytest.mark.parametrize('edge,fragment', [(0.005, '0.005 m apart'), (12.0, '12 m apart'),
                                           (1e-300, 'apart'), (1e300, 'from the body origin')])
def test_geometry_outside_the_physical_scale_is_refused(edge, fragment):
    with pytest.raises(GeometryError, match=fragment):
        TetraGeometry.regular(edge)


def test_geometry_at_the_bounds_is_accepted():
    for edge in (0.0101, 9.99):
        assert TetraGeometry.regular(edge).condition_number < 3


@pytest.mark.parametrize('where,value,fragment', [
    ('k', 1e308, r'k_soft\[0, 1, 2\] = 1e\+308'),
    ('k', 1.5, 'k_soft'),
    ('k', np.nan, 'k_soft'),
    ('b', 2e-4, r'b_hard\[0, 1\] = 0.0002 T'),
    ('b', -np.inf, 'b_hard'),
])
def test_calibration_parameters_beyond_physical_bounds_are_named(where, value, fragment):
    k, b = np.zeros((3, 3, 3)), np.zeros((3, 3))
    if where == 'k':
        k[0, 1, 2] = value
    else:
        b[0, 1] = value
    with pytest.raises(InputError, match=fragment):
        check_parameters(k, b, 'test')
    check_parameters(np.full((3, 3, 3), 0.99), np.full((3, 3), 0.99e-4))  # within bounds


def test_positions_must_be_finite_and_match_to_a_millimetre():
    geometry = TetraGeometry.regular(0.5)
    flat = np.array(geometry.to_flat())
    check_positions_match(flat + 0.9e-3, geometry.positions)
    with pytest.raises(InputError, match='differ by up to 0.0011 m'):
        check_positions_match(flat + np.r_[np.zeros(11), 1.1e-3], geometry.positions)
    nan = flat.copy()
    nan[4] = np.nan  # NaN compares false: the check must not pass it
    with pytest.raises(InputError, match=r'sensor_positions\[4\] = nan is not finite'):
        check_positions_match(nan, geometry.positions)


def test_plausible_reading_is_plausible_readings_of_one_reading():
    rng = np.random.default_rng(3)
    readings = rng.normal(0, 6e-4, (2000, 3))
    readings[rng.random((2000, 3)) < 0.01] = np.nan
    readings[rng.random((2000, 3)) < 0.01] = -np.inf
    readings[:5] = [[1e-3, 0, 0], [0, -1e-3, 0], [6e-4, 8e-4, 0], [1e300, 1e300, 0], [0, 0, 0]]
    for bound in (1e-4, 5e-4, 1e-3, 1.0):
        vector = plausible_readings(readings, bound)
        scalar = [plausible_reading(*r, max_field_t=bound) for r in readings.tolist()]
        np.testing.assert_array_equal(scalar, vector)
    assert 0 < vector.sum() < len(readings)
