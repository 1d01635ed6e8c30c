"""Helpers of the ROS integration tests (imported by name from test/ros/test_*.py; on the
path through pytest.ini's pythonpath).

Nodes run as child processes (``python -m tetra_gradiometer node ...``) on a ROS domain
unique to the test, discovery limited to localhost; the test process observes and drives
them through its own rclpy context (a Probe and a Feeder node spun in a thread).
"""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[2]
PARAMS = REPO / 'config' / 'tetra_gradiometer.yaml'
_counter = itertools.count()


def domain_range() -> range:
    """The ROS_DOMAIN_IDs this test process may use: 1..100 (101 and up are left to manual
    runs, e.g. scripts/realros), split into disjoint ranges, one per pytest-xdist worker
    (``PYTEST_XDIST_WORKER`` ``gwK`` of ``PYTEST_XDIST_WORKER_COUNT``), so two workers of one
    run never share a domain; a serial run has them all."""
    count = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
    worker = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    size = max(1, 100 // max(count, 1))
    first = 1 + (index % max(count, 1)) * size
    return range(first, min(first + size, 101))


def unique_domain() -> int:
    """A ROS_DOMAIN_ID for one test: the next in this worker's ``domain_range()``, starting at
    an offset from the pid (runs by other people on this machine start elsewhere; ros_graph
    also skips a domain where it sees foreign nodes)."""
    domains = domain_range()
    return domains[(os.getpid() * 7 + next(_counter)) % len(domains)]


def child_env(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(PYTHONPATH=str(REPO), ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1')
    return env


def ros_value(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        return '[' + ','.join(f"'{v}'" for v in value) + ']'
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(repr(float(v)) for v in value) + ']'
    return str(value)


class NodeProcess:
    """One ``python -m tetra_gradiometer node NAME`` child; stderr kept in a file."""

    def __init__(self, name: str, domain: int, params: dict[str, Any] | None = None,
                 params_file: Path = PARAMS, remaps: dict[str, str] | None = None) -> None:
        self.name = name
        self.log = tempfile.NamedTemporaryFile('w+', prefix=f'tg_{name}_', suffix='.log', delete=False)
        command = [sys.executable, '-m', 'tetra_gradiometer', 'node', name, '--params', str(params_file)]
        if params or remaps:
            command.append('--ros-args')
            for key, value in (params or {}).items():
                command += ['-p', f'{key}:={ros_value(value)}']
            for source, target in (remaps or {}).items():
                command += ['-r', f'{source}:={target}']
        self.process = subprocess.Popen(command, cwd=REPO, env=child_env(domain), stdout=self.log,
                                        stderr=subprocess.STDOUT, start_new_session=True)

    def output(self) -> str:
        return Path(self.log.name).read_text()

    def refusal(self, timeout_s: float = 30.0) -> tuple[int, str]:
        """Exit status and output of a node expected to refuse its start (stopped anyway)."""
        try:
            code = self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            code = None
        finally:
            output = self.output()
            self.stop()
        return code, output

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self) -> None:
        """SIGINT (clean shutdown), then SIGKILL if it lingers."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)
        self.log.close()


class Graph:
    """Child node processes plus in-process observer nodes on one domain."""

    def __init__(self, domain: int) -> None:
        self.domain = domain
        self.processes: dict[str, NodeProcess] = {}

    def start(self, name: str, remaps: dict[str, str] | None = None, **params: Any) -> NodeProcess:
        process = NodeProcess(name, self.domain, params, remaps=remaps)
        self.processes[name] = process
        return process

    def stop(self, name: str) -> None:
        self.processes.pop(name).stop()

    def logs(self) -> str:
        return '\n'.join(f'--- {n} ---\n{p.output()[-3000:]}' for n, p in self.processes.items())


@contextmanager
def ros_graph() -> Iterator[tuple[Graph, Any, 'Feeder']]:
    """``(graph, probe, feeder)``; every child process is stopped in ``finally``."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from tetra_gradiometer.cli._probe import Probe

    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    domain, context = _free_domain()
    graph = Graph(domain)
    executor = SingleThreadedExecutor(context=context)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    nodes: list = []
    try:
        # Every tensor of a test's replay (a few thousand) waits for the probe's thread.
        probe = Probe('test_probe', depth=20_000, context=context)
        feeder = Feeder(context=context)
        nodes = [probe, feeder]
        for node in nodes:
            executor.add_node(node)
        spinner.start()
        yield graph, probe, feeder
    finally:
        for name in list(graph.processes):
            graph.stop(name)
        executor.shutdown(timeout_sec=2)
        if spinner.is_alive():
            spinner.join(timeout=5)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def _free_domain(attempts: int = 10, listen_s: float = 0.7) -> tuple[int, Any]:
    """A domain where no other node is seen (other people's tests share this machine), with
    an initialised rclpy context on it."""
    import rclpy
    from rclpy.node import Node
    for _ in range(attempts):
        domain = unique_domain()
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain)
        scout = Node('domain_scout', context=context)
        time.sleep(listen_s)
        others = [n for n in scout.get_node_names() if n != 'domain_scout']
        scout.destroy_node()
        if not others:
            return domain, context
        rclpy.try_shutdown(context=context)
    raise RuntimeError(f'no free ROS domain found in {attempts} attempts')


def _feeder_class() -> type:
    from rclpy.node import Node
    from sensor_msgs.msg import MagneticField
    from tetra_gradiometer_msgs.msg import Calibration

    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.nodes.common import derived_qos, latched_qos

    class _Feeder(Node):
        """Publishes magnetometer sets, raw tensors (GradientTensor) and calibrations."""

        def __init__(self, **kwargs: Any) -> None:
            super().__init__('test_feeder', namespace='/tetra', **kwargs)
            self.types = cv.rclpy_types()
            self.mags = [self.create_publisher(MagneticField, t, 100) for t in cv.MAG_TOPICS]
            self.raw = self.create_publisher(gt.rclpy_class(), 'gradient/raw', derived_qos())
            self._calibration: Any = None

        @property
        def calibration(self) -> Any:
            """The publisher on ``calibration``, created when a test first uses it: a compensator
            refuses calibrations while a node other than its calibration_publisher publishes
            there."""
            if self._calibration is None:
                self._calibration = self.create_publisher(Calibration, 'calibration', latched_qos())
            return self._calibration

        def publish_set(self, stamp_ns: int, fields: np.ndarray, skip: tuple[int, ...] = ()) -> None:
            """Fields (4, 3) T at ``stamp_ns``; sensors in ``skip`` stay silent."""
            for s in range(4):
                if s not in skip:
                    self.mags[s].publish(cv.magnetic_field_msg(self.types, fields[s], stamp_ns, cv.MAG_FRAMES[s]))

        def publish_raw(self, stamp_ns: int, g: np.ndarray, b_reference: np.ndarray,
                        g_sigma: np.ndarray | None = None) -> None:
            """One raw set: ``G_m`` (3, 3) T/m, ``B_1'`` (3,) T, the tensor's 1-sigma (3, 3) T/m
            (None: unknown, NaN)."""
            sigma = gt.UNKNOWN_SIGMA if g_sigma is None else g_sigma
            tensor = gt.TensorSet(stamp_ns, g, sigma, b_reference)
            self.raw.publish(gt.gradient_tensor_msg(self.types, tensor))

    return _Feeder


def Feeder(**kwargs: Any) -> Any:  # noqa: N802 - a factory standing in for the class
    return _feeder_class()(**kwargs)


def calibration_msg(text: str) -> Any:
    """The tetra_gradiometer_msgs/Calibration of a calibration file's ``text``, as the
    calibrator publishes it (io/calibration_message.py)."""
    from tetra_gradiometer_msgs.msg import Calibration

    from tetra_gradiometer.io.calibration_message import calibration_fields

    return Calibration(**calibration_fields(text))


def wait_for(condition, timeout_s: float, what: str, graph: Graph | None = None) -> None:
    """Poll ``condition`` until true; on timeout fail with the children's logs."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout_s:g} s waiting for {what}'
                                 + (f'\n{graph.logs()}' if graph else ''))
        time.sleep(0.02)


def wait_matched(publisher: Any, count: int, timeout_s: float = 20.0) -> None:
    wait_for(lambda: publisher.get_subscription_count() >= count, timeout_s,
             f'{count} subscriber(s) on {publisher.topic_name}')


def wait_connected(probe: Any, graph: Graph, node: str, topic: str, publishers: int,
                   timeout_s: float = 30.0) -> None:
    """Until what ``node`` (a child process) publishes on ``topic`` reaches ``probe``: both
    sides of the discovery, instead of a fixed sleep after the publisher shows in the graph.

    The probe's side: its subscription on ``topic`` has matched ``publishers`` writers (the
    feeder's, in this process, count too). The node's side: a ``get_parameters`` round trip
    with a client made now. Its endpoints reach the node after those of every subscription the
    probe already has (one reliable, ordered discovery stream per participant; the probe and
    the feeder share one), and the reply needs the node's writer matched to the client's
    reader, so by then the node has matched the probe's subscription on ``topic`` too. The
    request is asked again each second: a server drops a reply whose reader it has not matched
    within 0.1 s (rmw_fastrtps), which a loaded machine makes happen."""
    from rcl_interfaces.srv import GetParameters

    subscriptions = [s for s in probe.subscriptions if s.topic_name == topic]
    assert subscriptions, f'the probe has no subscription on {topic}'
    wait_for(lambda: all(s.get_publisher_count() >= publishers for s in subscriptions), timeout_s,
             f'{publishers} publisher(s) matched on {topic}', graph)
    from tetra_gradiometer.cli._probe import ask

    client = probe.create_client(GetParameters, f'{node}/get_parameters')
    try:
        assert client.wait_for_service(timeout_sec=timeout_s), f'{node}/get_parameters'
        ask(client, GetParameters.Request(names=['use_sim_time']), timeout_s, 1.0)
    except TimeoutError as error:
        raise AssertionError(f'{error}\n{graph.logs()}') from None
    finally:
        probe.destroy_client(client)


def wait_tensor_delivers(probe: Any, graph: Graph, raw: int, readers: tuple[str, ...] = (),
                         timeout_s: float = 30.0) -> None:
    """Until the tensor node's output has matched its readers: at least ``raw`` on
    gradient/raw, and every reader the probe sees in the graph; and each node of ``readers``
    sees the tensor's writer. The graph
    showing a subscription does not mean the tensor's writer has matched it (its side of the
    discovery comes later on a loaded machine: the calibrator then missed the first 179-643
    of 1200 replayed sets), and a volatile reader misses what is published before; the
    tensor's /diagnostics report its writers' matched counts (rmw), a reader node's
    ``inputs`` status the publishers it knows."""
    def matched() -> bool:
        status = probe.status('tetra/tensor: matching')
        have_raw = int(status.get('gradient/raw subscribers', -1))
        if have_raw < max(raw, probe.count_subscribers('/tetra/gradient/raw')):
            return False
        return all(int(probe.status(f'tetra/{node}: inputs').get('/tetra/gradient/raw publishers', 0)) >= 1
                   for node in readers)

    wait_for(matched, timeout_s, f'the tensor node to match {raw} gradient/raw readers', graph)


def uniform_gradient_fields(positions: np.ndarray, b0: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Fields (4, 3) T of a linear field ``B(r) = b0 + G r`` at the sensor positions (4, 3) m:
    exact for eq. 7, an independent truth for the tensor node."""
    return b0[None, :] + positions @ g.T


def interference_set(n: int, rng: np.random.Generator, directions: str, geometry: Any = None) -> tuple[
        np.ndarray, np.ndarray, Any]:
    """Raw tensors (N, 3, 3) and ``B_1'`` (N, 3) of a clean-reference vehicle in a uniform field
    (``directions``: 'one' field direction or 'rich'), with its exact compensation parameters.

    Eq. 10 is written out here (``B_i' = B + K_i B + B_i^h``, sensor 1 clean), so the exact
    parameters are ``K_i1 = K_i``, ``b_i1 = B_i^h`` without the model's own code."""
    from tetra_gradiometer import core

    geometry = geometry or core.TetraGeometry.regular(0.5)
    k = rng.uniform(-3e-3, 3e-3, (4, 3, 3))
    k = 0.5 * (k + np.swapaxes(k, 1, 2))  # soft iron is symmetric (the 27-parameter model holds)
    k[0] = 0.0
    h = rng.uniform(-100e-9, 100e-9, (4, 3))
    h[0] = 0.0
    if directions == 'one':
        b = np.tile([0.0, 2e-5, -4.5e-5], (n, 1))
    else:
        b = rng.normal(size=(n, 3))
        b *= 5e-5 / np.linalg.norm(b, axis=1, keepdims=True)
    fields = b[:, None, :] + np.einsum('sij,nj->nsi', k, b) + h[None]
    exact = core.InterferenceParameters(k[1:], h[1:])
    return core.difference_tensor(fields, geometry), fields[:, 0], exact


def set_parameter(probe: Any, graph: Graph, node: str, name: str, value: str | float | bool) -> Any:
    """Call ``<node>/set_parameters`` for one string, bool or double parameter; return its
    ``SetParametersResult`` (the caller asserts success or refusal)."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    client = probe.create_client(SetParameters, f'{node}/set_parameters')
    assert client.wait_for_service(timeout_sec=30)
    if isinstance(value, bool):
        parameter_value = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    elif isinstance(value, str):
        parameter_value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
    else:
        parameter_value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(value))
    from tetra_gradiometer.cli._probe import RESEND_S, ask

    request = SetParameters.Request(parameters=[Parameter(name=name, value=parameter_value)])
    # Asked again on the same client, as Probe.call does (setting a value twice is harmless).
    try:
        return ask(client, request, 20.0, RESEND_S).results[0]
    except TimeoutError as error:
        raise AssertionError(f'{error}\n{graph.logs()}') from None


def change_state(probe: Any, node: str, transition: str, timeout_s: float = 30.0) -> bool:
    """Ask ``<node>/change_state`` (lifecycle_msgs) for ``transition`` by label; its success."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    client = probe.create_client(ChangeState, f'{node}/change_state')
    try:
        assert client.wait_for_service(timeout_sec=timeout_s), f'{node}/change_state'
        future = client.call_async(ChangeState.Request(transition=Transition(label=transition)))
        wait_for(future.done, timeout_s, f'{node}/change_state {transition}')
        return bool(future.result().success)
    finally:
        probe.destroy_client(client)


def reconfigure(probe: Any, graph: Graph, node: str, **params: Any) -> None:
    """Set parameters that a configured node refuses (``LOCKED``): deactivate, cleanup, set
    them, configure, activate, through the lifecycle services."""
    assert change_state(probe, node, 'deactivate') and change_state(probe, node, 'cleanup')
    for name, value in params.items():
        result = set_parameter(probe, graph, node, name, value)
        assert result.successful, result.reason
    assert change_state(probe, node, 'configure') and change_state(probe, node, 'activate')
