"""core/uncertainty.py against Monte Carlo: perturb the readings (or the parameters) many
times, compensate each draw with core.compensate_fields, and compare the spread."""
import numpy as np
import pytest

from tetra_gradiometer.core import InterferenceParameters, TetraGeometry, compensate_fields, difference_tensor
from tetra_gradiometer.core.uncertainty import compensated_sigma, noise_jacobian, noise_sigma, readings_sigma
from tetra_gradiometer.errors import InputError

GEOMETRY = TetraGeometry([[0.0, 0.0, 0.0], [0.6, 0.1, 0.0], [0.1, 0.45, 0.05], [0.2, 0.1, 0.5]])  # irregular
DRAWS = 40_000


def _parameters(rng, symmetric=False):
    k = rng.uniform(-0.05, 0.05, (3, 3, 3))
    if symmetric:
        k = 0.5 * (k + np.swapaxes(k, 1, 2))
    return InterferenceParameters(k, rng.uniform(-300e-9, 300e-9, (3, 3)))


@pytest.mark.parametrize('compensated', [False, True])
def test_sensor_noise_spread_matches_monte_carlo(compensated):
    rng = np.random.default_rng(0)
    parameters = _parameters(rng) if compensated else None
    sigma = 0.1e-9
    clean = rng.normal(0, 3e-5, (4, 3))
    draws = clean[None] + rng.normal(0, sigma, (DRAWS, 4, 3))
    g = compensate_fields(draws, parameters, GEOMETRY) if compensated else difference_tensor(draws, GEOMETRY)
    predicted = noise_sigma(GEOMETRY, sigma, parameters)
    # The standard deviation of a sample std from 40 000 draws is ~0.35 %: 2 % is > 5 sigma.
    np.testing.assert_allclose(g.std(axis=0), predicted, rtol=0.02)
    assert np.ptp(predicted) > 0.1 * predicted.max()  # an irregular array: components differ


def test_readings_sigma_of_four_different_correlated_covariances_matches_monte_carlo():
    """Each sensor its own covariance, with correlated axes: the raw tensor's spread."""
    rng = np.random.default_rng(3)
    roots = rng.normal(0, 0.1e-9, (4, 3, 3)) * np.array([1.0, 2.0, 0.5, 3.0])[:, None, None]
    covariances = roots @ np.swapaxes(roots, 1, 2)  # (4, 3, 3), positive definite
    noise = np.einsum('smn,dsn->dsm', roots, rng.normal(size=(DRAWS, 4, 3)))
    g = difference_tensor(rng.normal(0, 3e-5, (4, 3))[None] + noise, GEOMETRY)
    predicted = readings_sigma(noise_jacobian(GEOMETRY), covariances.reshape(4, 9))
    np.testing.assert_allclose(g.std(axis=0).reshape(9), predicted, rtol=0.02)
    # Isotropic and equal on every sensor: the white-noise figure.
    isotropic = np.tile(np.eye(3).reshape(9) * 0.2e-9**2, (4, 1))
    np.testing.assert_allclose(readings_sigma(noise_jacobian(GEOMETRY), isotropic).reshape(3, 3),
                               noise_sigma(GEOMETRY, 0.2e-9), rtol=1e-12)


def test_parameter_covariance_spread_matches_monte_carlo():
    rng = np.random.default_rng(1)
    for symmetric, n_parameters in ((True, 27), (False, 36)):
        parameters = _parameters(rng, symmetric)
        root = rng.normal(0, 1, (n_parameters, n_parameters))
        scale = np.r_[np.full(n_parameters - 9, 1e-4), np.full(9, 1e-9)]  # K dimensionless, b tesla
        covariance = (root @ root.T / n_parameters) * np.outer(scale, scale)
        theta = parameters.to_vector(symmetric=symmetric)
        fields = rng.normal(0, 3e-5, (3, 4, 3))
        samples = rng.multivariate_normal(theta, covariance, size=DRAWS // 4)
        g = np.array([compensate_fields(fields, InterferenceParameters.from_vector(t, symmetric=symmetric), GEOMETRY)
                      for t in samples])
        predicted = compensated_sigma(fields[:, 0], GEOMETRY, 0.0, parameters, covariance)
        assert predicted.shape == (3, 3, 3)
        np.testing.assert_allclose(g.std(axis=0), predicted, rtol=0.04)


def test_the_two_sources_add_in_quadrature_and_bad_covariances_are_named():
    rng = np.random.default_rng(2)
    parameters = _parameters(rng)
    b_reference = rng.normal(0, 3e-5, (5, 3))
    covariance = np.diag(np.r_[np.full(27, 1e-8), np.full(9, 1e-20)])
    both = compensated_sigma(b_reference, GEOMETRY, 0.1e-9, parameters, covariance)
    noise = compensated_sigma(b_reference, GEOMETRY, 0.1e-9, parameters)
    calibration = compensated_sigma(b_reference, GEOMETRY, 0.0, parameters, covariance)
    np.testing.assert_allclose(both**2, noise**2 + calibration**2, rtol=1e-12)
    with pytest.raises(InputError, match=r'\(27, 27\) or \(36, 36\)'):
        compensated_sigma(b_reference, GEOMETRY, 0.1e-9, parameters, np.eye(30))
