"""The compiled interface package tetra_gradiometer_msgs (built and installed into the venv by
`make setup`) from rclpy: imports, a publish/subscribe and a service call across two
processes, and its CDR equal to rosbags' reading of the same .msg text (io/interfaces.py):
values decoded both ways and the RIHS01 type hashes. Expected values are written out here;
decoded values are compared, never raw bytes (Fast DDS leaves CDR padding unset)."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
from ros_helpers import child_env, unique_domain

G = [1.5e-9, -2.25e-9, 3.0e-10, -2.25e-9, 4.0e-9, 0.0, 3.0e-10, 0.0, -5.5e-9]
SIGMA = [1e-11, float('nan'), 2e-11, 3e-11, 4e-11, float('nan'), 5e-11, 6e-11, 7e-11]

# The other process: publishes one GradientTensor (latched) and serves Calibrate, answering
# from the request so the reply shows the request arrived whole.
CHILD = """
import sys, rclpy
from math import nan
from rclpy.qos import QoSProfile, DurabilityPolicy, ReliabilityPolicy
from tetra_gradiometer_msgs.msg import GradientTensor
from tetra_gradiometer_msgs.srv import Calibrate
rclpy.init()
node = rclpy.create_node('interfaces_child')
qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(GradientTensor, '/interfaces_test/gradient', qos)
msg = GradientTensor()
msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = 1700000000, 123456789, 'tetra_array'
msg.g = %(g)r
msg.g_sigma = %(sigma)r
msg.reference_field.x, msg.reference_field.y, msg.reference_field.z = 2.1e-5, -3.4e-6, 4.4e-5
msg.reference_field_covariance[4] = 2e-20
msg.state = GradientTensor.UNCOMPENSATED
pub.publish(msg)
def calibrate(request, response):
    response.success = request.force
    response.message = 'effects ' + request.effects
    response.residual_t_per_m = request.window_s[1] - request.window_s[0]
    response.residual_over_floor = 1.25
    response.samples, response.rank = 3000, 36
    response.calibration_file = '/tmp/calibration.yaml'
    return response
node.create_service(Calibrate, '/interfaces_test/calibrate', calibrate)
print('ready', flush=True)
end = __import__('time').monotonic() + 60
while rclpy.ok() and __import__('time').monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
""" % {'g': G, 'sigma': SIGMA}


def _check_gradient(msg) -> None:
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 123_456_789, 'tetra_array')
    np.testing.assert_array_equal(msg.g, G)
    np.testing.assert_array_equal(msg.g_sigma, SIGMA)
    assert (msg.reference_field.x, msg.reference_field.y, msg.reference_field.z) == (2.1e-5, -3.4e-6, 4.4e-5)
    np.testing.assert_array_equal(msg.reference_field_covariance, [0, 0, 0, 0, 2e-20, 0, 0, 0, 0])
    assert (msg.state, msg.calibration_id) == (2, '')


def test_the_compiled_package_imports_with_its_constants_and_service():
    from tetra_gradiometer_msgs.msg import Calibration, GradientTensor
    from tetra_gradiometer_msgs.srv import Calibrate

    assert (GradientTensor.RAW, GradientTensor.COMPENSATED, GradientTensor.UNCOMPENSATED) == (0, 1, 2)
    assert len(GradientTensor().g) == 9 and len(Calibration().window_s) == 2
    assert len(Calibrate.Request().window_s) == 2 and Calibrate.Response().calibration_file == ''


def test_cdr_of_rclpy_and_rosbags_decode_to_the_same_values_both_ways():
    from rclpy.serialization import deserialize_message, serialize_message
    from tetra_gradiometer_msgs.msg import Calibration, GradientTensor

    from tetra_gradiometer.io.bag import typestore

    store = typestore()
    msg = GradientTensor()
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = 1_700_000_000, 123_456_789, 'tetra_array'
    msg.g, msg.g_sigma = G, SIGMA
    msg.reference_field.x, msg.reference_field.y, msg.reference_field.z = 2.1e-5, -3.4e-6, 4.4e-5
    msg.reference_field_covariance[4] = 2e-20
    msg.state = GradientTensor.UNCOMPENSATED
    _check_gradient(store.deserialize_cdr(serialize_message(msg), 'tetra_gradiometer_msgs/msg/GradientTensor'))

    cal = store.types['tetra_gradiometer_msgs/msg/Calibration'](
        header=store.types['std_msgs/msg/Header'](
            stamp=store.types['builtin_interfaces/msg/Time'](sec=12, nanosec=5), frame_id='tetra_array'),
        method='paper_ga', symmetric_k=True, sensor_positions=np.arange(12) * 0.125, terms=['thermal_drift'],
        parameter_names=['a', 'b'], parameters=np.array([1e-3, -2e-8]), covariance=np.array([1e-8, 0, 0, 4e-18]),
        sensor_noise_t=5e-11, residual_t_per_m=2.5e-11, rank=27, created_utc='2026-11-22T10:00:00Z',
        source='calibrator', window_s=np.array([1.5, 301.5]), signature='algorithm: HMAC-SHA256\n',
        document='method: paper_ga\n')
    back = deserialize_message(bytes(store.serialize_cdr(cal, cal.__msgtype__)), Calibration)
    assert (back.header.stamp.sec, back.header.stamp.nanosec, back.method, back.symmetric_k) == (12, 5, 'paper_ga', True)
    np.testing.assert_array_equal(back.sensor_positions, [0, .125, .25, .375, .5, .625, .75, .875, 1, 1.125, 1.25, 1.375])
    assert (list(back.terms), list(back.parameter_names)) == (['thermal_drift'], ['a', 'b'])
    np.testing.assert_array_equal(back.parameters, [1e-3, -2e-8])
    np.testing.assert_array_equal(back.covariance, [1e-8, 0, 0, 4e-18])
    assert (back.sensor_noise_t, back.residual_t_per_m, back.rank) == (5e-11, 2.5e-11, 27)
    assert (back.created_utc, back.source, list(back.window_s)) == ('2026-11-22T10:00:00Z', 'calibrator', [1.5, 301.5])
    assert (back.signature, back.document) == ('algorithm: HMAC-SHA256\n', 'method: paper_ga\n')


def test_rosidl_type_hashes_equal_rosbags():
    """The type hashes rosidl generated (the installed .json) equal rosbags' of the .msg text."""
    import json

    from tetra_gradiometer.io.bag import typestore

    store = typestore()
    share = __import__('pathlib').Path(sys.prefix, 'share', 'tetra_gradiometer_msgs')
    checked = 0
    for file in ('msg/GradientTensor.json', 'msg/Calibration.json', 'srv/Calibrate.json'):
        for entry in json.loads((share / file).read_text())['type_hashes']:
            name = entry['type_name']
            if name.startswith('tetra_gradiometer_msgs/') and name != 'tetra_gradiometer_msgs/srv/Calibrate' \
                    and not name.endswith('_Event'):  # the service and its event are no messages
                assert store.hash_rihs01(name) == entry['hash_string'], name
                checked += 1
    assert checked == 4  # two messages, the service's request and response


def test_publish_subscribe_and_a_service_call_across_two_processes(monkeypatch):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tetra_gradiometer_msgs.msg import GradientTensor
    from tetra_gradiometer_msgs.srv import Calibrate

    from tetra_gradiometer.io.bag import typestore

    domain = unique_domain()
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))  # the child's env (child_env) sets both too
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    child = subprocess.Popen([sys.executable, '-c', CHILD], env=child_env(domain), stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('interfaces_parent', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == 'ready'
        got: list = []
        qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
        node.create_subscription(GradientTensor, '/interfaces_test/gradient', got.append, qos)
        client = node.create_client(Calibrate, '/interfaces_test/calibrate')
        deadline = time.monotonic() + 30
        while not got and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert got, 'no GradientTensor from the other process within 30 s'
        _check_gradient(got[0])
        (info,) = node.get_publishers_info_by_topic('/interfaces_test/gradient')
        assert str(info.topic_type_hash) == typestore().hash_rihs01('tetra_gradiometer_msgs/msg/GradientTensor')

        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(Calibrate.Request(window_s=[10.0, 250.0], force=True, effects='auto'))
        executor.spin_until_future_complete(future, timeout_sec=30)
        reply = future.result()
        assert reply is not None, 'no Calibrate reply within 30 s'
        assert (reply.success, reply.message, reply.residual_t_per_m, reply.residual_over_floor) == (True, 'effects auto', 240.0, 1.25)
        assert (reply.samples, reply.rank, reply.calibration_file) == (3000, 36, '/tmp/calibration.yaml')
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
        child.kill()
        out, _ = child.communicate(timeout=10)
    if 'Traceback' in out:
        pytest.fail(f'the other process failed: {out[-2000:]}')
