"""``python -m tetra_gradiometer <command> ...``: the command-line entry beside ``ros2 run``.

Each command lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; only the chosen module is imported, so offline tools never load rclpy.
Exit codes: 0 success, 1 bad input, data or output (a
:class:`~tetra_gradiometer.errors.TetraError`: one ``error:`` line on stderr), 2 usage.
Any other exception is a bug and keeps its traceback. Set ``TETRA_DEBUG=1`` for a traceback
of a ``TetraError`` too.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from .errors import TetraError

COMMANDS: dict[str, tuple[str, str]] = {
    'paper': ('tetra_gradiometer.cli.paper', 'reproduce section 6 of Yu et al. 2014'),
    'simulate': ('tetra_gradiometer.cli.simulate', 'simulate a mission into a rosbag2 file'),
    'calibrate': ('tetra_gradiometer.cli.calibrate', 'identify the interference from a bag'),
    'compensate': ('tetra_gradiometer.cli.compensate', 'compensate a bag into CSV (and a bag)'),
    'discrepancy': ('tetra_gradiometer.cli.discrepancy', 'find the physics the model is missing'),
    'locate': ('tetra_gradiometer.cli.locate', 'detect and locate magnetic targets along a bag'),
    'survey': ('tetra_gradiometer.cli.survey', 'grid, georeference and report a survey bag'),
    'batch': (
        'tetra_gradiometer.cli.batch',
        'calibrate, compensate and analyse a folder of bags on a Dask cluster',
    ),
    'node': (
        'tetra_gradiometer.cli.node',
        'run one ROS 2 node (driver|tensor|calibrator|compensator|target)',
    ),
    'bringup': ('tetra_gradiometer.cli.bringup', 'run the four nodes together'),
    'record': ('tetra_gradiometer.cli.record', "record the sim driver's topics to a bag"),
    'demo': ('tetra_gradiometer.cli.demo', 'the main job: sim, trim, calibrate, survey, result'),
}


def _usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [f'  {name:<{width}}  {help_}' for name, (_, help_) in COMMANDS.items()]
    return (
        'usage: python -m tetra_gradiometer <command> [options]\n\ncommands:\n'
        + '\n'.join(lines)
        + '\n\n"python -m tetra_gradiometer <command> --help" describes each.'
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ('-h', '--help'):
        print(_usage())
        return 0
    if argv[0] not in COMMANDS:
        print(f'error: unknown command {argv[0]!r}\n\n{_usage()}', file=sys.stderr)
        return 2
    name = argv[0]
    module = importlib.import_module(COMMANDS[name][0])
    parser = argparse.ArgumentParser(
        prog=f'python -m tetra_gradiometer {name}', description=COMMANDS[name][1]
    )
    module.add_arguments(parser)
    args = parser.parse_args(argv[1:])
    try:
        return int(module.run(args) or 0)
    except TetraError as error:
        if os.environ.get('TETRA_DEBUG'):
            raise
        print(f'error: {error}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
