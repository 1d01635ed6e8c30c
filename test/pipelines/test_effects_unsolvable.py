"""A candidate whose held-out solve fails is named, never dropped silently.

A thruster's ESC reports exactly 0 A while it is off; one that runs only in the last fifth of
the trim leaves its current column zero on the other four held-out blocks, so the
``vehicle_current`` candidate (the battery and that thruster) cannot be solved when the last
block is held out. Before, it vanished from the selection without a word; now the notes, the
calibration file's diagnostics and the report say which effect, on which channels and why,
and the selection is the one the simulator's truth calls for (the vehicle has a thermal
drift only). Truth: the scenario's effects."""
import dataclasses
import json

import numpy as np
import pytest
import yaml
from cli_helpers import run_cli

from tetra_gradiometer.core import simulate
from tetra_gradiometer.io.calibration import load_calibration
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag
from tetra_gradiometer.io.scenario import load_scenario

AUX = '/thruster_aux/battery_state'
TRIM_S = 100.0
SCENARIO = {
    'seed': 5,
    'sample_rate_hz': 10,
    'noise_nT': 0.05,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': True}},
    'current': {'base_a': -6.0, 'step_amplitude_a': 3.0, 'step_s': 12.0,
                'thrusters': [{'topic': AUX, 'speed_a_per_m2_s2': -2.0}]},
    'temperature': {'mean_c': 15.0, 'ramp_c': 5.0, 'amplitude_c': 0.5, 'period_s': 437.0},
    'effects': {'thermal_drift': {'nT_per_degC': [[0.0, 0.0, 0.0], [0.2, -0.15, 0.1],
                                                  [-0.1, 0.25, 0.12], [0.18, 0.1, -0.22]]}},
    'segments': [{'trim': {'duration_s': TRIM_S, 'center_m': [3000.0, 3000.0, -50.0]}}],
}


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """The trim with the aux thruster's current exactly 0 A but in its last 15 s (it has no
    field: only the thermal drift is in the readings)."""
    tmp = tmp_path_factory.mktemp('unsolvable')
    path = tmp / 'scenario.yaml'
    path.write_text(yaml.safe_dump(SCENARIO))
    scenario, seed = load_scenario(path)
    mission = simulate(scenario, np.random.default_rng(seed))
    assert mission.current_topics[1] == AUX
    currents = mission.currents_a.copy()
    currents[mission.t < TRIM_S - 15.0, 1] = 0.0
    assert np.ptp(currents[mission.t >= TRIM_S - 15.0, 1]) > 0.1  # it varies while on
    mission = dataclasses.replace(mission, currents_a=currents)
    out = write_mission_bag(tmp / 'bag', mission, progress=False)
    params = tmp / 'params.yaml'
    params.write_text(params_document({
        'sensor_positions': scenario.geometry.to_flat(),
        'earth_field_enu': [float(v) for v in scenario.earth_field_enu],
    }))
    return out, params


def test_a_candidate_that_cannot_be_solved_is_named(bag, tmp_path, capsys):
    path, params = bag
    calibration, report = tmp_path / 'c.yaml', tmp_path / 'report'
    code, out, err = run_cli(capsys, 'calibrate', path, '--params', params, '--window', f'0:{TRIM_S - 0.2}',
                             '--out', calibration, '--report', report)
    assert code == 0, err
    # The selection is the truth's: the thermal drift, nothing else.
    assert [t.effect for t in load_calibration(calibration).parameters.terms] == ['thermal_drift']
    said = (f'effects: vehicle_current (current:/battery_state, current:{AUX}) could not be tested, '
            'its held-out solve failed (with k, b')
    assert said in out
    assert 'fitted without block 5 of 5: a regressor is zero on every sample' in out
    diagnostics = yaml.safe_load(calibration.read_text())['diagnostics']
    assert any(note.startswith(said) for note in diagnostics['notes'])
    assert 'block 5 of 5' in diagnostics['effects']['unsolved']['vehicle_current']
    document = json.loads((report / 'report.json').read_text())
    assert 'block 5 of 5' in document['effects']['unsolved']['vehicle_current']
    markdown = (report / 'report.md').read_text()
    assert '- vehicle_current: not tested, its held-out solve failed (with k, b' in markdown
