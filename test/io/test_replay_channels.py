"""nodes/replay.py: the driver replays the channels of the vehicle effects a bag records
(``/tetra/temperature`` and every sensor_msgs/BatteryState topic, as ``calibrate`` reads
them), with their recorded stamps and values, in log-time order, a channel's message ahead
of the magnetometers of the same log time; any other topic (where a vehicle signal may be)
as recorded. Through rosbags' own CDR (no ROS graph)."""
from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import BagWriter
from tetra_gradiometer.nodes import replay

T0 = 1_767_225_600 * 10**9
PERIOD_NS = 100_000_000
STORE = get_typestore(Stores.ROS2_JAZZY)
TYPES = cv.rosbags_types(STORE)
THRUSTER = '/thruster1/battery'
WATER = '/ctd/temperature'  # a Temperature topic that is no channel: played as recorded


def _bag(path):
    """Ten sets; a temperature and two currents at every set's log time (written after its
    magnetometers), a thruster current with a stamp 30 ms before its log time, and a
    Temperature topic the effects do not read (a signal topic)."""
    with BagWriter(path) as writer:
        for i in range(10):
            stamp = T0 + i * PERIOD_NS
            for s, topic in enumerate(cv.BAG_MAG_TOPICS):
                writer.write(topic, cv.magnetic_field_msg(writer.types, np.full(3, 1e-6 * (s + 1)), stamp,
                                                          cv.MAG_FRAMES[s]), stamp)
            writer.write(cv.TEMPERATURE_TOPIC, cv.temperature_msg(writer.types, 10.0 + i, stamp), stamp)
            writer.write(cv.BATTERY_TOPIC, cv.battery_msg(writer.types, -3.0 * i, stamp), stamp)
            writer.write(THRUSTER, cv.battery_msg(writer.types, 0.5 * i, stamp - 30_000_000), stamp)
            writer.write(WATER, cv.temperature_msg(writer.types, 99.0, stamp), stamp)
    return path


def test_every_channel_the_bag_records_is_replayed_as_recorded(tmp_path):
    bag = _bag(tmp_path / 'bag')
    info = replay.describe_bag(bag)
    assert info['channels'] == f'{cv.TEMPERATURE_TOPIC}, {cv.BATTERY_TOPIC}, {THRUSTER}'
    channels = info['channels'].split(', ')
    frames = list(replay.iter_frames(bag, TYPES))
    assert len(frames) == 10 * 8  # four magnetometers, three channels and WATER per set
    assert info['signals'] == ((WATER, 'sensor_msgs/msg/Temperature'),)
    found: dict[str, list[tuple[int, float]]] = {topic: [] for topic in channels}
    for frame in frames:
        (key, index, msg), = frame.items
        if key == replay.SIGNAL:
            assert STORE.deserialize_cdr(msg, 'sensor_msgs/msg/Temperature').temperature == 99.0  # as recorded
        elif key == replay.CHANNEL:
            value = msg.temperature if channels[index] == cv.TEMPERATURE_TOPIC else msg.current
            found[channels[index]].append((cv.stamp_to_ns(msg.header.stamp), value))
            assert frame.mag1_stamp is None
    stamps = [T0 + i * PERIOD_NS for i in range(10)]
    assert found[cv.TEMPERATURE_TOPIC] == [(t, 10.0 + i) for i, t in enumerate(stamps)]
    assert found[cv.BATTERY_TOPIC] == [(t, -3.0 * i) for i, t in enumerate(stamps)]
    assert found[THRUSTER] == [(t - 30_000_000, 0.5 * i) for i, t in enumerate(stamps)]
    # Log-time order, and within one log time the channels ahead of the magnetometers.
    clocks = [frame.clock_ns for frame in frames]
    assert clocks == sorted(clocks)
    for i in range(10):
        keys = [frame.items[0][0] for frame in frames[8 * i: 8 * i + 8]]
        assert keys == [replay.CHANNEL] * 3 + [replay.SIGNAL] + [replay.MAG] * 4, keys


def test_a_bag_without_channels_replays_only_its_magnetometers(tmp_path):
    with BagWriter(tmp_path / 'bag') as writer:
        for i in range(3):
            stamp = T0 + i * PERIOD_NS
            for s, topic in enumerate(cv.BAG_MAG_TOPICS):
                writer.write(topic, cv.magnetic_field_msg(writer.types, np.full(3, 1e-6), stamp,
                                                          cv.MAG_FRAMES[s]), stamp)
    assert replay.describe_bag(tmp_path / 'bag')['channels'] == ''
    assert {frame.items[0][0] for frame in replay.iter_frames(tmp_path / 'bag', TYPES)} == {replay.MAG}
