"""Declared signals in the nodes, without a DDS graph: a field of any message (a JointState
joint by name, a Float64 without header), its stamp, its message class from the graph, and
the driver's replay of a bag's signal topics.

Truth: the messages built here, the graph a stand-in node reports, the bag's recorded bytes."""
from __future__ import annotations

import math
from types import SimpleNamespace

from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from tetra_gradiometer.nodes.channels import channel_message, channel_stamp, message_class

FIN2 = 'signal:/joint_states#position[fin2]'


def test_a_declared_field_is_read_from_any_message_and_stamped():
    joints = JointState(name=['fin1', 'fin2'], position=[0.1, -0.25])
    joints.header.stamp.sec, joints.header.stamp.nanosec = 12, 5
    assert channel_message(FIN2, joints) == -0.25
    assert channel_stamp(joints, 99) == 12 * 10**9 + 5
    assert math.isnan(channel_message(FIN2, JointState(name=['fin1'], position=[0.1])))  # not reported
    power = Float64(data=3.5)
    assert channel_message('signal:/power/sonar#data', power) == 3.5
    assert channel_stamp(power, 99) == 99  # no header: the node's clock


def test_the_message_class_is_the_graphs():
    node = SimpleNamespace(get_topic_names_and_types=lambda: [
        ('/joint_states', ['sensor_msgs/msg/JointState']), ('/power/sonar', ['std_msgs/msg/Float64']),
        ('/custom', ['no_such_package/msg/Thing'])])
    assert message_class(node, '/joint_states') is JointState
    assert message_class(node, '/power/sonar') is Float64
    assert message_class(node, '/custom') is None and message_class(node, '/absent') is None


def test_the_replay_plays_the_signal_topics_as_recorded_channels_first(tmp_path):
    """A bag with fin angles (JointState) and a power board's current (Float64, no header):
    the driver's frames carry their recorded bytes, each before the sets of its log time, and
    rclpy publishes those bytes on a publisher of the recorded type."""
    import sys
    from pathlib import Path

    import numpy as np
    import rclpy
    from rosbags.highlevel import AnyReader

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'io'))
    from stream_faults import START_NS, short_mission

    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io.bag import BagWriter
    from tetra_gradiometer.nodes.channels import message_class_named
    from tetra_gradiometer.nodes.replay import SIGNAL, describe_bag, iter_frames

    mission = short_mission(trim_s=2.0, survey_s=1.0)
    with BagWriter(tmp_path / 'bag') as writer:
        for i, t in enumerate(mission.t):
            log = START_NS + int(round(t * 1e9))
            for s in range(4):
                data = cv.magnetic_field_cdr(mission.fields_measured[i, s], log, cv.MAG_FRAMES[s])
                writer.write_raw(cv.BAG_MAG_TOPICS[s], cv.MAGNETIC_FIELD, data, log)
            if i % 2 == 0:  # written after the set of its log time, played before it
                writer.write('/power/sonar', writer.types['std_msgs/msg/Float64'](data=float(i)), log)
    info = describe_bag(tmp_path / 'bag')
    assert info['signals'] == (('/power/sonar', 'std_msgs/msg/Float64'),)
    frames = list(iter_frames(tmp_path / 'bag', cv.rclpy_types()))
    played = [(f.clock_ns, item[2]) for f in frames for item in f.items if item[0] == SIGNAL]
    with AnyReader([tmp_path / 'bag']) as reader:
        recorded = [(log, bytes(raw)) for c, log, raw in reader.messages(
            [c for c in reader.connections if c.topic == '/power/sonar'])]
    assert played == recorded
    for k, frame in enumerate(frames):  # a signal message precedes the set of its log time
        if frame.items[0][0] == SIGNAL:
            assert (k == 0 or frames[k - 1].clock_ns < frame.clock_ns) and frames[k + 1].clock_ns == frame.clock_ns
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=0)
    try:
        node = rclpy.create_node('replay_bytes', context=context)
        publisher = node.create_publisher(message_class_named('std_msgs/msg/Float64'), '/power/sonar', 1)
        publisher.publish(played[0][1])  # rclpy takes the serialized message as it is
        node.destroy_node()
    finally:
        context.try_shutdown()
    assert message_class_named('no_such_package/msg/Thing') is None
