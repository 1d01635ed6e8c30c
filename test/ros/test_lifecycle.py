"""The nodes are managed (lifecycle) nodes: transitions through the standard lifecycle_msgs
services of a node process (a refused configure leaves it unconfigured; deactivate stops
the output and keeps the calibration; cleanup removes everything), and each node class's
transitions in process."""
from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from ros_helpers import calibration_msg, interference_set, ros_graph, unique_domain, wait_connected, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration

T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
NT = 1e-9
GEOMETRY = core.TetraGeometry.regular(0.5)


def _lifecycle(probe: Any, node: str, service: str, request: Any) -> Any:
    """Call ``<node>/<service>`` (lifecycle_msgs) and return the response."""
    from lifecycle_msgs.srv import ChangeState, GetState

    kind = ChangeState if service == 'change_state' else GetState
    client = probe.create_client(kind, f'{node}/{service}')
    assert client.wait_for_service(timeout_sec=30), f'{node}/{service} not available'
    future = client.call_async(request)
    wait_for(future.done, 30, f'{node}/{service}')
    probe.destroy_client(client)
    return future.result()


def state(probe: Any, node: str) -> str:
    from lifecycle_msgs.srv import GetState

    return _lifecycle(probe, node, 'get_state', GetState.Request()).current_state.label


def change(probe: Any, node: str, transition: str) -> bool:
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    ids = {
        'configure': Transition.TRANSITION_CONFIGURE,
        'activate': Transition.TRANSITION_ACTIVATE,
        'deactivate': Transition.TRANSITION_DEACTIVATE,
        'cleanup': Transition.TRANSITION_CLEANUP,
        'shutdown': Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
    }
    request = ChangeState.Request(transition=Transition(id=ids[transition]))
    return bool(_lifecycle(probe, node, 'change_state', request).success)


def _calibration(parameters: core.InterferenceParameters) -> CalibrationFile:
    return CalibrationFile(parameters=parameters, method='test', symmetric_k=False,
                           sensor_positions=GEOMETRY.to_flat())


def test_compensator_transitions_through_the_lifecycle_services(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text('tetra_gradiometer_calibration: 1\nk_soft: [[[0.1, ')
    g, b, exact = interference_set(40, rng=np.random.default_rng(3), directions='rich')
    assert np.abs(g).max() > 50 * NT  # the interference is there to be removed
    with ros_graph() as (graph, probe, feeder):
        process = graph.start('compensator', autostart=False, calibration_publisher='test_feeder', calibration_file=str(calibration_file))
        assert state(probe, 'compensator') == 'unconfigured'
        assert probe.count_publishers('/tetra/gradient/compensated') == 0

        # A corrupt calibration file: configure fails, says why, and the node stays unconfigured.
        assert not change(probe, 'compensator', 'configure')
        assert state(probe, 'compensator') == 'unconfigured'
        wait_for(lambda: 'configure refused' in process.output(), 10, 'the refusal in the log', graph)
        assert 'not valid YAML' in process.output() and str(calibration_file) in process.output()

        # Fixed (a calibration of zero parameters: pass-through), configure succeeds: inactive.
        zero = core.InterferenceParameters(np.zeros((3, 3, 3)), np.zeros((3, 3)))
        calibration_file.unlink()  # save_calibration replaces only a calibration file
        save_calibration(calibration_file, _calibration(zero))
        assert change(probe, 'compensator', 'configure')
        assert state(probe, 'compensator') == 'inactive'
        wait_matched(feeder.raw, 2)  # compensator and probe
        wait_connected(probe, graph, 'compensator', '/tetra/gradient/compensated', 1)
        with probe.lock:
            probe.collecting = True

        def send(first: int, count: int) -> None:
            for i in range(first, first + count):
                feeder.publish_raw(T0 + i * 10**8, g[i], b[i])

        def received() -> dict[int, np.ndarray]:
            with probe.lock:
                return dict(probe.tensors['gradient/compensated'])

        send(0, 10)  # inactive: ignored

        # Active: the file's pass-through, then the exact calibration from the topic. The
        # sets of one writer come in order: once the later ones are out, the earlier would be.
        assert change(probe, 'compensator', 'activate')
        assert state(probe, 'compensator') == 'active'
        send(10, 5)
        wait_for(lambda: len(received()) >= 5, 10, 'pass-through tensors', graph)
        assert sorted(received()) == [T0 + i * 10**8 for i in range(10, 15)]  # none of the inactive
        np.testing.assert_array_equal(received()[T0 + 10 * 10**8], g[10])
        feeder.calibration.publish(calibration_msg(_calibration(exact).to_yaml()))
        wait_for(lambda: 'compensating with topic' in process.output(), 10, 'the topic calibration', graph)
        send(15, 5)
        wait_for(lambda: len(received()) == 10, 10, 'compensated tensors', graph)
        assert max(np.abs(received()[T0 + i * 10**8]).max() for i in range(15, 20)) < 1e-6 * NT

        # Deactivated: nothing comes out; re-activated: the topic's calibration is still applied.
        assert change(probe, 'compensator', 'deactivate')
        assert state(probe, 'compensator') == 'inactive'
        send(20, 5)
        assert change(probe, 'compensator', 'activate')
        send(25, 5)
        wait_for(lambda: T0 + 29 * 10**8 in received(), 10, 'tensors after re-activation', graph)
        assert sorted(received()) == [T0 + i * 10**8 for i in (*range(10, 20), *range(25, 30))]
        assert max(np.abs(received()[T0 + i * 10**8]).max() for i in range(25, 30)) < 1e-6 * NT

        # Cleanup releases the publishers; shutdown finalizes.
        assert change(probe, 'compensator', 'deactivate')
        assert change(probe, 'compensator', 'cleanup')
        assert state(probe, 'compensator') == 'unconfigured'
        wait_for(lambda: probe.count_publishers('/tetra/gradient/compensated') == 0, 10,
                 'the publisher to go', graph)
        assert change(probe, 'compensator', 'shutdown')
        assert state(probe, 'compensator') == 'finalized'
        assert process.alive()  # a finalized node waits to be stopped; it does not crash


@pytest.mark.parametrize('name', ['tensor', 'calibrator', 'compensator', 'driver', 'target'])
def test_every_node_configures_activates_and_cleans_up_in_process(name, tmp_path):
    import rclpy
    from rclpy.parameter import Parameter

    from tetra_gradiometer.nodes.calibrator import CalibratorNode
    from tetra_gradiometer.nodes.compensator import CompensatorNode
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.target import TargetNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    classes = {'tensor': TensorNode, 'calibrator': CalibratorNode,
               'compensator': CompensatorNode, 'driver': DriverNode, 'target': TargetNode}
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain(), args=['--ros-args', '-r', '__ns:=/lifecycle_test'])
    try:
        overrides = [Parameter('autostart', value=False)]
        if name in ('calibrator', 'compensator'):
            overrides.append(Parameter('calibration_file', value=str(tmp_path / 'calibration.yaml')))
        if name == 'driver':
            overrides.append(Parameter('mode', value='sim'))
        node = classes[name](parameter_overrides=overrides, context=context)
        try:
            own = len(list(node.publishers)), len(list(node.subscriptions)), len(list(node.timers))
            assert node.state_label == 'unconfigured' and own[1:] == (0, 0)
            node.bring_up()
            assert node.state_label == 'active' and node.active
            assert len(list(node.publishers)) > own[0] and len(list(node.timers)) >= 1
            # The data's publishers are rclpy's lifecycle publishers (only /diagnostics and
            # rclpy's own are not: the statuses go on while inactive).
            from rclpy.lifecycle import LifecyclePublisher

            plain = {p.topic_name for p in node.publishers if not isinstance(p, LifecyclePublisher)}
            assert plain <= {'/diagnostics', '/parameter_events', '/rosout',
                             f'{node.get_fully_qualified_name()}/transition_event'}, plain
            assert all(not timer.is_canceled() for timer in node.timers)
            node.trigger_deactivate()
            assert node.state_label == 'inactive' and not node.active
            # Only the diagnostics timer runs on (WARN 'inactive' statuses).
            running = [timer for timer in node.timers if not timer.is_canceled()]
            assert len(running) == 1 and running[0].clock.clock_type.name == 'STEADY_TIME'
            node.trigger_cleanup()
            assert node.state_label == 'unconfigured'
            after = len(list(node.publishers)), len(list(node.subscriptions)), len(list(node.timers))
            assert after == own
            node.bring_up()  # configurable again after cleanup
            assert node.state_label == 'active'
            node.trigger_shutdown()
            assert node.state_label == 'finalized'
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_diagnostics_are_named_after_the_node_so_two_suites_do_not_collide():
    """A tensor node remapped into a vehicle namespace names its statuses after its fully
    qualified name; the software check has no hardware id, a magnetometer has its frame."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from tetra_gradiometer.nodes.tensor import TensorNode

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain(), args=['--ros-args', '-r', '__ns:=/auv2/tetra'])
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        tensor = TensorNode(parameter_overrides=[Parameter('diagnostics_period_s', value=0.1)], context=context)
        listener = rclpy.create_node('listener', context=context)
        nodes = [tensor, listener]
        seen: dict[str, str] = {}
        listener.create_subscription(DiagnosticArray, '/diagnostics',
                                     lambda msg: seen.update({s.name: s.hardware_id for s in msg.status}), 10)
        for node in nodes:
            executor.add_node(node)
        deadline = time.monotonic() + 10
        while 'auv2/tetra/tensor: matching' not in seen and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert seen.get('auv2/tetra/tensor: matching') == '', seen
        assert seen.get('auv2/tetra/tensor: mag2') == 'tetra_mag2', seen
        assert not any(name.startswith('tetra/') for name in seen), seen
    finally:
        executor.shutdown(timeout_sec=2)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_no_node_overrides_a_private_method_of_the_managed_node():
    """A node's own ``_name`` that is also one of ManagedNode's replaces it silently: the
    compensator's ``_release`` (of its held sets) once did, and cleanup then kept every
    publisher (this file's lifecycle tests caught it). Public hooks (``configure``,
    ``stop_work``, ...) are meant to be overridden; private ones never."""
    import inspect

    from tetra_gradiometer.nodes.calibrator import CalibratorNode
    from tetra_gradiometer.nodes.compensator import CompensatorNode
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.managed import ManagedNode
    from tetra_gradiometer.nodes.target import TargetNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    private = {name for name, value in vars(ManagedNode).items()
               if name.startswith('_') and not name.startswith('__') and inspect.isfunction(value)}
    assert '_release' in private  # the one that was overridden
    for node in (CalibratorNode, CompensatorNode, DriverNode, TargetNode, TensorNode):
        clashes = sorted(private & {name for klass in node.__mro__[:node.__mro__.index(ManagedNode)]
                                    for name in vars(klass)})
        assert not clashes, f'{node.__name__} overrides ManagedNode.{clashes}'
