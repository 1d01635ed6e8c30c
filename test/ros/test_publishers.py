"""A required input nobody publishes is an ERROR naming the topic as resolved, after
:data:`NO_PUBLISHER_S`; a publisher that appears clears it. Node logic without a DDS graph:
a stand-in node answers the graph queries.

Truth: the stand-in's publishers and the clock the test moves.
"""
from __future__ import annotations

from types import SimpleNamespace

from tetra_gradiometer.nodes import publishers
from tetra_gradiometer.nodes.publishers import NO_PUBLISHER_S, InputPublishers


class _Node:
    def __init__(self, topics):
        self.subscriptions = [SimpleNamespace(topic_name=t) for t in topics]
        self.graph: dict[str, list[str]] = {t: [] for t in topics}

    def get_publishers_info_by_topic(self, topic):
        return [SimpleNamespace(node_namespace='/tetra', node_name=n) for n in self.graph[topic]]

    def get_fully_qualified_name(self):
        return '/tetra/target'

    def get_logger(self):
        return SimpleNamespace(warning=lambda text: None)


def test_a_required_topic_without_publisher_is_an_error_naming_it(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(publishers.time, 'monotonic', lambda: now[0])
    node = _Node(['/nav/odometry_remapped', '/tetra/gradient/compensated', '/tetra/optional'])
    inputs = InputPublishers(node)
    inputs.require(node.subscriptions[0], node.subscriptions[1])
    node.graph['/tetra/gradient/compensated'] = ['compensator']
    inputs.check()
    assert inputs.status().level == bytes([0])  # start-up: not yet
    now[0] += NO_PUBLISHER_S + 1.0
    inputs.check()
    found = inputs.status()
    assert found.level == bytes([2]) and found.name == 'tetra/target: inputs'
    assert found.message.startswith(f'no publisher on /nav/odometry_remapped for {NO_PUBLISHER_S + 1:.0f} s')
    assert '/tetra/optional' not in found.message and 'compensated' not in found.message
    node.graph['/nav/odometry_remapped'] = ['navigation']
    inputs.check()
    assert inputs.status().level == bytes([0])
