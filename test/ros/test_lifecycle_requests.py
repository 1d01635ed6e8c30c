"""Lifecycle requests cannot kill a node: every transition id and label, valid or
not, from every state of every node, through the node's ``~/change_state`` callback in
process; the invalid ones answered ``success=false`` (the reason logged) and the node still
working. A deactivated node keeps publishing WARN ``inactive`` statuses on the steady clock
(``use_sim_time`` without ``/clock`` does not freeze them), and a node process asked for an
invalid transition over the service keeps running."""
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
LABELS = {'configure': 1, 'cleanup': 2, 'activate': 3, 'deactivate': 4, 'shutdown': None}
#: Every id lifecycle_msgs defines (create, destroy and the callbacks' results included) and
#: two it does not.
IDS = [*range(0, 9), 10, 11, 12, 13, 14, 15, 20, 21, 22, 30, 31, 32, 40, 41, 42, 50, 51, 52, 60,
       61, 62, 99, 255]
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


def _request(transition_id: int | None = None, label: str = '') -> Any:
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    return ChangeState.Request(transition=Transition(id=transition_id or 0, label=label))


def _ask(node: Any, request: Any) -> bool:
    from lifecycle_msgs.srv import ChangeState

    response = node._service_change_state.callback(request, ChangeState.Response())
    return bool(response.success)


def _reach(node: Any, state: str) -> None:
    """Drive ``node`` (unconfigured, inactive or active) to ``state`` with valid transitions."""
    order = ['unconfigured', 'inactive', 'active']
    while node.state_label != state:
        here, there = order.index(node.state_label), order.index(state)
        step = {(0, 1): node.trigger_configure, (1, 2): node.trigger_activate,
                (1, 0): node.trigger_cleanup, (2, 1): node.trigger_deactivate}
        step[(here, here + (1 if there > here else -1))]()


def _cases(state: str) -> list[tuple[str, Any, str | None]]:
    """(what, request, expected state or None when refused) for every id and label."""
    cases: list[tuple[str, Any, str | None]] = []
    for transition_id in IDS:
        cases.append((f'id {transition_id}', _request(transition_id), VALID[state].get(transition_id)))
    for label, transition_id in LABELS.items():
        ids = [t for t in VALID[state] if transition_id in (None, t) and (transition_id or t >= 5)]
        expected = VALID[state][ids[0]] if ids else None
        cases.append((f'label {label}', _request(label=label), expected))
    cases.append(('label bogus', _request(label='bogus'), None))
    return cases


@pytest.mark.parametrize('name', NODES)
def test_every_transition_from_every_state_is_answered_and_the_node_keeps_working(name, tmp_path):
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain(), args=['--ros-args', '-r', '__ns:=/lifecycle_requests'])
    node_class = _classes()[name]
    answered = 0
    try:
        node = node_class(parameter_overrides=_overrides(name, tmp_path), context=context)
        try:
            for state in ('unconfigured', 'inactive', 'active'):
                for what, request, expected in _cases(state):
                    _reach(node, state)
                    success = _ask(node, request)  # before the fix: RCLError out of the callback
                    answered += 1
                    assert success == (expected is not None), f'{name}: {what} from {state}'
                    if expected == 'finalized':  # terminal: a fresh node for the next case
                        assert node.state_label == 'finalized'
                        assert not _ask(node, _request(1)) and not _ask(node, _request(label='shutdown'))
                        node.destroy_node()
                        node = node_class(parameter_overrides=_overrides(name, tmp_path), context=context)
                        continue
                    assert node.state_label == (expected or state), f'{name}: {what} from {state}'
            # Finalized: every request refused, the node stays finalized.
            node.trigger_shutdown()
            for what, request, expected in _cases('finalized'):
                assert expected is None
                assert not _ask(node, request), f'{name}: {what} from finalized'
                answered += 1
                assert node.state_label == 'finalized'
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert answered == 4 * len(_cases('active'))


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
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    def call(probe: Any, kind: Any, service: str, request: Any) -> Any:
        client = probe.create_client(kind, f'compensator/{service}')
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(request)
        wait_for(future.done, 15, service)
        probe.destroy_client(client)
        return future.result()

    with ros_graph() as (graph, probe, feeder):
        process = graph.start('compensator')
        for transition in (Transition.TRANSITION_ACTIVATE, Transition.TRANSITION_CONFIGURE,
                           Transition.TRANSITION_CLEANUP, Transition.TRANSITION_DESTROY, 99):
            response = call(probe, ChangeState, 'change_state',
                            ChangeState.Request(transition=Transition(id=transition)))
            assert response.success is False
        time.sleep(0.5)
        assert process.alive(), process.output()
        assert call(probe, GetState, 'get_state', GetState.Request()).current_state.label == 'active'
        output = process.output()
        assert 'change_state refused: transition id 3 is not valid from state active' in output
        assert 'Traceback' not in output
