"""``batch`` and a channel the vehicle's effects need. ``batch`` calibrates each bag
on its own window, so its calibration only ever reads channels that bag records: the
without-channel option of ``compensate`` and ``locate`` (a calibration from another bag)
has nothing to do there. A bag whose vehicle has a current effect but no ``/battery_state``
is refused by the calibration, naming the effect and the channel, never calibrated as if the
current were zero. Truth: the scenario's effect."""
import numpy as np
import yaml
from cli_helpers import run_cli

from tetra_gradiometer.cli import fleet

SCENARIO = {
    'seed': 9,
    'sample_rate_hz': 10,
    'noise_nT': 0.05,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': True}},
    'current': {'base_a': -15.0, 'step_amplitude_a': 12.0, 'step_s': 15.0},
    'effects': {'vehicle_current': {'nT_per_A': [[0.0, 0.0, 0.0], [1.2, -0.8, 0.6],
                                                 [-0.9, 1.5, 0.7], [0.5, 0.9, -1.8]]}},
    'segments': [{'trim': {'duration_s': 80, 'center_m': [3000.0, 3000.0, -50.0]}}],
}


def test_a_bag_without_the_current_its_vehicle_needs_is_refused_by_name(tmp_path, capsys):
    fleet_dir = tmp_path / 'fleet'
    fleet_dir.mkdir()
    scenario = tmp_path / 'scenario.yaml'
    scenario.write_text(yaml.safe_dump(SCENARIO))
    code, _, err = run_cli(capsys, 'simulate', '--scenario', scenario, '--out', fleet_dir / 'magonly', '--mag-only')
    assert code == 0, err
    (fleet_dir / 'magonly.params.yaml').rename(fleet_dir / 'magonly.yaml')
    (bag,) = fleet.find_bags(fleet_dir)
    row = fleet.process_bag(fleet.make_job(bag, tmp_path / 'out', (0.0, 79.8), plots=False))
    assert row['status'] == 'refused', row
    assert 'vehicle_current' in row['reason'] and '/battery_state' in row['reason'], row
    assert not (tmp_path / 'out' / 'magonly' / fleet.CSV_FILE).exists()
    # The discrepancy analysis still ran over the bag; its gap is the unmodelled current's.
    assert row['gap_initial_nT'] > 10 * row['discrepancy_noise_floor_nT'], row
    assert np.isfinite(row['gap_final_nT'])
