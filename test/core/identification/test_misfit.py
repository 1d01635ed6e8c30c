"""core/identification/misfit: a field's misfit is symmetric and traceless, the vehicle's
is not (against a dipole's exact gradient and random pair-difference interference)."""
import numpy as np

from tetra_gradiometer.core import TetraGeometry, dipole_gradient
from tetra_gradiometer.core.identification.misfit import FIELD_SHARE, gradient_share

GEOMETRY = TetraGeometry.regular(0.5)
NOISE_T = 0.05e-9


def _noise(rng, n):
    """The tensor of white sensor noise (eq. 7 on four noisy readings)."""
    pairs = rng.normal(0, NOISE_T, (n, 4, 3))
    return np.swapaxes(pairs[:, 1:] - pairs[:, :1], 1, 2) @ GEOMETRY.a_inv


def test_a_passing_dipole_is_a_field():
    rng = np.random.default_rng(1)
    track = np.column_stack([np.linspace(-50, 50, 2000), np.zeros(2000), np.zeros(2000)])
    gradient = dipole_gradient(track, np.array([3e4, -2e4, 1e4]), np.array([0.0, 5.0, -30.0]))
    share = gradient_share(gradient + _noise(rng, 2000), GEOMETRY, NOISE_T)
    assert share > FIELD_SHARE


def test_vehicle_interference_is_not_a_field():
    rng = np.random.default_rng(2)
    n = 3000
    # A current's field on the sensors: per-sensor offsets times a scalar series, seen
    # through eq. 7 (pair differences times a^-1): a generic tensor, ~5/9 symmetric traceless.
    shares = []
    for _ in range(20):
        w = rng.normal(0, 1e-9, (3, 3))  # [axis, pair]
        current = rng.uniform(3, 27, n)
        misfit = current[:, None, None] * (w @ GEOMETRY.a_inv)[None]
        shares.append(gradient_share(misfit + _noise(rng, n), GEOMETRY, NOISE_T))
    assert max(shares) < FIELD_SHARE
    assert 0.3 < np.median(shares) < 0.8


def test_noise_alone_has_no_share():
    rng = np.random.default_rng(3)
    assert gradient_share(_noise(rng, 5000), GEOMETRY, NOISE_T) is None
