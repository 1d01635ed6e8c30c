"""A node in this process, without a DDS graph to wait on: constructed (configured and
activated by ``autostart``), driven by calling its callbacks, what it publishes captured.

Nothing is spun: no timer fires and no message arrives but the ones the test hands to a
callback, so what the node publishes follows from the test's inputs alone."""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from ros_helpers import unique_domain


#: ``[node, published]`` of each node in process; node None while it is being built.
_CAPTURES: list[list[Any]] = []


def _capture(publisher: Any, msg: Any) -> None:
    """Into the ``published`` of the node owning ``publisher`` (or of the one being built)."""
    for node, published in _CAPTURES:
        if node is None or any(p is publisher for p in node.publishers):
            published.append((publisher.topic_name, msg))
            return
    raise AssertionError(f'a publish on {publisher.topic_name} by no node in process')


@contextlib.contextmanager
def node_in_process(node_class: type, monkeypatch: Any, **parameters: Any) -> Iterator[tuple[Any, list]]:
    """``(node, published)``: a ``node_class`` built with ``parameters`` in a context of its
    own; ``published`` receives ``(topic, message)`` for every publish of its publishers (a
    serialized message stays bytes). Several may be open at once, each capturing its own."""
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.publisher import Publisher

    published: list[tuple[str, Any]] = []
    monkeypatch.setattr(Publisher, 'publish', _capture)
    capture = [None, published]
    _CAPTURES.append(capture)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain())
    node = None
    try:
        node = node_class(context=context,
                          parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()])
        capture[0] = node
        yield node, published
    finally:
        _CAPTURES.remove(capture)
        if node is not None:
            node.destroy_node()
        context.try_shutdown()


def last_status(published: list, name: str) -> dict:
    """The values of the last ``/diagnostics`` status ``name`` in ``published``, with its
    ``message`` and ``level`` (0 OK, 1 WARN, 2 ERROR); {} when none was published."""
    for topic, array in reversed(published):
        if topic == '/diagnostics':
            for found in array.status:
                if found.name == name:
                    return {**{v.key: v.value for v in found.values}, 'message': found.message,
                            'level': found.level[0]}
    return {}


def deserialized(published: list, topic: str, message_class: type) -> list:
    """The messages published on ``topic``, serialized ones deserialized as ``message_class``."""
    from rclpy.serialization import deserialize_message

    return [deserialize_message(m, message_class) if isinstance(m, bytes) else m
            for t, m in published if t == topic]


def set_sim_time(node: Any, stamp_ns: int) -> None:
    """The node's time (``use_sim_time``) to ``stamp_ns``, through its own ``/clock``
    subscription's callback, as a /clock message would set it."""
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock

    (clock,) = [s for s in node.subscriptions if s.topic_name == '/clock']
    clock.callback(Clock(clock=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)))



@contextlib.contextmanager
def compensator_in_process(monkeypatch: Any, **parameters: Any) -> Iterator[tuple[Any, list]]:
    """:func:`node_in_process` of the compensator, the graph (as the node asks it) naming
    its configured calibration publisher alone: a calibration handed to its callback is that
    node's, and its signature is checked as the topic's would be."""
    from tetra_gradiometer.nodes.compensator import CompensatorNode

    with node_in_process(CompensatorNode, monkeypatch, **parameters) as (node, published):
        monkeypatch.setattr(node._watch, 'publishers', lambda topic: [node._gate.publisher])
        yield node, published


def served(node: Any, name: str) -> Any:
    """The callback the node serves ``~/name`` with, as a request reaches it (its wrappers:
    the activity gate, the log line of a state-changing call)."""
    names = (f'~/{name}', f'{node.get_fully_qualified_name()}/{name}')  # as created, or expanded
    (service,) = [s for s in node.services if s.srv_name in names]
    return service.callback
