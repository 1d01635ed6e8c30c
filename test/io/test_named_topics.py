"""Every name a user gives is checked, and the data's own names are read: magnetometers and
odometry recorded under a vehicle namespace are found (and the line says so); a current topic
named on the command line that the bag lacks is refused naming what the bag has.

Truth: the simulated mission written under another namespace, byte for byte the same
messages as the plain bag; the plain bag's calibration.
"""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from cli_helpers import assert_refused, run_cli
from stream_faults import START_NS, short_mission, write_bag, write_params

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import BagWriter


def _named(path, mission, mag_topics, odom_topic, scale=1.0, writer=None, frames=cv.MAG_FRAMES):
    """The mission with sensor s on ``mag_topics[s]`` and odometry on ``odom_topic``; sensor
    2's field times ``scale`` (another vehicle's data)."""
    log = START_NS + np.round(mission.t * 1e9).astype(np.int64)
    with writer or BagWriter(path) as writer:
        for i, stamp in enumerate(log):
            for sensor in range(4):
                field = (scale if sensor == 1 else 1.0) * mission.fields_measured[i, sensor]
                data = cv.magnetic_field_cdr(field, int(stamp), frames[sensor])
                writer.write_raw(mag_topics[sensor], cv.MAGNETIC_FIELD, data, int(stamp))
            msg = cv.odometry_msg(writer.types, mission.position_enu[i], mission.orientation_xyzw[i], int(stamp))
            writer.write(odom_topic, msg, int(stamp))
    return path


def _namespaced(path, mission, prefix):
    return _named(path, mission, [prefix + t for t in cv.BAG_MAG_TOPICS], prefix + cv.ODOM_TOPIC)


def _calibration(capsys, tmp_path, name, bag, params, *options):
    code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params, '--out', tmp_path / f'{name}.yaml',
                             *options)
    assert code == 0, err
    return yaml.safe_load((tmp_path / f'{name}.yaml').read_text())['k_soft'], out


def test_a_namespaced_bag_is_read_as_the_plain_one_and_says_so(tmp_path, capsys):
    mission = short_mission(trim_s=40.0, survey_s=10.0)
    params = write_params(tmp_path / 'params.yaml')
    plain = write_bag(tmp_path / 'plain', mission)
    namespaced = _namespaced(tmp_path / 'auv1', mission, '/auv1')
    calibrations = {}
    for name, bag in (('plain', plain), ('auv1', namespaced)):
        code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params, '--out', tmp_path / f'{name}.yaml')
        assert code == 0, err
        calibrations[name] = yaml.safe_load((tmp_path / f'{name}.yaml').read_text())
        if name == 'auv1':
            assert 'topics read under another namespace: /auv1/tetra/mag1 as /tetra/mag1' in out
            assert '/auv1/odom as /odom' in out and 'regional gradient estimated jointly' in out
    assert calibrations['auv1']['k_soft'] == calibrations['plain']['k_soft']


def test_two_vehicles_in_one_bag_are_not_guessed(tmp_path, capsys):
    mission = short_mission(trim_s=20.0, survey_s=5.0)
    bag2 = tmp_path / 'fleet'
    log = START_NS + np.round(mission.t * 1e9).astype(np.int64)
    with BagWriter(bag2) as writer:
        for prefix in ('/auv1', '/auv2'):
            for i, stamp in enumerate(log):
                for sensor in range(4):
                    data = cv.magnetic_field_cdr(mission.fields_measured[i, sensor], int(stamp), cv.MAG_FRAMES[sensor])
                    writer.write_raw(prefix + cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD, data, int(stamp))
    params = write_params(tmp_path / 'params.yaml')
    assert_refused(run_cli(capsys, 'calibrate', bag2, '--params', params, '--out', tmp_path / 'c.yaml'),
                   "missing topic(s) ['/tetra/mag1'", '/auv1/tetra/mag1', '/auv2/tetra/mag1')


def test_a_current_topic_the_bag_lacks_is_refused_naming_what_it_has(tmp_path, capsys):
    mission = short_mission(trim_s=40.0, survey_s=5.0)
    bag = write_bag(tmp_path / 'bag', mission)
    params = write_params(tmp_path / 'params.yaml')
    assert_refused(run_cli(capsys, 'calibrate', bag, '--params', params, '--current-topics', '/esc1',
                           '--out', tmp_path / 'c.yaml'),
                   '--current-topics /esc1: not a sensor_msgs/BatteryState topic of',
                   'its BatteryState topics: none', '/tetra/mag1')
    assert not (tmp_path / 'c.yaml').exists()


def test_topics_named_on_the_command_line_are_read_in_sensor_order(tmp_path, capsys):
    """A driver's own names, in an order that is not the sensors': --mag-topics gives the
    sensor order, --odom-topic the navigation; the calibration is the plain bag's."""
    mission = short_mission(trim_s=40.0, survey_s=5.0)
    params = write_params(tmp_path / 'params.yaml')
    plain, _ = _calibration(capsys, tmp_path, 'plain', write_bag(tmp_path / 'plain', mission), params)
    names = ['/vn300/mag_c', '/vn300/mag_a', '/vn300/mag_d', '/vn300/mag_b']
    bag = _named(tmp_path / 'vendor', mission, names, '/ins/odometry')
    named, out = _calibration(capsys, tmp_path, 'named', bag, params, '--mag-topics', ','.join(names),
                              '--odom-topic', '/ins/odometry')
    assert np.allclose(named, plain, rtol=0, atol=1e-12)
    assert 'regional gradient estimated jointly' in out  # the odometry was read


def test_a_namespace_chooses_one_vehicle_of_two(tmp_path, capsys):
    mission = short_mission(trim_s=40.0, survey_s=5.0)
    params = write_params(tmp_path / 'params.yaml')
    plain, _ = _calibration(capsys, tmp_path, 'plain', write_bag(tmp_path / 'plain', mission), params)
    bag = tmp_path / 'fleet'
    with BagWriter(bag) as writer:
        for prefix, scale in (('/auv1', 1.0), ('/auv2', 1.01)):
            _named(bag, mission, [prefix + t for t in cv.BAG_MAG_TOPICS], prefix + cv.ODOM_TOPIC, scale,
                   writer=_Open(writer))
    auv1, _ = _calibration(capsys, tmp_path, 'auv1', bag, params, '--namespace', '/auv1')
    auv2, _ = _calibration(capsys, tmp_path, 'auv2', bag, params, '--namespace', 'auv2/')
    assert np.allclose(auv1, plain, rtol=0, atol=1e-12)
    assert np.abs(np.subtract(auv2, plain)).max() > 1e-3  # sensor 2's 1 % scale


class _Open:
    """An open writer lent to :func:`_named` (closed by its owner)."""

    def __init__(self, writer):
        self.writer = writer

    def __enter__(self):
        return self.writer

    def __exit__(self, *exc):
        return False


def test_a_topic_name_the_bag_lacks_is_refused_naming_what_it_has(tmp_path, capsys):
    mission = short_mission(trim_s=20.0, survey_s=5.0)
    bag = write_bag(tmp_path / 'bag', mission)
    params = write_params(tmp_path / 'params.yaml')
    for command, extra in (('calibrate', ('--out', tmp_path / 'c.yaml')),
                           ('compensate', ('--raw', '--csv', tmp_path / 'c.csv')),
                           ('locate', ('--raw', '--out', tmp_path / 'targets'))):
        assert_refused(run_cli(capsys, command, bag, '--params', params, '--odom-topic', '/nav/odom', *extra),
                       'no topic /nav/odom in the bag', '/odom (Odometry)', '/tetra/mag1 (MagneticField)')
    assert_refused(run_cli(capsys, 'calibrate', bag, '--params', params, '--namespace', '/auv9',
                           '--out', tmp_path / 'c.yaml'),
                   '--namespace /auv9: the bag records no magnetometer under it')
    names = '/tetra/mag1,/tetra/mag2,/tetra/mag3,/odom'
    assert_refused(run_cli(capsys, 'calibrate', bag, '--params', params, '--mag-topics', names,
                           '--out', tmp_path / 'c.yaml'),
                   '/odom holds nav_msgs/msg/Odometry, not sensor_msgs/msg/MagneticField')
    with pytest.raises(SystemExit) as usage:  # argparse's usage error
        run_cli(capsys, 'calibrate', bag, '--params', params, '--mag-topics', '/a,/b,/c', '--out', tmp_path / 'c.yaml')
    assert usage.value.code == 2 and '--mag-topics: expected 4 topics, got 3' in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in ('c.yaml', 'c.csv', 'targets'))


def test_frame_ids_of_other_sensors_or_frames_are_said(tmp_path, capsys):
    """The driver's frame_ids are evidence: mag1..4 carrying the frames of sensors 3, 1, 4,
    2 (topics in another order), or an FRD frame, are named on the reader's line."""
    mission = short_mission(trim_s=40.0, survey_s=5.0)
    params = write_params(tmp_path / 'params.yaml')
    topics = list(cv.BAG_MAG_TOPICS)
    for name, frames, said in (
            ('order', ('imu/mag3', 'imu/mag1', 'imu/mag4', 'imu/mag2'), "sensor 1: 'imu/mag3'"),
            ('frd', ('mag1_frd', 'mag2_frd', 'mag3_frd', 'mag4_frd'), "declares FRD (x forward"),
            ('plain', cv.MAG_FRAMES, None)):
        bag = _named(tmp_path / name, mission, topics, cv.ODOM_TOPIC, frames=frames)
        _, out = _calibration(capsys, tmp_path, name, bag, params)
        if said is None:
            assert 'carry frame_ids' not in out and 'declares' not in out
        else:
            assert said in out


def test_optional_topics_of_another_type_are_skipped_with_a_line(tmp_path, capsys):
    """/odom, /tetra/temperature and /battery_state recorded as std_msgs/Float64 (a driver's
    own choice): every command runs on the magnetometers and says what it did not read."""
    mission = short_mission(trim_s=40.0, survey_s=5.0)
    params = write_params(tmp_path / 'params.yaml')
    log = START_NS + np.round(mission.t * 1e9).astype(np.int64)
    with BagWriter(tmp_path / 'bag') as writer:
        for i, stamp in enumerate(log):
            for sensor in range(4):
                data = cv.magnetic_field_cdr(mission.fields_measured[i, sensor], int(stamp), cv.MAG_FRAMES[sensor])
                writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD, data, int(stamp))
            for topic in (cv.ODOM_TOPIC, '/tetra/temperature', '/battery_state'):
                writer.write(topic, writer.types['std_msgs/msg/Float64'](data=1.0), int(stamp))
    lines = {topic: f'{topic} holds std_msgs/msg/Float64, not {kind}: not read'
             for topic, kind in ((cv.ODOM_TOPIC, cv.ODOMETRY), ('/tetra/temperature', cv.TEMPERATURE),
                                 ('/battery_state', cv.BATTERY_STATE))}
    _, out = _calibration(capsys, tmp_path, 'c', tmp_path / 'bag', params)
    assert all(line in out for line in lines.values()), out
    code, out, err = run_cli(capsys, 'discrepancy', tmp_path / 'bag', '--params', params, '--out', tmp_path / 'd',
                             '--no-plots')
    assert code == 0 and all(f'input: {line}' in err for line in lines.values()), err
    code, out, err = run_cli(capsys, 'compensate', tmp_path / 'bag', '--params', params, '--calibration',
                             tmp_path / 'c.yaml', '--csv', tmp_path / 'o.csv')
    assert code == 0, err
