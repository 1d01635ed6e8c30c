"""Fault table, stream health: each magnetometer stream is checked before sets are
formed (core/streams.py, through the bag reader), and what is wrong is named with the sensor
and the time span. Refused: one ``error:`` line, exit 1, nothing written, the bag's bytes
unchanged. Warned: exit 0, the fault in the summary line and the calibration file's
diagnostics, the sets lost counted (never "0 sets skipped").

Truth is independent of the reader: the stamps and readings written (a 30 s trim and a 20 s
survey line at 10 Hz, simulated), the factor each fault was built with.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from cli_helpers import assert_refused, run_cli, snapshot
from stream_faults import START_NS, short_mission, write_bag, write_params

from tetra_gradiometer.core.streams import StreamChecker, magnitude_mismatch
from tetra_gradiometer.errors import StreamError

GPS_UNIX_S = 315_964_800


@pytest.fixture(scope='module')
def mission():
    return short_mission()


@pytest.fixture(scope='module')
def params(tmp_path_factory):
    root = tmp_path_factory.mktemp('params')
    return write_params(root / 'params.yaml'), write_params(root / 'bare.yaml', earth=False)


def _log(mission):
    return START_NS + np.round(mission.t * 1e9).astype(np.int64)


def _compensate(capsys, bag, params, out):
    return run_cli(capsys, 'compensate', bag, '--params', params, '--raw', '--csv', out)


def _csv_stamps(path):
    rows = path.read_text().splitlines()[1:]
    return [int(row.split(',')[0].replace('.', '')) for row in rows]


def _refused(capsys, tmp_path, bag, params, *fragments):
    """compensate refuses with one line holding ``fragments``; the bag is untouched, no CSV."""
    before = snapshot(bag)
    assert_refused(_compensate(capsys, bag, params, tmp_path / 'g.csv'), *fragments)
    assert snapshot(bag) == before and not (tmp_path / 'g.csv').exists()


# ----------------------------------------------------------------------------- refused


def test_all_header_stamps_zero_is_refused(mission, params, tmp_path, capsys):
    n = len(mission.t)
    bag = write_bag(tmp_path / 'bag', mission, stamps=[np.zeros(n, np.int64)] * 4)
    _refused(capsys, tmp_path, bag, params[0], 'every header stamp of /tetra/mag1, /tetra/mag2, /tetra/mag3, '
             '/tetra/mag4 is 0', 'does not fill header.stamp')


def test_one_sensor_with_zero_stamps_is_refused(mission, params, tmp_path, capsys):
    log = _log(mission)
    bag = write_bag(tmp_path / 'bag', mission, stamps=[log, log, log, np.zeros_like(log)])
    _refused(capsys, tmp_path, bag, params[0], 'every header stamp of /tetra/mag4 (sensor 4) is 0')


@pytest.mark.parametrize('factor,sensors,fragment', [
    (1e6, (0, 1, 2, 3), 'every magnetometer reads a median |B| of 49.'),
    (1e4, (0, 1, 2, 3), 'every magnetometer reads a median |B| of 0.49'),
    (1e4, (1,), '/tetra/mag2 (sensor 2) reads a median |B| of 0.49'),
    (1e9, (3,), '/tetra/mag4 (sensor 4) reads a median |B| of 4.9'),
])
@pytest.mark.parametrize('with_earth', [True, False])
def test_a_unit_written_as_tesla_is_refused_and_named(mission, params, tmp_path, capsys, factor, sensors,
                                                       fragment, with_earth):
    fields = mission.fields_measured.copy()
    fields[:, list(sensors)] *= factor
    bag = write_bag(tmp_path / 'bag', mission, fields=fields)
    unit = {1e6: 'µT written as tesla', 1e4: 'Gauss written as tesla', 1e9: 'nT written as tesla'}[factor]
    # The span: the readings the test took (0 s to the end of the 49.9 s recording).
    _refused(capsys, tmp_path, bag, params[0 if with_earth else 1], fragment, unit, '(0.0-49.9 s)')


def test_ten_times_the_earth_field_is_refused_by_calibrate(mission, params, tmp_path, capsys):
    bag = write_bag(tmp_path / 'bag', mission, fields=mission.fields_measured * 10)
    before = snapshot(bag)
    assert_refused(run_cli(capsys, 'calibrate', bag, '--params', params[0], '--out', tmp_path / 'c.yaml'),
                   'every magnetometer', '10x the Earth field of 49.2 µT (earth_field_enu)', 'no unit factor')
    assert snapshot(bag) == before and not (tmp_path / 'c.yaml').exists()


def test_a_sensor_in_another_epoch_is_refused_naming_it(mission, params, tmp_path, capsys):
    log = _log(mission)
    gps = log - GPS_UNIX_S * 10**9  # sensor 3 stamped in Unix seconds minus the GPS epoch
    bag = write_bag(tmp_path / 'bag', mission, stamps=[log, log, gps, log])
    _refused(capsys, tmp_path, bag, params[0], '/tetra/mag3 (sensor 3)', '-3.15965e+08 s', 'GPS time', 'another epoch')


def test_a_sensor_in_another_epoch_is_refused_also_when_logged_at_its_stamps(mission, params, tmp_path, capsys):
    """Without the recorder's log times to compare with (logged at the header stamps): its
    stamps never overlap the others'."""
    log = _log(mission)
    # Sensor 4 an hour later, logged at its stamps: a time zone.
    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io.bag import BagWriter
    with BagWriter(tmp_path / 'bag') as writer:
        for i, stamp in enumerate(log):
            for sensor in range(3):
                writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD,
                                 cv.magnetic_field_cdr(mission.fields_measured[i, sensor], int(stamp),
                                                       cv.MAG_FRAMES[sensor]), int(stamp))
        for i, stamp in enumerate(log + 3600 * 10**9):
            writer.write_raw(cv.BAG_MAG_TOPICS[3], cv.MAGNETIC_FIELD,
                             cv.magnetic_field_cdr(mission.fields_measured[i, 3], int(stamp), cv.MAG_FRAMES[3]),
                             int(stamp))
    _refused(capsys, tmp_path, tmp_path / 'bag', params[0], '/tetra/mag4 (sensor 4)', '+3600 s', 'time zone',
             'never overlap')


# ----------------------------------------------------------------------------- warned and counted


def test_a_sensor_that_stops_halfway_is_named_with_span_and_sets_lost(mission, params, tmp_path, capsys):
    n = len(mission.t)
    log = _log(mission)
    keep = [np.ones(n, bool)] * 4
    keep[2] = np.arange(n) < n // 2  # /tetra/mag3 stops at 24.9 s of 49.9 s
    bag = write_bag(tmp_path / 'bag', mission, keep=keep)
    before = snapshot(bag)
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert snapshot(bag) == before
    assert _csv_stamps(tmp_path / 'g.csv') == log[: n // 2].tolist()  # every set with all four
    assert f'{n - n // 2} sets skipped' in out and f'{n - n // 2} at stream ends' in out
    assert '/tetra/mag3 (sensor 3) stops at 24.9 s of 49.9 s: no data 24.9-49.9 s, 250 sets lost' in out
    # ... in the output bag's metadata (rosbag2 custom_data) ...
    code, out, err = run_cli(capsys, 'compensate', bag, '--params', params[0], '--raw', '--out-bag', tmp_path / 'out')
    assert code == 0, err
    metadata = yaml.safe_load((tmp_path / 'out' / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    faults = json.loads(metadata['custom_data']['tetra_gradiometer.stream_faults'])
    assert faults['sets_lost_stream_faults'] == 250 and faults['stream_faults'][0]['topic'] == '/tetra/mag3'
    # ... and in the calibration file's diagnostics (the output's metadata).
    code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params[0], '--out', tmp_path / 'c.yaml')
    assert code == 0, err
    assert '/tetra/mag3 (sensor 3) stops at 24.9 s' in out and '250 at stream ends' in out
    diagnostics = yaml.safe_load((tmp_path / 'c.yaml').read_text())['diagnostics']
    (fault,) = diagnostics['stream_faults']
    assert (fault['topic'], fault['kind'], fault['sets_lost']) == ('/tetra/mag3', 'stops', 250)
    assert fault['start_s'] == pytest.approx(24.9) and fault['end_s'] == pytest.approx(49.9)
    assert diagnostics['sets_in_window'] == n // 2 and diagnostics['sets_skipped_end'] == n - n // 2


def test_a_sensor_that_starts_late_is_named(mission, params, tmp_path, capsys):
    n = len(mission.t)
    keep = [np.ones(n, bool)] * 4
    keep[1] = np.arange(n) >= 100  # /tetra/mag2 from 10 s on
    bag = write_bag(tmp_path / 'bag', mission, keep=keep)
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert '/tetra/mag2 (sensor 2) starts late, at 10.0 s: no data 0.0-10.0 s, 100 sets lost' in out
    assert len(_csv_stamps(tmp_path / 'g.csv')) == n - 100


def test_a_jump_on_one_sensor_drops_its_misstamped_messages(mission, params, tmp_path, capsys):
    n = len(mission.t)
    log = _log(mission)
    jumped = log.copy()
    jumped[300:] += 100 * 10**9  # sensor 2's clock jumps 100 s ahead at 30 s
    bag = write_bag(tmp_path / 'bag', mission, stamps=[log, jumped, log, log])
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert f'/tetra/mag2 (sensor 2): {n - 300} messages whose stamps jumped +100 s on it alone dropped ' \
           '(30.0-49.9 s)' in out
    # Never paired with the others' readings of 100 s later: only the sets before the jump.
    assert _csv_stamps(tmp_path / 'g.csv') == log[:300].tolist()


def test_duplicated_stamps_with_different_readings_are_dropped_and_named(mission, params, tmp_path, capsys):
    log = _log(mission)
    repeated = log.copy()
    repeated[200:205] = repeated[199]  # five more messages at 19.9 s, each another reading
    bag = write_bag(tmp_path / 'bag', mission, stamps=[log, log, log, repeated])
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert '/tetra/mag4 (sensor 4): 6 messages sharing a stamp with another reading dropped (19.9-19.9 s)' in out
    stamps = _csv_stamps(tmp_path / 'g.csv')
    assert int(log[199]) not in stamps and int(log[198]) in stamps


def test_some_zero_stamps_are_dropped_and_counted(mission, params, tmp_path, capsys):
    log = _log(mission)
    holed = log.copy()
    holed[50:53] = 0
    bag = write_bag(tmp_path / 'bag', mission, stamps=[log, holed, log, log])
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert '/tetra/mag2 (sensor 2): 3 messages with header stamp 0 dropped' in out


def test_a_healthy_bag_has_no_stream_fault(mission, params, tmp_path, capsys):
    bag = write_bag(tmp_path / 'bag', mission)
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert '0 sets skipped' in out and 'sensor' not in out.split('sensor clocks')[0]
    assert _csv_stamps(tmp_path / 'g.csv') == _log(mission).tolist()


# ----------------------------------------------------------------------------- the core checker


@pytest.mark.parametrize('ratio,expected', [
    (1e6, 'µT'), (1.28e6, 'µT'), (1e4, 'Gauss'), (1e9, 'nT'), (1e7, 'milligauss'), (1e-9, 'twice'),
    (10.0, 'no unit factor'), (300.0, 'no unit factor'),
])
def test_unit_factors_are_named_within_half_a_decade(ratio, expected):
    assert expected in magnitude_mismatch(ratio)


def test_checker_raises_the_one_error_class_and_names_the_sensor():
    rng = np.random.default_rng(0)
    stamps = [np.arange(100, dtype=np.int64) * 10**8 + 10**18] * 4
    fields = [rng.normal(0, 1, (100, 3)) * 1e-6 + [0, 2e-5, -4.5e-5] for _ in range(4)]
    fields[2] = fields[2] * 1e4
    with pytest.raises(StreamError, match=r'/tetra/mag3 \(sensor 3\).*Gauss written as tesla'):
        StreamChecker().check(stamps, fields, final=True)


def test_a_stuck_sensor_is_dropped_and_named(mission, params, tmp_path, capsys):
    fields = mission.fields_measured.copy()
    fields[200:320, 2] = fields[199, 2]  # sensor 3 repeats its 19.9 s reading for 12 s
    bag = write_bag(tmp_path / 'bag', mission, fields=fields)
    code, out, err = _compensate(capsys, bag, params[0], tmp_path / 'g.csv')
    assert code == 0, err
    assert '/tetra/mag3 (sensor 3): 120 readings repeating the one before exactly (stuck) dropped (20.0-31.9 s)' in out
    assert '/tetra/mag3 (sensor 3) falls silent: no data 19.9-32.0 s' in out
    stamps = _csv_stamps(tmp_path / 'g.csv')
    log = _log(mission)
    assert not set(log[200:320].tolist()) & set(stamps) and int(log[199]) in stamps


@pytest.mark.parametrize('value,fragment', [(np.nan, 'every reading is NaN or inf (0.0-49.9 s)'),
                                            (0.0, 'it reads 0 (a sensor not connected?)')])
def test_a_dead_sensor_is_refused_and_named(mission, params, tmp_path, capsys, value, fragment):
    fields = mission.fields_measured.copy()
    fields[:, 1] = value
    bag = write_bag(tmp_path / 'bag', mission, fields=fields)
    _refused(capsys, tmp_path, bag, params[0], '/tetra/mag2 (sensor 2)', fragment)


def test_live_check_drops_one_sensor_off_the_clock_but_follows_a_restart_of_all():
    from tetra_gradiometer.core.live_streams import LiveStreamCheck
    check = LiveStreamCheck(tolerance_s=10.0, recent_s=2.0)
    reading = (0.0, 2e-5, -4.5e-5)
    t, now = START_NS, 0
    for i in range(10):  # four sensors on one clock
        assert all(check.accept(s, t + i * 10**8, now + i * 10**8, *reading) for s in range(4))
    now += 10**9
    assert not check.accept(2, t + 10**9 - GPS_UNIX_S * 10**9, now, *reading)  # sensor 3 on GPS time
    assert check.dropped[2]['other_clock'] == 1
    check = LiveStreamCheck(tolerance_s=10.0, recent_s=2.0)
    for s in range(4):
        assert check.accept(s, t + 10**9, now, *reading)
    restart = t - 3600 * 10**9  # every source restarts an hour earlier (a replay from its start)
    accepted = [check.accept(s, restart, now + 10**6, *reading) for s in range(4)]
    assert accepted == [False, False, True, True]  # once two have moved, the others' median has
    assert check.accept(0, restart + 10**8, now + 10**8, *reading)
    assert not check.accept(1, 0, now + 10**8, *reading) and check.dropped[1]['zero_stamp'] == 1


def test_live_check_names_a_sensor_in_gauss_and_is_silent_on_earth_fields():
    """The tensor node's magnitude text (core/live_streams.py) against the Earth's range: a
    sensor reading 50 000 nT written as Gauss-in-tesla (x 1e4) is named with the factor; the
    Earth's field itself, a sensor with no reading yet and one reading NaN say nothing."""
    from tetra_gradiometer.core.live_streams import LiveStreamCheck
    check = LiveStreamCheck(history=8)
    earth = np.array([0.0, 2e-5, -4.5e-5])
    for i in range(12):  # more than the history: the median of the last 8
        stamp = START_NS + i * 10**8
        assert check.accept(0, stamp, i * 10**8, *earth)
        assert check.accept(1, stamp, i * 10**8, *(earth * 1e4))
        assert check.accept(3, stamp, i * 10**8, *(earth * np.nan))
    assert check.magnitude_text(0) == '' and check.magnitude_text(2) == '' and check.magnitude_text(3) == ''
    text = check.magnitude_text(1)
    assert text.startswith(f'median |B| {np.linalg.norm(earth) * 1e4:.4g} of the last 8 readings, '
                           "outside the Earth field's 22-67 µT: "), text
    assert 'Gauss' in text, text
