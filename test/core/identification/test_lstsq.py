"""core/identification/lstsq.py: the exact linear solvers against model-generated truth
(parameters within their stated covariance, exact recovery, a dense lstsq written out here,
the null space the paper's objective cannot see)."""
import numpy as np
import pytest
from scipy import stats
from scipy.linalg import block_diag

from tetra_gradiometer.core import (IdentifiabilityError, InterferenceParameters, TetraGeometry, constraint_lstsq, difference_tensor,
                                    interference_tensor, known_gradient_lstsq, paper_bounds)
from tetra_gradiometer.core.identification import constraint_objective
from tetra_gradiometer.core.model import SYMMETRIC_EXPANSION
from interference_helpers import make_interference, trim_data

GEOMETRY = TetraGeometry.regular(0.5)
EDGE_M = 0.5


def test_known_gradient_lstsq_recovers_parameters_within_stated_covariance():
    rng = np.random.default_rng(3)
    noise = 0.1e-9
    interference = make_interference(rng)
    measured = trim_data(rng, interference, n=600, noise=noise)
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
    interference = make_interference(rng, clean_reference=False)
    measured = trim_data(rng, interference, n=300)
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
    interference = make_interference(rng)
    measured = trim_data(rng, interference, n=200)
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
    measured = trim_data(rng, make_interference(rng), n=100)
    lower, upper = paper_bounds()
    calibration = constraint_lstsq(difference_tensor(measured, GEOMETRY), measured[:, 0], GEOMETRY,
                                   bounds=(lower, upper))
    theta = calibration.parameters.to_vector(symmetric=True)
    assert np.all(theta >= lower - 1e-15) and np.all(theta <= upper + 1e-15)


@pytest.mark.parametrize('symmetric', [True, False])
def test_fast_known_gradient_solve_equals_a_dense_least_squares(symmetric):
    """The QR-reduced solver against a plain numpy lstsq on the full 9N x P design (eq. 18
    written out here), on data generated with the symmetric model itself, for the 27- and
    36-parameter reductions. (The whitening does not move the point estimate: every pair has
    the same regressors, so GLS equals OLS; the covariance it yields is checked by the
    chi-square test above.)"""
    rng = np.random.default_rng(11)
    geometry = TetraGeometry.regular(EDGE_M)
    n = 300
    b_ref = rng.normal(size=(n, 3)) * 5e-5
    k = rng.uniform(-0.01, 0.01, (3, 3, 3))
    k = 0.5 * (k + np.swapaxes(k, 1, 2))
    h = rng.uniform(-50e-9, 50e-9, (3, 3))
    g = np.einsum('irc,nc->nri', k, b_ref) + h.T[None]
    g = g @ geometry.a_inv + rng.normal(size=(n, 3, 3)) * 1e-10
    fast = known_gradient_lstsq(g, b_ref, geometry, symmetric_k=symmetric)
    # Dense: unknowns K_i[r, c] (27) and h_i[r] (9); rows (n, r, j); whiten as the solver does.
    w = geometry.a @ (np.eye(3) - np.ones((3, 3)) / 6.0)
    design = np.zeros((n, 3, 3, 36))
    for i in range(3):
        for r in range(3):
            for c in range(3):
                design[:, r, :, 9 * i + 3 * r + c] = b_ref[:, c, None] * geometry.a_inv[i][None, :]
            design[:, r, :, 27 + 3 * i + r] = geometry.a_inv[i][None, :]
    if symmetric:  # K_i[r, c] = K_i[c, r]: 6 unknowns per pair
        design = design @ block_diag(SYMMETRIC_EXPANSION, SYMMETRIC_EXPANSION, SYMMETRIC_EXPANSION, np.eye(9))
    n_par = design.shape[-1]
    design_w = np.einsum('nrjp,jk->nrkp', design, w).reshape(-1, n_par)
    scale = np.linalg.norm(design_w, axis=0)
    theta, *_ = np.linalg.lstsq(design_w / scale, (g @ w).reshape(-1), rcond=None)
    theta /= scale
    got = fast.parameters.to_vector(symmetric=symmetric)
    assert np.abs(got - theta).max() <= 1e-9 * np.abs(theta).max()
    assert fast.rank == n_par
    np.testing.assert_allclose(fast.parameters.k_soft, k, atol=1e-4)


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
