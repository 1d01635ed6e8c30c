"""A recorded channel whose survey values lie outside what the calibration saw is named before
it is trusted: the battery current's sign convention flipped between the trim and the survey (a
driver update) is a warning naming the channel and the likely cause; the same bag with the
convention kept says nothing.

Truth: the simulator's bag; the flipped copy differs from it only in the sign of the survey's
recorded /battery_state currents (the physics, the fields, are unchanged).
"""
import numpy as np
import yaml
from cli_helpers import rewrite_bag, run_cli

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import typestore

SCENARIO = {
    'seed': 5,
    'sample_rate_hz': 10,
    'noise_nT': 0.05,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': True}},
    'current': {'base_a': 15.0, 'step_amplitude_a': 8.0, 'step_s': 15.0},
    'effects': {'vehicle_current': {'nT_per_A': [[1.5, -0.8, 1.1], [-1.2, 0.9, 0.7], [0.6, 1.4, -1.0],
                                                 [1.0, -0.5, 0.8]]}},
    'segments': [
        {'trim': {'duration_s': 120, 'center_m': [3000.0, 3000.0, -50.0]}},
        {'line': {'start_m': [-100.0, 0.0, -40.0], 'end_m': [100.0, 0.0, -40.0], 'speed_m_s': 2.0}},
    ],
}


def _flipped_copy(bag, out, after_s):
    """``bag`` with every /battery_state current after ``after_s`` (s from the start) negated."""
    types = cv.rosbags_types(typestore())

    def flip(msg, t_s):
        if t_s <= after_s:
            return None
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        return cv.battery_msg(types, -float(msg.current), stamp)

    return rewrite_bag(bag, out, cv.BATTERY_TOPIC, flip)


def test_a_current_with_another_sign_on_the_survey_is_named(tmp_path, capsys):
    scenario = tmp_path / 'wires.yaml'
    scenario.write_text(yaml.safe_dump(SCENARIO))
    code, _, err = run_cli(capsys, 'simulate', '--scenario', scenario, '--out', tmp_path / 'bag')
    assert code == 0, err
    params = tmp_path / 'bag.params.yaml'
    code, out, err = run_cli(capsys, 'calibrate', tmp_path / 'bag', '--params', params, '--window', '0:119',
                             '--effects', 'vehicle_current', '--out', tmp_path / 'c.yaml')
    assert code == 0, err
    flipped = _flipped_copy(tmp_path / 'bag', tmp_path / 'flipped', after_s=121.0)
    said = {}
    for name, bag in (('kept', tmp_path / 'bag'), ('flipped', flipped)):
        code, out, err = run_cli(capsys, 'compensate', bag, '--params', params, '--calibration',
                                 tmp_path / 'c.yaml', '--csv', tmp_path / f'{name}.csv')
        assert code == 0, err
        said[name] = err
    assert 'extrapolated' not in said['kept'], said['kept']
    assert 'warning: extrapolated beyond the calibration: vehicle_current (/battery_state)' in said['flipped']
    assert 'another sign convention than at the calibration?' in said['flipped']
