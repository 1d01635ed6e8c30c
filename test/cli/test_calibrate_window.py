"""calibrate without --window finds its own window: the manoeuvring spans of the
bag (pipelines/window_check.excited_spans), ranked by the trim guidance's prediction, each
checked as --window would check it; a failing --window names the best passing window of the
bag. Truth: the simulator's segments and g_true, the sample bags' recorded truth. The spans
on analytic fields: test/pipelines/test_window_check.py."""
import numpy as np
import pytest
import yaml

from tetra_gradiometer.core import noise_floor
from tetra_gradiometer.io.params import geometry_from_params, load_params

from test.io.cli_helpers import assert_refused, run_cli

NOISE_NT = 0.05
LINE = {'speed_m_s': 2.0, 'roll_amplitude_deg': 3.0, 'pitch_amplitude_deg': 2.0}
TRIM = {'heading_rate_deg_s': 5.0, 'roll_amplitude_deg': 20.0, 'roll_period_s': 9.0,
        'pitch_amplitude_deg': 15.0, 'pitch_period_s': 14.0, 'speed_m_s': 1.0}
#: A line, a trim over the target (its window check fails: a field-like misfit), a line, the
#: trim far from the target (the one to find), a line over the target.
SCENARIO = {
    'seed': 5, 'sample_rate_hz': 10, 'noise_nT': NOISE_NT, 'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [1500.0, 19000.0, -47000.0]},
    'dipoles': [{'position_m': [0.0, 0.0, -70.0], 'moment_Am2': [4.0e4, -2.0e4, 3.0e4]}],
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': False}},
    'segments': [
        {'line': {'start_m': [-80.0, 5.0, -50.0], 'end_m': [80.0, 5.0, -50.0], **LINE}},
        {'trim': {'duration_s': 160, 'center_m': [0.0, 0.0, -50.0], **TRIM}},
        {'line': {'start_m': [80.0, -5.0, -50.0], 'end_m': [-80.0, -5.0, -50.0], **LINE}},
        {'trim': {'duration_s': 100, 'center_m': [4000.0, 3000.0, -50.0], **TRIM}},
        {'line': {'start_m': [-80.0, 15.0, -55.0], 'end_m': [80.0, 15.0, -55.0], **LINE}},
    ],
}


@pytest.fixture(scope='module')
def mission(tmp_path_factory):
    root = tmp_path_factory.mktemp('window')
    (root / 'scenario.yaml').write_text(yaml.safe_dump(SCENARIO))
    code = run_cli(_NoCapture(), 'simulate', '--scenario', root / 'scenario.yaml', '--out',
                   root / 'bag')[0]
    assert code == 0
    truth = np.load(root / 'bag.truth.npz')
    t = (truth['stamps_ns'] - truth['stamps_ns'][0]) * 1e-9
    segment = truth['segment']
    return root, t, segment, truth


class _NoCapture:
    """capsys stand-in for a module fixture (output is not checked there)."""

    def readouterr(self):
        return type('Captured', (), {'out': '', 'err': ''})()


def _survey_ratio(csv, truth, params) -> float:
    lines = np.array([str(k) == 'line' for k in truth['segment_kind']])[truth['segment']]
    table = np.loadtxt(csv, delimiter=',', skiprows=1, usecols=range(1, 10))
    residual = table - truth['g_true'].reshape(-1, 9) * 1e9
    floor = noise_floor(NOISE_NT * 1e-9, geometry_from_params(load_params(params))) * 1e9
    return float(np.sqrt(np.mean(residual[lines] ** 2)) / floor)


def test_without_window_finds_the_far_trim_and_compensates_at_the_floor(mission, capsys):
    root, t, segment, truth = mission
    params = root / 'bag.params.yaml'
    code, out, err = run_cli(capsys, 'calibrate', root / 'bag', '--params', params,
                             '--out', root / 'c.yaml')
    assert code == 0, err
    far = t[segment == 3]  # the trim 4 km from the target
    line = next(l for l in out.splitlines() if 'found in the bag' in l)
    t0, t1 = (float(v) for v in line.split('window ')[1].split(' s')[0].split(':'))
    assert far[0] - 0.05 <= t0 and t1 <= far[-1] + 0.05, line
    assert t1 - t0 >= 0.8 * (far[-1] - far[0]), line
    assert 'before it,' in line and 'window check' in line  # the trim over the target failed
    record = yaml.safe_load((root / 'c.yaml').read_text())
    assert record['diagnostics']['window_found']['window_s'] == [pytest.approx(t0), pytest.approx(t1)]
    assert run_cli(capsys, 'compensate', root / 'bag', '--params', params, '--calibration',
                   root / 'c.yaml', '--csv', root / 'c.csv')[0] == 0
    assert _survey_ratio(root / 'c.csv', truth, params) <= 1.2


def test_a_failing_window_names_the_best_passing_window_of_the_bag(mission, capsys):
    root, t, segment, _ = mission
    over_target = t[segment == 1]
    window = f'{round(over_target[0], 1):g}:{round(over_target[-1], 1):g}'
    result = run_cli(capsys, 'calibrate', root / 'bag', '--params', root / 'bag.params.yaml',
                     '--window', window, '--out', root / 'never.yaml')
    far = t[segment == 3]
    assert_refused(result, f'the window ({window} s) does not fit the model',
                   'the best passing window in the bag: --window ')
    suggested = result[2].split('the best passing window in the bag: --window ')[1].split(' ')[0]
    t0, t1 = (float(v) for v in suggested.split(':'))
    assert far[0] - 0.05 <= t0 and t1 <= far[-1] + 0.05
    assert not (root / 'never.yaml').exists()


def test_a_bag_without_a_manoeuvre_is_refused_saying_so(tmp_path, capsys):
    line_only = {**SCENARIO, 'segments': [SCENARIO['segments'][0]]}
    (tmp_path / 's.yaml').write_text(yaml.safe_dump(line_only))
    assert run_cli(capsys, 'simulate', '--scenario', tmp_path / 's.yaml', '--out',
                   tmp_path / 'bag', '--mag-only')[0] == 0
    result = run_cli(capsys, 'calibrate', tmp_path / 'bag', '--params',
                     tmp_path / 'bag.params.yaml', '--out', tmp_path / 'c.yaml')
    assert_refused(result, 'no span of the bag manoeuvres', 'fly a trim manoeuvre')


def test_sample_bags_calibrated_without_window_compensate_the_survey(tmp_path, capsys):
    """bags/trim without --window, then bags/survey against its recorded truth topic."""
    from rosbags.highlevel import AnyReader

    repo = __import__('pathlib').Path(__file__).resolve().parents[2]
    assert run_cli(capsys, 'simulate', '--scenario', repo / 'bags/trim.yaml', '--out',
                   tmp_path / 'trim_sim', '--mag-only')[0] == 0
    params = tmp_path / 'trim_sim.params.yaml'
    code, out, err = run_cli(capsys, 'calibrate', repo / 'bags/trim', '--params', params,
                             '--out', tmp_path / 'c.yaml')
    assert code == 0 and 'found in the bag' in out, err
    assert run_cli(capsys, 'compensate', repo / 'bags/survey', '--params', params,
                   '--calibration', tmp_path / 'c.yaml', '--csv', tmp_path / 's.csv')[0] == 0
    with AnyReader([repo / 'bags/survey']) as reader:
        connections = [c for c in reader.connections if c.topic == '/tetra/gradient/truth']
        truth = {}
        for connection, _, raw in reader.messages(connections=connections):
            message = reader.deserialize(raw, connection.msgtype)
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            truth[stamp] = np.asarray(message.position) * 1e9
    stamps = np.loadtxt(tmp_path / 's.csv', delimiter=',', skiprows=1, usecols=0, dtype=str)
    table = np.loadtxt(tmp_path / 's.csv', delimiter=',', skiprows=1, usecols=range(1, 10))
    keys = [int(s.replace('.', '')) for s in stamps]
    kept = [i for i, key in enumerate(keys) if key in truth]
    assert len(kept) > 1000
    residual = table[kept] - np.array([truth[keys[i]] for i in kept])
    floor = noise_floor(0.1e-9, geometry_from_params(load_params(params))) * 1e9
    assert np.sqrt(np.mean(residual**2)) <= 1.2 * floor


def test_the_checked_solve_names_the_passing_manoeuvre_it_holds(mission):
    """What the calibrator node calls (identify_checked on its samples): all the samples fail,
    and the passing span it names is the far trim, not the trim over the target."""
    from tetra_gradiometer.core import difference_tensor
    from tetra_gradiometer.core.identification import Options
    from tetra_gradiometer.core.timebase import DEFAULT_TIMEBASE
    from tetra_gradiometer.pipelines.calibration import read_window
    from tetra_gradiometer.pipelines.window_check import identify_checked

    root, t, segment, _ = mission
    geometry = geometry_from_params(load_params(root / 'bag.params.yaml'))
    sets = read_window(root / 'bag', None, timebase=DEFAULT_TIMEBASE)
    checked = identify_checked(
        'known_gradient_lstsq_general', sets.stamps_ns, difference_tensor(sets.fields, geometry),
        sets.fields[:, 0], geometry, Options(), window='all', first_ns=sets.first_ns, force=True)
    assert not checked.check.passed
    t0, t1 = checked.check.passing_window
    far = t[segment == 3]
    assert far[0] - 0.05 <= t0 and t1 <= far[-1] + 0.05
    assert f'{t0:g}-{t1:g}' in checked.check.text('{0:g}-{1:g}')


def test_batch_without_a_window_calibrates_on_the_window_found(tmp_path):
    """batch's task without --window: as calibrate, the window found, named in the row."""
    from pathlib import Path

    from tetra_gradiometer.cli import fleet

    repo = Path(__file__).resolve().parents[2]
    bag = fleet.FleetBag('trim', repo / 'bags/trim', repo / 'bags/trim.yaml')
    row = fleet.process_bag(fleet.make_job(bag, tmp_path / 'out', None, plots=False))
    assert row['status'] == 'ok', row
    assert row['window'] == '0:119.9 s'
