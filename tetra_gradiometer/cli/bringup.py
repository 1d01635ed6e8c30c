"""``python -m tetra_gradiometer bringup [--params FILE] [--mode sim|replay] [--bag PATH]
[--loop] [--unconfigured]``: the four nodes in one process (the data path on rclpy's
EventsExecutor, the calibrator on a MultiThreadedExecutor of its own) until the driver has
played its source (a bag, a simulated mission) and the chain has drained, then a summary:
sets played, tensors, compensated and dropped. ``--loop`` plays the source again and again
until Ctrl-C (the driver's ``loop``); so does ``--unconfigured``, which leaves the nodes
to an external manager.

The nodes are lifecycle nodes (nodes/managed.py): bringup creates them unconfigured and
then configures and activates each in the order tensor, calibrator, compensator, driver (the
consumers first, so no set is published to nobody), as the launch file does; a refused
configuration ends bringup with its ``error:`` line. ``--unconfigured`` leaves them
unconfigured for an external lifecycle manager (``lifecycle_msgs`` services)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from typing import Any

from ._args import MAX_RATE, finite_float
from .node import PARAMS_HELP, ros_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--params', default='', help=PARAMS_HELP)
    parser.add_argument(
        '--mode',
        choices=('sim', 'replay'),
        help='driver source (no default: this, --bag or mode in the params file is needed)',
    )
    parser.add_argument('--bag', help='replay: rosbag2 folder')
    parser.add_argument(
        '--rate',
        type=finite_float(0.0, MAX_RATE),
        help=f'driver speed, multiple of real time, 0 to {MAX_RATE:g} (0: as fast as the graph)',
    )
    parser.add_argument('--scenario', help='sim: scenario YAML (default: built-in)')
    parser.add_argument(
        '--calibration-file', help='calibration file of calibrator and compensator'
    )
    parser.add_argument(
        '--loop',
        action='store_true',
        help='play the source again from its start each time it ends, until Ctrl-C',
    )
    parser.add_argument(
        '--unconfigured',
        action='store_true',
        help='leave the nodes unconfigured for an external lifecycle manager',
    )
    parser.add_argument(
        '--ros-args',
        dest='ros_args',
        nargs=argparse.REMAINDER,
        default=[],
        help='further ROS arguments for all four nodes',
    )


def driver_overrides(args: argparse.Namespace) -> list[Any]:
    """Driver parameters given on the command line."""
    from rclpy.parameter import Parameter

    out = [
        Parameter('min_subscribers', value=1)
    ]  # the tensor node is here: do not lose the first sets
    if args.mode:
        out.append(Parameter('mode', value=args.mode))
    if args.bag:
        out.append(Parameter('bag', value=os.path.abspath(args.bag)))
        if not args.mode:
            out.append(Parameter('mode', value='replay'))
    if args.rate is not None:
        out.append(Parameter('rate', value=float(args.rate)))
    if args.loop:
        out.append(Parameter('loop', value=True))
    if args.scenario:
        out.append(Parameter('scenario', value=os.path.abspath(args.scenario)))
    return out


def create_nodes(args: argparse.Namespace, driver_extra: Sequence[Any] = ()) -> list[Any]:
    """The four nodes (rclpy must be initialised), command-line overrides applied, in start
    order and unconfigured."""
    from rclpy.parameter import Parameter

    from ..nodes.calibrator import CalibratorNode
    from ..nodes.compensator import CompensatorNode
    from ..nodes.driver import DriverNode
    from ..nodes.tensor import TensorNode

    managed = [Parameter('autostart', value=False)]
    calibration = managed + (
        [Parameter('calibration_file', value=os.path.abspath(args.calibration_file))]
        if args.calibration_file
        else []
    )
    nodes: list[Any] = []
    try:
        nodes.append(TensorNode(parameter_overrides=list(managed)))
        nodes.append(CalibratorNode(parameter_overrides=list(calibration)))
        nodes.append(CompensatorNode(parameter_overrides=list(calibration)))
        driver = managed + driver_overrides(args) + list(driver_extra)
        nodes.append(DriverNode(parameter_overrides=driver))
    except BaseException:
        for node in nodes:
            node.destroy_node()
        raise
    return nodes


def run(args: argparse.Namespace) -> int:
    import threading

    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from ..nodes.calibrator import CalibratorNode
    from ..nodes.process import events_executor, spin, stop_graph, stop_on_signals

    # Our own Ctrl-C handling (a flag the spin loop reads), so callbacks stop before the
    # context goes.
    stop = stop_on_signals()
    rclpy.init(
        args=ros_arguments(args.params, args.ros_args),
        signal_handler_options=SignalHandlerOptions.NO,
    )
    nodes: list[Any] = []
    # The data path (driver, tensor, compensator) on the events executor in this thread, as
    # each runs alone (nodes/process.spin_node); the calibrator on its own multithreaded one
    # (a waiting ~/calibrate must not block its diagnostics and ~/cancel), in another thread.
    data_path, calibrator = events_executor(), MultiThreadedExecutor(num_threads=4)
    worker = threading.Thread(target=calibrator.spin, daemon=True)
    try:
        nodes = create_nodes(args)
        for node in nodes:
            (calibrator if isinstance(node, CalibratorNode) else data_path).add_node(node)
        worker.start()
        if not args.unconfigured:
            for node in nodes:
                node.bring_up()
            if not args.loop:
                threading.Thread(target=stop_when_played, args=(nodes, stop), daemon=True).start()
        spin(data_path, stop=stop)
        if played(nodes):
            print(summary(nodes), flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in nodes:
            node.stop_work()
        stop_graph([data_path, calibrator], worker, nodes)
    return 0


#: The chain has drained once its counts stay the same this long after the driver has played
#: its source, s; bringup stops waiting for it after DRAIN_LIMIT_S.
QUIET_S, DRAIN_LIMIT_S = 1.0, 30.0


def played(nodes: Sequence[Any]) -> bool:
    """The driver (the last of ``nodes``) has played its whole source."""
    return bool(nodes) and getattr(nodes[-1], 'state', '') == 'finished'


def _counts(nodes: Sequence[Any]) -> tuple[int, ...]:
    tensor, _, compensator, _ = nodes
    return (tensor.sets_published, tensor.sets_invalid, compensator.published,
            compensator.dropped_non_finite)


def stop_when_played(nodes: Sequence[Any], stop: Any, poll_s: float = 0.1) -> None:
    """Set ``stop`` once the driver has played its source and the tensor and compensator
    nodes' counts have stayed the same for :data:`QUIET_S` (or :data:`DRAIN_LIMIT_S` passed)."""
    import time

    last: tuple[int, ...] = ()
    since = finished = 0.0
    while not stop.wait(poll_s):
        if not played(nodes):
            continue
        now, counts = time.monotonic(), _counts(nodes)
        finished = finished or now
        if counts != last:
            last, since = counts, now
        elif now - since >= QUIET_S or now - finished >= DRAIN_LIMIT_S:
            stop.set()


def summary(nodes: Sequence[Any]) -> str:
    """What the chain made of the source: sets played, tensors, compensated, dropped."""
    tensor, _, compensator, driver = nodes
    played_sets = driver.sets_published
    share = 100.0 * compensator.compensated / played_sets if played_sets else 0.0
    passed = compensator.published - compensator.compensated
    lines = [
        f'bringup: played {played_sets} sets; tensor node: {tensor.sets_published} tensors, '
        f'{tensor.sets_invalid} invalid;',
        f'compensator: {compensator.compensated} compensated ({share:.1f} % of the sets '
        f'played), {passed} passed through uncompensated (no calibration yet), '
        f'{tensor.sets_published - compensator.published} dropped (non-finite, or a '
        'channel unknown: never compensated with zero)',
    ]
    return '\n'.join(lines)
