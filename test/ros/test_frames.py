"""Frame ids (REP 103/105) of what the nodes publish (in this process): the simulating
driver's odometry (/tetra/odom, never the vehicle's /odom) is odom -> base_link and its magnetometers tetra_mag1..4 by default, every
frame id is a parameter, the tensor publishes its gradient (with B_1') in ``array_frame_id``;
a frame id with a leading '/' (tf2 refuses those) is refused at start-up."""
from __future__ import annotations

from in_process import deserialized, node_in_process
from ros_helpers import NodeProcess, unique_domain


def _frames(monkeypatch, tensor_params: dict, **driver_params) -> dict[str, tuple[str, ...]]:
    """The frame ids of what a simulating driver publishes (its first sets) and of the tensor
    node's gradient/raw made of them, both nodes in this process (test/ros/in_process.py)."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import MagneticField

    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    with node_in_process(DriverNode, monkeypatch, mode='sim', rate=0.0, max_duration_s=2.0,
                         **driver_params) as (driver, played):
        driver._tick()  # the first sets, up to the rate-0 window
    mags = [deserialized(played, f'/tetra/mag{s}', MagneticField) for s in range(1, 5)]
    (odom, *_) = deserialized(played, '/tetra/odom', Odometry)
    seen = {f'mag{s + 1}': (mags[s][0].header.frame_id,) for s in range(4)}
    seen['odom'] = (odom.header.frame_id, odom.child_frame_id)
    seen['absolute odom messages'] = (str(len([t for t, _ in played if t == '/odom'])),)
    with node_in_process(TensorNode, monkeypatch, **tensor_params) as (tensor, published):
        for i in range(len(mags[0])):
            for s in range(4):
                tensor._on_mag(s, serialize_message(mags[s][i]))
    (raw, *_) = deserialized(published, '/tetra/gradient/raw', gt.rclpy_class())
    seen['raw'] = (raw.header.frame_id,)
    return seen


def test_default_frames_follow_rep_105(monkeypatch):
    seen = _frames(monkeypatch, {})
    assert seen['odom'] == ('odom', 'base_link')
    assert seen['absolute odom messages'] == ('0',)  # the vehicle's /odom is not the driver's
    assert [seen[f'mag{s}'][0] for s in range(1, 5)] == ['tetra_mag1', 'tetra_mag2', 'tetra_mag3', 'tetra_mag4']
    assert seen['raw'] == ('tetra_array',)


def test_every_frame_id_is_a_parameter(monkeypatch):
    seen = _frames(monkeypatch, {'array_frame_id': 'auv/gradiometer'}, odom_frame_id='map',
                   base_frame_id='auv/base_link', sensor_frame_ids=['auv/m1', 'auv/m2', 'auv/m3', 'auv/m4'])
    assert seen['odom'] == ('map', 'auv/base_link')
    assert [seen[f'mag{s}'][0] for s in range(1, 5)] == ['auv/m1', 'auv/m2', 'auv/m3', 'auv/m4']
    assert seen['raw'] == ('auv/gradiometer',)


def test_a_frame_id_with_a_leading_slash_is_refused_at_start():
    code, output = NodeProcess('tensor', unique_domain(), {'array_frame_id': '/tetra_array'}).refusal()
    assert code == 1 and 'Traceback' not in output, output
    line = [line for line in output.splitlines() if 'cannot start:' in line]
    assert len(line) == 1 and "'array_frame_id'" in line[0] and 'leading "/"' in line[0], output


def test_sensor_frame_ids_must_name_four_frames():
    code, output = NodeProcess('driver', unique_domain(), {'sensor_frame_ids': ['a', 'b', 'c']}).refusal()
    assert code == 1 and "'sensor_frame_ids'" in output and 'must name 4 frames' in output, output
