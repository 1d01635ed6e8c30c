"""core/identification/paper_ga.py: the genetic algorithm against its own objective written
out (eq. 21) and against random search within the bounds of eq. 23."""
import time

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


def _ga_data():
    rng = np.random.default_rng(8)
    measured = trim_data(rng, make_interference(rng), n=30, noise=0.1e-9)
    return difference_tensor(measured, GEOMETRY), measured[:, 0]


def test_paper_ga_without_a_budget_reached_draws_and_returns_exactly_the_same():
    g_m, b = _ga_data()
    plain = paper_ga(g_m, b, GEOMETRY, rng=np.random.default_rng(1), generations=200)
    budgeted = paper_ga(g_m, b, GEOMETRY, rng=np.random.default_rng(1), generations=200,
                        deadline=time.monotonic() + 600.0, should_stop=lambda: False)
    np.testing.assert_array_equal(plain.parameters.to_vector(symmetric=True), budgeted.parameters.to_vector(symmetric=True))
    assert plain.details == budgeted.details
    assert plain.details['generations'] == 200 and 'stopped' not in plain.details


def test_paper_ga_stops_at_its_deadline_and_on_should_stop_with_its_best_so_far():
    g_m, b = _ga_data()
    started = time.monotonic()
    timed = paper_ga(g_m, b, GEOMETRY, rng=np.random.default_rng(1), generations=20000,
                     deadline=started + 0.2)
    assert time.monotonic() - started < 1.0
    assert timed.details['stopped'] == 'deadline' and timed.details['generations_requested'] == 20000
    assert 0 < timed.details['generations'] < 20000
    assert timed.details['objective_final'] <= timed.details['objective_initial']

    calls = []
    stopped = paper_ga(g_m, b, GEOMETRY, rng=np.random.default_rng(1), generations=20000,
                       should_stop=lambda: calls.append(1) or len(calls) > 50)
    assert stopped.details['stopped'] == 'should_stop' and stopped.details['generations'] == 50
    # The first 50 generations are those of an unbudgeted 50-generation run.
    fifty = paper_ga(g_m, b, GEOMETRY, rng=np.random.default_rng(1), generations=50)
    np.testing.assert_array_equal(stopped.parameters.to_vector(symmetric=True), fifty.parameters.to_vector(symmetric=True))


def test_identify_passes_the_budget_of_its_options_to_paper_ga():
    from tetra_gradiometer.core.identification import Options, identify
    g_m, b = _ga_data()
    result = identify('paper_ga', g_m, b, GEOMETRY,
                      Options(rng=np.random.default_rng(1), generations=20000, should_stop=lambda: True))
    assert result.details['stopped'] == 'should_stop' and result.details['generations'] == 0
    result = identify('paper_ga', g_m, b, GEOMETRY,
                      Options(rng=np.random.default_rng(1), generations=20000, deadline_s=time.monotonic()))
    assert result.details['stopped'] == 'deadline'
