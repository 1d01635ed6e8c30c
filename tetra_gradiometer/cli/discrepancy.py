"""``python -m tetra_gradiometer discrepancy BAG --params FILE --out DIR [--window T0:T1]``."""

from __future__ import annotations

import argparse
import sys
import time

from ..core.discrepancy import CANDIDATES, RecordedRun, Settings, analyze
from ..errors import InputError
from ..io.outputs import REPORT, check_output
from ..io.params import earth_field_from_params, geometry_from_params, load_params
from ..io.recording import read_recording
from ..io.report import write_report
from ._args import parse_window


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='rosbag2 folder (sqlite3 or mcap) of a recorded run')
    parser.add_argument(
        '--params', required=True, help='ROS 2 parameter file (sensor_positions, earth_field_enu)'
    )
    parser.add_argument(
        '--out', required=True, help='output folder for report.json, report.md and plots'
    )
    parser.add_argument(
        '--candidates',
        default=None,
        help='comma-separated subset of the library: ' + ','.join(c.name for c in CANDIDATES),
    )
    parser.add_argument(
        '--folds', type=int, default=Settings.n_folds, help='cross-validation folds (default 5)'
    )
    parser.add_argument(
        '--max-effects',
        type=int,
        default=Settings.max_effects,
        help='stop after this many effects',
    )
    parser.add_argument(
        '--relevance',
        type=float,
        default=Settings.relevance,
        help='minimum held-out RMS an effect must explain, in noise floors (default 1)',
    )
    parser.add_argument(
        '--window',
        default=None,
        metavar='T0:T1',
        help='analyse only this part of the run, seconds from the first sample (either end may be '
        'left out; default the whole run)',
    )
    parser.add_argument(
        '--keep-targets',
        action='store_true',
        help='do not look for and exclude target passages (spans dominated by a localized field '
        'that no candidate represents)',
    )
    parser.add_argument(
        '--no-plots', action='store_true', help='write report.json and report.md only'
    )
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous report folder at --out (anything else there is refused)',
    )


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    window = parse_window(args.window)
    inputs = (args.bag, args.params)
    check_output(args.out, REPORT, force=args.force, inputs=inputs)  # refuse before the analysis
    params = load_params(args.params)
    geometry = geometry_from_params(params, str(args.params))
    earth = earth_field_from_params(params, str(args.params))
    recording = read_recording(args.bag)
    run_data = RecordedRun(
        recording.t_s,
        recording.fields,
        recording.orientation_xyzw,
        recording.temperature_c,
        recording.current_a,
        recording.missing,
    )
    candidates = (
        tuple(n.strip() for n in args.candidates.split(',') if n.strip())
        if args.candidates
        else None
    )
    if args.folds < 2:
        raise InputError(f'--folds must be at least 2, got {args.folds}')
    settings = Settings(
        n_folds=args.folds,
        max_effects=args.max_effects,
        relevance=args.relevance,
        candidates=candidates,
        exclude_targets=not args.keep_targets,
    )
    report = analyze(run_data, geometry, earth, settings=settings, window_s=window)
    out = write_report(report, args.out, plots=not args.no_plots, force=args.force, inputs=inputs)
    for note in report.notes:
        print(f'note: {note}', file=sys.stderr)
    for name, reason in report.untestable.items():
        print(f'untestable: {name}: {reason}', file=sys.stderr)
    for span in report.excluded_spans:
        print(
            f'excluded {span["start_s"]:.1f}-{span["end_s"]:.1f} s: {span["reason"]}',
            file=sys.stderr,
        )
    named = ', '.join(report.named_effects) or 'none'
    print(
        f'named effects: {named}; held-out gap {report.gap_initial_nT:.4g} -> '
        f'{report.gap_final_nT:.4g} nT, noise floor {report.noise_floor_nT:.4g} nT; '
        f'adequate: {"yes" if report.adequate else "no"}; '
        f'{time.perf_counter() - started:.1f} s; report in {out}'
    )
    return 0
