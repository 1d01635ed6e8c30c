"""Argument helpers shared by the commands: the input bag and its matching, ``--window``,
``--progress``, ``--force``, and the ``type=`` factories that check every numeric option at
parse time.

A value out of its range is a usage error: argparse prints the usage and one line
``... error: argument --NAME: must be ... in RANGE, got 'VALUE'`` and exits 2 (no
traceback, nothing read or written).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

from ..core.timebase import SYNC_METHODS, TimeBase
from ..core.units import S_PER_MS
from ..errors import InputError
from ..io.topics import BagSource, topic_list

if TYPE_CHECKING:
    from ..pipelines.effects_choice import EffectsChoice

__all__ = [
    'MAX_FALSE_ALARMS_PER_HOUR',
    'MAX_RATE',
    'MAX_SEED',
    'MAX_TOLERANCE_MS',
    'add_bag_arguments',
    'add_force_argument',
    'add_progress_arguments',
    'bag_from_args',
    'say_health',
    'timebase_from_args',
    'finite_float',
    'int_range',
    'parse_window',
    'positive_float',
    'seed_arg',
    'window_arg',
]

#: Largest seed any command takes: the driver node's ``seed`` parameter range (int32), so a
#: seed means the same on the command line, in a scenario file and on the node.
MAX_SEED = 2**31 - 1

#: ``--rate`` (bringup, record, demo): the driver node's ``rate`` parameter range, x real time.
MAX_RATE = 1_000.0

#: ``--false-alarms-per-hour`` range (``compensate --report``, ``locate``): above 0, at most one a
#: minute (a detector that cries wolf is off).
MAX_FALSE_ALARMS_PER_HOUR = 60.0
#: ``--tolerance-ms`` range: above 0; at most 1 s (a set spread over more is not a set).
MAX_TOLERANCE_MS = 1000.0
#: ``--reference-rate-hz`` range: 0 (sensor 1's stamps) to 10 kHz.
MAX_REFERENCE_RATE_HZ = 10_000.0
#: ``--max-gap-periods`` range: 1 (no gap at all) to 1000.
MAX_GAP_PERIODS = 1000.0

_WINDOW_FORMAT = '--window must be T0:T1 in seconds from the first stamp'


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e15 else f'{value:g}'


def finite_float(
    lo: float,
    hi: float,
    unit: str = '',
    *,
    lo_open: bool = False,
    hi_open: bool = False,
) -> Callable[[str], float]:
    """A ``type=`` for a finite float in ``[lo, hi]`` (``lo_open``/``hi_open``: that end
    excluded); anything else (text, NaN, inf, out of range) is an
    :class:`argparse.ArgumentTypeError` naming the range and the unit."""
    unit_text = f' {unit}' if unit else ''
    allowed = (
        f'{_number(lo)} {"<" if lo_open else "<="} x {"<" if hi_open else "<="} '
        f'{_number(hi)}{unit_text}'
    )

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        above = value > lo if lo_open else value >= lo
        below = value < hi if hi_open else value <= hi
        if not (math.isfinite(value) and above and below):
            raise argparse.ArgumentTypeError(
                f'must be a finite number with {allowed}, got {text!r}'
            )
        return value

    parse.__name__ = 'number'
    return parse


def positive_float(hi: float, unit: str = '') -> Callable[[str], float]:
    """A ``type=`` for a finite float with ``0 < x <= hi``."""
    return finite_float(0.0, hi, unit, lo_open=True)


def int_range(lo: int, hi: int, unit: str = '') -> Callable[[str], int]:
    """A ``type=`` for an integer (decimal digits, optional sign) in ``[lo, hi]``."""
    unit_text = f' {unit}' if unit else ''

    def parse(text: str) -> int:
        try:
            value: int | None = int(text.strip(), 10)
        except ValueError:  # not an integer, or too many digits to convert
            value = None
        if value is None or not lo <= value <= hi:
            raise argparse.ArgumentTypeError(
                f'must be an integer with {lo} <= n <= {hi}{unit_text}, got {text!r}'
            )
        return value

    parse.__name__ = 'integer'
    return parse


#: ``--seed``: a non-negative int32 (numpy's generators refuse negative seeds).
seed_arg = int_range(0, MAX_SEED)


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


def window_arg(text: str) -> tuple[float, float]:
    """``type=`` of ``--window``: :func:`parse_window` as a usage error."""
    try:
        parsed = parse_window(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix('--window ')) from None
    assert parsed is not None
    return parsed


def add_tracking_arguments(parser: argparse.ArgumentParser, outputs: str = '') -> None:
    """``--track-calibration`` / ``--freeze-calibration`` (``args.track``: None when neither
    is given, then pipelines.tracking.TRACK_BY_DEFAULT decides)."""
    from ..pipelines.tracking import TRACK_BY_DEFAULT

    track = parser.add_mutually_exclusive_group()
    track.add_argument(
        '--track-calibration',
        dest='track',
        action='store_true',
        default=None,
        help="follow the calibration's change along the survey (core/tracking.py: drift and "
        "steps of the offsets, from the tensor's symmetry and trace and, with /odom, the "
        "body's turns; never learning from a detected anomaly's pass where /odom places it)"
        + outputs
        + (' (the default)' if TRACK_BY_DEFAULT else ''),
    )
    track.add_argument(
        '--freeze-calibration',
        dest='track',
        action='store_false',
        help='compensate with the calibration as fitted on the trim'
        + ('' if TRACK_BY_DEFAULT else ' (the default)'),
    )


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
    """The input of the offline commands: ``BAG``, ``--params`` and how sets are formed
    (``--sync``, ``--reference-rate-hz``, ``--max-gap-periods``, ``--tolerance-ms``)."""
    parser.add_argument('bag', help='rosbag2 folder (sqlite3 or mcap) following the data contract')
    parser.add_argument('--params', required=True, help='ROS 2 params YAML with sensor_positions')
    parser.add_argument(
        '--sync',
        choices=SYNC_METHODS,
        default='interpolate',
        help="how the four sensors' readings become sets: 'interpolate' (default) resamples "
        'each sensor to the reference instants (sensors on their own clocks, stamps = sample '
        "times); 'nearest' pairs stamps within --tolerance-ms (sensors sampled together whose "
        'stamps are arrival times)',
    )
    parser.add_argument(
        '--reference-rate-hz',
        type=finite_float(0.0, MAX_REFERENCE_RATE_HZ, 'Hz'),
        default=0.0,
        help="reference instants: 0 (default) sensor 1's stamps; > 0 a regular grid at this "
        'rate (interpolate only)',
    )
    parser.add_argument(
        '--max-gap-periods',
        type=finite_float(1.0, MAX_GAP_PERIODS),
        default=3.0,
        help="never interpolate across a gap longer than this many of the sensor's sample "
        'periods: such sets are skipped and counted (default 3)',
    )
    parser.add_argument(
        '--tolerance-ms',
        type=positive_float(MAX_TOLERANCE_MS, 'ms'),
        default=2.0,
        help='--sync nearest: largest spread of the four header stamps in one set, 0 < ms <= '
        f'{MAX_TOLERANCE_MS:g} (default 2 ms)',
    )
    names = parser.add_argument_group(
        'topics',
        'default: the contract names (README, "Topics"), or the one namespace the bag records '
        'them under; every name given must be a topic of the bag',
    )
    names.add_argument(
        '--namespace',
        type=_namespace,
        metavar='/NS',
        help='the vehicle namespace the topics are recorded under: /auv1 reads /auv1/tetra/mag1 '
        'as /tetra/mag1, /auv1/odom as /odom, ...',
    )
    names.add_argument(
        '--mag-topics',
        type=topics_type(4, '--mag-topics'),
        default=(),
        metavar='/M1,/M2,/M3,/M4',
        help='the four magnetometer topics, in the order of sensor_positions',
    )
    names.add_argument(
        '--odom-topic',
        type=_one_topic('--odom-topic'),
        metavar='/TOPIC',
        help='the nav_msgs/Odometry topic (ENU/FLU, REP 103)',
    )


def bag_from_args(args: argparse.Namespace) -> BagSource:
    """The input bag of :func:`add_bag_arguments` with the topic names given for it."""
    return BagSource(
        str(args.bag), args.namespace or '', tuple(args.mag_topics), args.odom_topic or ''
    )


def timebase_from_args(args: argparse.Namespace) -> TimeBase:
    """The :class:`~tetra_gradiometer.core.timebase.TimeBase` of :func:`add_bag_arguments`."""
    return TimeBase(
        sync=args.sync,
        reference_rate_hz=args.reference_rate_hz,
        max_gap_periods=args.max_gap_periods,
        tolerance_s=args.tolerance_ms * S_PER_MS,
    )


def topics_type(count: int | None, what: str) -> Callable[[str], tuple[str, ...]]:
    """A ``type=`` of absolute ROS topic names, comma-separated (``count`` of them)."""

    def parse(text: str) -> tuple[str, ...]:
        try:
            topics = topic_list(text, count, what)
        except InputError as error:  # argparse names the option
            raise argparse.ArgumentTypeError(str(error).removeprefix(f'{what}: ')) from None
        if not topics:
            raise argparse.ArgumentTypeError(f'{what}: no topic in {text!r}')
        return topics

    return parse


def _namespace(text: str) -> str:
    """``--namespace``: ``auv1``, ``/auv1`` and ``/auv1/`` are one namespace."""
    return _one_topic('--namespace')('/' + text.strip().strip('/'))


def _one_topic(what: str) -> Callable[[str], str]:
    many = topics_type(1, what)
    return lambda text: many(text)[0]


def add_current_topics_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        '--current-topics',
        type=topics_type(None, '--current-topics'),
        default=(),
        metavar='T1,T2',
        help='sensor_msgs/BatteryState topics whose current the vehicle_current effect reads, '
        'besides /battery_state and every BatteryState topic the bag records (e.g. a topic '
        'recorded under another message type name)',
    )


def add_effects_arguments(parser: argparse.ArgumentParser) -> None:
    """``--effects``, ``--effects-from`` and ``--current-topics`` (pipelines/terms)."""
    from ..core.effects import EFFECTS

    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        '--effects',
        default='auto',
        metavar='auto|none|NAME,...',
        help='vehicle effects fitted with k, b: auto (default: those whose channels the bag '
        "has and that pass the window's held-out test), none (the paper's k, b only), or "
        f'names of {", ".join(EFFECTS)} (fitted whatever the test says)',
    )
    group.add_argument(
        '--effects-from',
        default=None,
        metavar='REPORT',
        help='fit the effects a discrepancy report.json named (those of the registry)',
    )
    add_current_topics_argument(parser)


def effects_from_args(args: argparse.Namespace) -> EffectsChoice:
    """The :class:`~tetra_gradiometer.pipelines.effects_choice.EffectsChoice` of the arguments."""
    from ..pipelines.effects_choice import EffectsChoice

    if args.effects_from is not None:
        return EffectsChoice.from_report(args.effects_from, args.current_topics)
    return EffectsChoice.parse(args.effects, args.current_topics)


def say_health(document: dict, where: str = '') -> None:
    """The health monitor's verdict (``document``: ``pipelines.health``'s report), always:
    a warning on stderr when it alarms."""
    if document['alarms']:
        print(f'warning: health: {document["verdict"]}{where}', file=sys.stderr)
    else:
        print(f'health: {document["verdict"]}{where}')


def say_forced(calibration: str, warnings: tuple[str, ...]) -> None:
    """Every use of a calibration kept over a failed check (``--force``) says so, on stderr."""
    for warning in warnings:
        print(f'warning: {calibration} was kept over a failed check: {warning}', file=sys.stderr)
