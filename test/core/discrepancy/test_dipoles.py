"""Targets modelled as dipoles: with the track (/odom position) and the
geometry, a target passed close to the track is fitted as a point dipole in the base model
instead of excluded; its position is checked against the simulator's truth, and the effects
named are exactly the hidden ones."""

import numpy as np
import pytest

from tetra_gradiometer.core.discrepancy import analyze
from tetra_gradiometer.core.discrepancy.dipoles import Track, _grid_costs, unit_fields
from tetra_gradiometer.core.discrepancy.synthetic import make_case
from tetra_gradiometer.core.fields import dipole_field
from tetra_gradiometer.core.geometry import TetraGeometry
from tetra_gradiometer.core.targets import sensor_points


def test_unit_fields_are_the_dipole_field_in_the_body_frame():
    # Independent truth: core.fields.dipole_field at each sensor, rotated to the body.
    rng = np.random.default_rng(5)
    geometry = TetraGeometry.regular(0.5)
    n = 7
    angles = rng.uniform(-np.pi, np.pi, (n, 3))
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_euler('ZYX', angles).as_matrix()
    position = rng.uniform(-50, 50, (n, 3))
    source = np.array([3.0, -20.0, -40.0])
    moment = np.array([2e4, -1e4, 3e4])
    got = np.einsum(
        'nsak,k->nsa', unit_fields(Track(position, rotation, geometry), source), moment
    )
    points = sensor_points(position, rotation, geometry)
    for s in range(4):
        world = dipole_field(points[:, s], moment, source) * 1e9
        body = np.einsum('nji,nj->ni', rotation, world)
        np.testing.assert_allclose(got[:, s], body, rtol=1e-10)


def test_grid_costs_are_the_least_squares_residual_of_each_source():
    # Independent truth: numpy's lstsq of the centred data on the dipole's field and a
    # constant per channel, one source at a time; the batched normal equations must agree.
    rng = np.random.default_rng(8)
    geometry = TetraGeometry.regular(0.5)
    n = 40
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_euler('ZYX', rng.uniform(-np.pi, np.pi, (n, 3))).as_matrix()
    position = np.column_stack([np.linspace(-30, 30, n), np.zeros(n), np.full(n, -40.0)])
    track = Track(position, rotation, geometry)
    true = unit_fields(track, np.array([5.0, 12.0, -70.0])) @ np.array([2e4, -1e4, 3e4])
    data = true + rng.normal(0.0, 0.05, true.shape)
    for sensors in [(0, 1, 2, 3), (1, 2, 3)]:
        view = data if len(sensors) == 4 else data[:, 1:] - data[:, :1]
        y = view.reshape(n, -1)
        y = (y - y.mean(axis=0)).reshape(-1)
        sources = rng.uniform([-40, -40, -90], [40, 40, -50], (9, 3))
        got = _grid_costs(track, sensors, y, sources)
        for source, cost in zip(sources, got, strict=True):
            f = unit_fields(track, source)
            f = f if len(sensors) == 4 else f[:, 1:] - f[:, :1]
            a = f.reshape(n, -1, 3)
            a = (a - a.mean(axis=0)).reshape(-1, 3)
            coef = np.linalg.lstsq(a, y, rcond=None)[0]
            np.testing.assert_allclose(cost, np.sum((y - a @ coef) ** 2), rtol=1e-7)


@pytest.fixture(scope='module', params=[(), ('eddy_current',)], ids=['clean', 'eddy'])
def analysed(request):
    effects = request.param
    case = make_case(41 if effects else 40, effects, duration_s=150.0, near_target=True)
    report = analyze(
        case.recording(), case.scenario.geometry, case.scenario.earth_field_enu, keep_series=False
    )
    return case, effects, report


def test_the_target_is_modelled_and_only_the_hidden_effect_named(analysed):
    case, effects, report = analysed
    assert report.named_effects == list(effects), (report.named_effects, report.notes)
    truth = case.scenario.dipoles[-1].position
    assert len(report.targets) >= 1
    errors = [np.linalg.norm(np.array(t['position_m']) - truth) for t in report.targets]
    assert min(errors) < 0.5, report.targets
    assert report.excluded_fraction == 0.0 and report.excluded_spans == []
    assert report.gap_final_nT <= 1.2 * report.noise_floor_nT
    assert report.adequate


def test_without_odom_position_the_workflow_falls_back_to_exclusion():
    case = make_case(40, (), duration_s=150.0, near_target=True)
    report = analyze(case.recording(), None, case.scenario.earth_field_enu, keep_series=False)
    assert report.targets == []
    assert any('cannot be fitted as dipoles' in note for note in report.notes)
    assert report.excluded_spans
