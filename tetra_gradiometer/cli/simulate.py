"""``python -m tetra_gradiometer simulate --scenario FILE --out BAG [--storage sqlite3|mcap]``.

Flies a scenario file (format: :mod:`tetra_gradiometer.io.scenario`) and writes the bag
``BAG/``, ``BAG.params.yaml`` and ``BAG.truth.npz`` beside it, each atomically; the work and
the files' contents are :func:`tetra_gradiometer.pipelines.simulation.simulate_to_bag`.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import time

import numpy as np

from ..core.units import NS_PER_S, NT_PER_T
from ..errors import InputError
from ..io.bag import STORAGES
from ..pipelines.simulation import SimulatedBag, simulate_to_bag
from ._args import add_force_argument, add_progress_arguments, seed_arg

DEFAULT_START = '2026-01-01T00:00:00Z'


#: ``--start-utc`` range: from the epoch (stamps are unsigned seconds in ROS 2) to 2200, well
#: inside int64 nanoseconds (which end in 2262) for any mission length.
START_RANGE = ('1970-01-01T00:00:00Z', '2200-01-01T00:00:00Z')


def parse_start(text: str) -> int:
    """An ISO 8601 time (UTC unless it names its offset) -> integer nanoseconds since the
    epoch, within :data:`START_RANGE`.

    Raises
    ------
    InputError
        Not an ISO 8601 time, or outside :data:`START_RANGE`.
    """
    try:
        when = _dt.datetime.fromisoformat(text.replace('Z', '+00:00'))
    except ValueError:
        raise InputError(f'--start-utc: not an ISO 8601 time: {text!r}') from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.UTC)
    seconds = when.timestamp()
    lo, hi = (
        _dt.datetime.fromisoformat(t.replace('Z', '+00:00')).timestamp() for t in START_RANGE
    )
    if not lo <= seconds <= hi:
        raise InputError(
            f'--start-utc must be from {START_RANGE[0]} to {START_RANGE[1]}, got {text!r}'
        )
    return int(round(seconds)) * NS_PER_S


def start_utc(text: str) -> int:
    """``type=`` of ``--start-utc``: :func:`parse_start` as a usage error."""
    try:
        return parse_start(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(
            str(error).removeprefix('--start-utc').lstrip(': ')
        ) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--scenario', required=True, help='scenario YAML (see config/scenarios/)')
    parser.add_argument(
        '--out',
        required=True,
        help='rosbag2 folder to write (with BAG.params.yaml and BAG.truth.npz beside it)',
    )
    add_force_argument(parser, 'the previous output of simulate at --out')
    parser.add_argument(
        '--storage', choices=sorted(STORAGES), default='sqlite3', help='default: sqlite3'
    )
    parser.add_argument(
        '--seed', type=seed_arg, default=None, help="override the scenario's seed, 0 <= n < 2^31"
    )
    parser.add_argument(
        '--start-utc',
        type=start_utc,
        default=DEFAULT_START,
        help=f'header stamp of the first sample, ISO 8601, {START_RANGE[0][:4]} to '
        f'{START_RANGE[1][:4]} (default {DEFAULT_START})',
    )
    parser.add_argument(
        '--mag-only',
        action='store_true',
        help='write only /tetra/mag1..4 (no /odom, temperature, battery)',
    )
    add_progress_arguments(parser)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    start_ns = args.start_utc  # ns since the epoch, parsed by argparse (start_utc)
    result = simulate_to_bag(
        args.scenario,
        args.out,
        seed=args.seed,
        start_ns=start_ns,
        storage=args.storage,
        mag_only=args.mag_only,
        progress=args.progress,
        force=args.force,
    )
    _print_summary(result)
    print(f'bag:    {result.bag} ({args.storage})')
    print(f'params: {result.params}')
    print(f'truth:  {result.truth}')
    print(f'done in {time.perf_counter() - started:.1f} s')
    return 0


def _print_summary(result: SimulatedBag) -> None:
    scenario = result.scenario
    b_norm = np.linalg.norm(scenario.earth_field_enu) * NT_PER_T
    print(
        f'simulated {len(result.mission)} sample sets, {scenario.duration_s:.1f} s at '
        f'{scenario.sample_rate_hz:g} Hz, '
        f'{len(scenario.segments)} segment(s), {len(scenario.dipoles)} dipole(s), '
        f'|B_earth| = {b_norm:.0f} nT, noise {scenario.noise_t * NT_PER_T:g} nT, '
        f'seed {result.seed}, effects: {", ".join(scenario.effects.active()) or "none"}'
    )
