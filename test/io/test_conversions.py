"""io/conversions.py: the tensor message through rosbags' own CDR serializer and back."""
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from tetra_gradiometer.io import conversions as cv


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
