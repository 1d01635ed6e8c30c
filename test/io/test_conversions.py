"""io/conversions.py: the tensor JointState of older recordings through rosbags' own CDR
serializer and back; the MagneticField CDR against rclpy's and rosbags'."""
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io import gradient_tensor as gt


def test_tensor_message_round_trip_through_rosbags_cdr():
    store = get_typestore(Stores.ROS2_JAZZY)
    types = cv.rosbags_types(store)
    g = np.arange(9.0).reshape(3, 3) * 1e-9
    msg = cv.tensor_msg(types, g, 1_700_000_000_123_456_789)
    back = store.deserialize_cdr(store.serialize_cdr(msg, cv.JOINT_STATE), cv.JOINT_STATE)
    np.testing.assert_array_equal(cv.tensor_from_msg(back), g)
    assert cv.stamp_to_ns(back.header.stamp) == 1_700_000_000_123_456_789
    back.name = list(reversed(back.name))
    back.position = back.position[::-1]
    np.testing.assert_array_equal(cv.tensor_from_msg(back), g)  # order by name, not position
    back.name[0] = 'gxq'
    with pytest.raises(cv.MessageError, match='gxx'):
        cv.tensor_from_msg(back)


# --------------------------------------------------------------- serialized (CDR) messages
# Truth: rclpy's serialization (the RMW's type support) and rosbags' own CDR codec, two
# implementations independent of the hand-written writers and readers.

FRAMES = ['', 'a', 'ab', 'abc', 'abcd', 'tetra_array', 'vehicle_7/tetra_mag1']


@pytest.fixture
def fast_only(monkeypatch):
    """The readers' fast path only: any fallback to rclpy's deserialization fails the test."""
    def refuse(data, type_name):
        raise AssertionError(f'fell back to rclpy for a {type_name}')
    monkeypatch.setattr(cv, '_deserialize', refuse)


def _typestore():
    return get_typestore(Stores.ROS2_JAZZY)


@pytest.mark.parametrize('frame', FRAMES)
def test_cdr_writers_are_read_back_by_rclpy_and_rosbags(frame):
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import MagneticField
    from std_msgs.msg import Float64

    assert cv.cdr_agrees()
    stamp = 1_700_000_000_123_456_789
    field, covariance = np.array([1e-5, -2e-5, 4.5e-5]), np.arange(9.0) * 1e-20
    store = _typestore()
    reading = cv.magnetic_field_cdr(field, stamp, frame, covariance)
    for back in (deserialize_message(reading, MagneticField),
                 store.deserialize_cdr(reading, cv.MAGNETIC_FIELD)):
        assert (cv.stamp_to_ns(back.header.stamp), back.header.frame_id) == (stamp, frame)
        np.testing.assert_array_equal(cv.magnetic_field_reading(back), np.r_[field, covariance])
    assert deserialize_message(cv.float64_cdr(-2.5e-3), Float64).data == -2.5e-3
    unknown = deserialize_message(cv.magnetic_field_cdr(field, stamp, frame), MagneticField)
    np.testing.assert_array_equal(unknown.magnetic_field_covariance, cv.UNKNOWN_COVARIANCE)


@pytest.mark.parametrize('frame', FRAMES)
def test_cdr_readers_read_rclpy_and_rosbags_serializations(frame, fast_only):
    from rclpy.serialization import serialize_message

    stamp = 1_600_000_000_000_000_001
    field, covariance = np.array([3e-5, 1e-6, -4e-5]), np.eye(3).reshape(9) * 4e-20
    store, types = _typestore(), cv.rclpy_types()
    rosbags = cv.rosbags_types(store)
    readings = [
        serialize_message(cv.magnetic_field_msg(types, field, stamp, frame, covariance)),
        store.serialize_cdr(cv.magnetic_field_msg(rosbags, field, stamp, frame, covariance),
                            cv.MAGNETIC_FIELD),
    ]
    for data in readings:
        got_stamp, got_frame, got_reading = cv.magnetic_field_from_cdr(bytes(data))
        assert (got_stamp, got_frame) == (stamp, frame) and cv.stamp_from_cdr(bytes(data)) == stamp
        np.testing.assert_array_equal(got_reading, np.r_[field, covariance])


@pytest.mark.parametrize('data', [b'', b'\x00\x01\x00\x00', b'\x01\x00\x00\x00' + bytes(40),
                                  b'\x00\x01\x00\x00' + bytes(8) + b'\xff\xff\x00\x00'])
def test_cdr_readers_refuse_garbage_with_a_message_error(data):
    with pytest.raises(cv.MessageError):
        cv.magnetic_field_from_cdr(data)
    with pytest.raises(cv.MessageError):
        gt.GradientTensorCdr('tetra_array').read(data)


@pytest.mark.parametrize('stamp', [0, 1_767_225_600_000_000_001, 2**31 * 10**9 - 1])
def test_the_bag_writers_extra_topics_are_the_bytes_of_rosbags_and_rclpy(stamp):
    """odometry_cdr, temperature_cdr and battery_cdr (what write_mission_bag records) against
    the message objects: byte for byte through rosbags' CDR codec (which zeroes the padding),
    and read back by rclpy as the message it builds (rclpy's own bytes leave the padding
    uninitialized)."""
    from rclpy.serialization import deserialize_message, serialize_message

    store, types = _typestore(), cv.rclpy_types()
    rosbags = cv.rosbags_types(store)
    position, orientation = np.array([-1234.5, 6.25e3, -48.125]), np.array([0.1, -0.7, 0.5, 0.49])
    for celsius_or_amps in (-15.3, 0.0, 21.7):
        cases = [
            (cv.odometry_cdr(position, orientation, stamp), cv.ODOMETRY,
             lambda t: cv.odometry_msg(t, position, orientation, stamp)),
            (cv.temperature_cdr(celsius_or_amps, stamp), cv.TEMPERATURE,
             lambda t: cv.temperature_msg(t, celsius_or_amps, stamp)),
            (cv.battery_cdr(celsius_or_amps, stamp), cv.BATTERY_STATE,
             lambda t: cv.battery_msg(t, celsius_or_amps, stamp)),
        ]
        for data, type_name, message in cases:
            assert data == bytes(store.serialize_cdr(message(rosbags), type_name)), type_name
            read = deserialize_message(data, types[type_name])
            expected = deserialize_message(serialize_message(message(types)), types[type_name])
            assert repr(read) == repr(expected), type_name  # NaN fields: repr, not ==
