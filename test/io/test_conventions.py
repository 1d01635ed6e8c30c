"""The array's conventions from its own data (core/conventions.py): a sensor mounted turned or
mirrored is named by ``calibrate`` instead of fitted around; positions listed in another order
or a frame other than the readings' are named from the compensated tensor's symmetry.

Truth: the simulator's readings turned by a known signed permutation (what a sensor mounted that
way reads), the simulator's noise-free fields of dipole targets (the forward model, not the
tensor code), and geometries whose rows are reordered by hand.
"""
from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import assert_refused, run_cli
from scipy.spatial.transform import Rotation
from stream_faults import GEOMETRY, short_mission, write_bag, write_params

from tetra_gradiometer.core import Scenario, SurveyLine, TetraGeometry, TrimManoeuvre, simulate
from tetra_gradiometer.core.conventions import FRD, relative_axes, tensor_conventions
from tetra_gradiometer.core.geometry import difference_tensor
from tetra_gradiometer.core.simulator import Dipole, random_interference

EARTH = [0.0, 2.0e-5, -4.5e-5]


def _turned(fields, sensor, matrix):
    out = fields.copy()
    out[:, sensor - 1] = out[:, sensor - 1] @ np.asarray(matrix).T
    return out


@pytest.mark.parametrize('sensor, matrix, named', [
    (3, Rotation.from_euler('z', 180, degrees=True).as_matrix(), '(-x, -y, z): turned 180 deg about z'),
    (2, FRD, '(x, -y, -z): turned 180 deg about x (FRD'),
    (4, Rotation.from_euler('y', 90, degrees=True).as_matrix(), 'turned 90 deg about y'),
    (2, np.diag([1.0, 1.0, -1.0]), '(x, y, -z): mirrored'),
])
def test_a_turned_or_mirrored_sensor_is_named_on_a_trim(sensor, matrix, named):
    rng = np.random.default_rng(sensor)
    # A strong vehicle: 5 % soft iron and 2 uT hard iron on every sensor, sensor 1 included.
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH, segments=[TrimManoeuvre(60.0)],
                        interference=random_interference(rng, k_scale=0.05, b_scale_t=2e-6, reference_clean=False))
    fields = simulate(scenario, rng).fields_measured
    assert relative_axes(fields) == ()
    findings = relative_axes(_turned(fields, sensor, matrix))
    assert [f.sensor for f in findings] == [sensor]
    assert np.allclose(findings[0].matrix, matrix, atol=1e-9)
    assert named in findings[0].text()


def test_no_sensor_is_named_on_clean_trims_of_many_vehicles():
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        trim = TrimManoeuvre(40.0, roll_amplitude_deg=rng.uniform(0, 25), pitch_amplitude_deg=rng.uniform(0, 20))
        scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH, segments=[trim],
                            interference=random_interference(rng, k_scale=0.08, b_scale_t=3e-6,
                                                             reference_clean=False))
        assert relative_axes(simulate(scenario, rng).fields_measured) == (), seed


def test_a_straight_line_is_not_tested():
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH, segments=[SurveyLine((0, 0, -50), (100, 0, -50))])
    fields = simulate(scenario, np.random.default_rng(0)).fields_measured
    assert relative_axes(_turned(fields, 2, FRD)) is None


def test_calibrate_refuses_a_turned_sensor_naming_it(tmp_path, capsys):
    mission = short_mission(trim_s=40.0, survey_s=10.0)
    turned = _turned(mission.fields_measured, 3, Rotation.from_euler('z', 180, degrees=True).as_matrix())
    bag = write_bag(tmp_path / 'bag', mission, fields=turned)
    params = write_params(tmp_path / 'params.yaml')
    assert_refused(run_cli(capsys, 'calibrate', bag, '--params', params, '--out', tmp_path / 'c.yaml'),
                   "sensor 3's axes are not sensor 1's", 'turned 180 deg about z')
    assert not (tmp_path / 'c.yaml').exists()


@pytest.fixture(scope='module')
def survey_fields():
    """Noise-free readings over two strong dipoles, and the noise one tensor element gets."""
    dipoles = (Dipole([60.0, 4.0, -58.0], [0.0, 400.0, -600.0]), Dipole([140.0, -6.0, -57.0], [300.0, 0.0, 500.0]))
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH, dipoles=dipoles,
                        segments=[SurveyLine((0, 0, -50), (200, 0, -50), roll_amplitude_deg=5.0)])
    return simulate(scenario, np.random.default_rng(3)).fields_true


def test_the_declared_positions_and_frame_pass_on_a_survey(survey_fields):
    assert tensor_conventions(difference_tensor(survey_fields, GEOMETRY), GEOMETRY.positions, 1e-10) is None


def test_an_irregular_array_names_its_reordered_positions(survey_fields):
    positions = GEOMETRY.positions + np.array([[0, 0, 0], [0.1, 0, 0], [0, -0.08, 0.05], [0.02, 0, 0.1]])
    geometry = TetraGeometry(positions)
    rng = np.random.default_rng(7)
    scenario = Scenario(geometry=geometry, earth_field_enu=EARTH,
                        dipoles=(Dipole([60.0, 4.0, -58.0], [0.0, 400.0, -600.0]),),
                        segments=[SurveyLine((0, 0, -50), (120, 0, -50))])
    fields = simulate(scenario, rng).fields_true
    for order, named in (([3, 2, 1, 0], 'listed in reverse order'), ([0, 2, 1, 3], 'in the order 1, 3, 2, 4')):
        declared = TetraGeometry(positions[order])
        finding = tensor_conventions(difference_tensor(fields, declared), declared.positions, 1e-11)
        assert finding is not None and finding.declared > 0.2 and finding.best_share < 0.01
        assert named in finding.best[0], finding.text()
    frd = tensor_conventions(difference_tensor(fields @ FRD, geometry), geometry.positions, 1e-11)
    assert 'the magnetometers read in FRD' in frd.text() and 'sensor_positions are in FRD' in frd.text()


def test_compensate_names_positions_listed_in_reverse_and_is_quiet_when_right(tmp_path, capsys):
    from tetra_gradiometer.io.params import params_document

    positions = GEOMETRY.positions + np.array([[0, 0, 0], [0.1, 0, 0], [0, -0.08, 0.05], [0.02, 0, 0.1]])
    rng = np.random.default_rng(11)
    scenario = Scenario(geometry=TetraGeometry(positions), earth_field_enu=EARTH, noise_t=1e-10,
                        interference=random_interference(rng), sample_rate_hz=10.0,
                        dipoles=(Dipole([160.0, 3.0, -56.0], [0.0, 500.0, -700.0]),),
                        segments=[TrimManoeuvre(60.0), SurveyLine((0, 0, -50), (240, 0, -50))])
    mission = simulate(scenario, rng)
    bag = write_bag(tmp_path / 'bag', mission)
    texts = {}
    for name, declared in (('right', positions), ('reversed', positions[::-1])):
        params = tmp_path / f'{name}.yaml'
        params.write_text(params_document({'sensor_positions': declared.ravel().tolist(), 'earth_field_enu': EARTH}))
        calibration = tmp_path / f'{name}_c.yaml'
        code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params, '--window', '0:59',
                                 '--out', calibration)
        assert code == 0, err
        code, out, err = run_cli(capsys, 'compensate', bag, '--params', params, '--calibration', calibration,
                                 '--csv', tmp_path / f'{name}.csv')
        assert code == 0, err
        texts[name] = err
    assert 'not a gradient' not in texts['right']
    assert 'warning: the compensated tensor is not a gradient' in texts['reversed']
    assert 'sensor_positions were listed in reverse order' in texts['reversed']


def test_frame_ids_are_read_as_evidence_of_order_and_frame():
    from tetra_gradiometer.core.conventions import frame_id_hints

    assert frame_id_hints(['tetra_mag1', 'tetra_mag2', 'tetra_mag3', 'tetra_mag4']) == ''
    assert frame_id_hints(['sensor_0', 'sensor_1', 'sensor_2', 'sensor_3']) == ''  # numbered from 0
    assert frame_id_hints(['base_link'] * 4) == ''  # one frame for all: says nothing of order
    reversed_order = frame_id_hints(['Magnetometer-4', 'magnetometer-3', 'magnetometer-2', 'magnetometer-1'])
    assert "sensor 1: 'Magnetometer-4'" in reversed_order and 'another order' in reversed_order
    assert 'declares NED' in frame_id_hints(['mag1_ned', 'mag2', 'mag3', 'mag4'])
    assert frame_id_hints(['friday_mag1', 'mag2', 'mag3', 'mag4']) == ''  # 'frd' only as a word
