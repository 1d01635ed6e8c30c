"""core/identification/pei_yeo.py: per-sensor maps onto the reference recovered exactly from
readings generated here with known maps and offsets."""
import numpy as np

from tetra_gradiometer.core import TetraGeometry, pei_yeo_2009

GEOMETRY = TetraGeometry.regular(0.5)


def _uniform_field_attitudes(rng, n, magnitude=5e-5):
    """Body-frame readings of a uniform field under random attitudes (a trim manoeuvre)."""
    directions = rng.normal(size=(n, 3))
    return magnitude * directions / np.linalg.norm(directions, axis=1)[:, None]


def test_pei_yeo_recovers_per_sensor_maps_onto_the_reference():
    rng = np.random.default_rng(9)
    n = 200
    background = _uniform_field_attitudes(rng, n)
    maps = np.eye(3) + rng.normal(0, 1e-2, (3, 3, 3))
    offsets = rng.normal(0, 1e-7, (3, 3))
    fields = np.repeat(background[:, None, :], 4, axis=1)
    # Sensor i reads M_i^-1 (B - o_i), so that M_i B_i' + o_i = B.
    fields[:, 1:] = np.einsum('sij,nsj->nsi', np.linalg.inv(maps), background[:, None, :] - offsets[None])
    calibration = pei_yeo_2009(fields)
    np.testing.assert_allclose(calibration.matrices, maps, atol=1e-9)
    np.testing.assert_allclose(calibration.offsets, offsets, atol=1e-14)
    np.testing.assert_allclose(calibration.compensate_fields(fields, GEOMETRY), 0.0, atol=1e-12)
