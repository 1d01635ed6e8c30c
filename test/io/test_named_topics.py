"""Every name a user gives is checked, and the data's own names are read: magnetometers and
odometry recorded under a vehicle namespace are found (and the line says so); a current topic
named on the command line that the bag lacks is refused naming what the bag has.

Truth: the simulated mission written under another namespace, byte for byte the same
messages as the plain bag; the plain bag's calibration.
"""
from __future__ import annotations

import numpy as np
import yaml
from cli_helpers import assert_refused, run_cli
from stream_faults import START_NS, short_mission, write_bag, write_params

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import BagWriter


def _namespaced(path, mission, prefix):
    log = START_NS + np.round(mission.t * 1e9).astype(np.int64)
    with BagWriter(path) as writer:
        for i, stamp in enumerate(log):
            for sensor in range(4):
                data = cv.magnetic_field_cdr(mission.fields_measured[i, sensor], int(stamp), cv.MAG_FRAMES[sensor])
                writer.write_raw(prefix + cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD, data, int(stamp))
            msg = cv.odometry_msg(writer.types, mission.position_enu[i], mission.orientation_xyzw[i], int(stamp))
            writer.write(prefix + cv.ODOM_TOPIC, msg, int(stamp))
    return path


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
