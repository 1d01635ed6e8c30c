"""Argument helpers shared by the commands: the input bag and its matching, ``--window``,
``--progress``, ``--force``."""

from __future__ import annotations

import argparse
import math

from ..errors import InputError

__all__ = ['add_bag_arguments', 'add_force_argument', 'add_progress_arguments', 'parse_window']

_WINDOW_FORMAT = '--window must be T0:T1 in seconds from the first stamp'


def parse_window(text: str | None) -> tuple[float, float] | None:
    """``'T0:T1'`` (seconds, either end optional) -> ``(t0, t1)``; None for the whole bag.

    Raises
    ------
    InputError
        Not two numbers separated by ``:``, or not ``0 <= T0 < T1``.
    """
    if text is None:
        return None
    parts = text.split(':')
    if len(parts) != 2:
        raise InputError(f'{_WINDOW_FORMAT}, got {text!r}')
    try:
        t0 = float(parts[0]) if parts[0].strip() else 0.0
        t1 = float(parts[1]) if parts[1].strip() else math.inf
    except ValueError:
        raise InputError(f'{_WINDOW_FORMAT}, got {text!r}') from None
    if not (math.isfinite(t0) and t0 >= 0 and t1 > t0):
        raise InputError(f'--window needs 0 <= T0 < T1, got {text!r}')
    return t0, t1


def add_progress_arguments(parser: argparse.ArgumentParser) -> None:
    """``--progress`` / ``--no-progress`` into ``args.progress`` (None: only on a terminal)."""
    progress = parser.add_mutually_exclusive_group()
    progress.add_argument(
        '--progress',
        dest='progress',
        action='store_true',
        default=None,
        help='always show a progress bar',
    )
    progress.add_argument(
        '--no-progress', dest='progress', action='store_false', help='never show a progress bar'
    )


def add_force_argument(parser: argparse.ArgumentParser, what: str) -> None:
    """``--force``: replace ``what`` (a previous output of ours); anything else is refused."""
    parser.add_argument(
        '--force',
        action='store_true',
        help=f'replace {what} (anything else there is refused)',
    )


def add_bag_arguments(parser: argparse.ArgumentParser) -> None:
    """The input of the offline commands: ``BAG``, ``--params``, ``--tolerance-ms``."""
    parser.add_argument('bag', help='rosbag2 folder (sqlite3 or mcap) following the data contract')
    parser.add_argument('--params', required=True, help='ROS 2 params YAML with sensor_positions')
    parser.add_argument(
        '--tolerance-ms',
        type=float,
        default=2.0,
        help='largest spread of the four header stamps in one set (default 2 ms)',
    )
