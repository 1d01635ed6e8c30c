"""``python -m tetra_gradiometer discrepancy BAG --params FILE --out DIR [--window T0:T1]``.

The work is :func:`tetra_gradiometer.pipelines.discrepancy.analyze_bag` (``batch`` calls it
too); the report folder is :func:`tetra_gradiometer.reports.discrepancy.write_report`.
"""

from __future__ import annotations

import argparse
import sys
import time

from ..core.discrepancy import CANDIDATES, LIBRARY, Settings
from ..io.outputs import REPORT, check_output
from ..io.params import earth_field_from_params, geometry_from_params, load_params
from ..pipelines.discrepancy import analyze_bag
from ..reports.discrepancy import channel_warnings, percent_text, write_report
from ._args import (
    add_bag_arguments,
    bag_from_args,
    finite_float,
    int_range,
    timebase_from_args,
    window_arg,
)

#: ``--folds``: at least 2 (one to fit, one to test); the run is cut into ~40 blocks, so more
#: than 20 folds leave each fewer than 2 blocks.
MAX_FOLDS = 20
#: ``--relevance``, in noise floors: 0 (the F-test alone decides) to 100.
MAX_RELEVANCE = 100.0


def candidate_names(text: str) -> tuple[str, ...]:
    """``type=`` of ``--candidates``: comma-separated names of the library, at least one."""
    names = tuple(n.strip() for n in text.split(',') if n.strip())
    unknown = [n for n in names if n not in LIBRARY]
    if not names or unknown:
        raise argparse.ArgumentTypeError(
            f'unknown candidate(s) {unknown}; the library has {", ".join(LIBRARY)}'
            if unknown
            else f'give at least one of {", ".join(LIBRARY)}, got {text!r}'
        )
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bag_arguments(parser)  # BAG, --params (sensor_positions, earth_field_enu), --sync ...
    parser.add_argument(
        '--out', required=True, help='output folder for report.json, report.md and plots'
    )
    parser.add_argument(
        '--candidates',
        type=candidate_names,
        default=None,
        help='comma-separated subset of the library: ' + ','.join(c.name for c in CANDIDATES),
    )
    parser.add_argument(
        '--folds',
        type=int_range(2, MAX_FOLDS),
        default=Settings.n_folds,
        help=f'cross-validation folds, 2 to {MAX_FOLDS} (default {Settings.n_folds})',
    )
    parser.add_argument(
        '--max-effects',
        type=int_range(1, len(CANDIDATES)),
        default=Settings.max_effects,
        help=f"stop after this many effects, 1 to {len(CANDIDATES)} (the library's size; "
        f'default {Settings.max_effects})',
    )
    parser.add_argument(
        '--relevance',
        type=finite_float(0.0, MAX_RELEVANCE),
        default=Settings.relevance,
        help='minimum held-out RMS an effect must explain, in noise floors, 0 to '
        f'{MAX_RELEVANCE:g} (default {Settings.relevance:g})',
    )
    parser.add_argument(
        '--window',
        type=window_arg,
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


def settings_from_args(args: argparse.Namespace) -> Settings:
    """The search's :class:`Settings` from the options (none given: ``Settings()``)."""
    return Settings(
        n_folds=args.folds,
        max_effects=args.max_effects,
        relevance=args.relevance,
        candidates=args.candidates,
        exclude_targets=not args.keep_targets,
    )


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    args.bag = bag_from_args(args)  # the folder and the topic names given for it
    window = args.window  # (t0, t1) or None, checked by argparse (_args.window_arg)
    inputs = (args.bag, args.params)
    check_output(args.out, REPORT, force=args.force, inputs=inputs)  # refuse before the analysis
    params = load_params(args.params)
    geometry = geometry_from_params(params, str(args.params))
    earth = earth_field_from_params(params, str(args.params))
    report, recording = analyze_bag(
        args.bag,
        geometry,
        earth,
        settings=settings_from_args(args),
        window=window,
        timebase=timebase_from_args(args),
    )
    out = write_report(report, args.out, plots=not args.no_plots, force=args.force, inputs=inputs)
    for reason in recording.missing.values():  # why each optional input was not read
        if not reason.endswith('is not in the bag'):
            print(f'input: {reason}', file=sys.stderr)
    for note in report.notes:
        print(f'note: {note}', file=sys.stderr)
    for name, reason in report.untestable.items():
        print(f'untestable: {name}: {reason}', file=sys.stderr)
    for span in report.excluded_spans:
        print(
            f'excluded {span["start_s"]:.1f}-{span["end_s"]:.1f} s: {span["reason"]}',
            file=sys.stderr,
        )
    if recording.dropped.total or recording.skipped_messages:
        print(
            f'input: implausible sets dropped: {recording.dropped.text()}; '
            f'{recording.skipped_messages} undecodable messages skipped'
        )
    for warning in channel_warnings(report):
        print(f'not tested: {warning}')
    signals = report.data.get('signals_read', [])
    if signals:
        print(
            f'recorded signals tested: {len(signals)} ({", ".join(signals[:6])}'
            + (', ...)' if len(signals) > 6 else ')')
        )
    for note in report.data.get('signals_left_out', []):
        print(f'signal left out: {note}', file=sys.stderr)
    if report.data.get('vehicle_signals'):
        declared = ', '.join(f"'{d}'" for d in report.data['vehicle_signals'])
        print(f'declare them in the params file: vehicle_signals: [{declared}]')
    named = ', '.join(report.named_effects) or 'none'
    if report.unresolved_effects:
        named += f' (unresolved, not named: {", ".join(report.unresolved_effects)})'
    excluded = ''
    if report.excluded_fraction > 0:
        excluded = f'excluded {percent_text(report.excluded_fraction)} % of the samples; '
    print(
        f'named effects: {named}; held-out gap {report.gap_initial_nT:.4g} -> '
        f'{report.gap_final_nT:.4g} nT, noise floor {report.noise_floor_nT:.4g} nT; '
        f'adequate: {"yes" if report.adequate else "no"}; {excluded}'
        f'{time.perf_counter() - started:.1f} s; report in {out}'
    )
    return 0
