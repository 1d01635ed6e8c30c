"""Every numeric option of every command is checked at parse time (cli/_args.py type=
factories): a value out of its physical range, NaN, inf or text is a usage error, exit 2,
with one ``error:`` line naming the option and the allowed range, and no traceback;
nothing is read or written. In range values parse to what the commands use."""

import argparse
import importlib
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tetra_gradiometer.__main__ import COMMANDS, main
from tetra_gradiometer.core.discrepancy import CANDIDATES

REPO = Path(__file__).resolve().parents[2]

#: The required arguments of each command (never read: parsing stops at the bad option).
REQUIRED = {
    'calibrate': ['BAG', '--params', 'P.yaml', '--out', 'C.yaml'],
    'compensate': ['BAG', '--params', 'P.yaml', '--csv', 'O.csv'],
    'simulate': ['--scenario', 'S.yaml', '--out', 'OUT'],
    'discrepancy': ['BAG', '--params', 'P.yaml', '--out', 'OUT'],
    'batch': ['DIR', '--out', 'OUT'],
    'survey': ['BAG', '--params', 'P.yaml', '--calibration', 'C.yaml', '--out', 'OUT', '--origin', '43,5'],
    'paper': ['--out', 'OUT'],
    'bringup': [],
    'record': ['--out', 'OUT', '--duration', '5'],
    'demo': [],
}

TOLERANCE = ('0 < x <= 1000 ms',)
SEED = ('0 <= n <= 2147483647',)

#: (command, option, bad value, fragments of the one error line)
BAD = [
    # --tolerance-ms (calibrate, compensate, discrepancy): the cases
    *[
        (command, '--tolerance-ms', value, TOLERANCE)
        for command in ('compensate', 'calibrate', 'discrepancy', 'survey')
        for value in ('inf', 'nan', '-1', '1e9', '0', 'abc', '1000.001')
    ],
    # how sets are formed (calibrate, compensate, discrepancy)
    *[
        (command, option, value, fragment)
        for command in ('compensate', 'calibrate', 'discrepancy', 'survey')
        for option, fragment, values in (
            ('--reference-rate-hz', ('0 <= x <= 10000 Hz',), ('-1', 'nan', 'inf', '10001', 'x')),
            ('--max-gap-periods', ('1 <= x <= 1000',), ('0.5', 'nan', 'inf', '1001', 'x')),
        )
        for value in values
    ],
    ('compensate', '--sync', 'spline', ("invalid choice: 'spline'",)),
    # compensate
    *[('compensate', '--sensor-noise-nt', value, ('0 < x <= 1000 nT',)) for value in ('0', '-1', 'nan', 'inf', '1001', 'x')],
    *[('compensate', '--false-alarms-per-hour', value, ('0 < x <= 60 per hour',)) for value in ('0', '-1', 'nan', '61')],
    # calibrate
    ('calibrate', '--window', '10:5', ('0 <= T0 < T1',)),
    ('calibrate', '--current-topics', 'battery', ('battery is not an absolute topic name',)),
    ('calibrate', '--current-topics', ',', ("no topic in ','",)),
    # the topic names of every command reading a bag (cli/_args.add_bag_arguments)
    *[case for command in ('calibrate', 'compensate', 'discrepancy', 'survey') for case in (
        (command, '--mag-topics', '/a,/b,/c', ('expected 4 topics, got 3',)),
        (command, '--mag-topics', '/a,/a,/b,/c', ('a topic is named twice',)),
        (command, '--odom-topic', 'odom', ('odom is not an absolute topic name',)),
        (command, '--namespace', 'auv 1', ('/auv 1 is not an absolute topic name',)))],
    ('calibrate', '--window', 'a:b', ('T0:T1',)),
    ('calibrate', '--window', '5', ('T0:T1',)),
    ('calibrate', '--window', 'nan:5', ('0 <= T0 < T1',)),
    ('calibrate', '--window', '3:nan', ('0 <= T0 < T1',)),
    ('calibrate', '--seed', '-1', SEED),
    ('calibrate', '--seed', str(2**31), SEED),
    ('calibrate', '--seed', '1.5', SEED),
    ('calibrate', '--generations', '0', ('1 <= n <= 100000',)),
    ('calibrate', '--generations', '100001', ('1 <= n <= 100000',)),
    ('calibrate', '--max-sets', '9', ('10 <= n <= 1000000',)),
    ('calibrate', '--max-sets', '9' * 5000, ('10 <= n <= 1000000',)),
    ('calibrate', '--max-coverage-condition', '0.5', ('1 <= x <= 1e+16',)),
    ('calibrate', '--max-coverage-condition', 'inf', ('1 <= x <= 1e+16',)),
    ('calibrate', '--max-coverage-condition', 'nan', ('1 <= x <= 1e+16',)),
    # simulate
    ('simulate', '--seed', '-1', SEED),
    ('simulate', '--seed', 'x', SEED),
    ('simulate', '--start-utc', '1969-12-31T23:59:59Z', ('1970-01-01', '2200-01-01')),
    ('simulate', '--start-utc', '9999-01-01T00:00:00Z', ('1970-01-01', '2200-01-01')),
    ('simulate', '--start-utc', 'yesterday', ('not an ISO 8601 time',)),
    # discrepancy
    ('discrepancy', '--folds', '1', ('2 <= n <= 20',)),
    ('discrepancy', '--folds', '21', ('2 <= n <= 20',)),
    ('discrepancy', '--max-effects', '0', (f'1 <= n <= {len(CANDIDATES)}',)),
    ('discrepancy', '--max-effects', str(len(CANDIDATES) + 1), (f'1 <= n <= {len(CANDIDATES)}',)),
    ('discrepancy', '--relevance', '-0.1', ('0 <= x <= 100',)),
    ('discrepancy', '--relevance', 'nan', ('0 <= x <= 100',)),
    ('discrepancy', '--relevance', '1e3', ('0 <= x <= 100',)),
    ('discrepancy', '--window', '3:1', ('0 <= T0 < T1',)),
    ('discrepancy', '--candidates', 'eddy_current,nonsense', ("['nonsense']", 'eddy_current')),
    ('discrepancy', '--candidates', ',', ('at least one of',)),
    # batch
    ('batch', '--window', '3:1', ('0 <= T0 < T1',)),
    *[('batch', '--workers', value, ('1 <= n <= 256',)) for value in ('0', '257', '1.5', 'x')],
    *[('batch', '--survey-origin', value, fragment)
      for value, fragment in (('95,5', ('latitude',)), ('43', ('LAT,LON',)), ('0,nan', ('LAT,LON',)))],
    # survey
    *[('survey', '--origin', value, fragment)
      for value, fragment in (('95,5', ('latitude',)), ('0,181', ('longitude',)), ('x,y', ('LAT,LON',)))],
    *[('survey', '--cell-m', value, ('0 < x <= 10000 m',)) for value in ('0', '-1', 'nan', 'inf', '1e5', 'x')],
    *[('survey', '--max-distance-m', value, ('0 < x <= 100000 m',)) for value in ('0', 'nan', '1e6')],
    *[('survey', '--sensor-noise-nt', value, ('0 < x <= 1000 nT',)) for value in ('0', 'nan', '1001')],
    *[('survey', '--false-alarms-per-hour', value, ('0 < x <= 60 /h',)) for value in ('0', 'nan', '61')],
    # paper
    ('paper', '--generations', '0', ('1 <= n <= 100000',)),
    ('paper', '--seed', str(2**31), SEED),
    # bringup, record, demo (parsed before ROS starts)
    ('bringup', '--rate', '-1', ('0 <= x <= 1000',)),
    ('bringup', '--rate', 'inf', ('0 <= x <= 1000',)),
    ('bringup', '--rate', '1001', ('0 <= x <= 1000',)),
    ('record', '--duration', '0', ('0 < x <= 86400 s',)),
    ('record', '--duration', 'nan', ('0 < x <= 86400 s',)),
    ('record', '--duration', '86401', ('0 < x <= 86400 s',)),
    ('record', '--seed', '-2', ('-1 <= n <= 2147483647',)),
    ('record', '--rate', '0', ('0 < x <= 1000',)),
    ('record', '--rate', 'inf', ('0 < x <= 1000',)),
    ('demo', '--rate', '-1', ('0 <= x <= 1000',)),
    ('demo', '--rate', 'nan', ('0 <= x <= 1000',)),
]


def _usage_error(capsys, argv):
    """Run ``main(argv)`` in-process: (exit status, the stderr lines)."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    captured = capsys.readouterr()
    assert captured.out == ''
    return stop.value.code, captured.err


@pytest.mark.parametrize('command, option, value, fragments', BAD)
def test_out_of_range_option_is_one_usage_error(capsys, monkeypatch, tmp_path, command, option,
                                                 value, fragments):
    monkeypatch.chdir(tmp_path)  # any output would land here
    argv = [command, *REQUIRED[command], f'{option}={value}']
    code, err = _usage_error(capsys, argv)
    assert code == 2, err
    assert 'Traceback' not in err
    errors = [line for line in err.splitlines() if ': error: ' in line]
    assert len(errors) == 1, err
    assert err.splitlines()[-1] == errors[0] and err.startswith('usage: '), err
    assert f'argument {option}: ' in errors[0], errors[0]
    for fragment in fragments:
        assert fragment in errors[0], (fragment, errors[0])
    assert list(tmp_path.iterdir()) == []


def test_every_numeric_option_is_covered():
    """Each option whose value is a number (or a window, seed, time) has a type= from
    cli/_args.py or the command's own check, and a case in BAD: a new option without one
    fails here."""
    covered = {(command, option) for command, option, _, _ in BAD}
    for command in REQUIRED:
        parser = argparse.ArgumentParser()
        importlib.import_module(COMMANDS[command][0]).add_arguments(parser)
        for action in parser._actions:
            if action.type in (int, float):
                pytest.fail(f'{command} {action.option_strings}: bare type={action.type.__name__}')
            if action.type is not None and action.option_strings:
                assert (command, action.option_strings[0]) in covered, (command, action.dest)


@pytest.mark.parametrize('value', ['inf', 'nan', '-1', '1e9'])
def test_tolerance_through_the_real_command_line(tmp_path, value):
    """The issue's case, in a subprocess: ``compensate BAG ... --tolerance-ms inf`` gave a
    traceback."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop('TETRA_DEBUG', None)
    result = subprocess.run(
        [sys.executable, '-m', 'tetra_gradiometer', 'compensate', str(tmp_path / 'bag'),
         '--params', str(tmp_path / 'p.yaml'), '--csv', str(tmp_path / 'o.csv'),
         '--tolerance-ms', value],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120,
    )
    assert result.returncode == 2, result.stderr
    assert 'Traceback' not in result.stderr and result.stdout == ''
    errors = [line for line in result.stderr.splitlines() if ': error: ' in line]
    assert len(errors) == 1 and 'argument --tolerance-ms' in errors[0], result.stderr
    assert f"0 < x <= 1000 ms, got '{value}'" in errors[0]
    assert list(tmp_path.iterdir()) == []


def _parse(command, *options):
    parser = argparse.ArgumentParser()
    importlib.import_module(COMMANDS[command][0]).add_arguments(parser)
    return parser.parse_args([*REQUIRED[command], *options])


@pytest.mark.parametrize('command, options, attribute, expected', [
    ('compensate', [], 'tolerance_ms', 2.0),
    ('compensate', [], 'sync', 'interpolate'),
    ('compensate', [], 'reference_rate_hz', 0.0),
    ('calibrate', ['--reference-rate-hz', '100'], 'reference_rate_hz', 100.0),
    ('calibrate', [], 'max_gap_periods', 3.0),
    ('calibrate', ['--max-gap-periods', '1000'], 'max_gap_periods', 1000.0),
    ('compensate', ['--tolerance-ms', '1000'], 'tolerance_ms', 1000.0),
    ('calibrate', ['--tolerance-ms', '0.001'], 'tolerance_ms', 0.001),
    ('calibrate', [], 'window', None),
    ('calibrate', ['--window', ':300'], 'window', (0.0, 300.0)),
    ('calibrate', ['--window', '600:'], 'window', (600.0, math.inf)),
    ('calibrate', ['--window', '0:299.95'], 'window', (0.0, 299.95)),
    ('calibrate', ['--seed', str(2**31 - 1)], 'seed', 2**31 - 1),
    ('calibrate', ['--generations', '1'], 'generations', 1),
    ('calibrate', [], 'max_sets', 50_000),
    ('calibrate', ['--max-coverage-condition', '1e12'], 'max_coverage_condition', 1e12),
    ('simulate', [], 'start_utc', 1_767_225_600 * 10**9),
    ('simulate', ['--start-utc', '1970-01-01T00:00:00Z'], 'start_utc', 0),
    ('simulate', ['--seed', '0'], 'seed', 0),
    ('discrepancy', [], 'candidates', None),
    ('discrepancy', ['--candidates', ' time_skew, eddy_current '], 'candidates',
     ('time_skew', 'eddy_current')),
    ('discrepancy', ['--folds', '20', '--relevance', '0'], 'folds', 20),
    ('discrepancy', ['--relevance', '0'], 'relevance', 0.0),
    ('discrepancy', ['--window', '10:'], 'window', (10.0, math.inf)),
    ('batch', [], 'workers', None),
    ('batch', ['--workers', '256', '--window', '0:59'], 'window', (0.0, 59.0)),
    ('paper', [], 'generations', 1000),
    ('bringup', ['--rate', '0'], 'rate', 0.0),
    ('bringup', [], 'rate', None),
    ('record', ['--seed', '-1', '--rate', '1000'], 'seed', -1),
    ('record', [], 'duration', 5.0),
    ('demo', [], 'rate', 0.0),
    ('demo', ['--rate', '20'], 'rate', 20.0),
])
def test_in_range_values_parse(command, options, attribute, expected):
    assert getattr(_parse(command, *options), attribute) == expected


BINARY = b'\xff\xfe\x00\x00/**: {}\n'


@pytest.mark.parametrize('command, kind', [
    ('calibrate', 'params'), ('compensate', 'params'), ('discrepancy', 'params'),
    ('simulate', 'scenario'),
])
def test_non_utf8_input_file_is_one_error_naming_it(capsys, monkeypatch, tmp_path, command, kind):
    """A params or scenario file that is not UTF-8 text: exit 1, one ``error:`` line naming
    the file and the byte, nothing written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / 'in').mkdir()
    bad = tmp_path / 'in' / 'P.yaml'
    bad.write_bytes(BINARY)
    argv = [str(a).replace('P.yaml', str(bad)).replace('S.yaml', str(bad)) for a in REQUIRED[command]]
    extra = ['--raw'] if command == 'compensate' else []
    code = main([command, *argv, *extra])
    captured = capsys.readouterr()
    assert code == 1, captured
    assert captured.err == f'error: {kind} file {bad} is not UTF-8 text: byte 0xff at offset 0 (invalid start byte)\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['in']
