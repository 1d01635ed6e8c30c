"""Lifecycle requests are rclpy's: every valid transition from every state of every node
leaves it where the standard lifecycle says (its state as the node reports it); a node
process asked for transitions that are not valid from its state (rcl_lifecycle refuses
them, rclpy sends no reply) keeps running and still answers the valid ones. No module
touches rclpy's private lifecycle members. A deactivated node keeps publishing WARN
``inactive`` statuses on the steady clock (``use_sim_time`` without ``/clock`` does not
freeze them)."""
from __future__ import annotations

import os
import time
from typing import Any

import pytest
from ros_helpers import ros_graph, unique_domain, wait_for

#: The standard lifecycle (lifecycle_msgs/Transition ids) a client may drive, independent of
#: the code under test: state -> {transition id: resulting state}.
VALID = {
    'unconfigured': {1: 'inactive', 5: 'finalized'},
    'inactive': {2: 'unconfigured', 3: 'active', 6: 'finalized'},
    'active': {4: 'inactive', 7: 'finalized'},
    'finalized': {},
}
NODES = ['tensor', 'calibrator', 'compensator', 'driver', 'target']


def _classes() -> dict[str, Any]:
    from tetra_gradiometer.nodes.calibrator import CalibratorNode
    from tetra_gradiometer.nodes.compensator import CompensatorNode
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.target import TargetNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    return {'tensor': TensorNode, 'calibrator': CalibratorNode, 'compensator': CompensatorNode,
            'driver': DriverNode, 'target': TargetNode}


def _overrides(name: str, tmp_path: Any, **extra: Any) -> list:
    from rclpy.parameter import Parameter

    overrides = [Parameter('autostart', value=False)]
    if name in ('calibrator', 'compensator'):
        overrides.append(Parameter('calibration_file', value=str(tmp_path / 'calibration.yaml')))
    if name == 'driver':
        overrides += [Parameter('mode', value='sim'), Parameter('max_duration_s', value=5.0)]
    overrides += [Parameter(k, value=v) for k, v in extra.items()]
    return overrides


def _reach(node: Any, state: str) -> None:
    """Drive ``node`` (unconfigured, inactive or active) to ``state`` with valid transitions."""
    order = ['unconfigured', 'inactive', 'active']
    while node.state_label != state:
        here, there = order.index(node.state_label), order.index(state)
        step = {(0, 1): node.trigger_configure, (1, 2): node.trigger_activate,
                (1, 0): node.trigger_cleanup, (2, 1): node.trigger_deactivate}
        step[(here, here + (1 if there > here else -1))]()


@pytest.mark.parametrize('name', NODES)
def test_every_valid_transition_from_every_state_leaves_the_node_where_the_lifecycle_says(
        name, tmp_path):
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain(), args=['--ros-args', '-r', '__ns:=/lifecycle_requests'])
    node_class = _classes()[name]
    done = 0
    try:
        node = node_class(parameter_overrides=_overrides(name, tmp_path), context=context)
        try:
            for state in ('unconfigured', 'inactive', 'active'):
                for transition_id, expected in VALID[state].items():
                    _reach(node, state)
                    trigger = {1: node.trigger_configure, 2: node.trigger_cleanup,
                               3: node.trigger_activate, 4: node.trigger_deactivate}.get(
                                   transition_id, node.trigger_shutdown)
                    trigger()
                    done += 1
                    assert node.state_label == expected, f'{name}: {transition_id} from {state}'
                    assert node.active == (expected == 'active')
                    if expected == 'finalized':  # terminal: a fresh node for the next case
                        node.destroy_node()
                        node = node_class(parameter_overrides=_overrides(name, tmp_path), context=context)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert done == 7


def test_no_module_touches_rclpys_private_lifecycle_members():
    from pathlib import Path

    package = Path(__file__).resolve().parents[2] / 'tetra_gradiometer'
    private = ('_state_machine', '_service_change_state', '_service_get_state', '_LifecycleNode__',
               '_managed_entities', '_callbacks[')
    found = [(path.name, name) for path in package.rglob('*.py') for name in private
             if name in path.read_text(encoding='utf-8')]
    assert found == []


class _Listener:
    """Every status on /diagnostics named with ``prefix``, from its creation on."""

    def __init__(self, node: Any, executor: Any, prefix: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self.seen: list = []
        self.executor = executor
        node.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda msg: self.seen.extend(s for s in msg.status if s.name.startswith(prefix)), 100)

    def during(self, seconds: float) -> list:
        """The statuses received while spinning ``seconds`` (and any received just before)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
        seen, self.seen = self.seen, []
        return seen


@pytest.mark.parametrize('name', ['compensator', 'tensor'])
def test_a_deactivated_node_keeps_reporting_inactive_on_the_steady_clock(name, tmp_path):
    """use_sim_time with no /clock: the node's ROS time stands still at 0, yet the statuses
    come every 0.1 s (steady clock); deactivated, every status is WARN 'inactive: ...'."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()  # a namespace of its own: another test's nodes on the domain differ
    rclpy.init(context=context, domain_id=unique_domain(), args=['--ros-args', '-r', f'__ns:=/steady{os.getpid()}'])
    executor = SingleThreadedExecutor(context=context)
    nodes: list = []
    try:
        node = _classes()[name](parameter_overrides=_overrides(
            name, tmp_path, diagnostics_period_s=0.1, use_sim_time=True), context=context)
        listener = rclpy.create_node('listener', context=context)
        nodes = [node, listener]
        for each in nodes:
            executor.add_node(each)
        statuses = _Listener(listener, executor, node.get_fully_qualified_name().lstrip('/') + ': ')
        node.bring_up()
        assert node.get_clock().now().nanoseconds == 0  # sim time, no /clock: frozen
        statuses.during(0.3)  # those of the configuration (inactive) still in flight
        active = statuses.during(1.5)
        assert len({s.name for s in active}) >= 1 and len(active) >= 5, active
        assert not any(s.message.startswith('inactive') for s in active)
        node.trigger_deactivate()
        statuses.during(0.3)  # the last active ones still in flight
        inactive = statuses.during(1.5)
        names = {s.name for s in active}
        assert len(inactive) >= 5 * len(names)  # 15 periods of 0.1 s, each with every status
        assert {s.name for s in inactive} == names
        assert all(s.level[0] >= 1 and s.message.startswith('inactive: ') for s in inactive), inactive
        # Shut down: the statuses' last word is WARN 'finalized', then nothing more comes.
        statuses.during(0.3)
        node.trigger_shutdown()
        last = {s.name: s for s in statuses.during(0.5)}  # (earlier ones may still be queued)
        assert set(last) == names and all(
            s.level[0] >= 1 and s.message.startswith('finalized (shut down): ') for s in last.values()), last
        assert statuses.during(0.5) == []
    finally:
        executor.shutdown(timeout_sec=2)
        for each in nodes:
            each.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_node_process_asked_for_an_invalid_transition_keeps_running():
    """rcl_lifecycle refuses a transition that is not valid from the node's state (rclpy
    sends no reply: the call times out); the process keeps running, says so, and answers the
    valid requests that follow."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    def call(probe: Any, kind: Any, service: str, request: Any, timeout: float = 15) -> Any:
        client = probe.create_client(kind, f'compensator/{service}')
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(request)
        try:
            wait_for(future.done, timeout, service)
        except AssertionError:
            return None
        finally:
            probe.destroy_client(client)
        return future.result()

    with ros_graph() as (graph, probe, feeder):
        process = graph.start('compensator')
        for transition in (Transition.TRANSITION_ACTIVATE, Transition.TRANSITION_CONFIGURE,
                           Transition.TRANSITION_CLEANUP, 99):
            request = ChangeState.Request(transition=Transition(id=transition))
            assert call(probe, ChangeState, 'change_state', request, timeout=2) is None
        assert process.alive(), process.output()
        assert call(probe, GetState, 'get_state', GetState.Request()).current_state.label == 'active'
        deactivate = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_DEACTIVATE))
        assert call(probe, ChangeState, 'change_state', deactivate).success is True
        assert call(probe, GetState, 'get_state', GetState.Request()).current_state.label == 'inactive'
        output = process.output()
        assert 'No transition matching 3 found for current state active' in output
        assert 'request refused: Failed to trigger lifecycle state machine transition' in output
        assert 'deactivate: active -> inactive' in output
        assert 'Traceback' not in output
