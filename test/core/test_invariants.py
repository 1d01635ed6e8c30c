"""core/invariants.py against the eigenvalues (I1 = l1 l2 + l2 l3 + l1 l3, I2 = l1 l2 l3)
and their invariance under rotation; a dipole's tensor has I0 = 0 and -I1 >= 0."""
import numpy as np
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core.invariants import tensor_invariants


def test_invariants_are_the_symmetric_functions_of_the_eigenvalues_and_frame_free():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(50, 3, 3))
    sym = 0.5 * (a + np.swapaxes(a, 1, 2))
    l = np.linalg.eigvalsh(sym)
    expected = np.column_stack([l.sum(1), l[:, 0] * l[:, 1] + l[:, 1] * l[:, 2] + l[:, 0] * l[:, 2], l.prod(1)])
    np.testing.assert_allclose(tensor_invariants(a), expected, atol=1e-12)
    r = Rotation.random(50, random_state=4).as_matrix()
    rotated = np.einsum('nij,njk,nlk->nil', r, a, r)
    np.testing.assert_allclose(tensor_invariants(rotated), expected, atol=1e-12)
    np.testing.assert_allclose(tensor_invariants(3.0 * a), expected * [3.0, 9.0, 27.0], atol=1e-10)


def test_a_dipole_gradient_has_zero_trace_and_negative_i1():
    m = np.array([1.0, -2.0, 0.5])
    r = np.array([3.0, 1.0, -2.0])
    d = np.linalg.norm(r)
    rhat = r / d
    # grad of B = 3 (m.r) r / d^5 - m / d^3, up to mu0/4pi
    g = 3 / d**4 * (np.outer(m, rhat) + np.outer(rhat, m) + (m @ rhat) * (np.eye(3) - 5 * np.outer(rhat, rhat)))
    i0, i1, i2 = tensor_invariants(g[None])[0]
    assert abs(i0) < 1e-12 * np.abs(g).max() and i1 < 0
    assert (i2 / 2) ** 2 <= (-i1 / 3) ** 3 * (1 + 1e-9)
