"""``python -m tetra_gradiometer calibrate BAG --params FILE --out CALIB.yaml [options]``.

Identifies the interference parameters ``k``, ``b`` (eq. 18) from the magnetometer sets of
a bag and writes them as a calibration file (:mod:`tetra_gradiometer.io.calibration`),
atomically.

The window, in seconds from the bag's first matched set (``T0:T1``, either end may be
left out; default the whole bag), is where the **true gradient is taken as zero**: a trim
manoeuvre in a uniform field, away from targets (``constraint_lstsq`` and ``paper_ga``
do not use that assumption). ``--method`` is one of the registry's methods whose result is
a calibration file (``core.identification.CALIBRATION_METHODS``; ``--help`` describes them).

The window is read streaming; only its sets are kept. A window of more than ``--max-sets``
sets is thinned uniformly (every k-th set) to bound the solver's memory (the design holds
9 x 36 floats per set); the printed summary says so.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from ..core import difference_tensor
from ..core.identification import (
    CALIBRATION_METHODS,
    DEFAULT_METHOD,
    MAX_COVERAGE_CONDITION,
    METHODS,
    IdentifiabilityError,
    Options,
    identify,
)
from ..core.identification.paper_ga import GENERATIONS
from ..core.units import NT_PER_T, S_PER_MS, S_PER_NS
from ..errors import InputError
from ..io.bag import BagError, MagneticBag
from ..io.calibration import CalibrationFile, save_calibration
from ..io.outputs import CALIBRATION, check_output
from ..io.params import geometry_from_params, load_params

DEFAULT_MAX_SETS = 50_000


def parse_window(text: str | None) -> tuple[float, float] | None:
    """``'T0:T1'`` (seconds, either end optional) -> ``(t0, t1)``; None for the whole bag."""
    if text is None:
        return None
    parts = text.split(':')
    if len(parts) != 2:
        raise InputError(f'--window must be T0:T1 in seconds from the first stamp, got {text!r}')
    try:
        t0 = float(parts[0]) if parts[0].strip() else 0.0
        t1 = float(parts[1]) if parts[1].strip() else float('inf')
    except ValueError:
        raise InputError(
            f'--window must be T0:T1 in seconds from the first stamp, got {text!r}'
        ) from None
    if not (np.isfinite(t0) and t0 >= 0 and t1 > t0):
        raise InputError(f'--window needs 0 <= T0 < T1, got {text!r}')
    return t0, t1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='rosbag2 folder (sqlite3 or mcap) following the data contract')
    parser.add_argument('--params', required=True, help='ROS 2 params YAML with sensor_positions')
    parser.add_argument(
        '--window',
        default=None,
        metavar='T0:T1',
        help='seconds from the first set where the true gradient is zero (default: whole bag)',
    )
    parser.add_argument(
        '--method',
        choices=CALIBRATION_METHODS,
        default=DEFAULT_METHOD,
        help='; '.join(f'{name}: {METHODS[name].description}' for name in CALIBRATION_METHODS)
        + f' (default: {DEFAULT_METHOD})',
    )
    parser.add_argument('--out', required=True, help='calibration YAML to write')
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous calibration file at --out (anything else there is refused)',
    )
    parser.add_argument('--seed', type=int, default=0, help='paper_ga: random seed (default 0)')
    parser.add_argument(
        '--generations', type=int, default=None, help='paper_ga: generations (default 1000)'
    )
    parser.add_argument(
        '--wide-bounds',
        action='store_true',
        help='paper_ga: |k| <= 1, |b| <= 1000 nT instead of the printed bounds',
    )
    parser.add_argument(
        '--tolerance-ms',
        type=float,
        default=2.0,
        help='largest spread of the four header stamps in one set (default 2 ms)',
    )
    parser.add_argument(
        '--max-sets',
        type=int,
        default=DEFAULT_MAX_SETS,
        help=f'thin the window to at most this many sets (default {DEFAULT_MAX_SETS})',
    )
    parser.add_argument(
        '--max-coverage-condition',
        type=float,
        default=MAX_COVERAGE_CONDITION,
        help=f'refuse windows whose attitude coverage condition number exceeds this '
        f'(default {MAX_COVERAGE_CONDITION:g})',
    )
    progress = parser.add_mutually_exclusive_group()
    progress.add_argument('--progress', dest='progress', action='store_true', default=None)
    progress.add_argument('--no-progress', dest='progress', action='store_false')


def read_window(
    bag_path: str, window: tuple[float, float] | None, *, tolerance_s: float, progress: bool | None
) -> tuple[np.ndarray, np.ndarray, float, object]:
    """Sets in the window: stamps (n,), fields (n, 4, 3); the bag's span (s); the counters."""
    stamps, fields = [], []
    first = last = None
    with MagneticBag(bag_path) as bag:
        sets = bag.iter_sets(tolerance_s=tolerance_s, progress=progress)
        for chunk_stamps, chunk_fields in sets:
            first = int(chunk_stamps[0]) if first is None else first
            last = int(chunk_stamps[-1])
            beyond = False
            if window is not None:
                t = (chunk_stamps - first) * S_PER_NS
                keep = (t >= window[0]) & (t <= window[1])
                chunk_stamps, chunk_fields = chunk_stamps[keep], chunk_fields[keep]
                beyond = t[-1] > window[1]
            if len(chunk_stamps):
                stamps.append(chunk_stamps)
                fields.append(chunk_fields)
            if beyond:  # sets come in stamp order: the rest of the bag lies beyond the window
                sets.close()
                break
        counters = bag.counters
    span = (last - first) * S_PER_NS
    if not stamps:
        raise BagError(
            f'{bag_path}: the window {window[0]:g}:{window[1]:g} s holds no sample set '
            f'(the bag spans 0:{span:.3f} s from its first stamp)'
        )
    return np.concatenate(stamps), np.concatenate(fields), span, counters


def _format_matrix(rows: np.ndarray, fmt: str) -> str:
    return '[' + '; '.join(' '.join(fmt.format(v) for v in row) for row in rows) + ']'


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    window = parse_window(args.window)
    if args.max_sets < 10:
        raise InputError(f'--max-sets must be at least 10, got {args.max_sets}')
    inputs = (args.bag, args.params)
    check_output(args.out, CALIBRATION, force=args.force, inputs=inputs)  # refuse before any work
    geometry = geometry_from_params(load_params(args.params), source=args.params)
    stamps, fields, span, counters = read_window(
        args.bag, window, tolerance_s=args.tolerance_ms * S_PER_MS, progress=args.progress
    )
    finite = np.isfinite(fields).all(axis=(1, 2))
    non_finite = int((~finite).sum())
    stamps, fields = stamps[finite], fields[finite]
    if not len(stamps):
        raise BagError(
            f'{args.bag}: every set in the window has a non-finite reading ({non_finite} sets)'
        )
    n_window = len(stamps)
    thinned = 1
    if n_window > args.max_sets:
        thinned = int(np.ceil(n_window / args.max_sets))
        stamps, fields = stamps[::thinned], fields[::thinned]
    g_measured = difference_tensor(fields, geometry)
    b_reference = fields[:, 0, :]
    window_text = 'whole bag' if window is None else f'{window[0]:g}:{window[1]:g} s'
    method = args.method
    if args.generations is not None and args.generations < 1:
        raise InputError(f'--generations must be >= 1, got {args.generations}')
    try:
        options = Options(
            rng=np.random.default_rng(args.seed),
            generations=args.generations or GENERATIONS,
            wide_bounds=args.wide_bounds,
            max_coverage_condition=args.max_coverage_condition,
        )
        calibration = identify(method, g_measured, b_reference, geometry, options)
    except IdentifiabilityError as error:
        raise IdentifiabilityError(
            f'the window ({window_text}, {len(stamps)} sets): {error}'
        ) from None
    coverage = calibration.details['attitude_coverage_condition']
    record = CalibrationFile.from_calibration(calibration, geometry)
    extra = {
        'bag': str(args.bag),
        'window_s': window_text,
        'sets_in_window': n_window,
        'thinned_every': thinned,
        'attitude_coverage_condition': coverage,
        'read_span_s': span,
        'non_finite_sets_skipped': non_finite,
    }
    if method == 'paper_ga':
        extra['seed'] = args.seed
    record = dataclasses.replace(record, diagnostics={**record.diagnostics, **extra})
    save_calibration(args.out, record, force=args.force, inputs=inputs)

    summary = calibration.summary()
    print(
        f'calibrated {args.bag}: method {method}, window {window_text} '
        f'({n_window} sets{f", every {thinned}th used" if thinned > 1 else ""}; read {span:.1f} s of the bag; '
        f'{counters.dropped_messages} messages unmatched, {counters.out_of_order} out of order, '
        f'{non_finite} sets with a non-finite reading skipped)'
    )
    print(
        f'  parameters {summary["n_parameters"]}, rank {summary["rank"]} '
        f'(null space {summary["null_space_dim"]}), condition number {summary["condition_number"]:.3g}'
    )
    print(
        f'  residual RMS {summary["residual_rms_nT_per_m"]:.4g} nT/m, attitude coverage condition number '
        f'{coverage:.3g}'
        + (
            f', sensor noise estimate {summary["sensor_noise_nT"]:.3g} nT'
            if 'sensor_noise_nT' in summary
            else ''
        )
    )
    if 'objective_final' in summary:
        print(
            f'  GA objective {summary["objective_initial"]:.4g} -> {summary["objective_final"]:.4g} (T/m)^2 '
            f'after {summary["generations"]} generations, seed {args.seed}'
        )
    errors = getattr(calibration, 'standard_errors', None)
    n_k = calibration.n_parameters - 9
    parameters = calibration.parameters
    for pair in range(3):
        line = (
            f'  K_{pair + 2}1 = {_format_matrix(parameters.k_soft[pair], "{:+.6f}")}   '
            f'B_{pair + 2}1^h = [{" ".join(f"{v:+.3f}" for v in parameters.b_hard[pair] * NT_PER_T)}] nT'
        )
        if errors is not None:
            b_err = errors[n_k + 3 * pair : n_k + 3 * pair + 3] * NT_PER_T
            line += f' (+-{b_err.max():.2g})'
        print(line)
    if errors is not None:
        print(
            f'  largest standard error: K {errors[:n_k].max():.2g}, B^h {errors[n_k:].max() * NT_PER_T:.2g} nT'
        )
    print(f'wrote {args.out} in {time.perf_counter() - started:.1f} s')
    return 0
