"""io/recording.py with several current channels: a simulated mission with thrusters
written to a bag carries one BatteryState topic per channel, and reading it back (our
reader, the calibration's channel reader, and rosbags itself) gives what was simulated."""
import dataclasses

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tetra_gradiometer.core import CurrentProfile, Scenario, TetraGeometry, Thruster, TrimManoeuvre, simulate
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.channels import current_channels, read_channels
from tetra_gradiometer.io.recording import read_recording, write_mission_bag

GEOMETRY = TetraGeometry.regular(0.5)
TOPICS = ('/thruster_1/battery_state', '/thruster_2/battery_state', '/payload/battery_state')
# BatteryState.current is a float32.
FLOAT32 = 4e-6


def _mission(topics=TOPICS, seed=2):
    profile = CurrentProfile(-3.0, 1.0, 10.0, tuple(Thruster(t, step_s=7.0) for t in topics))
    return simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5], segments=[TrimManoeuvre(20.0)],
                             noise_t=1e-10, current=profile), np.random.default_rng(seed))


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_every_current_channel_goes_to_its_topic_and_comes_back(tmp_path, storage):
    mission = _mission()
    write_mission_bag(tmp_path / 'run', mission, storage=storage, progress=False)
    # rosbags itself: one BatteryState per channel per sample, stamped as the sample.
    currents = {}
    with AnyReader([tmp_path / 'run']) as reader:
        for connection, timestamp, raw in reader.messages():
            if connection.msgtype == 'sensor_msgs/msg/BatteryState':
                msg = reader.deserialize(raw, connection.msgtype)
                assert timestamp == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                currents.setdefault(connection.topic, []).append(msg.current)
    assert set(currents) == {'/battery_state', *TOPICS}
    for j, topic in enumerate(mission.current_topics):
        np.testing.assert_allclose(currents[topic], mission.currents_a[:, j], rtol=0, atol=FLOAT32)
    # Our reader: the battery's as before, every further channel by topic.
    recording = read_recording(tmp_path / 'run')
    np.testing.assert_allclose(recording.current_a, mission.current_a, rtol=0, atol=FLOAT32)
    assert tuple(recording.extra_currents) == tuple(sorted(TOPICS))
    for j, topic in enumerate(mission.current_topics[1:], start=1):
        np.testing.assert_allclose(recording.extra_currents[topic], mission.currents_a[:, j], rtol=0, atol=FLOAT32)
    # The calibration's channel reader finds the thrusters by name.
    with MagneticBag(tmp_path / 'run') as bag:
        series = read_channels(bag, current_channels(TOPICS))
    assert set(series) == {f'current:{t}' for t in ('/battery_state', *TOPICS)}
    np.testing.assert_allclose(series['current:/payload/battery_state'].values, mission.currents_a[:, 3],
                               rtol=0, atol=FLOAT32)


def test_a_battery_only_mission_writes_one_current_topic(tmp_path):
    mission = _mission(topics=())
    write_mission_bag(tmp_path / 'run', mission, progress=False)
    with MagneticBag(tmp_path / 'run') as bag:
        assert bag.topics_of_type('sensor_msgs/msg/BatteryState') == ('/battery_state',)
    recording = read_recording(tmp_path / 'run')
    assert recording.extra_currents == {} and recording.current_a is not None


def test_a_channel_that_never_knows_its_current_is_named_missing(tmp_path):
    mission = _mission(topics=TOPICS[:2])
    unknown = mission.currents_a.copy()
    unknown[:, 2] = np.nan
    write_mission_bag(tmp_path / 'run', dataclasses.replace(mission, currents_a=unknown), progress=False)
    recording = read_recording(tmp_path / 'run')
    assert list(recording.extra_currents) == [TOPICS[0]]
    assert TOPICS[1] in recording.missing and 'no known current' in recording.missing[TOPICS[1]]
