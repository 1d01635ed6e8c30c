"""``python -m tetra_gradiometer <command> ...``: the command-line entry beside ``ros2 run``.

Each command lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; only the chosen module is imported, so offline tools never load rclpy.
Exit codes: 0 success, 1 bad input, data or output (a
:class:`~tetra_gradiometer.errors.TetraError`: one ``error:`` line on stderr), 2 usage.
Any other exception is a bug and keeps its traceback. Set ``TETRA_DEBUG=1`` for a traceback
of a ``TetraError`` too.

Signals and the system's limits, the same for every command: SIGTERM is handled as SIGINT
(a ``KeyboardInterrupt``: outputs in progress remove their temporaries, previous outputs stay;
exit 143, 130 for SIGINT); a reader that closes the pipe (``| head``) ends the command quietly
with the shell's SIGPIPE status 141; a disk that is full (``ENOSPC``, ``EDQUOT``) or a file
past ``ulimit -f`` (``EFBIG``: SIGXFSZ is ignored so the write fails instead of killing the
process) is one ``error:`` line, exit 1. ROS commands install their own handlers over these.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import shlex
import signal
import sys
import threading
from types import FrameType

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


#: Exit statuses of a command stopped by a signal: 128 + the signal's number, as a shell
#: reports a process the signal killed.
EXIT_SIGINT, EXIT_SIGPIPE, EXIT_SIGTERM = 130, 141, 143
#: OSError numbers that say the storage is full, not that the program is wrong.
STORAGE_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, so that it unwinds as after Ctrl-C."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


def _install_signal_handlers() -> None:
    if threading.current_thread() is not threading.main_thread():
        return  # main() called from a thread (a test): signals are the caller's
    signal.signal(signal.SIGTERM, _terminate)
    if hasattr(signal, 'SIGXFSZ'):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


def _quiet_stdout() -> None:
    """After a broken pipe: stdout to /dev/null, so the interpreter's last flush is silent."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # no real stdout (captured by a test)
        pass


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` names (default ``sys.argv[1:]``); its exit status."""
    try:
        try:
            return _main(argv)
        finally:  # --help and usage errors too: a closed pipe fails here, not at exit
            sys.stdout.flush()
    except BrokenPipeError:
        _quiet_stdout()
        return EXIT_SIGPIPE


def _main(argv: list[str] | None) -> int:
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
    # the command as typed, for the files that say how they were made
    parser.set_defaults(command_line=f'{parser.prog} {shlex.join(argv[1:])}')
    args = parser.parse_args(argv[1:])
    _install_signal_handlers()
    try:
        return int(module.run(args) or 0)
    except TetraError as error:
        if os.environ.get('TETRA_DEBUG'):
            raise
        return _error_line(str(error))
    except OSError as error:
        if error.errno not in STORAGE_FULL or os.environ.get('TETRA_DEBUG'):
            raise  # anything else is a bug, with its traceback
        where = f' ({error.filename})' if error.filename else ''
        return _error_line(f'{error.strerror or error}{where}: nothing was replaced')
    except Terminated:
        return EXIT_SIGTERM
    except KeyboardInterrupt:
        return EXIT_SIGINT


def _error_line(text: str) -> int:
    """Print ``error: TEXT`` (one line) on stderr; exit status 1."""
    try:
        print(f'error: {text}', file=sys.stderr)
    except BrokenPipeError:  # stderr closed as well: nothing more to say
        pass
    return 1


if __name__ == '__main__':
    sys.exit(main())
