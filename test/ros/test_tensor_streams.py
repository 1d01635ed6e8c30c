"""nodes/tensor.py, stream faults live (core/streams.LiveStreamCheck), in this process
(test/ros/in_process.py: the readings handed to its callbacks, serialized): a sensor stamped
in another epoch, zero stamps, and a sensor in Gauss are named per sensor on /diagnostics,
their readings dropped and counted; the node keeps publishing the exact tensor of the good
sets."""
from __future__ import annotations

import numpy as np
from in_process import deserialized, last_status, node_in_process
from ros_helpers import uniform_gradient_fields

from tetra_gradiometer import core
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io import gradient_tensor as gt

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: stamps ahead of the clock are refused (max_stamp_ahead_s)
GPS_UNIX_NS = 315_964_800 * 10**9
GEOMETRY = core.TetraGeometry.regular(0.5)
B0 = np.array([12e-6, -20e-6, 43e-6])
G_KNOWN = np.array([[120.0, 35.0, -12.0], [35.0, -80.0, 22.0], [-12.0, 22.0, -40.0]]) * NT
FIELDS = uniform_gradient_fields(GEOMETRY.positions, B0, G_KNOWN)


def _tensor_node(monkeypatch, **params):
    from tetra_gradiometer.nodes.tensor import TensorNode

    return node_in_process(TensorNode, monkeypatch, **params)


def _reading(node, sensor: int, field, stamp_ns: int) -> None:
    from rclpy.serialization import serialize_message

    message = cv.magnetic_field_msg(cv.rclpy_types(), field, stamp_ns, cv.MAG_FRAMES[sensor])
    node._on_mag(sensor, serialize_message(message))


def _statuses(node, published) -> dict:
    node._publish_diagnostics()
    return {s: last_status(published, f'tetra/tensor: mag{s}') for s in range(1, 5)}


def _raw(published) -> dict[int, np.ndarray]:
    return {t.stamp_ns: t.g for t in map(gt.tensor_set_from_msg,
                                         deserialized(published, '/tetra/gradient/raw', gt.rclpy_class()))}


def test_stamps_off_the_other_sensors_and_zero_stamps_are_dropped_and_named(monkeypatch):
    with _tensor_node(monkeypatch, sync='nearest', warn_throttle_s=30.0) as (node, published):
        for i in range(40):
            stamp = T0 + i * 10**8
            for s in range(4):
                sensor_stamp = stamp
                if s == 2 and 10 <= i < 20:
                    sensor_stamp = stamp - GPS_UNIX_NS  # sensor 3 on GPS time for 1 s
                if s == 1 and i in (25, 26):
                    sensor_stamp = 0  # an unfilled header on sensor 2
                _reading(node, s, FIELDS[s], sensor_stamp)
        statuses = _statuses(node, published)
        raw = _raw(published)
    mag3, mag2 = statuses[3], statuses[2]
    assert mag3['dropped_other_clock'] == '10' and mag2['dropped_zero_stamp'] == '2'
    assert mag3['level'] == 1 and "10 stamped off the other sensors' clock" in mag3['message'], mag3
    assert mag2['level'] == 1 and '2 with header stamp 0' in mag2['message'], mag2
    assert sorted(raw) == [T0 + i * 10**8 for i in range(40) if not (10 <= i < 20 or i in (25, 26))]
    tensors = np.array(list(raw.values()))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-12 * 1e-6)


def test_a_sensor_in_gauss_is_named_on_diagnostics(monkeypatch):
    gauss = FIELDS.copy()
    gauss[3] *= 1e4  # 0.5 G written as 0.5 T: beyond max_field_t, every set dropped
    with _tensor_node(monkeypatch) as (node, published):
        for i in range(30):
            for s in range(4):
                _reading(node, s, gauss[s], T0 + i * 10**8)
        statuses = _statuses(node, published)
        assert 'Gauss written as tesla' in statuses[4]['message'], statuses[4]
        assert _raw(published) == {}
