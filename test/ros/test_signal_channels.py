"""Declared signals in the nodes, without a DDS graph: a field of any message (a JointState
joint by name, a Float64 without header), its stamp, and its message class from the graph.

Truth: the messages built here and the graph a stand-in node reports."""
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
