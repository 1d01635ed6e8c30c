"""io/channels and the scalar channels' fast decode (io/bag_decode.decode_scalar)."""
import numpy as np
import pytest

from tetra_gradiometer.core import Scenario, TetraGeometry, TrimManoeuvre, simulate
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.bag_skips import guarded_messages
from tetra_gradiometer.io.channels import ChannelSeries, channel_topic, runs
from tetra_gradiometer.io.recording import write_mission_bag


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    rng = np.random.default_rng(3)
    scenario = Scenario(TetraGeometry.regular(0.5), np.array([0, 2e-5, -4.5e-5]),
                        (TrimManoeuvre(20.0),), sample_rate_hz=10.0)
    path = tmp_path_factory.mktemp('channels') / 'bag'
    write_mission_bag(path, simulate(scenario, rng), storage='mcap')
    return path


@pytest.mark.parametrize(('topic', 'field'), [(cv.BATTERY_TOPIC, 'current'),
                                              (cv.TEMPERATURE_TOPIC, 'temperature')])
def test_the_fast_scalar_decode_equals_rosbags(bag, topic, field):
    with MagneticBag(bag) as reader:
        series = reader.read_series(topic)
        connections = reader._connections(topic)
        slow = [
            (reader.reader.deserialize(raw, c.msgtype), log)
            for c, log, raw in guarded_messages(reader.reader, connections, lambda r: None)
        ]
    values = np.array([getattr(m, field) for m, _ in slow])
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m, _ in slow])
    np.testing.assert_array_equal(series.values[:, 0], values)
    np.testing.assert_array_equal(series.stamps_ns, stamps)


def test_a_channel_is_unknown_where_no_message_is_near():
    s = 10**9
    series = ChannelSeries('current:/battery_state', np.array([0, 1, 2, 10, 11]) * s,
                           np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    at = np.array([0.5, 2.0, 4.1, 6.0, 7.9, 10.5, 13.5, 14.0]) * s
    out = series.on(at.astype(np.int64))
    # Currents: 2 s from the nearest message at most; linear between messages.
    np.testing.assert_allclose(out[[0, 1, 5]], [1.5, 3.0, 4.5])
    assert np.all(np.isnan(out[[2, 3, 4, 6, 7]]))
    np.testing.assert_allclose(runs(at.astype(np.int64), np.isnan(out), 0), [(4.1, 7.9), (13.5, 14.0)])
    assert channel_topic('current:/thruster_2/battery') == '/thruster_2/battery'
    assert channel_topic('temperature') == cv.TEMPERATURE_TOPIC
