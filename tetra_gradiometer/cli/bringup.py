"""``python -m tetra_gradiometer bringup [--params FILE] [--mode sim|replay] [--bag PATH]
[--unconfigured]``: the four nodes in one process until Ctrl-C (the data path on rclpy's
EventsExecutor, the calibrator on a MultiThreadedExecutor of its own).

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
        spin(data_path, stop=stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in nodes:
            node.stop_work()
        stop_graph([data_path, calibrator], worker, nodes)
    return 0
