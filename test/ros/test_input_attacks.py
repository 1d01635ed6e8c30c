"""Issue 34, inputs from where they should come: a second publisher on an input topic is a
WARN naming its node, and a reading stamped ahead of the node's clock (another process's mag2
500 ms ahead over real DDS; odometry 1 s ahead, in this process) is refused and counted and
never evicts the real readings."""
from __future__ import annotations

import time

import numpy as np
from ros_helpers import ros_graph, uniform_gradient_fields, wait_connected, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io import conversions as cv

NT = 1e-9
GEOMETRY = core.TetraGeometry.regular(0.5)
FIELDS = uniform_gradient_fields(GEOMETRY.positions, np.array([12e-6, -20e-6, 43e-6]),
                                 np.diag([100.0, -60.0, -40.0]) * NT)


def test_mag2_from_another_process_stamped_ahead_is_refused_and_named_and_no_real_set_is_lost():
    import rclpy
    from sensor_msgs.msg import MagneticField

    n, forged_at = 150, 50
    with ros_graph() as (graph, probe, feeder):
        process = graph.start('tensor', diagnostics_period_s=0.2)
        intruder = rclpy.create_node('intruder', namespace='/tetra', context=probe.context)
        try:
            mag2 = intruder.create_publisher(MagneticField, 'mag2', 100)
            for publisher in [*feeder.mags, mag2]:
                wait_matched(publisher, 1)
            wait_connected(probe, graph, 'tensor', '/tetra/gradient/raw', 2)
            wait_for(lambda: 'publishers on /tetra/mag2' in probe.status('tetra/tensor: inputs').get('message', ''),
                     10, 'the second publisher named', graph)
            status = probe.status('tetra/tensor: inputs')
            assert status['level'] == 1 and '/tetra/intruder' in status['message'], status
            assert '/tetra/test_feeder' in status['message']
            with probe.lock:
                probe.collecting = True
            for i in range(n):  # live: sample times are now, 100 Hz
                feeder.publish_set(time.time_ns(), FIELDS)
                if i == forged_at:  # the issue's: mag2 stamped 500 ms ahead
                    ahead = time.time_ns() + 5 * 10**8
                    mag2.publish(cv.magnetic_field_msg(feeder.types, FIELDS[1] * 2, ahead, cv.MAG_FRAMES[1]))
                time.sleep(0.01)
            # Every set whose later neighbour came is formed (interpolation waits for the next
            # reading of each sensor): before the fix the forged stamp put the real mag2
            # readings of the next 0.5 s out of order, and their sets were lost.
            wait_for(lambda: probe.counts['gradient/raw'] >= n - 1, 10, f'{n - 1} tensors ({probe.counts})', graph)
            wait_for(lambda: probe.status('tetra/tensor: inputs').get('refused_future mag2') == '1', 10,
                     'the refusal counted', graph)
            assert 'ahead of the clock' in probe.status('tetra/tensor: inputs')['message'] or \
                probe.status('tetra/tensor: inputs')['level'] == 1
            raw = probe.tensors['gradient/raw']
            assert all(np.abs(g - np.diag([100.0, -60.0, -40.0]) * NT).max() < 1e-3 * NT for g in raw.values())
            output = process.output()
            assert 'refused a /tetra/mag2 message stamped' in output and '/tetra/intruder' in output
            assert 'jumped back' not in output
        finally:
            intruder.destroy_node()


def test_odometry_stamped_ahead_is_refused_by_the_target_and_calibrator(monkeypatch, tmp_path):
    """In this process (test/ros/in_process.py): an odometry message 1 s ahead of the node's
    clock, then one stamped now, handed to each node's odom callback."""
    from in_process import last_status, node_in_process

    from tetra_gradiometer.nodes.calibrator import CalibratorNode
    from tetra_gradiometer.nodes.target import TargetNode

    types = cv.rclpy_types()
    for node_class, name, extra in ((TargetNode, 'target', {}),
                                    (CalibratorNode, 'calibrator', {'calibration_file': str(tmp_path / 'c.yaml')})):
        with node_in_process(node_class, monkeypatch, **extra) as (node, published):
            now = time.time_ns()
            node._on_odom(cv.odometry_msg(types, np.array([200.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]), now + 10**9))
            node._on_odom(cv.odometry_msg(types, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), now))
            node._publish_diagnostics()
            assert last_status(published, f'tetra/{name}: inputs')['refused_future odom'] == '1', name
            if name == 'target':
                assert last_status(published, 'tetra/target: targets')['dropped_out_of_order'] == '0'
