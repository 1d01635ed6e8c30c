"""Issue 12, "honest uncertainty", against the mission simulator's ground truth: the
parameter covariance of the known-gradient fit matches the parameters' real scatter over
noise seeds, and on a fresh survey 92-98 % of the compensated components lie within 2 sigma
(core/uncertainty.py) of ``g_true``; SigmaModel against the design written out."""
import numpy as np
import pytest

from tetra_gradiometer.core import (Dipole, InterferenceParameters, Scenario, SurveyLine, TetraGeometry,
                                    TrimManoeuvre, compensate_fields, difference_tensor, known_gradient_lstsq,
                                    random_interference, simulate)
from tetra_gradiometer.core.design import interference_design
from tetra_gradiometer.core.uncertainty import SigmaModel, compensated_sigma, noise_sigma

GEOMETRY = TetraGeometry.regular(0.5)
EARTH_T = np.array([0.0, 21000e-9, -45376.2e-9])
NOISE_T = 0.1e-9
TRIM = TrimManoeuvre(60.0, center=(3000.0, 3000.0, -50.0), heading_rate_deg_s=12.0, roll_period_s=7.0,
                     pitch_period_s=9.0)
SURVEY = SurveyLine((-60.0, 0.0, -50.0), (60.0, 0.0, -50.0), speed_m_s=2.0)
TARGET = Dipole((0.0, 0.0, -75.0), (3.0e4, 2.0e4, -3.3e4))


def _scenario(segment, interference, dipoles=()):
    return Scenario(GEOMETRY, EARTH_T, (segment,), sample_rate_hz=10.0, dipoles=dipoles,
                    interference=interference, noise_t=NOISE_T)


def _calibrate(mission, symmetric):
    return known_gradient_lstsq(difference_tensor(mission.fields_measured, GEOMETRY),
                                mission.fields_measured[:, 0], GEOMETRY, symmetric_k=symmetric)


@pytest.mark.parametrize('symmetric,reference_clean', [(False, False), (True, True)])
def test_reported_parameter_sigma_matches_the_scatter_over_seeds(symmetric, reference_clean):
    """One vehicle, one trim trajectory, 120 noise seeds: the spread of the identified
    parameters around the simulator's exact ones (eq. 14) against the sigma the fit reports."""
    interference = random_interference(np.random.default_rng(100), k_scale=0.01, b_scale_t=300e-9,
                                       reference_clean=reference_clean)
    truth = interference.effective_parameters().to_vector(symmetric=symmetric)
    scenario = _scenario(TRIM, interference)
    errors, sigmas = [], []
    for seed in range(120):
        calibration = _calibrate(simulate(scenario, np.random.default_rng(seed)), symmetric)
        errors.append(calibration.parameters.to_vector(symmetric=symmetric) - truth)
        sigmas.append(calibration.standard_errors)
    errors, sigmas = np.array(errors), np.array(sigmas)
    # Per parameter: RMS error around the truth (120 dof) over the RMS reported sigma.
    ratio = np.sqrt(np.mean(errors**2, axis=0)) / np.sqrt(np.mean(sigmas**2, axis=0))
    pooled = np.sqrt(np.mean((errors / sigmas) ** 2))
    print(f'symmetric={symmetric}: scatter / reported sigma: pooled {pooled:.3f}, '
          f'per parameter {ratio.min():.3f} .. {ratio.max():.3f} (median {np.median(ratio):.3f})')
    assert 0.9 < pooled < 1.1
    # A ratio from 120 seeds has a standard error of 1 / sqrt(240) = 6.5 %: 20 % is 3 of those.
    assert np.all((0.8 < ratio) & (ratio < 1.2)), ratio
    assert sigmas.min() > 0


def _coverage(seed, symmetric, reference_clean):
    rng = np.random.default_rng(seed)
    interference = random_interference(rng, k_scale=0.01, b_scale_t=300e-9, reference_clean=reference_clean)
    calibration = _calibrate(simulate(_scenario(TRIM, interference), rng), symmetric)
    survey = simulate(_scenario(SURVEY, interference, (TARGET,)), np.random.default_rng(seed + 10_000))
    g = compensate_fields(survey.fields_measured, calibration.parameters, GEOMETRY)
    noise_t = calibration.details['sensor_noise_nT'] * 1e-9
    sigma = compensated_sigma(survey.fields_measured[:, 0], GEOMETRY, noise_t, calibration.parameters,
                              calibration.covariance)
    assert np.abs(survey.g_true).max() > 100 * sigma.max()  # a real target, not a zero truth
    return float(np.mean(np.abs(g - survey.g_true) <= 2 * sigma)), sigma


@pytest.mark.parametrize('symmetric,reference_clean', [(False, False), (False, True), (True, True)])
def test_two_sigma_covers_92_to_98_percent_of_the_compensated_components(symmetric, reference_clean):
    fractions = []
    for seed in range(6):
        fraction, sigma = _coverage(seed, symmetric, reference_clean)
        fractions.append(fraction)
    print(f'symmetric={symmetric} reference_clean={reference_clean}: within 2 sigma',
          ' '.join(f'{f:.4f}' for f in fractions))
    assert all(0.92 <= f <= 0.98 for f in fractions), fractions
    assert 0.94 <= np.mean(fractions) <= 0.97  # Gaussian: 95.45 %


def test_sigma_that_is_too_small_fails_the_coverage():
    """The coverage check can fail: the same data with the sensor-noise term halved."""
    rng = np.random.default_rng(3)
    interference = random_interference(rng, k_scale=0.01, b_scale_t=300e-9)
    calibration = _calibrate(simulate(_scenario(TRIM, interference), rng), False)
    survey = simulate(_scenario(SURVEY, interference, (TARGET,)), np.random.default_rng(99))
    g = compensate_fields(survey.fields_measured, calibration.parameters, GEOMETRY)
    sigma = compensated_sigma(survey.fields_measured[:, 0], GEOMETRY, NOISE_T / 2, calibration.parameters,
                              calibration.covariance)
    assert np.mean(np.abs(g - survey.g_true) <= 2 * sigma) < 0.8


@pytest.mark.parametrize('n_parameters', [27, 36])
def test_sigma_model_equals_the_design_written_out(n_parameters):
    """SigmaModel's quadratic form against diag(A_n C A_n^T) + noise with A_n from
    interference_design at every sample, and its one-sample path against the vectorized one."""
    rng = np.random.default_rng(7)
    symmetric = n_parameters == 27
    k = rng.uniform(-0.02, 0.02, (3, 3, 3))
    parameters = InterferenceParameters(0.5 * (k + np.swapaxes(k, 1, 2)) if symmetric else k,
                                        rng.uniform(-3e-7, 3e-7, (3, 3)))
    root = rng.normal(size=(n_parameters, n_parameters))
    scale = np.r_[np.full(n_parameters - 9, 1e-5), np.full(9, 1e-10)]
    covariance = root @ root.T * np.outer(scale, scale)
    b_reference = rng.normal(0, 4e-5, (50, 3))
    design = interference_design(b_reference, GEOMETRY, symmetric=symmetric)
    expected = np.sqrt(np.einsum('nqp,pr,nqr->nq', design, covariance, design).reshape(-1, 3, 3)
                       + noise_sigma(GEOMETRY, NOISE_T, parameters) ** 2)
    model = SigmaModel.build(GEOMETRY, NOISE_T, parameters, covariance)
    np.testing.assert_allclose(model(b_reference), expected, rtol=1e-10)
    np.testing.assert_allclose(model.one(b_reference[4]), expected[4], rtol=1e-10)
    assert not model.form.flags.writeable
    raw = SigmaModel.build(GEOMETRY, NOISE_T)
    np.testing.assert_allclose(raw(b_reference), np.broadcast_to(noise_sigma(GEOMETRY, NOISE_T), (50, 3, 3)))
