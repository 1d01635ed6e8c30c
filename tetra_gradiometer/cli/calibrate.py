"""``python -m tetra_gradiometer calibrate BAG --params FILE --out CALIB.yaml [options]``.

Identifies the interference parameters ``k``, ``b`` (eq. 18) from the magnetometer sets of
a bag and writes them as a calibration file (:mod:`tetra_gradiometer.io.calibration`),
atomically.

The window, in seconds from the bag's first matched set (``T0:T1``, either end may be
left out; without it, the window is found in the bag:
:mod:`tetra_gradiometer.pipelines.window_search`), is where the **true gradient is taken as
zero**: a trim manoeuvre in a uniform field, away from targets (``constraint_lstsq`` and
``paper_ga`` do not use that assumption). ``--method`` is one of the registry's methods
whose result is a calibration file (``core.identification.CALIBRATION_METHODS``; ``--help``
describes them).

The work is :func:`tetra_gradiometer.pipelines.trim.calibrate_assessed` (``batch``
calls it too): the window is read streaming, and thinned to at most ``--max-sets`` sets (the
printed summary says so); the trim assessment of the sets used (predicted survey accuracy,
coverage, enough or the next manoeuvre) refuses a window that does not excite the
parameters. The assessment is printed, and ``--report DIR`` writes it with plots
(:mod:`tetra_gradiometer.reports.calibration`).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..core.effects import Term, effect
from ..core.geometry import TetraGeometry
from ..core.identification import (
    CALIBRATION_METHODS,
    DEFAULT_METHOD,
    MAX_COVERAGE_CONDITION,
    METHODS,
)
from ..core.timebase import clocks_text
from ..core.units import NT_PER_T
from ..errors import AssumptionError, IdentifiabilityError
from ..io.calibration import save_calibration
from ..io.outputs import CALIBRATION, CALIBRATION_REPORT, check_output
from ..io.params import (
    earth_field_from_params,
    geometry_from_params,
    load_params,
    vehicle_signals_from_params,
)
from ..pipelines.calibration import DEFAULT_MAX_SETS, MIN_SETS, BagCalibration
from ..pipelines.trim import WindowAssessment, calibrate_assessed
from ..pipelines.window_search import find_window
from ..reports.calibration import write_calibration_report
from ._args import (
    add_bag_arguments,
    add_effects_arguments,
    add_force_argument,
    add_progress_arguments,
    bag_from_args,
    effects_from_args,
    finite_float,
    int_range,
    seed_arg,
    timebase_from_args,
    window_arg,
)

#: ``--generations``: at least one, at most 100x the paper's 1000 (~0.2 s per 1000).
MAX_GENERATIONS = 100_000
#: ``--max-sets``: the window held in memory is 96 B a set (1e6 sets: ~100 MB), and the
#: solver's design grows with it; 20x the default.
MAX_SETS = 1_000_000
#: ``--max-coverage-condition``: a condition number is >= 1; past 1e16 (1 / machine
#: epsilon) the coverage matrix is numerically singular and the bound means nothing.
MAX_CONDITION = 1e16


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bag_arguments(parser)
    parser.add_argument(
        '--window',
        type=window_arg,
        default=None,
        metavar='T0:T1',
        help='seconds from the first set where the true gradient is zero (default: found in the '
        'bag: the best manoeuvring span that passes the checks, printed with why)',
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
        '--key-file',
        default=None,
        metavar='FILE',
        help="sign the calibration (HMAC-SHA256) with the key of the nodes' "
        'calibration_key_file, so that a compensator configured with that key loads it '
        '(mode 600, at least 32 bytes)',
    )
    add_effects_arguments(parser)
    parser.add_argument(
        '--report',
        default=None,
        metavar='DIR',
        help='also write a calibration report folder: report.json, report.md, plots of the '
        'residual over the window, attitude coverage, parameters with sigma and the '
        'predicted survey accuracy',
    )
    add_force_argument(
        parser,
        'a previous calibration file at --out (and report at --report); also write a '
        'calibration whose window fails its self-test, with the warning in the file',
    )
    parser.add_argument(
        '--seed', type=seed_arg, default=0, help='paper_ga: random seed, 0 <= n < 2^31 (default 0)'
    )
    parser.add_argument(
        '--generations',
        type=int_range(1, MAX_GENERATIONS),
        default=None,
        help=f'paper_ga: generations, 1 to {MAX_GENERATIONS} (default 1000)',
    )
    parser.add_argument(
        '--wide-bounds',
        action='store_true',
        help='paper_ga: |k| <= 1, |b| <= 1000 nT instead of the printed bounds',
    )
    parser.add_argument(
        '--max-sets',
        type=int_range(MIN_SETS, MAX_SETS),
        default=DEFAULT_MAX_SETS,
        help=f'thin the window to at most this many sets, {MIN_SETS} to {MAX_SETS} '
        f'(default {DEFAULT_MAX_SETS})',
    )
    parser.add_argument(
        '--max-coverage-condition',
        type=finite_float(1.0, MAX_CONDITION),
        default=MAX_COVERAGE_CONDITION,
        help=f'refuse windows whose attitude coverage condition number exceeds this, '
        f'1 to {MAX_CONDITION:g} (default {MAX_COVERAGE_CONDITION:g})',
    )
    add_progress_arguments(parser)


def _format_matrix(rows: np.ndarray, fmt: str) -> str:
    return '[' + '; '.join(' '.join(fmt.format(v) for v in row) for row in rows) + ']'


def _signer(key_file: str | None) -> Callable[[str], str] | None:
    """The calibrator's signature with the key in ``key_file`` (None: unsigned); the key is
    checked as the nodes check theirs
    (:func:`~tetra_gradiometer.nodes.authentication.load_key`)."""
    if key_file is None:
        return None
    # Imported here: only a signed calibration needs the nodes' authentication module.
    from ..nodes.authentication import load_key, sign

    key = load_key(Path(key_file))
    return lambda text: sign(text, key)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    args.bag = bag_from_args(args)  # the folder and the topic names given for it
    inputs = (args.bag, args.params)
    check_output(args.out, CALIBRATION, force=args.force, inputs=inputs)  # refuse before any work
    if args.report is not None:  # nor over the calibration file it sits beside
        check_output(args.report, CALIBRATION_REPORT, force=args.force, inputs=(*inputs, args.out))
    signer = _signer(args.key_file)  # a bad key refused before any work
    params = load_params(args.params)
    geometry = geometry_from_params(params, source=args.params)
    earth = earth_field_from_params(params, str(args.params))
    signals = vehicle_signals_from_params(params, str(args.params))
    result, window_assessment, why = _calibrate(args, geometry, earth, signals)
    save_calibration(args.out, result.record, force=args.force, inputs=inputs, sign=signer)
    _print_summary(args, result)
    if why:
        print(f'  {why}')
    _print_assessment(window_assessment)
    written = [str(args.out)]
    if args.report is not None:
        write_calibration_report(
            args.report,
            result,
            window_assessment,
            geometry,
            force=args.force,
            inputs=(*inputs, args.out),
        )
        written.append(str(args.report))
    print(f'wrote {" and ".join(written)} in {time.perf_counter() - started:.1f} s')
    return 0


def _calibrate(
    args: argparse.Namespace,
    geometry: TetraGeometry,
    earth: np.ndarray | None,
    signals: tuple[str, ...] = (),
) -> tuple[BagCalibration, WindowAssessment, str]:
    """The calibration on ``--window``, or on the window found in the bag without one
    (:func:`~tetra_gradiometer.pipelines.window_search.find_window`), with a line saying
    which and why ('' for a given window). A given window that fails names the best passing
    window of the bag; ``--force`` without a window and none passing calibrates the whole
    bag, with the warning."""
    options = dict(
        method=args.method,
        seed=args.seed,
        generations=args.generations,
        wide_bounds=args.wide_bounds,
        max_coverage_condition=args.max_coverage_condition,
        timebase=timebase_from_args(args),
        max_sets=args.max_sets,
        progress=args.progress,
        effects=dataclasses.replace(effects_from_args(args), signals=signals),
    )
    if args.window is None:
        try:
            found = find_window(args.bag, geometry, earth, **options)
        except AssumptionError:
            if not args.force:
                raise
        else:
            return found.result, found.window, found.why
    try:
        result, assessment = calibrate_assessed(
            args.bag, geometry, earth, window=args.window, force=args.force, **options
        )
    except (AssumptionError, IdentifiabilityError) as error:
        if args.window is None:
            raise
        try:
            found = find_window(args.bag, geometry, earth, exclude=args.window, **options)
        except AssumptionError:
            raise error from None
        raise type(error)(
            f'{error}; the best passing window in the bag: {found.chosen.option} ({found.why})'
        ) from None
    return result, assessment, ''


def _print_assessment(window: WindowAssessment) -> None:
    """The trim assessment: enough or not, coverage, the worst survey attitude, the advice."""
    assessment = window.assessment
    for note in window.notes:
        print(f'  ({note})')
    if assessment is None:
        return
    print(f'  trim assessment: {assessment.text()}')
    print(
        f'    coverage: {assessment.coverage.text}; condition number '
        f'{assessment.condition_number:.3g}'
    )
    worst, (heading, roll, pitch) = assessment.worst
    print(
        f'    worst survey attitude: heading {heading:.0f}°, roll {roll:+.0f}°, pitch '
        f'{pitch:+.0f}°: {worst * NT_PER_T:.3g} nT/m'
    )
    advice = assessment.advice
    if advice is not None:
        print(
            f'    next manoeuvre: {advice.text} ({advice.duration_s:.0f} s; worst survey sigma '
            f'after it {advice.worst_sigma * NT_PER_T:.3g} nT/m)'
        )


def _print_summary(args: argparse.Namespace, result: BagCalibration) -> None:
    calibration, counters = result.calibration, result.counters
    thinned = result.thinned_every
    every = f', every {thinned}th used' if thinned > 1 else ''
    print(
        f'calibrated {args.bag}: method {args.method}, window {result.window} '
        f'({result.sets_in_window} sets{every}; read {result.span_s:.1f} s of the bag; '
        f'{counters.text()}, '
        f'implausible sets dropped: {result.dropped.text()})'
    )
    if result.clocks is not None:
        print(f'  {clocks_text(result.clocks)}')
    if result.skipped_summary:
        print(f'  {result.skipped_summary}')
    summary = calibration.summary()
    print(
        f'  parameters {summary["n_parameters"]}, rank {summary["rank"]} '
        f'(null space {summary["null_space_dim"]}), '
        f'condition number {summary["condition_number"]:.3g}'
    )
    noise = (
        f', sensor noise estimate {summary["sensor_noise_nT"]:.3g} nT'
        if 'sensor_noise_nT' in summary
        else ''
    )
    print(
        f'  residual RMS {summary["residual_rms_nT_per_m"]:.4g} nT/m, '
        f'attitude coverage condition number {result.coverage_condition:.3g}{noise}'
    )
    _print_window_check(result)
    if 'objective_final' in summary:
        print(
            f'  GA objective {summary["objective_initial"]:.4g} -> '
            f'{summary["objective_final"]:.4g} (T/m)^2 '
            f'after {summary["generations"]} generations, seed {args.seed}'
        )
    _print_parameters(result)


def _print_window_check(result: BagCalibration) -> None:
    """The regional gradient (or why it is assumed zero) and the window's self-test."""
    for note in result.notes:
        print(f'  {note}')
    pairs = result.checked.regional_text()
    if pairs:
        print(f'  regional gradient (world ENU, nT/m; signal, not compensated): {pairs}')
    if result.check is not None:
        verdict = 'passes' if result.check.passed else 'FAILS'
        print(f'  window check {verdict}: {result.check.text()}')


def _print_parameters(result: BagCalibration) -> None:
    errors = getattr(result.calibration, 'standard_errors', None)
    parameters = result.record.parameters
    n_base = result.calibration.n_parameters - 9 * parameters.n_term_regressors
    n_k = n_base - 9
    for pair in range(3):
        b_hard = ' '.join(f'{v:+.3f}' for v in parameters.b_hard[pair] * NT_PER_T)
        line = (
            f'  K_{pair + 2}1 = {_format_matrix(parameters.k_soft[pair], "{:+.6f}")}   '
            f'B_{pair + 2}1^h = [{b_hard}] nT'
        )
        if errors is not None:
            b_err = errors[n_k + 3 * pair : n_k + 3 * pair + 3] * NT_PER_T
            line += f' (+-{b_err.max():.2g})'
        print(line)
    if errors is not None:
        print(
            f'  largest standard error: K {errors[:n_k].max():.2g}, '
            f'B^h {errors[n_k:n_base].max() * NT_PER_T:.2g} nT'
        )
    _print_terms(parameters.terms, None if errors is None else errors[n_base:])


def _print_terms(terms: tuple[Term, ...], errors: np.ndarray | None) -> None:
    """Each vehicle-effect term: the largest coefficient (file unit) with its 1-sigma, what
    it reads, and the held-out test that kept it."""
    offset = 0
    for term in terms:
        spec = effect(term.effect)
        values = term.coefficients * spec.file_factor
        sigma = (
            None if errors is None else errors[offset : offset + values.size] * spec.file_factor
        )
        offset += values.size
        big = int(np.argmax(np.abs(values)))
        largest = f'{values.flat[big]:+.4g}' + ('' if sigma is None else f' +- {sigma[big]:.2g}')
        test = term.evidence
        held_out = (
            f'; held-out {test["heldout_rms_without_nT"]:.3g} -> '
            f'{test["heldout_rms_with_nT"]:.3g} nT'
            if 'heldout_rms_with_nT' in test
            else ''
        )
        print(
            f'  term {term.effect} ({", ".join(spec.labels(term.inputs))}): largest '
            f'coefficient {largest} {spec.file_unit}{held_out}'
        )
