"""``python -m tetra_gradiometer simulate --scenario FILE --out BAG [--storage sqlite3|mcap]``.

Flies a scenario file (format: :mod:`tetra_gradiometer.io.scenario`) and writes three
things, each atomically (temporary name, then rename):

* ``BAG/`` -- a rosbag2 folder per the data contract: ``/tetra/mag1..4`` (MagneticField,
  tesla, body frame, header stamp = sample time), ``/odom``, ``/tetra/temperature``,
  ``/battery_state``;
* ``BAG.params.yaml`` -- beside the folder (not inside: a rosbag2 folder belongs to its
  storage): ``/**: ros__parameters:`` with ``sensor_positions`` (12 floats, m) and
  ``earth_field_enu`` (3 floats, T);
* ``BAG.truth.npz`` -- beside the folder: ``stamps_ns`` (N,) int64 (the header stamps),
  ``t_s`` (N,) s from the first sample, ``g_true`` (N, 3, 3) T/m (eq. 7 on the clean,
  noise-free fields: the compensation target), ``g_analytic`` (N, 3, 3) T/m (the exact
  gradient at the array centroid), ``segment`` (N,) index into the scenario's segments,
  ``segment_kind`` (S,) 'trim' / 'line', ``b_background`` (N, 3) T (true field at sensor 1,
  body frame), ``k_soft`` (4, 3, 3) and ``b_hard`` (4, 3) T (the per-sensor interference),
  ``k_effective`` (3, 3, 3) and ``b_effective`` (3, 3) T (the exact parameters of eq. 18 for
  ``B^b = B_1'``), ``noise_t``, ``sample_rate_hz``, ``seed``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import time
from pathlib import Path

import numpy as np

from ..core import TrimManoeuvre, simulate
from ..core.units import NS_PER_S, NT_PER_T
from ..errors import InputError
from ..io.bag import STORAGES
from ..io.outputs import BAG, PARAMS, TRUTH, atomic_output, atomic_write_text, check_output
from ..io.params import params_document
from ..io.recording import mission_stamps_ns, write_mission_bag
from ..io.scenario import load_scenario

DEFAULT_START = '2026-01-01T00:00:00Z'


def sidecar_paths(bag: str | os.PathLike) -> tuple[Path, Path]:
    """``(BAG.params.yaml, BAG.truth.npz)`` beside the bag folder ``BAG``."""
    bag = Path(bag)
    return bag.with_name(bag.name + '.params.yaml'), bag.with_name(bag.name + '.truth.npz')


def parse_start(text: str) -> int:
    """An ISO 8601 UTC time -> integer nanoseconds since the epoch."""
    try:
        when = _dt.datetime.fromisoformat(text.replace('Z', '+00:00'))
    except ValueError:
        raise InputError(f'--start-utc: not an ISO 8601 time: {text!r}') from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.UTC)
    seconds = when.timestamp()
    if seconds < 0:
        raise InputError(f'--start-utc must not be before 1970: {text!r}')
    return int(round(seconds)) * NS_PER_S


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--scenario', required=True, help='scenario YAML (see config/scenarios/)')
    parser.add_argument(
        '--out',
        required=True,
        help='rosbag2 folder to write (with BAG.params.yaml and BAG.truth.npz beside it)',
    )
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace the previous output of simulate at --out (anything else there is refused)',
    )
    parser.add_argument(
        '--storage', choices=sorted(STORAGES), default='sqlite3', help='default: sqlite3'
    )
    parser.add_argument('--seed', type=int, default=None, help="override the scenario's seed")
    parser.add_argument(
        '--start-utc',
        default=DEFAULT_START,
        help=f'header stamp of the first sample (default {DEFAULT_START})',
    )
    parser.add_argument(
        '--mag-only',
        action='store_true',
        help='write only /tetra/mag1..4 (no /odom, temperature, battery)',
    )
    progress = parser.add_mutually_exclusive_group()
    progress.add_argument(
        '--progress',
        dest='progress',
        action='store_true',
        default=None,
        help='always show a progress bar',
    )
    progress.add_argument('--no-progress', dest='progress', action='store_false')


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    scenario, seed = load_scenario(args.scenario)
    if args.seed is not None:
        seed = args.seed
    start_ns = parse_start(args.start_utc)
    out = Path(args.out)
    params_path, truth_path = sidecar_paths(out)
    inputs = (args.scenario,)
    # Refuse before any work: nothing is simulated or written when an output is not ours.
    for path, kind in ((out, BAG), (params_path, PARAMS), (truth_path, TRUTH)):
        check_output(path, kind, force=args.force, inputs=inputs)
    mission = simulate(scenario, np.random.default_rng(seed))
    stamps = mission_stamps_ns(mission, start_ns)
    optional = not args.mag_only
    write_mission_bag(
        out,
        mission,
        start_ns=start_ns,
        storage=args.storage,
        odom=optional,
        temperature=optional,
        battery=optional,
        progress=args.progress,
        force=args.force,
        inputs=inputs,
        command='simulate',
    )
    params = {
        'sensor_positions': scenario.geometry.to_flat(),
        'earth_field_enu': [float(v) for v in scenario.earth_field_enu],
    }
    atomic_write_text(
        params_path,
        '# Written by "python -m tetra_gradiometer simulate" from '
        f'{Path(args.scenario).name}\n' + params_document(params),
        PARAMS,
        force=args.force,
        inputs=inputs,
    )
    effective = scenario.interference.effective_parameters()
    with atomic_output(truth_path, TRUTH, force=args.force, inputs=inputs) as tmp:
        with open(tmp, 'wb') as handle:
            np.savez_compressed(
                handle,
                stamps_ns=stamps,
                t_s=mission.t,
                g_true=mission.g_true,
                g_analytic=mission.g_analytic,
                segment=mission.segment.astype(np.int32),
                segment_kind=np.array(
                    ['trim' if isinstance(s, TrimManoeuvre) else 'line' for s in scenario.segments]
                ),
                b_background=mission.b_background,
                k_soft=scenario.interference.k_soft,
                b_hard=scenario.interference.b_hard,
                k_effective=effective.k_soft,
                b_effective=effective.b_hard,
                noise_t=scenario.noise_t,
                sample_rate_hz=scenario.sample_rate_hz,
                seed=seed,
            )
    b_norm = np.linalg.norm(scenario.earth_field_enu) * NT_PER_T
    print(
        f'simulated {len(mission)} sample sets, {scenario.duration_s:.1f} s at {scenario.sample_rate_hz:g} Hz, '
        f'{len(scenario.segments)} segment(s), {len(scenario.dipoles)} dipole(s), '
        f'|B_earth| = {b_norm:.0f} nT, noise {scenario.noise_t * NT_PER_T:g} nT, seed {seed}, '
        f'effects: {", ".join(scenario.effects.active()) or "none"}'
    )
    print(f'bag:    {out} ({args.storage})')
    print(f'params: {params_path}')
    print(f'truth:  {truth_path}')
    print(f'done in {time.perf_counter() - started:.1f} s')
    return 0
