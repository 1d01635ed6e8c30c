"""The method registry: one vocabulary for the CLI, the node, the paper and the docs; each
entry solves what it says (truth: the simulator's exact interference parameters)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from tetra_gradiometer.core import (
    Scenario,
    TetraGeometry,
    TrimManoeuvre,
    difference_tensor,
    random_interference,
    simulate,
)
from tetra_gradiometer.core.identification import (
    CALIBRATION_METHODS,
    DEFAULT_METHOD,
    METHODS,
    Options,
    identify,
)
from tetra_gradiometer.errors import CalibrationFileError, IdentifiabilityError, InputError
from tetra_gradiometer.io.calibration import CalibrationFile

REPO = Path(__file__).resolve().parents[3]
GEOMETRY = TetraGeometry.regular(0.5)


@pytest.fixture(scope='module')
def trim():
    """A noise-free trim whose sensor 1 carries its own soft and hard iron."""
    rng = np.random.default_rng(21)
    scenario = Scenario(
        geometry=GEOMETRY,
        earth_field_enu=np.array([1.5e-5, 2.0e-5, -4.2e-5]),
        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9, reference_clean=False),
        segments=(TrimManoeuvre(duration_s=60.0),),
        noise_t=0.0,
    )
    mission = simulate(scenario, rng)
    g = difference_tensor(mission.fields_measured, GEOMETRY)
    return scenario, mission, g, mission.fields_measured[:, 0, :]


def test_the_general_known_gradient_solve_recovers_the_exact_parameters(trim):
    scenario, _, g, b = trim
    exact = scenario.interference.effective_parameters()  # K_i1 (I + K_1)^-1, not symmetric
    result = identify('known_gradient_lstsq_general', g, b, GEOMETRY)
    assert result.method == 'known_gradient_lstsq_general'
    assert result.n_parameters == METHODS['known_gradient_lstsq_general'].n_parameters == 36
    np.testing.assert_allclose(result.parameters.k_soft, exact.k_soft, rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.parameters.b_hard, exact.b_hard, rtol=0, atol=1e-15)


def test_the_symmetric_solve_cannot_represent_a_dirty_reference_sensor(trim):
    scenario, mission, g, b = trim
    result = identify('known_gradient_lstsq', g, b, GEOMETRY)
    assert result.n_parameters == METHODS['known_gradient_lstsq'].n_parameters == 27
    residual = result.compensate_fields(mission.fields_measured, GEOMETRY) - mission.g_true
    assert np.sqrt(np.mean(residual**2)) > 1e-10  # > 0.1 nT/m: the asymmetric part is left


def _asymmetry_and_trace(g):
    return (np.sqrt(np.mean((g - np.swapaxes(g, 1, 2)) ** 2)),
            np.sqrt(np.mean(np.trace(g, axis1=1, axis2=2) ** 2)))


def test_the_constraint_solve_makes_the_tensor_nearly_symmetric_and_traceless(trim):
    # Eqs. 20-22: the objective is the asymmetry and trace of the compensated tensor. With a
    # dirty sensor 1 the 27 symmetric parameters cannot reach zero, but nearly.
    _, mission, g, b = trim
    result = identify('constraint_lstsq', g, b, GEOMETRY)
    before = _asymmetry_and_trace(g)
    after = _asymmetry_and_trace(result.compensate_fields(mission.fields_measured, GEOMETRY))
    assert after[0] < 0.01 * before[0] and after[1] < 0.01 * before[1], (before, after)


def test_paper_ga_needs_a_seeded_generator_and_stays_in_its_bounds(trim):
    _, _, g, b = trim
    with pytest.raises(InputError, match='rng'):
        identify('paper_ga', g, b, GEOMETRY)
    result = identify('paper_ga', g, b, GEOMETRY, Options(rng=np.random.default_rng(0), generations=5))
    assert result.method == 'paper_ga' and result.details['generations'] == 5
    k = result.parameters.k_soft
    assert k.min() >= 0 and k.max() <= 0.01  # eq. 23 as printed


def test_pei_yeo_maps_sensors_onto_the_reference_but_gives_no_calibration_file(trim):
    _, mission, g, b = trim
    with pytest.raises(InputError, match='fields_measured'):
        identify('pei_yeo_2009', g, b, GEOMETRY)
    result = identify('pei_yeo_2009', g, b, GEOMETRY, Options(fields_measured=mission.fields_measured))
    mapped = result.corrected_fields(mission.fields_measured)
    clean_diff = mission.fields_true[:, 1:] - mission.fields_true[:, :1]
    assert np.abs((mapped[:, 1:] - mapped[:, :1]) - clean_diff).max() < 1e-12
    assert 'pei_yeo_2009' not in CALIBRATION_METHODS
    with pytest.raises(CalibrationFileError, match='no k, b'):
        CalibrationFile.from_calibration(result, GEOMETRY)


def test_unknown_methods_and_a_single_field_direction_are_refused_by_name(trim):
    _, _, g, b = trim
    with pytest.raises(InputError, match="unknown method 'simplex'.*known_gradient_lstsq_general"):
        identify('simplex', g, b, GEOMETRY)
    one_direction = np.tile(b[:1], (len(b), 1))
    with pytest.raises(IdentifiabilityError, match='attitude coverage condition number'):
        identify(DEFAULT_METHOD, g, one_direction, GEOMETRY)


def test_every_consumer_reads_the_registry():
    from tetra_gradiometer.cli import calibrate, demo

    for module in (calibrate, demo):
        parser = argparse.ArgumentParser()
        module.add_arguments(parser)
        action = next(a for a in parser._actions if a.dest == 'method')
        assert tuple(action.choices) == CALIBRATION_METHODS and action.default == DEFAULT_METHOD
    from tetra_gradiometer.cli.paper import METHODS as PAPER_METHODS

    assert PAPER_METHODS == tuple(METHODS)
    docs = (REPO / 'docs' / 'architecture.md').read_text() + (REPO / 'README.md').read_text()
    for name in METHODS:
        assert f'`{name}`' in docs, name
