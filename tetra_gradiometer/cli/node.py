"""``python -m tetra_gradiometer node <driver|tensor|calibrator|compensator|target>
[--params FILE] [--ros-args ...]``: one node in this process, as ``ros2 run
tetra_gradiometer <name>`` would.

Parameters come from the nodes' declared defaults, ``--params FILE``
and any further ``--ros-args`` (e.g. ``-p rate:=10.0``, ``-r __ns:=/other``). A missing
params file is one ``error:`` line (exit 1); a refused parameter, an undeclared one or
unparsable ROS arguments are one ``cannot start:`` log line, exit 1 (nodes/process.spin_node).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ParamsError

NODES = ('driver', 'tensor', 'calibrator', 'compensator', 'target')
PARAMS_HELP = (
    'ROS 2 parameter file (/**: ros__parameters:); default: none, every parameter at its '
    "declared default (config/tetra_gradiometer.yaml lists them, installed to the package's "
    'share directory)'
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('name', choices=NODES, help='which node')
    parser.add_argument('--params', default='', help=PARAMS_HELP)
    parser.add_argument(
        '--ros-args',
        dest='ros_args',
        nargs=argparse.REMAINDER,
        default=[],
        help='further ROS arguments, e.g. --ros-args -p rate:=10.0',
    )


def ros_arguments(params: str, extra: list[str]) -> list[str]:
    """rclpy argv: program name, then ``--ros-args --params-file FILE ...``."""
    args = ['tetra_gradiometer', '--ros-args']
    if params:
        args += ['--params-file', params]
    return args + list(extra)


def run(args: argparse.Namespace) -> int:
    if args.params and not Path(args.params).is_file():
        raise ParamsError(f'--params {args.params}: no such file')
    from ..nodes.process import run_node  # signals handled before the node's imports

    return run_node(args.name, ros_arguments(args.params, args.ros_args))
