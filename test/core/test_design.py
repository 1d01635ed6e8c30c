"""core/design.py: the design matrices against eq. 18 and eq. 20 written out here from the
sensor positions (D = (k B_1' + b) a^-1; the asymmetries and the trace of D)."""
import numpy as np

from tetra_gradiometer.core import InterferenceParameters, TetraGeometry, interference_tensor
from tetra_gradiometer.core.design import constraint_design, constraint_residual, interference_design

GEOMETRY = TetraGeometry.regular(0.5)


def _eq_18(b_ref, k, h):
    """D_n = (K_21 B + b_2, K_31 B + b_3, K_41 B + b_4) a^-1, a = (r_2 - r_1, r_3 - r_1, r_4 - r_1)."""
    positions = np.array(GEOMETRY.positions)
    a_inv = np.linalg.inv((positions[1:] - positions[0]).T)
    return np.array([np.column_stack([k[i] @ b + h[i] for i in range(3)]) @ a_inv for b in b_ref])


def _eq_20(d):
    """D12 - D21, D13 - D31, D23 - D32, trace, per sample."""
    return np.stack([d[:, 0, 1] - d[:, 1, 0], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 2] - d[:, 2, 1],
                     np.trace(d, axis1=1, axis2=2)], axis=1)


def _parameters(rng, symmetric):
    k = rng.normal(0, 1e-2, (3, 3, 3))
    if symmetric:
        k = 0.5 * (k + np.swapaxes(k, 1, 2))
    return InterferenceParameters(k, rng.normal(0, 1e-7, (3, 3)))


def test_design_matrix_reproduces_eq_18():
    rng = np.random.default_rng(1)
    b_ref = rng.normal(0, 5e-5, (7, 3))
    for symmetric in (True, False):
        pairs = _parameters(rng, symmetric)
        truth = _eq_18(b_ref, pairs.k_soft, pairs.b_hard)
        assert np.abs(truth).max() > 1e-8
        design = interference_design(b_ref, GEOMETRY, symmetric=symmetric)
        assert design.shape == (7, 9, 27 if symmetric else 36)
        theta = pairs.to_vector(symmetric=symmetric)
        np.testing.assert_allclose(design @ theta, truth.reshape(7, 9), rtol=1e-12, atol=1e-20)
        np.testing.assert_allclose(interference_tensor(b_ref, pairs, GEOMETRY), truth, rtol=1e-12, atol=1e-20)


def test_constraint_design_gives_the_asymmetries_and_trace_of_d():
    rng = np.random.default_rng(2)
    b_ref = rng.normal(0, 5e-5, (20, 3))
    for symmetric in (True, False):
        pairs = _parameters(rng, symmetric)
        truth = _eq_20(_eq_18(b_ref, pairs.k_soft, pairs.b_hard))
        design = constraint_design(b_ref, GEOMETRY, symmetric=symmetric)
        assert design.shape == (20, 4, 27 if symmetric else 36)
        np.testing.assert_allclose(design @ pairs.to_vector(symmetric=symmetric), truth, rtol=1e-12,
                                   atol=1e-20)


def test_constraint_residual_by_hand():
    g = np.array([[[1.0, 2.0, 3.0], [5.0, 7.0, 11.0], [13.0, 17.0, 19.0]]])
    np.testing.assert_array_equal(constraint_residual(g), [[2.0 - 5.0, 3.0 - 13.0, 11.0 - 17.0, 27.0]])
    symmetric_traceless = np.array([[[1.0, 2.0, 3.0], [2.0, -4.0, 5.0], [3.0, 5.0, 3.0]]])
    np.testing.assert_array_equal(constraint_residual(symmetric_traceless), [[0.0, 0.0, 0.0, 0.0]])
