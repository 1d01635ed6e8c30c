"""Frame ids (REP 103/105) as a user sees them on the topics: the simulating
driver's odometry (/tetra/odom, never the vehicle's /odom) is odom -> base_link and its magnetometers tetra_mag1..4 by default, every
frame id is a parameter, the tensor publishes its gradient (with B_1') in ``array_frame_id``;
a frame id with a leading '/' (tf2 refuses those) is refused at start-up."""
from __future__ import annotations

import time

from ros_helpers import NodeProcess, ros_graph, unique_domain, wait_for


def _frames(probe, graph, **driver_params) -> dict[str, tuple[str, ...]]:
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import MagneticField

    from tetra_gradiometer.io import gradient_tensor as gt

    from tetra_gradiometer.nodes.common import derived_qos, sensor_qos

    seen: dict[str, tuple[str, ...]] = {}

    def keep(name, *ids):
        seen.setdefault(name, ids)

    probe.create_subscription(Odometry, '/tetra/odom', lambda m: keep('odom', m.header.frame_id, m.child_frame_id),
                              derived_qos())
    for s in range(4):
        probe.create_subscription(MagneticField, f'/tetra/mag{s + 1}',
                                  lambda m, s=s: keep(f'mag{s + 1}', m.header.frame_id), sensor_qos(100))
    probe.create_subscription(gt.rclpy_class(), '/tetra/gradient/raw', lambda m: keep('raw', m.header.frame_id),
                              derived_qos())
    # Real time for 10 s: a reader that matches the driver's writers late (discovery on a
    # loaded machine) still gets later messages; one per topic is all this test needs.
    graph.start('driver', mode='sim', rate=1.0, min_subscribers=2, max_duration_s=10.0, start_paused=True, **driver_params)
    # Volatile topics: the driver's writers known to every reader before it plays.
    wait_for(lambda: probe.count_publishers('/tetra/odom') >= 1 and probe.count_publishers('/tetra/mag4') >= 2,
             30, 'the driver', graph)
    time.sleep(1.0)
    assert probe.call('driver/resume').success
    wait_for(lambda: len(seen) == 6, 30, 'a message on each topic', graph)
    seen['absolute odom publishers'] = (str(probe.count_publishers('/odom')),)
    return seen


def test_default_frames_follow_rep_105():
    with ros_graph() as (graph, probe, _):
        graph.start('tensor')
        seen = _frames(probe, graph)
    assert seen['odom'] == ('odom', 'base_link')
    assert seen['absolute odom publishers'] == ('0',)  # the vehicle's /odom is not the driver's
    assert [seen[f'mag{s}'][0] for s in range(1, 5)] == ['tetra_mag1', 'tetra_mag2', 'tetra_mag3', 'tetra_mag4']
    assert seen['raw'] == ('tetra_array',)


def test_every_frame_id_is_a_parameter():
    with ros_graph() as (graph, probe, _):
        graph.start('tensor', array_frame_id='auv/gradiometer')
        seen = _frames(probe, graph, odom_frame_id='map', base_frame_id='auv/base_link',
                       sensor_frame_ids=['auv/m1', 'auv/m2', 'auv/m3', 'auv/m4'])
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
