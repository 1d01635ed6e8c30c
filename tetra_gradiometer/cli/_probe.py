"""The operator side of the in-process graphs of ``demo`` and ``record`` (and of the tests):
:func:`init_local_ros` starts rclpy for them, and :class:`Probe`, the operator/observer node,
calls the services (Trigger, and the calibrator's Calibrate), collects tensors by stamp, and
keeps the latest ``/diagnostics`` status of every component. Not part of the graph's
contract."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from tetra_gradiometer_msgs.srv import Calibrate

from ..io import gradient_tensor as gt
from ..nodes.common import DERIVED_DEPTH, NAMESPACE, derived_qos

TENSOR_TOPICS = ('gradient/raw', 'gradient/compensated', 'gradient/truth')
RESEND_S = 5.0
"""s: an unanswered request is sent again after this (see :meth:`Probe.call`)."""
NOT_RESENT = frozenset({'calibrate'})
"""Services not asked twice: a second ``~/calibrate`` during a solve is refused, so its
answer would stand for the first one's."""


def init_local_ros(params: str) -> int:
    """Start rclpy for a graph in this process and return its ``ROS_DOMAIN_ID``.

    The domain is the environment's, else one derived from the pid (1..100); discovery stays
    on this host unless ``ROS_AUTOMATIC_DISCOVERY_RANGE`` says otherwise; ``params`` is a
    ROS 2 parameter file ('' for none); the nodes log warnings and errors only. Ctrl-C and
    SIGTERM raise KeyboardInterrupt (rclpy's own handler is off), so the caller stops its
    executor before the context goes (``nodes.process.stop_graph``).
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from ..nodes.process import interrupt_on_signals
    from .node import ros_arguments

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    value = os.environ.get('ROS_DOMAIN_ID')
    domain = int(value) if value else 1 + os.getpid() % 100
    interrupt_on_signals()
    rclpy.init(
        args=ros_arguments(params, ['--log-level', 'warn']),
        domain_id=domain,
        signal_handler_options=SignalHandlerOptions.NO,
    )
    return domain


def ask(client: Any, request: Any, timeout_s: float, resend_s: float | None) -> Any:
    """The response to ``request`` on a service ``client`` whose node another thread spins,
    the request sent again on the same client every ``resend_s`` while unanswered (None:
    once): rmw_fastrtps drops a reply whose reader the server has not matched within 100 ms
    (see :meth:`Probe.call`); only for a request that may be repeated. Raises TimeoutError
    after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        future = client.call_async(request)
        ask_again = deadline if resend_s is None else time.monotonic() + resend_s
        while not future.done():
            if time.monotonic() > deadline:
                client.remove_pending_request(future)
                raise TimeoutError(
                    f'service {client.srv_name} did not answer within {timeout_s:g} s'
                )
            if time.monotonic() > ask_again:
                client.remove_pending_request(future)
                break
            time.sleep(0.005)
        else:
            return future.result()


class Probe(Node):
    """Collects ``gradient/raw|compensated|truth`` (T/m) by stamp while ``collecting``.

    ``depth``: the reader queue of each tensor topic. A probe spun beside other work (the
    tests' main thread) takes messages more slowly than a rate-0 replay sends them; past
    ``depth`` waiting messages the oldest are dropped (1113 of 1500 arrived at 1000)."""

    def __init__(self, name: str = 'probe', depth: int = DERIVED_DEPTH, **kwargs) -> None:
        kwargs.setdefault('namespace', NAMESPACE)
        super().__init__(name, **kwargs)
        self.lock = threading.Lock()
        self.collecting = False
        self.tensors: dict[str, dict[int, np.ndarray]] = {t: {} for t in TENSOR_TOPICS}
        self.counts = {t: 0 for t in TENSOR_TOPICS}
        self.diagnostics: dict[str, Any] = {}
        self.percent = float('nan')
        for topic in TENSOR_TOPICS:
            self.create_subscription(
                gt.rclpy_class(), topic, partial(self._on_tensor, topic), derived_qos(depth)
            )
        self.create_subscription(Float64, 'compensated_percent', self._on_percent, derived_qos())
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        self._service_clients: dict[str, Any] = {}

    def _on_tensor(self, topic: str, msg: Any) -> None:
        with self.lock:
            self.counts[topic] += 1
            if self.collecting:
                tensor = gt.tensor_set_from_msg(msg)
                self.tensors[topic][tensor.stamp_ns] = tensor.g

    def _on_percent(self, msg: Float64) -> None:
        self.percent = msg.data

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            self.diagnostics[s.name] = {
                'level': s.level[0] if isinstance(s.level, bytes) else int(s.level),
                'message': s.message,
                **{kv.key: kv.value for kv in s.values},
            }

    def paired(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Stamps (n,) and raw, compensated, true tensors (n, 3, 3) on the common stamps."""
        with self.lock:
            common = sorted(set.intersection(*(set(d) for d in self.tensors.values())))
            raw, compensated, truth = (
                np.array([self.tensors[t][s] for s in common]).reshape(-1, 3, 3)
                for t in TENSOR_TOPICS
            )
        return np.array(common, dtype=np.int64), raw, compensated, truth

    def call(self, service: str, timeout_s: float = 30.0, request: Any = None) -> Any:
        """Call a service (spun by another thread) with ``request``; return the response. A
        service named ``calibrate`` is a tetra_gradiometer_msgs/Calibrate (``request`` None:
        its defaults, the node's parameters on every sample), the others std_srvs/Trigger.

        A request left unanswered for :data:`RESEND_S` is sent again on the same client, except
        to the services in :data:`NOT_RESENT`: rmw_fastrtps drops a reply when the server has
        not matched the client's reply reader within 100 ms of the request
        (ros2/rmw_fastrtps#390, #467), which a server or client just created on a loaded
        machine misses, and the client would wait forever (a fresh-clone ``make test`` lost
        the reply to a second driver's ``~/resume``). By then the server has matched it. The
        other services are idempotent: a repeat changes nothing the first did not.
        """
        name = service.rsplit('/', 1)[-1]
        kind = Calibrate if name == 'calibrate' else Trigger
        client = self._service_clients.get(service)
        if client is None:
            client = self._service_clients[service] = self.create_client(kind, service)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise TimeoutError(f'service {service} is not available')
        request = kind.Request() if request is None else request
        return ask(client, request, timeout_s, None if name in NOT_RESENT else RESEND_S)

    def wait_for(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout_s:g} s waiting for {what}')
            time.sleep(0.02)

    def status(self, name: str) -> dict[str, Any]:
        return self.diagnostics.get(name, {})
