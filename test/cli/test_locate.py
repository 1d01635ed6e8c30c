"""cli/locate.py end to end through the CLI (in-process, test_compensate.cli): simulate (trim,
then survey lines over two dipoles) -> calibrate on the trim -> locate; the targets against the
simulator's dipoles (ground truth), targets.json through its reader; the refusals."""
import json

import numpy as np
import pytest
import yaml

from tetra_gradiometer.io.targets import read_targets

from .test_compensate import cli

TRUTH = [
    {'position_m': [-40.0, -6.0, -45.0], 'moment_Am2': [15000.0, 5000.0, -8000.0]},
    {'position_m': [35.0, 9.0, -44.0], 'moment_Am2': [-20000.0, 30000.0, -25000.0]},
]


def survey_mission() -> dict:
    lines = []
    for i, y in enumerate((-16.0, 0.0, 16.0)):
        a, b = (-120.0, 120.0) if i % 2 == 0 else (120.0, -120.0)
        lines.append({'line': {'start_m': [a, y, -25.0], 'end_m': [b, y, -25.0], 'speed_m_s': 2.0}})
    return {
        'seed': 5, 'sample_rate_hz': 10, 'noise_nT': 0.05, 'geometry': {'regular_edge_m': 0.5},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]}, 'dipoles': TRUTH,
        'interference': {'random': {'k_scale': 0.005, 'b_scale_nT': 150, 'reference_clean': False}},
        'segments': [{'trim': {'duration_s': 120, 'center_m': [3000.0, 3000.0, -25.0]}}, *lines],
    }


@pytest.fixture(scope='module')
def located(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('locate')
    (tmp / 'mission.yaml').write_text(yaml.safe_dump(survey_mission()))
    cli('simulate', '--scenario', tmp / 'mission.yaml', '--out', tmp / 'mission')
    params = tmp / 'mission.params.yaml'
    cli('calibrate', tmp / 'mission', '--params', params, '--window', '0:119.95', '--out', tmp / 'calib.yaml')
    out = cli('locate', tmp / 'mission', '--params', params, '--calibration', tmp / 'calib.yaml', '--out',
              tmp / 'targets', '--comparison')
    return tmp, out


def test_every_target_is_found_and_located_within_its_figures(located):
    tmp, out = located
    document = read_targets(tmp / 'targets' / 'targets.json')
    assert document['frame'] == 'odom' and document['tensor'] == 'compensated'
    assert len(document['targets']) == len(TRUTH), document['targets']
    for truth in TRUTH:
        target = min(document['targets'],
                     key=lambda t: np.linalg.norm(np.subtract(t['position_m'], truth['position_m'])))
        assert np.linalg.norm(np.subtract(target['position_m'], truth['position_m'])) <= 0.2
        moment = np.array(truth['moment_Am2'])
        assert np.linalg.norm(np.subtract(target['moment_Am2'], moment)) <= 0.03 * np.linalg.norm(moment)
        assert 0 < max(target['position_sigma_m']) < 0.2
        # Seen on the lines (after the 120 s trim), in order.
        assert 120.0 <= target['first_seen_s'] <= target['last_seen_s'] <= 480.0
        assert target['fit_rms_nT_per_m'] == pytest.approx(0.05 * 2.8, rel=0.3)  # the noise, nothing else
    assert 'compensated: ' in out.stdout and 'targets in' in out.stdout


def test_the_raw_comparison_map_and_report_are_written(located):
    tmp, _ = located
    folder = tmp / 'targets'
    raw = json.loads((folder / 'targets_raw.json').read_text())
    assert raw['tensor'] == 'raw' and raw['frame'] == 'odom'
    assert (folder / 'map.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    report = (folder / 'report.md').read_text()
    assert 'Compensated tensor' in report and 'Raw tensor' in report


def test_locate_needs_a_calibration_or_raw_and_never_replaces_what_is_not_its_own(located):
    tmp, _ = located
    params = tmp / 'mission.params.yaml'
    result = cli('locate', tmp / 'mission', '--params', params, '--out', tmp / 'other', check=False)
    assert result.returncode == 1 and result.stderr.startswith('error: give --calibration')
    result = cli('locate', tmp / 'mission', '--params', params, '--raw', '--out', tmp / 'calib.yaml', check=False)
    assert result.returncode == 1 and 'error:' in result.stderr and 'Traceback' not in result.stderr
    assert yaml.safe_load((tmp / 'calib.yaml').read_text())['method']  # untouched


def test_odometry_with_z_as_depth_is_named(located, capsys):
    """The same bag with /odom's z written as a depth (positive down, as some INS publish):
    the track and every target above the odom origin is named; the right bag (the module
    fixture's locate of it) says nothing."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'io'))
    from cli_helpers import rewrite_bag

    from tetra_gradiometer.__main__ import main

    tmp, out = located

    def as_depth(msg, t_s):
        msg.pose.pose.position.z = -msg.pose.pose.position.z
        return msg

    depth = rewrite_bag(tmp / 'mission', tmp / 'depth', '/odom', as_depth)
    params, calibration = tmp / 'mission.params.yaml', tmp / 'calib.yaml'
    assert main(['locate', str(depth), '--params', str(params), '--calibration', str(calibration),
                 '--out', str(tmp / 'depth_targets')]) == 0
    err = capsys.readouterr().err
    assert 'warning: /odom z looks like a depth (positive down): the track lies at z = +25.0' in err
    assert 'depth' not in out.stderr
