"""Who publishes on a node's inputs: another process on the vehicle's ROS domain
can publish on any topic, and nothing in a message says who sent it.

rclpy hands a subscription callback no publisher identity on the EventsExecutor the nodes
spin (measured, rclpy 7.1.6: a callback taking the message info fails there; elsewhere the
info has no publisher gid), so a node judges the topic, not the message: from the ROS graph
(``get_publishers_info_by_topic``: node name and namespace of every publisher) it knows
every publisher of each of its subscriptions. :class:`InputPublishers` reports

* a topic with an expected publisher (the compensator's ``calibration``: the calibrator)
  where any other node publishes, and
* any other input topic with more than one publisher (every input of the suite has one:
  the driver, the tensor node, the compensator, the navigation, the vehicle),

as a WARN naming the nodes (a log line when a publisher appears, and the ``inputs``
status on ``/diagnostics`` while it is there), and a topic the node cannot work without
(:meth:`InputPublishers.require`) that nobody has published for :data:`NO_PUBLISHER_S` as an
ERROR naming the topic as resolved after remapping (a remap to a name nobody publishes,
or its node not running). The graph is read once per diagnostics period
and when a calibration arrives, never per sample.

Without SROS2 a node's name is whatever its process chose (``-r __node:=calibrator``), so
this makes a second publisher visible; it does not prove who the first one is. That takes
the calibration's signature (:mod:`.authentication`) or SROS2 (docs/ros.md, *Security*).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from .common import ERROR, OK, WARN, status

#: A required input without a publisher this long (s, steady clock) is an ERROR: longer than
#: a launch's start-up and the discovery of its nodes.
NO_PUBLISHER_S = 10.0

#: What rmw reports for an endpoint whose node it has not learned yet.
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'


def full_name(namespace: str, name: str) -> str:
    """``/ns/name`` from a namespace and a node name."""
    return f'{namespace.rstrip("/")}/{name}'


def resolve_node_name(node: Any, name: str) -> str:
    """A node name as ``node`` would resolve it: absolute as given, else in its namespace."""
    return name if name.startswith('/') else full_name(node.get_namespace(), name)


class InputPublishers:
    """The publishers of ``node``'s subscriptions and the unexpected ones among them.

    ``expected``: resolved topic -> the one node (fully qualified) allowed to publish it;
    other topics may have any one publisher."""

    def __init__(self, node: Any, expected: Mapping[str, str] | None = None) -> None:
        self.node = node
        self.expected = dict(expected or {})
        self._reported: set[tuple[str, str]] = set()
        self.unexpected: dict[str, list[str]] = {}
        self.counts: dict[str, int] = {}
        self.horizon: Any = None  # the node's StampHorizon (nodes/stamps.py), if it has one
        self._refused_reported = 0
        self.required: set[str] = set()
        self._alone_since: dict[str, float] = {}  # required topic -> steady s, no publisher

    def require(self, *subscriptions: Any) -> None:
        """The node cannot work without these subscriptions' topics (resolved names)."""
        self.required |= {s.topic_name for s in subscriptions}

    def watch_stamps(self, tolerance_s: float, warn_throttle_s: float = 5.0) -> Any:
        """A :class:`~.stamps.StampHorizon` of the node, its refusals in :meth:`status`."""
        from .stamps import StampHorizon

        self.horizon = StampHorizon(self.node, tolerance_s, warn_throttle_s)
        return self.horizon

    def publishers(self, topic: str) -> list[str]:
        """Fully qualified names of the nodes publishing ``topic`` (one per publisher)."""
        infos = self.node.get_publishers_info_by_topic(topic)
        return sorted(full_name(i.node_namespace, i.node_name) for i in infos)

    def unexpected_on(self, topic: str) -> list[str]:
        """The publishers of ``topic`` that should not be there (all of them, when a topic
        without an expected publisher has several)."""
        names = [n for n in self.publishers(topic) if not n.endswith(UNKNOWN_NODE)]  # yet
        self.counts[topic] = len(names)
        allowed = self.expected.get(topic)
        if allowed is not None:
            others = [n for n in names if n != allowed]
            if names.count(allowed) > 1:  # another node under the expected one's name
                others.append(f'{allowed} (x{names.count(allowed)}: a second node of that name)')
            return others
        return names if len(names) > 1 else []

    def check(self) -> None:
        """Look at every input topic; WARN once per newly seen unexpected publisher."""
        topics = sorted({s.topic_name for s in self.node.subscriptions})
        self.unexpected = {}
        for topic in topics:
            others = self.unexpected_on(topic)
            if others:
                self.unexpected[topic] = others
            for name in others:
                if (topic, name) not in self._reported:
                    self._reported.add((topic, name))
                    self.node.get_logger().warning(self.describe(topic, others))
        # a publisher that left and comes back is reported again
        self._reported &= {(t, n) for t, names in self.unexpected.items() for n in names}
        now = time.monotonic()
        for topic in self.required:
            if self.counts.get(topic, 0):
                self._alone_since.pop(topic, None)
            else:
                self._alone_since.setdefault(topic, now)

    def unpublished(self) -> list[str]:
        """The required topics nobody has published for :data:`NO_PUBLISHER_S`, each with
        for how long."""
        now = time.monotonic()
        return [
            f'no publisher on {topic} for {now - since:.0f} s'
            for topic, since in sorted(self._alone_since.items())
            if now - since > NO_PUBLISHER_S
        ]

    def describe(self, topic: str, others: list[str]) -> str:
        allowed = self.expected.get(topic)
        if allowed is not None:
            return (
                f'unexpected publisher on {topic}: {", ".join(others)} (only {allowed} may '
                'publish it)'
            )
        return f'{len(others)} publishers on {topic}: {", ".join(others)} (one expected)'

    def status(self) -> Any:
        """``<node>: inputs``: ERROR naming a required topic without a publisher; WARN naming
        the unexpected publishers, or while messages stamped ahead of the clock are refused
        (since the last report); else OK."""
        values: dict[str, Any] = {f'{t} publishers': n for t, n in sorted(self.counts.items())}
        if self.horizon is not None:
            values.update(self.horizon.values())
        unpublished = self.unpublished()
        if unpublished:
            text = '; '.join(unpublished) + (
                ': nothing to work on (a remap to a topic nobody publishes, or its node is not '
                'running)'
            )
            return status(self.node, 'inputs', ERROR, text, '', values)
        if self.horizon is not None:
            refused = sum(self.horizon.refused.values())
            new, self._refused_reported = refused - self._refused_reported, refused
            if new > 0:
                topics = ', '.join(sorted(self.horizon.refused))
                text = (
                    f'{new} messages stamped more than {self.horizon.tolerance_s:g} s ahead of '
                    f'the clock refused since the last report ({topics}): a wrong clock or '
                    'another publisher'
                )
                if self.unexpected:
                    text = f'{text}; ' + '; '.join(
                        self.describe(t, names) for t, names in sorted(self.unexpected.items())
                    )
                return status(self.node, 'inputs', WARN, text, '', values)
        if not self.unexpected:
            return status(
                self.node, 'inputs', OK, 'no unexpected publisher on the input topics', '', values
            )
        text = '; '.join(self.describe(t, names) for t, names in sorted(self.unexpected.items()))
        return status(self.node, 'inputs', WARN, text, '', values)
