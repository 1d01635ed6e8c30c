"""Interference model, compensation and identification against model-generated truth."""
import numpy as np
import pytest
from scipy import stats

from tetra_gradiometer.core import (IdentifiabilityError, InterferenceParameters, SensorInterference,
                                    TetraGeometry, constraint_lstsq, difference_tensor,
                                    interference_tensor, known_gradient_lstsq, paper_bounds, paper_ga,
                                    pei_yeo_2009)
from tetra_gradiometer.core.design import constraint_design, interference_design
from tetra_gradiometer.core.identification import constraint_objective
from tetra_gradiometer.core.model import compensate_fields

GEOMETRY = TetraGeometry.regular(0.5)


def _symmetric(rng, scale, n):
    k = rng.uniform(-scale, scale, (n, 3, 3))
    return 0.5 * (k + np.swapaxes(k, 1, 2))


def _interference(rng, *, clean_reference=True):
    k = _symmetric(rng, 5e-3, 4)
    b = rng.uniform(-150e-9, 150e-9, (4, 3))
    if clean_reference:
        k[0], b[0] = 0.0, 0.0
    return SensorInterference(k, b)


def _uniform_field_attitudes(rng, n, magnitude=5e-5):
    """Body-frame readings of a uniform field under random attitudes (a trim manoeuvre)."""
    directions = rng.normal(size=(n, 3))
    return magnitude * directions / np.linalg.norm(directions, axis=1)[:, None]


def _trim_data(rng, interference, n=400, noise=0.0):
    background = _uniform_field_attitudes(rng, n)
    fields_true = np.repeat(background[:, None, :], 4, axis=1)
    measured = interference.apply(fields_true, background) + rng.normal(0, noise, (n, 4, 3)) if noise else \
        interference.apply(fields_true, background)
    return measured


def test_parameter_vector_round_trip():
    rng = np.random.default_rng(0)
    pairs = _interference(rng).pair_parameters()
    for symmetric in (True, False):
        theta = pairs.to_vector(symmetric=symmetric)
        assert theta.shape == ((27,) if symmetric else (36,))
        back = InterferenceParameters.from_vector(theta, symmetric=symmetric)
        np.testing.assert_array_equal(back.k_soft, pairs.k_soft)
        np.testing.assert_array_equal(back.b_hard, pairs.b_hard)


def test_symmetric_packing_refuses_an_asymmetric_k():
    k = np.zeros((3, 3, 3))
    k[0, 0, 1] = 1e-3
    with pytest.raises(ValueError, match='not symmetric'):
        InterferenceParameters(k, np.zeros((3, 3))).to_vector(symmetric=True)


def test_design_matrix_reproduces_the_interference_tensor():
    rng = np.random.default_rng(1)
    b_ref = rng.normal(0, 5e-5, (7, 3))
    for symmetric, pairs in ((True, _interference(rng).pair_parameters()),
                             (False, InterferenceParameters(rng.normal(0, 1e-2, (3, 3, 3)),
                                                            rng.normal(0, 1e-7, (3, 3))))):
        design = interference_design(b_ref, GEOMETRY, symmetric=symmetric)
        expected = interference_tensor(b_ref, pairs, GEOMETRY).reshape(7, 9)
        np.testing.assert_allclose(design @ pairs.to_vector(symmetric=symmetric), expected, rtol=1e-12,
                                   atol=1e-20)


def test_compensation_with_true_parameters_recovers_the_true_difference_tensor():
    rng = np.random.default_rng(2)
    n = 50
    # A non-uniform true field: uniform background plus a linear gradient across the array.
    gradient = _symmetric(rng, 1e-7, n)
    gradient -= np.trace(gradient, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3
    background = _uniform_field_attitudes(rng, n)
    fields_true = background[:, None, :] + np.einsum('nij,sj->nsi', gradient, GEOMETRY.positions)
    g_true = difference_tensor(fields_true, GEOMETRY)
    for clean in (True, False):
        interference = _interference(rng, clean_reference=clean)
        measured = interference.apply(fields_true, fields_true[:, 0, :])
        g_c = compensate_fields(measured, interference.effective_parameters(), GEOMETRY)
        np.testing.assert_allclose(g_c, g_true, atol=1e-9 * np.abs(g_true).max())
        g_m = difference_tensor(measured, GEOMETRY)
        assert np.abs(g_m - g_true).max() > 1e3 * np.abs(g_c - g_true).max()


def test_known_gradient_lstsq_recovers_parameters_within_stated_covariance():
    rng = np.random.default_rng(3)
    noise = 0.1e-9
    interference = _interference(rng)
    measured = _trim_data(rng, interference, n=600, noise=noise)
    g_m = difference_tensor(measured, GEOMETRY)
    calibration = known_gradient_lstsq(g_m, measured[:, 0], GEOMETRY, symmetric_k=True)
    truth = interference.pair_parameters().to_vector(symmetric=True)
    error = calibration.parameters.to_vector(symmetric=True) - truth
    chi2 = error @ np.linalg.solve(calibration.covariance, error)
    assert calibration.rank == 27
    # chi-square with 27 degrees of freedom: inside its central 99.8 %.
    assert stats.chi2.ppf(0.001, 27) < chi2 < stats.chi2.ppf(0.999, 27)
    assert np.all(np.abs(error) < 5 * calibration.standard_errors)
    assert calibration.details['sensor_noise_nT'] == pytest.approx(noise * 1e9, rel=0.1)


def test_general_model_is_exact_when_sensor_one_is_not_clean():
    rng = np.random.default_rng(4)
    interference = _interference(rng, clean_reference=False)
    measured = _trim_data(rng, interference, n=300)
    g_m = difference_tensor(measured, GEOMETRY)
    general = known_gradient_lstsq(g_m, measured[:, 0], GEOMETRY, symmetric_k=False)
    effective = interference.effective_parameters()
    np.testing.assert_allclose(general.parameters.k_soft, effective.k_soft, atol=1e-9)
    np.testing.assert_allclose(general.parameters.b_hard, effective.b_hard, atol=1e-15)
    symmetric = known_gradient_lstsq(g_m, measured[:, 0], GEOMETRY, symmetric_k=True)
    assert symmetric.residual_rms > 1e3 * max(general.residual_rms, 1e-18)


def test_known_gradient_refuses_a_single_field_direction():
    rng = np.random.default_rng(5)
    background = np.tile([2e-5, 0.0, -4.5e-5], (100, 1)) + rng.normal(0, 1e-12, (100, 3))
    fields = np.repeat(background[:, None, :], 4, axis=1)
    with pytest.raises(IdentifiabilityError, match='condition number'):
        known_gradient_lstsq(difference_tensor(fields, GEOMETRY), background, GEOMETRY)
    with pytest.raises(IdentifiabilityError, match='too few'):
        known_gradient_lstsq(difference_tensor(fields[:3], GEOMETRY), background[:3], GEOMETRY)


def test_constraint_objective_cannot_see_the_symmetric_traceless_part():
    rng = np.random.default_rng(6)
    interference = _interference(rng)
    measured = _trim_data(rng, interference, n=200)
    g_m = difference_tensor(measured, GEOMETRY)
    calibration = constraint_lstsq(g_m, measured[:, 0], GEOMETRY)
    assert calibration.rank <= 15 and calibration.null_space_dim >= 12
    # Its null space really is invisible: D of a null vector is symmetric and traceless.
    design, _ = constraint_objective(g_m, measured[:, 0], GEOMETRY)
    _, s, vt = np.linalg.svd(design / np.linalg.norm(design, axis=0), full_matrices=True)
    null = vt[calibration.rank:] / np.linalg.norm(design, axis=0)
    d = interference_tensor(measured[:, 0], InterferenceParameters.from_vector(null[0], symmetric=True), GEOMETRY)
    assert np.abs(d - np.swapaxes(d, 1, 2)).max() < 1e-9 * np.abs(d).max()
    assert np.abs(np.trace(d, axis1=1, axis2=2)).max() < 1e-9 * np.abs(d).max()
    # It fits the symmetry/trace equations exactly, yet leaves interference behind.
    assert calibration.residual_rms < 1e-12 * np.abs(g_m).max()
    g_c = calibration.compensate_fields(measured, GEOMETRY)
    assert np.sqrt(np.mean(g_c**2)) > 0.1 * np.sqrt(np.mean(g_m**2))


def test_constraint_lstsq_respects_bounds():
    rng = np.random.default_rng(7)
    measured = _trim_data(rng, _interference(rng), n=100)
    lower, upper = paper_bounds()
    calibration = constraint_lstsq(difference_tensor(measured, GEOMETRY), measured[:, 0], GEOMETRY,
                                   bounds=(lower, upper))
    theta = calibration.parameters.to_vector(symmetric=True)
    assert np.all(theta >= lower - 1e-15) and np.all(theta <= upper + 1e-15)


def test_paper_ga_lowers_the_objective_below_random_search():
    rng = np.random.default_rng(8)
    measured = _trim_data(rng, _interference(rng), n=30, noise=0.1e-9)
    g_m = difference_tensor(measured, GEOMETRY)
    result = paper_ga(g_m, measured[:, 0], GEOMETRY, rng=np.random.default_rng(1), generations=300)
    design, target = constraint_objective(g_m, measured[:, 0], GEOMETRY)

    def objective(theta):
        residual = design @ theta - target
        return residual @ residual

    lower, upper = paper_bounds()
    theta = result.parameters.to_vector(symmetric=True)
    assert np.all(theta >= lower) and np.all(theta <= upper)
    random_points = np.random.default_rng(2).uniform(lower, upper, (300, 27))
    assert objective(theta) < min(objective(p) for p in random_points)
    assert objective(theta) == pytest.approx(result.details['objective_final'], rel=1e-6)
    assert result.details['objective_final'] < result.details['objective_initial']


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


def test_nan_and_wrong_shapes_raise_clear_errors():
    good = np.zeros((20, 3, 3))
    b_ref = np.ones((20, 3)) * 1e-5
    with pytest.raises(ValueError, match='g_measured has a non-finite value at index'):
        bad = good.copy()
        bad[4, 1, 2] = np.nan
        known_gradient_lstsq(bad, b_ref, GEOMETRY)
    with pytest.raises(ValueError, match=r'b_reference must have shape \(N, 3\)'):
        constraint_lstsq(good, np.ones((20, 4)), GEOMETRY)
    with pytest.raises(ValueError, match='sample counts differ'):
        known_gradient_lstsq(good, b_ref[:10], GEOMETRY)
    with pytest.raises(ValueError, match=r'parameter vector must have shape \(27,\)'):
        InterferenceParameters.from_vector(np.zeros(26), symmetric=True)
    assert constraint_design(b_ref, GEOMETRY, symmetric=True).shape == (20, 4, 27)
