"""security/policy.xml (SROS2) against the graph the nodes build: each node's
enclave grants exactly the topics it publishes and subscribes and the services it serves
(the five nodes brought up in process, use_sim_time on, the compensator with a calibration
whose terms read the vehicle's channels, the driver at rate 0: every endpoint a node can
have), none of them calls a service, only the driver may publish mag1..4, only the
calibrator the calibration, and only the operator enclave may call the services that change
the suite's state. Enforcement itself cannot run here: the PyPI Fast DDS has no security
plugins (docs/ros.md, Security)."""
from __future__ import annotations

import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from ros_helpers import REPO, unique_domain

from tetra_gradiometer import core
from tetra_gradiometer.core.effects import Term
from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration

NAMESPACE = '/tetra'
NODES = ('tensor', 'calibrator', 'compensator', 'target', 'driver')
KINDS = {('topics', 'publish'): 'publish', ('topics', 'subscribe'): 'subscribe',
         ('services', 'reply'): 'reply', ('services', 'request'): 'request'}


def _absolute(name: str, namespace: str, node: str) -> str:
    """A policy name resolved as SROS2 resolves it: ``~/x`` the node's, ``x`` in its namespace."""
    if name.startswith('~/'):
        return f'{namespace.rstrip("/")}/{node}/{name[2:]}'
    return name if name.startswith('/') else f'{namespace.rstrip("/")}/{name}'


def _policy() -> dict[str, dict[str, dict[str, set[str]]]]:
    """enclave path -> node -> kind -> resolved names granted (ALLOW)."""
    root = ET.parse(REPO / 'security' / 'policy.xml').getroot()
    assert root.tag == 'policy' and root.get('version') == '0.2.0'
    grants: dict[str, dict[str, dict[str, set[str]]]] = {}
    for enclave in root.iter('enclave'):
        nodes = grants.setdefault(enclave.get('path'), {})
        for profile in enclave.iter('profile'):
            kinds = nodes.setdefault(profile.get('node'), {kind: set() for kind in KINDS.values()})
            for group in profile:
                for (tag, rule), kind in KINDS.items():
                    if group.tag == tag and group.get(rule) == 'ALLOW':
                        kinds[kind] |= {_absolute(item.text, profile.get('ns'), profile.get('node'))
                                        for item in group}
                assert all(value == 'ALLOW' for value in group.attrib.values()), group.attrib  # no DENY
    return grants


@pytest.fixture(scope='module')
def graph(tmp_path_factory) -> dict[str, dict[str, set[str]]]:
    """node -> kind -> the resolved names its endpoints have in the ROS graph."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from tetra_gradiometer.nodes.calibrator import CalibratorNode
    from tetra_gradiometer.nodes.compensator import CompensatorNode
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.target import TargetNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    tmp = tmp_path_factory.mktemp('policy')
    terms = (Term('thermal_drift', ('temperature',), np.zeros((3, 3, 1)), reference=(10.0,), channel_noise=(0.01,)),
             Term('vehicle_current', ('current:/battery_state',), np.zeros((3, 3, 1)), channel_noise=(0.01,)))
    save_calibration(tmp / 'terms.yaml', CalibrationFile(
        parameters=core.InterferenceParameters(np.zeros((3, 3, 3)), np.zeros((3, 3)), terms), method='test',
        symmetric_k=False, sensor_positions=core.TetraGeometry.regular(0.5).to_flat()))
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain(), args=['--ros-args', '-r', f'__ns:={NAMESPACE}'])
    sim = [Parameter('use_sim_time', value=True)]
    nodes = [
        TensorNode(parameter_overrides=sim, context=context),
        CalibratorNode(parameter_overrides=[*sim, Parameter('calibration_file', value=str(tmp / 'new.yaml'))],
                       context=context),
        CompensatorNode(parameter_overrides=[*sim, Parameter('calibration_file', value=str(tmp / 'terms.yaml')),
                                             Parameter('track_calibration', value=True)],
                        context=context),
        TargetNode(parameter_overrides=sim, context=context),
        DriverNode(parameter_overrides=[*sim, Parameter('mode', value='sim'), Parameter('rate', value=0.0),
                                        Parameter('max_duration_s', value=1.0), Parameter('start_paused', value=True)],
                   context=context),
    ]
    executor = SingleThreadedExecutor(context=context)
    try:
        for node in nodes:
            executor.add_node(node)
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        look = nodes[0]
        queries = {'publish': look.get_publisher_names_and_types_by_node,
                   'subscribe': look.get_subscriber_names_and_types_by_node,
                   'reply': look.get_service_names_and_types_by_node,
                   'request': look.get_client_names_and_types_by_node}
        return {name: {kind: {topic for topic, _ in query(name, NAMESPACE)} for kind, query in queries.items()}
                for name in NODES}
    finally:
        executor.shutdown(timeout_sec=2)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize('name', NODES)
def test_each_node_enclave_grants_exactly_what_the_node_uses(graph, name):
    grants = _policy()[f'/tetra_gradiometer/{name}']
    assert list(grants) == [name]  # one node per enclave
    assert graph[name]['publish'] and graph[name]['reply']  # the graph was there
    for kind in KINDS.values():
        assert grants[name][kind] == graph[name][kind], (name, kind)


def test_one_publisher_per_input_and_only_the_operator_changes_state(graph):
    policy = _policy()
    publishers: dict[str, set[str]] = {}
    callers: dict[str, set[str]] = {}
    for path, nodes in policy.items():
        for kinds in nodes.values():
            for topic in kinds['publish']:
                publishers.setdefault(topic, set()).add(path)
            for service in kinds['request']:
                callers.setdefault(service, set()).add(path)
    for sensor in range(1, 5):
        assert publishers[f'/tetra/mag{sensor}'] == {'/tetra_gradiometer/driver'}
    assert publishers['/tetra/calibration'] == {'/tetra_gradiometer/calibrator'}
    # /diagnostics statuses are trusted only from the suite's own enclaves.
    assert publishers['/diagnostics'] == {f'/tetra_gradiometer/{name}' for name in NODES}
    # Every service a node serves that changes it: only the operator may call it.
    changing = {service for name in NODES for service in graph[name]['reply']
                if service.rsplit('/', 1)[1] in ('start', 'stop', 'calibrate', 'cancel', 'reset_metrics',
                                                  'resume', 'pause', 'change_state', 'set_parameters',
                                                  'set_parameters_atomically')}
    assert len(changing) == 7 + 3 * len(NODES)
    for service in changing:
        assert callers.get(service) == {'/tetra_gradiometer/operator'}, service
    assert set(callers) <= {service for name in NODES for service in graph[name]['reply']}
