"""cli/compensate.py (with cli/simulate.py and cli/calibrate.py before it) end to end, through
the CLI: simulate -> bag -> calibrate -> compensate, checked against independent truth (the
simulator's ground truth, closed-form fields); the failures of both commands with the one
error line that names the problem.

The commands run in-process through ``__main__.main`` (the code path of ``python -m
tetra_gradiometer``: parsing, the one ``error:`` line, exit statuses 1 and 2); one round trip
(mcap) runs as real subprocesses, the entry point and interpreter exit included. A subprocess
costs ~0.9 s CPU of imports (docs/testing.md), and this module ran ~40 of them."""
import contextlib
import io
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.core import TetraGeometry, dipole_field, dipole_gradient, noise_floor
from tetra_gradiometer.io.bag import BagWriter
from tetra_gradiometer.__main__ import main
from tetra_gradiometer.io.params import params_document

REPO = Path(__file__).resolve().parents[2]
START_NS = 1_767_225_600 * 10**9 + 123_456_789
NOISE_NT = 0.05
EDGE_M = 0.5


def cli_process(*args, check=True):
    """``python -m tetra_gradiometer ARGS`` in a subprocess: its exit status, stdout, stderr."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop('TETRA_DEBUG', None)
    result = subprocess.run([sys.executable, '-m', 'tetra_gradiometer', *map(str, args)], capture_output=True,
                            text=True, env=env, cwd=REPO, timeout=300)
    if check and result.returncode != 0:
        raise AssertionError(f'exit {result.returncode}\nstdout: {result.stdout}\nstderr: {result.stderr}')
    return result


def cli(*args, check=True):
    """The same in-process (``__main__.main``): what a subprocess would return, without its
    ~0.9 s of imports. A usage error (argparse's SystemExit) is exit status 2, as there."""
    debug = os.environ.pop('TETRA_DEBUG', None)  # it would add a traceback to the error line
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else 1
        finally:
            if debug is not None:
                os.environ['TETRA_DEBUG'] = debug
    result = SimpleNamespace(returncode=code, stdout=out.getvalue(), stderr=err.getvalue())
    if check and result.returncode != 0:
        raise AssertionError(f'exit {result.returncode}\nstdout: {result.stdout}\nstderr: {result.stderr}')
    return result


def small_mission(reference_clean: bool) -> dict:
    """60 s trim far from the target, then a 60 s pass 25 m above a dipole, 10 Hz."""
    return {
        'seed': 42, 'sample_rate_hz': 10, 'noise_nT': NOISE_NT, 'geometry': {'regular_edge_m': EDGE_M},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'dipoles': [{'position_m': [0.0, 0.0, -75.0], 'moment_Am2': [3.0e4, 2.0e4, -3.3e4]}],
        'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': reference_clean}},
        'segments': [{'trim': {'duration_s': 60, 'center_m': [3000.0, 3000.0, -50.0], 'heading_rate_deg_s': 12.0,
                               'roll_period_s': 7.0, 'pitch_period_s': 9.0}},
                     {'line': {'start_m': [-60.0, 0.0, -50.0], 'end_m': [60.0, 0.0, -50.0], 'speed_m_s': 2.0}}],
    }


def read_csv(path):
    lines = Path(path).read_text().splitlines()
    stamps_ns = [int(row.split(',')[0].replace('.', '')) for row in lines[1:]]
    values = np.loadtxt(path, delimiter=',', skiprows=1, usecols=range(1, 10))
    return lines[0], np.array(stamps_ns, dtype=np.int64), values.reshape(-1, 3, 3)


@pytest.mark.parametrize('storage,reference_clean', [('sqlite3', True), pytest.param('mcap', False, marks=pytest.mark.slow)])
def test_round_trip_reaches_the_noise_floor(tmp_path, storage, reference_clean):
    run = cli if storage == 'sqlite3' else cli_process  # mcap: the real entry point, as a user runs it
    scenario = tmp_path / 'mission.yaml'
    scenario.write_text(yaml.safe_dump(small_mission(reference_clean)))
    bag = tmp_path / 'mission'
    out = run('simulate', '--scenario', scenario, '--out', bag, '--storage', storage,
              '--start-utc', '2026-01-01T00:00:00Z')
    assert 'simulated 1200 sample sets' in out.stdout
    assert list(bag.glob('*.mcap' if storage == 'mcap' else '*.db3'))
    params = yaml.safe_load((tmp_path / 'mission.params.yaml').read_text())['/**']['ros__parameters']
    assert np.allclose(params['sensor_positions'], TetraGeometry.regular(EDGE_M).to_flat())
    assert np.isclose(np.linalg.norm(params['earth_field_enu']), 50_000e-9, rtol=1e-6)
    truth = np.load(tmp_path / 'mission.truth.npz')

    out = run('calibrate', bag, '--params', tmp_path / 'mission.params.yaml', '--window', '0:59.95',
              '--out', tmp_path / 'calib.yaml')
    assert 'rank 36' in out.stdout and 'condition number' in out.stdout and 'attitude coverage' in out.stdout
    calibration = yaml.safe_load((tmp_path / 'calib.yaml').read_text())
    assert calibration['method'] == 'known_gradient_lstsq_general'
    assert calibration['diagnostics']['sets_in_window'] == 600
    # The identified parameters against the simulator's interference (eq. 14, exact).
    assert np.allclose(calibration['b_hard_T'], truth['b_effective'], atol=0.5e-9)
    assert np.allclose(calibration['k_soft'], truth['k_effective'], atol=1e-5)

    run('compensate', bag, '--params', tmp_path / 'mission.params.yaml', '--calibration', tmp_path / 'calib.yaml',
        '--csv', tmp_path / 'comp.csv', '--out-bag', tmp_path / 'comp_bag')
    run('compensate', bag, '--params', tmp_path / 'mission.params.yaml', '--raw', '--csv', tmp_path / 'raw.csv')
    header, stamps, compensated = read_csv(tmp_path / 'comp.csv')
    _, raw_stamps, raw = read_csv(tmp_path / 'raw.csv')
    assert header == ('stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz,'
                      'sigma_gxx,sigma_gxy,sigma_gxz,sigma_gyx,sigma_gyy,sigma_gyz,sigma_gzx,sigma_gzy,sigma_gzz,'
                      'db_21x,db_21y,db_21z,db_31x,db_31y,db_31z,db_41x,db_41y,db_41z')  # tracked: the default
    assert Path(tmp_path / 'raw.csv').read_text().startswith('stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz\n')
    assert np.array_equal(stamps, truth['stamps_ns']) and np.array_equal(raw_stamps, stamps)
    assert stamps[0] == 1_767_225_600 * 10**9  # absolute seconds, from --start-utc
    survey = truth['segment'] == 1
    g_true_nt = truth['g_true'] * 1e9
    floor = noise_floor(NOISE_NT * 1e-9, TetraGeometry.regular(EDGE_M)) * 1e9
    after = np.sqrt(np.mean((compensated[survey] - g_true_nt[survey]) ** 2))
    before = np.sqrt(np.mean((raw[survey] - g_true_nt[survey]) ** 2))
    assert after < 1.25 * floor, (after, floor)
    assert before / after > 1000, (before, after)
    # The pass is over a target: the truth is far from zero there, so this is no trivial match.
    assert np.abs(g_true_nt[survey]).max() > 50

    # The tensor bag: GradientTensor as the nodes publish it, the CSV's values in T/m.
    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.io.bag import MagneticBag
    with MagneticBag(tmp_path / 'comp_bag') as out_bag:
        messages = [(c.topic, c.msgtype, out_bag.reader.deserialize(r, c.msgtype))
                    for c, _, r in out_bag.reader.messages()]
    assert {(topic, msgtype) for topic, msgtype, _ in messages} == {('/tetra/gradient/compensated', gt.GRADIENT_TENSOR)}
    sets = [gt.tensor_set_from_msg(m) for _, _, m in messages]
    assert [t.stamp_ns for t in sets] == stamps.tolist()
    assert np.allclose(np.array([t.g for t in sets]) * 1e9, compensated, atol=2e-6)
    sigma_csv = np.loadtxt(tmp_path / 'comp.csv', delimiter=',', skiprows=1, usecols=range(10, 19))
    assert np.allclose(np.array([t.g_sigma.reshape(9) for t in sets]) * 1e9, sigma_csv, atol=2e-6)
    assert {(t.state, t.calibration_id) for t in sets} == {(gt.COMPENSATED, calibration['created_utc'])}
    assert calibration['created_utc']
    references = np.array([t.reference_field for t in sets])
    assert np.allclose(np.linalg.norm(references, axis=1), 50_000e-9, rtol=0.05)  # B_1', the Earth's field


def test_csv_columns_and_units_against_analytic_fields(tmp_path):
    """No simulator, no interference, no noise: fields written by hand from closed forms."""
    geometry = TetraGeometry.regular(EDGE_M)
    rng = np.random.default_rng(8)
    n = 40
    stamps = START_NS + np.arange(n, dtype=np.int64) * 10_000_000 + rng.integers(0, 1000, n)
    earth = np.array([0.0, 2.1e-5, -4.5e-5])
    # 1. A linear field B = B0 + M r with an asymmetric M: the difference tensor is exactly M,
    #    so every column must land where G_ij = dB_i/dx_j puts it.
    m_linear = np.arange(1.0, 10.0).reshape(3, 3) * 1e-7  # T/m, asymmetric, known entries
    linear = earth + np.einsum('ij,sj->si', m_linear, geometry.positions)
    # 2. A dipole 60 m away along a direction varying per sample: units (nT/m) against
    #    core.fields.dipole_gradient at the centroid, within the d/R truncation.
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    moment = np.array([4e6, -2e6, 3e6])
    sources = geometry.centroid + 60.0 * directions
    dipole = np.array([[dipole_field(geometry.positions, moment, s)] for s in sources])[:, 0] + earth
    fields = np.concatenate([np.broadcast_to(linear, (n, 4, 3)), dipole])
    all_stamps = np.concatenate([stamps, stamps[-1] + 10_000_000 + stamps - stamps[0]])
    with BagWriter(tmp_path / 'bag', storage='mcap') as writer:
        writer.write_fields(all_stamps, fields)
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': geometry.to_flat()}))
    cli('compensate', tmp_path / 'bag', '--params', tmp_path / 'params.yaml', '--raw', '--csv', tmp_path / 'g.csv')
    header, csv_stamps, g = read_csv(tmp_path / 'g.csv')
    assert header.split(',') == ['stamp_s', 'gxx', 'gxy', 'gxz', 'gyx', 'gyy', 'gyz', 'gzx', 'gzy', 'gzz']
    assert csv_stamps.tolist() == all_stamps.tolist()  # absolute, exact to the nanosecond
    text_stamp = Path(tmp_path / 'g.csv').read_text().splitlines()[1].split(',')[0]
    assert text_stamp == f'{all_stamps[0] // 10**9}.{all_stamps[0] % 10**9:09d}'
    assert np.allclose(g[:n], m_linear * 1e9, atol=1e-5)  # nT/m, gxy = dBx/dy = 2e-7 T/m = 200 nT/m
    assert g[0, 0, 1] == pytest.approx(200.0) and g[0, 1, 0] == pytest.approx(400.0)
    analytic = np.array([dipole_gradient(geometry.centroid[None], moment, s)[0] for s in sources]) * 1e9
    scale = np.abs(analytic).max(axis=(1, 2))
    assert np.all(np.abs(g[n:] - analytic).max(axis=(1, 2)) < 0.03 * scale)  # d/R = 0.8 %
    assert scale.min() > 1.0  # nT/m: a unit error of 1e9 could not pass


# ---------------------------------------------------------------- failures


@pytest.fixture(scope='module')
def good(tmp_path_factory):
    """A small good bag + params + calibration shared by the failure cases."""
    root = tmp_path_factory.mktemp('good')
    document = small_mission(True)
    document['segments'][0]['trim']['duration_s'] = 20
    document['segments'][1]['line']['end_m'] = [-20.0, 0.0, -50.0]
    (root / 'mission.yaml').write_text(yaml.safe_dump(document))
    cli('simulate', '--scenario', root / 'mission.yaml', '--out', root / 'bag', '--mag-only')
    cli('calibrate', root / 'bag', '--params', root / 'bag.params.yaml', '--window', '0:19.9',
        '--out', root / 'calib.yaml')
    return root


def assert_fails(result, *fragments):
    assert result.returncode == 1, (result.returncode, result.stdout, result.stderr)
    assert result.stderr.startswith('error: '), result.stderr
    assert 'Traceback' not in result.stderr
    for fragment in fragments:
        assert fragment in result.stderr, (fragment, result.stderr)


def _bag_with(path, topics, n=50, offsets_ns=(0, 0, 0, 0), storage='sqlite3'):
    with BagWriter(path, storage=storage) as writer:
        for i in range(n):
            for sensor, topic in enumerate(cv.BAG_MAG_TOPICS):
                if topic in topics:
                    stamp = START_NS + i * 100_000_000 + offsets_ns[sensor]
                    writer.write(topic, cv.magnetic_field_msg(writer.types, np.array([0.0, 2e-5, -4e-5]), stamp,
                                                              cv.MAG_FRAMES[sensor]), stamp)
    return path


def both_commands(good, bag, params=None, *options):
    params = params or good / 'bag.params.yaml'
    return (cli('calibrate', bag, '--params', params, '--out', good / 'never.yaml', *options, check=False),
            cli('compensate', bag, '--params', params, '--calibration', good / 'calib.yaml',
                '--csv', good / 'never.csv', *options, check=False))


def test_missing_topic(good, tmp_path):
    bag = _bag_with(tmp_path / 'three', cv.BAG_MAG_TOPICS[:3])
    for result in both_commands(good, bag):
        assert_fails(result, "missing topic(s) ['/tetra/mag4']")
    assert not (good / 'never.yaml').exists() and not (good / 'never.csv').exists()


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_empty_bag(good, tmp_path, storage):
    with BagWriter(tmp_path / 'empty', storage=storage) as writer:
        for topic in cv.BAG_MAG_TOPICS:
            writer._connection(topic, cv.MAGNETIC_FIELD)  # topics declared, no message
    for result in both_commands(good, tmp_path / 'empty'):
        assert_fails(result, 'empty bag')


def test_wrong_message_type_on_a_magnetometer_topic(good, tmp_path):
    with BagWriter(tmp_path / 'typed') as writer:
        for sensor, topic in enumerate(cv.BAG_MAG_TOPICS):
            if sensor == 1:
                writer.write(topic, cv.temperature_msg(writer.types, 12.0, START_NS), START_NS)
            else:
                writer.write(topic, cv.magnetic_field_msg(writer.types, np.zeros(3), START_NS, cv.MAG_FRAMES[sensor]),
                             START_NS)
    for result in both_commands(good, tmp_path / 'typed'):
        assert_fails(result, '/tetra/mag2 has type sensor_msgs/msg/Temperature, expected sensor_msgs/msg/MagneticField')


def test_sensors_that_cannot_be_matched_by_stamp(good, tmp_path):
    """Pairing stamps (--sync nearest) 5 ms apart within 2 ms: no set. (Resampling, the
    default, forms them: test/io/test_realworld.py.)"""
    bag = _bag_with(tmp_path / 'skewed', cv.BAG_MAG_TOPICS, offsets_ns=(0, 0, 0, 5_000_000))
    for result in both_commands(good, bag, None, '--sync', 'nearest'):
        assert_fails(result, 'no sample set could be formed (nearest stamps within 2 ms)', 'messages unmatched')
    assert not (good / 'never.csv').exists()


def test_window_with_too_little_attitude_diversity(good, tmp_path):
    document = small_mission(True)
    document['segments'] = [{'line': {'start_m': [2000.0, 0.0, -50.0], 'end_m': [2060.0, 0.0, -50.0]}}]
    (tmp_path / 'straight.yaml').write_text(yaml.safe_dump(document))
    cli('simulate', '--scenario', tmp_path / 'straight.yaml', '--out', tmp_path / 'bag', '--mag-only')
    for method in ('known_gradient_lstsq_general', 'known_gradient_lstsq', 'constraint_lstsq', 'paper_ga'):
        result = cli('calibrate', tmp_path / 'bag', '--params', tmp_path / 'bag.params.yaml', '--method', method,
                     '--out', tmp_path / 'c.yaml', check=False)
        assert_fails(result, 'too little attitude diversity', 'attitude coverage condition number')
    condition = float(result.stderr.split('condition number ')[1].split(' ')[0])
    assert condition > 1e4
    assert not (tmp_path / 'c.yaml').exists()


def test_window_outside_the_bag_and_malformed_windows(good):
    result = cli('calibrate', good / 'bag', '--params', good / 'bag.params.yaml', '--window', '500:600',
                 '--out', good / 'never.yaml', check=False)
    assert_fails(result, 'holds no sample set', 'the bag spans 0:')
    for window in ('5', 'a:b', '10:5'):  # malformed: a usage error (exit 2), one error line
        result = cli('calibrate', good / 'bag', '--params', good / 'bag.params.yaml', '--window', window,
                     '--out', good / 'never.yaml', check=False)
        assert result.returncode == 2 and 'Traceback' not in result.stderr, result.stderr
        assert result.stderr.splitlines()[-1].endswith(f"argument --window: {'needs 0 <= T0 < T1' if window == '10:5' else 'must be T0:T1 in seconds from the first stamp'}, got {window!r}"), result.stderr
    assert not (good / 'never.yaml').exists()


@pytest.mark.parametrize('content,fragment', [
    ({'earth_field_enu': [0.0, 2e-5, -4e-5]}, 'sensor_positions is missing'),
    ({'sensor_positions': [0.0] * 11}, 'sensor_positions must be 12 finite floats, got 11'),
    ({'sensor_positions': ['a'] * 12}, 'sensor_positions must be 12 numbers'),
    ({'sensor_positions': [0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0]}, 'sensors must not be coplanar'),
])
def test_params_without_valid_sensor_positions(good, tmp_path, content, fragment):
    (tmp_path / 'p.yaml').write_text(params_document(content))
    for result in both_commands(good, good / 'bag', params=tmp_path / 'p.yaml'):
        assert_fails(result, fragment)


def test_other_input_errors_name_the_problem(good, tmp_path):
    assert_fails(both_commands(good, tmp_path / 'nowhere')[0], 'bag not found')
    assert_fails(cli('calibrate', good / 'bag', '--params', tmp_path / 'none.yaml', '--out', tmp_path / 'c.yaml',
                     check=False), 'params file not found')
    assert_fails(cli('compensate', good / 'bag', '--params', good / 'bag.params.yaml', '--calibration',
                     tmp_path / 'none.yaml', '--csv', tmp_path / 'x.csv', check=False), 'cannot read calibration file')
    moved = TetraGeometry.regular(0.6).to_flat()
    (tmp_path / 'p.yaml').write_text(params_document({'sensor_positions': moved}))
    assert_fails(cli('compensate', good / 'bag', '--params', tmp_path / 'p.yaml', '--calibration',
                     good / 'calib.yaml', '--csv', tmp_path / 'x.csv', check=False), 'other sensor positions')
    assert_fails(cli('compensate', good / 'bag', '--params', good / 'bag.params.yaml', '--raw', check=False),
                 'nothing to write')
    (tmp_path / 'bad.yaml').write_text('segments: [{trim: {duration_s: -5}}]\n')
    assert_fails(cli('simulate', '--scenario', tmp_path / 'bad.yaml', '--out', tmp_path / 'b', check=False),
                 'duration_s must be positive')


def test_a_set_with_a_non_finite_reading_is_skipped_and_counted(tmp_path):
    geometry = TetraGeometry.regular(EDGE_M)
    n = 30
    stamps = START_NS + np.arange(n, dtype=np.int64) * 10_000_000
    m_linear = np.arange(1.0, 10.0).reshape(3, 3) * 1e-7
    fields = np.repeat((np.array([0.0, 2e-5, -4e-5]) + geometry.positions @ m_linear.T)[None], n, axis=0)
    fields[7, 2, 1] = np.nan
    with BagWriter(tmp_path / 'bag') as writer:
        writer.write_fields(stamps, fields)
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': geometry.to_flat()}))
    out = cli('compensate', tmp_path / 'bag', '--params', tmp_path / 'params.yaml', '--raw',
              '--csv', tmp_path / 'g.csv')
    assert '29 sets' in out.stdout and 'implausible sets dropped: 1 non-finite' in out.stdout
    _, csv_stamps, g = read_csv(tmp_path / 'g.csv')
    assert csv_stamps.tolist() == np.delete(stamps, 7).tolist()
    assert np.allclose(g, m_linear * 1e9, atol=1e-5)
