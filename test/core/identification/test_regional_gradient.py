"""core/identification/lstsq.py: the known-gradient solve jointly with a constant regional
(world-frame) gradient, against truth built here: attitudes from scipy, readings of a linear
field at the four sensors (exact for the difference tensor), eq. 10 interference
(``SensorInterference.apply``) and sensor noise; a dense whitened lstsq written out here."""

import numpy as np
import pytest
from interference_helpers import make_interference
from scipy import stats
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import (
    InterferenceParameters,
    TetraGeometry,
    calibration_residual,
    difference_tensor,
    known_gradient_lstsq,
)
from tetra_gradiometer.core.identification import Options, identify
from tetra_gradiometer.errors import IdentifiabilityError, InputError

GEOMETRY = TetraGeometry.regular(0.5)
B_EARTH = np.array([0.0, 20000e-9, -45000e-9])  # ENU, tesla
NOISE = 0.1e-9  # per sensor axis, tesla
#: A regional gradient of 4 nT/m (Frobenius), symmetric and traceless, ENU.
G_WORLD = np.array([[2.0, 1.0, 0.5], [1.0, 1.0, -1.5], [0.5, -1.5, -3.0]])
G_WORLD = 4e-9 * G_WORLD / np.linalg.norm(G_WORLD)
W = GEOMETRY.a @ (np.eye(3) - np.ones((3, 3)) / 6.0)  # the solver's whitener, written out
#: c = (gxx, gxy, gxz, gyy, gyz), gzz = -gxx - gyy, as the docs state.
REGIONAL_BASIS_BY_HAND = np.array([
    [[1, 0, 0], [0, 0, 0], [0, 0, -1]],
    [[0, 1, 0], [1, 0, 0], [0, 0, 0]],
    [[0, 0, 1], [0, 0, 0], [1, 0, 0]],
    [[0, 0, 0], [0, 1, 0], [0, 0, -1]],
    [[0, 0, 0], [0, 0, 1], [0, 1, 0]],
], dtype=float)


def trim_attitudes(rng, n):
    """A trim manoeuvre's attitudes: heading all round, pitch +-20 deg, roll +-25 deg."""
    euler = np.column_stack(
        [rng.uniform(-180, 180, n), rng.uniform(-20, 20, n), rng.uniform(-25, 25, n)]
    )
    return Rotation.from_euler('ZYX', euler, degrees=True)


def body_gradient(rotation, g_world):
    r = rotation.as_matrix()
    return np.einsum('nai,ab,nbj->nij', r, g_world, r)


def trim_in_gradient(rng, g_world, n=1500, noise=NOISE, clean_reference=True):
    """``(g_measured, b_reference, quaternions, truth theta vector, symmetric)``: a linear
    field ``B(x) = B_1 + G_b (x - p_1)`` read by the four sensors with eq. 10 interference."""
    rotation = trim_attitudes(rng, n)
    background = rotation.inv().apply(B_EARTH)  # R^T B_earth, body frame
    g_body = body_gradient(rotation, g_world)
    offsets = GEOMETRY.positions - GEOMETRY.positions[0]
    fields_true = background[:, None, :] + np.einsum('nij,sj->nsi', g_body, offsets)
    interference = make_interference(rng, clean_reference=clean_reference)
    measured = interference.apply(fields_true, background) + rng.normal(0, noise, (n, 4, 3))
    truth = interference.effective_parameters() if not clean_reference else \
        interference.pair_parameters()
    g_measured = difference_tensor(measured, GEOMETRY)
    return g_measured, measured[:, 0], rotation.as_quat(), truth


@pytest.mark.parametrize('symmetric', [True, False])
def test_regional_gradient_is_recovered_within_three_sigma(symmetric):
    for seed in range(5):
        rng = np.random.default_rng(seed)
        g, b, q, _ = trim_in_gradient(rng, G_WORLD, clean_reference=symmetric)
        fit = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=symmetric, orientation_xyzw=q)
        error = fit.regional_gradient_enu - G_WORLD
        assert np.all(np.abs(error) < 3 * fit.regional_gradient_sigma), (seed, error)
        assert fit.rank == fit.n_parameters  # of the interference parameters; the gradient took 5 more
        # What it reports is a symmetric, traceless tensor in T/m.
        np.testing.assert_allclose(fit.regional_gradient_enu, fit.regional_gradient_enu.T)
        assert abs(np.trace(fit.regional_gradient_enu)) < 1e-12 * np.abs(G_WORLD).max()
        assert fit.details['sensor_noise_nT'] == pytest.approx(NOISE * 1e9, rel=0.05)


def test_reported_sigma_matches_the_scatter_over_seeds():
    errors, sigmas = [], []
    for seed in range(100):
        g, b, q, _ = trim_in_gradient(np.random.default_rng(100 + seed), G_WORLD, n=800)
        fit = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=False, orientation_xyzw=q)
        errors.append(fit.regional_gradient_enu - G_WORLD)
        sigmas.append(fit.regional_gradient_sigma)
    ratio = np.mean(sigmas, axis=0) / np.std(errors, axis=0)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert np.all(np.abs(np.mean(errors, axis=0)) < 4 * np.mean(sigmas, axis=0) / 10)  # no bias


def test_interference_is_recovered_as_well_as_without_a_gradient():
    rng = np.random.default_rng(7)
    g, b, q, truth = trim_in_gradient(rng, G_WORLD, n=2000)
    joint = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q)
    # The same readings without the regional gradient, fitted the old way.
    plain = known_gradient_lstsq(g - body_gradient(Rotation.from_quat(q), G_WORLD), b, GEOMETRY)
    assert joint.covariance.shape == plain.covariance.shape == (27, 27)
    truth_vector = truth.to_vector(symmetric=True)
    for fit in (joint, plain):
        error = fit.parameters.to_vector(symmetric=True) - truth_vector
        chi2 = error @ np.linalg.solve(fit.covariance, error)
        assert stats.chi2.ppf(0.001, 27) < chi2 < stats.chi2.ppf(0.999, 27)
    inflation = joint.standard_errors / plain.standard_errors
    assert np.median(inflation) < 1.2 and inflation.max() < 2.0, inflation


def test_without_orientation_a_regional_gradient_biases_the_fit():
    rng = np.random.default_rng(8)
    g, b, q, truth = trim_in_gradient(rng, G_WORLD, n=2000)
    truth_vector = truth.to_vector(symmetric=True)
    chi2 = {}
    for name, orientation in (('old', None), ('joint', q)):
        fit = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=orientation)
        error = fit.parameters.to_vector(symmetric=True) - truth_vector
        chi2[name] = error @ np.linalg.solve(fit.covariance, error)
        if orientation is None:
            # The unmodelled gradient also passes for sensor noise several times too large.
            assert fit.details['sensor_noise_nT'] > 2 * NOISE * 1e9
            assert fit.regional_gradient_enu is None
    assert chi2['old'] > 10 * stats.chi2.ppf(0.999, 27) > chi2['joint']


def test_joint_solve_equals_a_dense_whitened_lstsq():
    """Across several TSQR chunks (4500 samples), against the 9N x 41 problem written out."""
    rng = np.random.default_rng(9)
    n = 4500
    g, b, q, _ = trim_in_gradient(rng, G_WORLD, n=n, clean_reference=False)
    fit = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=False, orientation_xyzw=q)
    # Columns: D of each unit parameter (eq. 18 by hand), then R^T E_k R for the 5 basis tensors.
    columns = []
    for p in range(36):
        unit = InterferenceParameters.from_vector(np.eye(36)[p], symmetric=False)
        k_part = np.einsum('irc,nc->nri', unit.k_soft, b)  # column i: K_i1 B_1' + B_i1^h
        columns.append((k_part + unit.b_hard.T[None]) @ GEOMETRY.a_inv)
    for e in REGIONAL_BASIS_BY_HAND:
        columns.append(body_gradient(Rotation.from_quat(q), e))
    design = np.stack([(c @ W).reshape(-1) for c in columns], axis=1)
    scale = np.linalg.norm(design, axis=0)
    x, *_ = np.linalg.lstsq(design / scale, (g @ W).reshape(-1), rcond=None)
    x /= scale
    np.testing.assert_allclose(fit.parameters.to_vector(symmetric=False), x[:36],
                               rtol=1e-7, atol=1e-9 * np.abs(x[:36]).max())
    entries = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2)]
    coefficients = [fit.regional_gradient_enu[i, j] for i, j in entries]
    np.testing.assert_allclose(coefficients, x[36:], rtol=1e-7, atol=1e-15)
    residual = (g @ W).reshape(-1) - design @ x
    sigma2 = residual @ residual / (residual.size - 41)
    covariance = sigma2 * np.linalg.inv(design.T @ design)
    np.testing.assert_allclose(fit.covariance, covariance[:36, :36], rtol=1e-5, atol=0)
    np.testing.assert_allclose(np.sqrt(covariance[36, 36]), fit.regional_gradient_sigma[0, 0],
                               rtol=1e-5)


def test_compensation_leaves_the_regional_gradient_and_the_residual_removes_it():
    rng = np.random.default_rng(10)
    g, b, q, _ = trim_in_gradient(rng, G_WORLD, n=1000, noise=0.0)
    fit = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q)
    np.testing.assert_allclose(fit.regional_gradient_enu, G_WORLD, atol=1e-15)
    expected_body = body_gradient(Rotation.from_quat(q), G_WORLD)
    # calibration_residual: G_m - D - R^T G_w R, here zero; without orientation it is the
    # compensated tensor, which keeps the regional gradient (it is signal).
    with_orientation = calibration_residual(fit, g, b, GEOMETRY, orientation_xyzw=q)
    assert np.abs(with_orientation).max() < 1e-6 * np.abs(G_WORLD).max()
    compensated = calibration_residual(fit, g, b, GEOMETRY)
    np.testing.assert_allclose(compensated, expected_body, atol=1e-6 * np.abs(G_WORLD).max())


def test_summary_gives_the_regional_gradient_in_nT_per_m():
    g, b, q, _ = trim_in_gradient(np.random.default_rng(11), G_WORLD, n=500)
    summary = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q).summary()
    np.testing.assert_allclose(summary['regional_gradient_enu_nT_per_m'], G_WORLD * 1e9, atol=0.1)
    assert np.all(np.array(summary['regional_gradient_sigma_nT_per_m']) > 0)
    assert summary['regional_gradient_norm_nT_per_m'] == pytest.approx(4.0, abs=0.1)
    plain = known_gradient_lstsq(g, b, GEOMETRY).summary()
    assert not any(key.startswith('regional') for key in plain)


def test_registry_passes_orientation_through():
    g, b, q, _ = trim_in_gradient(np.random.default_rng(12), G_WORLD, n=500)
    for method in ('known_gradient_lstsq', 'known_gradient_lstsq_general'):
        result = identify(method, g, b, GEOMETRY, Options(orientation_xyzw=q))
        direct = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=method == 'known_gradient_lstsq',
                                      orientation_xyzw=q)
        np.testing.assert_array_equal(result.regional_gradient_enu, direct.regional_gradient_enu)
        assert identify(method, g, b, GEOMETRY).regional_gradient_enu is None


def test_the_path_without_orientation_is_unchanged():
    """Without orientation: no regional fields, and the same numbers as the 4-pseudo-sample
    solve written out in test_lstsq (here: as the joint solve on gradient-free data, which
    must agree within noise, and as an explicit ``orientation_xyzw=None``)."""
    g, b, q, _ = trim_in_gradient(np.random.default_rng(13), np.zeros((3, 3)), n=1500)
    old = known_gradient_lstsq(g, b, GEOMETRY)
    again = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=None)
    np.testing.assert_array_equal(old.parameters.to_vector(symmetric=True),
                                  again.parameters.to_vector(symmetric=True))
    np.testing.assert_array_equal(old.covariance, again.covariance)
    assert old.regional_gradient_enu is None and old.regional_gradient_sigma is None
    assert set(old.details) == {'attitude_coverage_condition', 'sensor_noise_nT'}
    joint = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q)
    theta = joint.parameters.to_vector(symmetric=True)
    assert np.all(np.abs(theta - old.parameters.to_vector(symmetric=True))
                  < 2 * joint.standard_errors)
    assert np.all(np.abs(joint.regional_gradient_enu) < 4 * joint.regional_gradient_sigma)


def test_refuses_non_finite_or_misshapen_orientation():
    g, b, q, _ = trim_in_gradient(np.random.default_rng(14), G_WORLD, n=200)
    bad = q.copy()
    bad[[5, 17], 2] = np.nan
    with pytest.raises(InputError, match='2 non-finite rows of 200 .first at index 5'):
        known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=bad)
    with pytest.raises(InputError, match=r'shape \(200, 4\)'):
        known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q[:, :3])
    zero = q.copy()
    zero[3] = 0.0
    with pytest.raises(InputError, match='1 zero quaternions'):
        known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=zero)
    with pytest.raises(InputError, match='non-finite rows'):
        calibration_residual(known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q), g, b,
                             GEOMETRY, orientation_xyzw=bad)


def test_refuses_attitudes_that_cannot_separate_the_gradient():
    """Four attitudes only: the general interference model fits any four tensors, so a
    regional gradient is invisible."""
    rng = np.random.default_rng(15)
    rotation = trim_attitudes(rng, 4)
    index = np.repeat(np.arange(4), 50)
    q = rotation.as_quat()[index]
    b = rotation.inv().apply(B_EARTH)[index]
    g = body_gradient(Rotation.from_quat(q), G_WORLD) + rng.normal(0, 1e-10, (200, 3, 3))
    with pytest.raises(IdentifiabilityError, match='cannot separate a regional gradient'):
        known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=False, orientation_xyzw=q)
