"""core/identification/paper_ga.py: the genetic algorithm against its own objective written
out (eq. 21) and against random search within the bounds of eq. 23."""
import numpy as np
import pytest

from tetra_gradiometer.core import (InterferenceParameters, TetraGeometry,
                                    difference_tensor, paper_bounds, paper_ga)
from interference_helpers import make_interference, trim_data

GEOMETRY = TetraGeometry.regular(0.5)


def test_paper_ga_lowers_the_objective_below_random_search():
    rng = np.random.default_rng(8)
    measured = trim_data(rng, make_interference(rng), n=30, noise=0.1e-9)
    g_m = difference_tensor(measured, GEOMETRY)
    result = paper_ga(g_m, measured[:, 0], GEOMETRY, rng=np.random.default_rng(1), generations=300)
    positions = np.array(GEOMETRY.positions)
    a_inv = np.linalg.inv((positions[1:] - positions[0]).T)  # eq. 6, from the positions

    def objective(theta):
        """Eq. 21 written out: the asymmetries and trace of G_c = G_m - D, D by eq. 18."""
        p = InterferenceParameters.from_vector(theta, symmetric=True)
        columns = np.einsum('irc,nc->nri', p.k_soft, measured[:, 0]) + p.b_hard.T[None]
        g_c = g_m - columns @ a_inv
        values = [g_c[:, 0, 1] - g_c[:, 1, 0], g_c[:, 0, 2] - g_c[:, 2, 0], g_c[:, 1, 2] - g_c[:, 2, 1],
                  np.trace(g_c, axis1=1, axis2=2)]
        return float(sum(np.sum(v**2) for v in values))

    lower, upper = paper_bounds()
    theta = result.parameters.to_vector(symmetric=True)
    assert np.all(theta >= lower) and np.all(theta <= upper)
    random_points = np.random.default_rng(2).uniform(lower, upper, (300, 27))
    assert objective(theta) < min(objective(p) for p in random_points)
    assert objective(theta) == pytest.approx(result.details['objective_final'], rel=1e-6)
    assert result.details['objective_final'] < result.details['objective_initial']
