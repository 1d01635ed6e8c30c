"""io/channels and the channels' fast decode (io/bag_decode.decode_channel): temperature,
current and the odometry pose, against rosbags' deserializer."""
import numpy as np
import pytest

from tetra_gradiometer.core import Scenario, TetraGeometry, TrimManoeuvre, simulate
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.bag_decode import _UnsupportedEncoding, decode_channel
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


def _pose(msg):
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return [p.x, p.y, p.z, q.x, q.y, q.z, q.w]


@pytest.mark.parametrize(('topic', 'value'), [(cv.BATTERY_TOPIC, lambda m: [m.current]),
                                              (cv.TEMPERATURE_TOPIC, lambda m: [m.temperature]),
                                              (cv.ODOM_TOPIC, _pose)])
def test_the_fast_channel_decode_equals_rosbags(bag, topic, value):
    with MagneticBag(bag) as reader:
        series = reader.read_series(topic)
        connections = reader._connections(topic)
        slow = [
            (reader.reader.deserialize(raw, c.msgtype), log)
            for c, log, raw in guarded_messages(reader.reader, connections, lambda r: None)
        ]
    values = np.array([value(m) for m, _ in slow])
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m, _ in slow])
    np.testing.assert_array_equal(series.values, values)
    np.testing.assert_array_equal(series.stamps_ns, stamps)


@pytest.mark.parametrize('little_endian', [True, False])
def test_the_odometry_decode_reads_any_frame_ids_in_either_byte_order(little_endian):
    """Messages serialized by rosbags, with frame ids of every alignment; cut short they are
    refused (rosbags' deserializer then names the fault)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    t = {name.rsplit('/', 1)[-1]: cls for name, cls in store.types.items()}
    rng = np.random.default_rng(5)
    frames = [('', ''), ('o', 'base_link'), ('odom', 'b'), ('abcdefg', 'hij'), ('x' * 9, '')]
    for frame, child in frames:
        pose = rng.normal(size=7)
        msg = t['Odometry'](
            header=t['Header'](stamp=t['Time'](sec=1_700_000_000, nanosec=123), frame_id=frame),
            child_frame_id=child,
            pose=t['PoseWithCovariance'](
                pose=t['Pose'](position=t['Point'](*pose[:3]), orientation=t['Quaternion'](*pose[3:])),
                covariance=rng.normal(size=36)),
            twist=t['TwistWithCovariance'](
                twist=t['Twist'](linear=t['Vector3'](1.0, 2.0, 3.0), angular=t['Vector3'](4.0, 5.0, 6.0)),
                covariance=rng.normal(size=36)))
        raw = bytes(store.serialize_cdr(msg, cv.ODOMETRY, little_endian=little_endian))
        stamp, decoded = decode_channel(raw, cv.ODOMETRY)
        assert stamp == 1_700_000_000 * 10**9 + 123
        np.testing.assert_array_equal(decoded, pose)
        with pytest.raises(_UnsupportedEncoding):
            decode_channel(raw[:-1], cv.ODOMETRY)


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
