"""The operator probe's service calls survive a reply that never comes (rmw_fastrtps drops one
when the server has not matched the client's reply reader in time): a server in this process
takes the first request and leaves it unanswered, as the middleware does."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import pytest

from .ros_helpers import ros_graph


@contextmanager
def _dropping_server(name: str, kind: str = 'Trigger'):
    """``(probe, taken)``: a server ``name`` (std_srvs/Trigger, or tetra_gradiometer_msgs/
    Calibrate) on the probe's context, polled by hand:
    the first request is taken and dropped, every later one answered with its ordinal;
    ``taken`` the monotonic times of the requests it took."""
    from rclpy.node import Node
    from std_srvs.srv import Trigger
    from tetra_gradiometer_msgs.srv import Calibrate

    service_type = {'Trigger': Trigger, 'Calibrate': Calibrate}[kind]
    stop, taken = threading.Event(), []
    with ros_graph() as (_, probe, _feeder):
        node = Node('dropper', context=probe.context)
        service = node.create_service(service_type, name, lambda request, response: response)

        def run() -> None:
            try:
                while not stop.is_set():
                    with service.handle:
                        _, header = service.handle.service_take_request(service_type.Request)
                    if header is None:  # nothing to take
                        time.sleep(0.01)
                        continue
                    taken.append(time.monotonic())
                    if len(taken) > 1:
                        service.send_response(
                            service_type.Response(success=True, message=f'request {len(taken)}'), header
                        )
            finally:
                node.destroy_node()

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        try:
            yield probe, taken
        finally:
            stop.set()
            thread.join(timeout=5)


def test_an_unanswered_request_is_sent_again_on_the_same_client_and_its_answer_returned(monkeypatch):
    from tetra_gradiometer.cli import _probe

    monkeypatch.setattr(_probe, 'RESEND_S', 0.5)
    with _dropping_server('/dropper/resume') as (probe, taken):
        started = time.monotonic()
        reply = probe.call('/dropper/resume', timeout_s=20)
    assert (reply.success, reply.message) == (True, 'request 2')
    assert len(taken) == 2
    assert taken[1] - taken[0] >= 0.4 and taken[1] - started < 10  # resent after 0.5 s; taken by 10 ms polls


def test_a_calibrate_request_is_not_sent_twice(monkeypatch):
    """A second ``~/calibrate`` during a solve is refused: the probe waits for the first."""
    from tetra_gradiometer.cli import _probe

    monkeypatch.setattr(_probe, 'RESEND_S', 0.5)
    with _dropping_server('/dropper/calibrate', 'Calibrate') as (probe, taken):
        with pytest.raises(TimeoutError, match='did not answer within 2 s'):
            probe.call('/dropper/calibrate', timeout_s=2)
    assert len(taken) == 1
