"""io/recording.py: a simulated mission written to a bag and read back as it was simulated."""
import dataclasses
import sqlite3

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tetra_gradiometer.core import Scenario, SensorClocks, SensorStream, TetraGeometry, TrimManoeuvre, simulate
from tetra_gradiometer.errors import InputError
from tetra_gradiometer.io.recording import read_recording, write_mission_bag

GEOMETRY = TetraGeometry.regular(0.5)
START_NS = 1_767_225_600 * 10**9


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_mission_bag_round_trip(tmp_path, storage):
    rng = np.random.default_rng(2)
    mission = simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5],
                                segments=[TrimManoeuvre(20.0)], noise_t=1e-10), rng)
    write_mission_bag(tmp_path / 'run', mission, storage=storage, battery=False)
    recording = read_recording(tmp_path / 'run')
    np.testing.assert_array_equal(recording.fields, mission.fields_measured)
    np.testing.assert_allclose(recording.t_s, mission.t, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(recording.orientation_xyzw * mission.orientation_xyzw, axis=1)), 1.0,
                               atol=1e-12)
    np.testing.assert_allclose(recording.position_m, mission.position_enu, atol=1e-9)
    np.testing.assert_allclose(recording.temperature_c, mission.temperature_c)
    assert recording.current_a is None and '/battery_state' in recording.missing


def _clocked_mission():
    clocks = SensorClocks(offset_s=[0.0, 1.5e-3, 2.5e-3, 4e-3], jitter_s=0.2e-3,
                          rate_hz=[50.0, 50.0, 100.0, 100.0], loss_fraction=0.02)
    return simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5], segments=[TrimManoeuvre(10.0)],
                             noise_t=1e-10, clocks=clocks), np.random.default_rng(3))


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_mission_bag_with_sensor_clocks_logs_each_stream_on_its_own_stamps(tmp_path, storage):
    mission = _clocked_mission()
    write_mission_bag(tmp_path / 'run', mission, start_ns=START_NS, storage=storage, battery=False)
    topics = {}
    with AnyReader([tmp_path / 'run']) as reader:  # rosbags itself, not our reader
        for connection, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert timestamp == stamp  # logged at the header stamp, the true sample time
            value = ([msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z]
                     if connection.msgtype == 'sensor_msgs/msg/MagneticField' else None)
            topics.setdefault(connection.topic, []).append((stamp, value))
    assert set(topics) == {'/tetra/mag1', '/tetra/mag2', '/tetra/mag3', '/tetra/mag4', '/odom',
                           '/tetra/temperature'}
    for sensor, stream in enumerate(mission.streams):
        stamps, fields = zip(*topics[f'/tetra/mag{sensor + 1}'], strict=True)
        assert list(stamps) == [START_NS + int(round(t * 1e9)) for t in stream.t]
        np.testing.assert_array_equal(np.array(fields), stream.fields)
    assert len(mission.streams[2]) > 1.9 * len(mission.streams[0])  # 100 Hz against 50 Hz
    expected = [START_NS + int(round(t * 1e9)) for t in mission.t]  # sensor 1's instants, all
    assert [s for s, _ in topics['/odom']] == [s for s, _ in topics['/tetra/temperature']] == expected
    assert len(expected) > len(mission.streams[0])  # ... also those whose message was lost
    if storage == 'sqlite3':  # written as a recorder logs: in stamp order across topics
        (db,) = (tmp_path / 'run').glob('*.db3')
        with sqlite3.connect(db) as connection:
            order = [row[0] for row in connection.execute('SELECT timestamp FROM messages ORDER BY id')]
        assert order == sorted(order) and len(order) == sum(len(v) for v in topics.values())


def test_mission_bag_refuses_stream_stamps_that_do_not_increase(tmp_path):
    mission = _clocked_mission()
    streams = list(mission.streams)
    streams[2] = SensorStream(np.array([0.5, 0.5 + 1e-10]), np.zeros((2, 3)))  # the same ns
    with pytest.raises(InputError, match='stamps of sensor 3 must increase'):
        write_mission_bag(tmp_path / 'run', dataclasses.replace(mission, streams=tuple(streams)))
    assert not (tmp_path / 'run').exists()
