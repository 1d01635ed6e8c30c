"""Targets modelled as dipoles (issue 31): with the track (/odom position) and the
geometry, a target passed close to the track is fitted as a point dipole in the base model
instead of excluded; its position is checked against the simulator's truth, and the effects
named are exactly the hidden ones."""

import numpy as np
import pytest

from tetra_gradiometer.core.discrepancy import analyze
from tetra_gradiometer.core.discrepancy.dipoles import Track, unit_fields
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
