"""Collinear and constant current channels: a hotel load that does not change makes
the battery current (hotel + thrusters) the sum of the thrusters' it also records plus a
constant, and a battery alone with a constant load is a constant. ``calibrate`` leaves the
redundant channel out with a note (never a singular solve: before, the battery and thruster
coefficients came out at -6000 +- 5500 nT/A with a condition number of 8.5e7), fits the
others, and the survey compensates to the noise floor; an effect asked for by name that has
no independent channel left is refused by name. Truth: the simulator's coefficients and
``g_true``."""
import numpy as np
import pytest
import yaml
from cli_helpers import assert_refused, run_cli

from tetra_gradiometer.io.calibration import load_calibration

#: nT/A per sensor [axis][channel]: battery, port, starboard (sensor 1 clean).
NT_PER_A = [[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
            [[0.6, 0.9, -0.2], [-0.4, 0.3, 0.5], [1.1, -0.6, 0.2]],
            [[-0.3, 0.2, 0.8], [0.8, -0.5, 0.3], [0.5, 0.4, -0.9]],
            [[1.2, -0.4, 0.1], [0.4, 0.7, -0.6], [-0.7, 0.2, 1.0]]]
THRUSTER = {'idle_a': -0.4, 'speed_a_per_m2_s2': -2.2, 'activity_a_per_deg_s': [-0.08, -0.05, -0.05],
            'step_amplitude_a': 1.0}
PORT, STARBOARD = '/thruster_port/battery_state', '/thruster_starboard/battery_state'
TRIM = '0:149'


class _NoCapture:
    """run_cli's capsys for a module fixture (output is not checked there)."""

    def readouterr(self):
        class _Out:
            out = err = ''
        return _Out()


def _survey_residual(csv, truth):
    """RMS of the survey's compensated tensor minus the truth and of its 1-sigma, nT/m."""
    rows = np.loadtxt(csv, delimiter=',', skiprows=1)
    stamps = np.array([int(line.split(',', 1)[0].replace('.', '')) for line in csv.read_text().splitlines()[1:]])
    index = np.searchsorted(truth['stamps_ns'], stamps)
    assert np.array_equal(truth['stamps_ns'][index], stamps)
    survey = truth['t_s'][index] > 150.5
    residual = rows[survey, 1:10] - truth['g_true'][index[survey]].reshape(-1, 9) * 1e9
    return np.sqrt(np.mean(residual**2)), np.sqrt(np.mean(rows[survey, 10:19] ** 2))


def _scenario(thrusters: bool) -> dict:
    current = {'base_a': -3.0, 'step_amplitude_a': 0.0, 'step_s': 25.0}  # a constant hotel load
    effects = {'vehicle_current': {'nT_per_A': NT_PER_A if thrusters else [[s[0] for s in sensor] for sensor in NT_PER_A]}}
    if thrusters:
        current['thrusters'] = [{'topic': PORT, 'turn_a_per_deg_s': -0.05, 'step_s': 20.0, **THRUSTER},
                                {'topic': STARBOARD, 'turn_a_per_deg_s': 0.05, 'step_s': 27.0, **THRUSTER}]
    return {
        'seed': 7, 'sample_rate_hz': 10, 'noise_nT': 0.05, 'geometry': {'regular_edge_m': 0.5},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': True}},
        'segments': [
            {'trim': {'duration_s': 150, 'center_m': [3000.0, 3000.0, -50.0]}},
            {'line': {'start_m': [-150.0, 0.0, -40.0], 'end_m': [150.0, 0.0, -40.0], 'speed_m_s': 2.0,
                      'roll_amplitude_deg': 2.0, 'pitch_amplitude_deg': 1.0}},
        ],
        'current': current,
        'effects': effects,
    }


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('collinear')
    out = {}
    for name, thrusters in (('thrusters', True), ('battery', False)):
        scenario = tmp / f'{name}.yaml'
        scenario.write_text(yaml.safe_dump(_scenario(thrusters)))
        code, _, err = run_cli(_NoCapture(), 'simulate', '--scenario', scenario, '--out', tmp / name)
        assert code == 0, err
        out[name] = (tmp / name, tmp / f'{name}.params.yaml', np.load(tmp / f'{name}.truth.npz'))
    return out


def test_a_battery_that_is_a_constant_plus_the_thrusters_is_left_out(bags, tmp_path, capsys):
    bag, params, truth = bags['thrusters']
    calibration = tmp_path / 'c.yaml'
    code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params, '--window', TRIM, '--out', calibration)
    assert code == 0, err
    assert 'current:/battery_state = -3 +1 x current:/thruster_port' in out, out
    assert 'left out' in out
    loaded = load_calibration(calibration)
    assert loaded.diagnostics['condition_number'] < 1e3, loaded.diagnostics
    (term,) = [t for t in loaded.parameters.terms if t.effect == 'vehicle_current']
    assert term.inputs == (f'current:{PORT}', f'current:{STARBOARD}')
    # The battery's wiring carries the thrusters' currents too: each thruster's coefficient
    # in the pair differences is its own plus the battery's, sensor i minus sensor 1 (clean).
    truth_nt = np.array(NT_PER_A)
    expected = truth_nt[1:, :, 1:] + truth_nt[1:, :, :1]  # [pair][axis][thruster]
    np.testing.assert_allclose(term.coefficients * 1e9, expected, rtol=0, atol=0.03)
    csv = tmp_path / 'c.csv'
    code, _, err = run_cli(capsys, 'compensate', bag, '--params', params, '--calibration', calibration, '--csv', csv)
    assert code == 0, err
    residual, sigma = _survey_residual(csv, truth)
    assert residual < 1.2 * sigma and sigma < 0.2, (residual, sigma)


def test_a_constant_battery_current_is_hard_iron_and_named_when_asked_for(bags, tmp_path, capsys):
    bag, params, truth = bags['battery']
    calibration = tmp_path / 'c.yaml'
    code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params, '--window', TRIM, '--out', calibration)
    assert code == 0, err
    assert 'current:/battery_state is constant on the window (-3' in out, out
    assert load_calibration(calibration).parameters.terms == ()
    csv = tmp_path / 'c.csv'
    code, _, err = run_cli(capsys, 'compensate', bag, '--params', params, '--calibration', calibration, '--csv', csv)
    assert code == 0, err
    residual, sigma = _survey_residual(csv, truth)
    assert residual < 1.2 * sigma, (residual, sigma)  # a constant current stays a constant field
    assert_refused(
        run_cli(capsys, 'calibrate', bag, '--params', params, '--window', TRIM, '--out', tmp_path / 'x.yaml',
                '--effects', 'vehicle_current'),
        'vehicle_current needs a channel that varies on the window', 'current:/battery_state',
    )
