"""core/model.py: the interference model, its parameter vector and compensation against
model-generated truth."""
import numpy as np
import pytest

from tetra_gradiometer.core import InterferenceParameters, TetraGeometry, difference_tensor
from tetra_gradiometer.core.model import compensate_fields
from interference_helpers import make_interference, random_symmetric, uniform_field_attitudes

GEOMETRY = TetraGeometry.regular(0.5)


def test_parameter_vector_round_trip():
    rng = np.random.default_rng(0)
    pairs = make_interference(rng).pair_parameters()
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


def test_compensation_with_the_exact_parameters_recovers_the_true_gradient():
    rng = np.random.default_rng(2)
    n = 50
    # A non-uniform true field: uniform background plus a linear gradient across the array.
    gradient = random_symmetric(rng, 1e-7, n)
    gradient -= np.trace(gradient, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3
    background = uniform_field_attitudes(rng, n)
    fields_true = background[:, None, :] + np.einsum('nij,sj->nsi', gradient, GEOMETRY.positions)
    g_true = gradient  # exact for a linear field (eq. 7 has no truncation error then)
    for clean in (True, False):
        interference = make_interference(rng, clean_reference=clean)
        k, h = np.array(interference.k_soft), np.array(interference.b_hard)
        # Eq. 10 written out: B_i' = B_i + K_i B^b + B_i^h, B^b the clean field at sensor 1.
        measured = fields_true + np.einsum('sij,nj->nsi', k, fields_true[:, 0, :]) + h[None]
        np.testing.assert_allclose(interference.apply(fields_true, fields_true[:, 0, :]), measured, rtol=1e-15,
                                   atol=1e-20)
        # Eq. 14 by hand: B^b = (I + K_1)^-1 (B_1' - B_1^h), so K_i1 -> (K_i - K_1)(I + K_1)^-1.
        effective = interference.effective_parameters()
        k_exact = (k[1:] - k[0]) @ np.linalg.inv(np.eye(3) + k[0])
        np.testing.assert_allclose(effective.k_soft, k_exact, rtol=1e-12, atol=1e-18)
        np.testing.assert_allclose(effective.b_hard, (h[1:] - h[0]) - k_exact @ h[0], rtol=1e-12, atol=1e-24)
        g_c = compensate_fields(measured, effective, GEOMETRY)
        np.testing.assert_allclose(g_c, g_true, atol=1e-9 * np.abs(g_true).max())
        g_m = difference_tensor(measured, GEOMETRY)
        assert np.abs(g_m - g_true).max() > 1e3 * np.abs(g_c - g_true).max()


def test_a_parameter_vector_of_the_wrong_length_is_refused():
    with pytest.raises(ValueError, match=r'parameter vector must have shape \(27,\)'):
        InterferenceParameters.from_vector(np.zeros(26), symmetric=True)
