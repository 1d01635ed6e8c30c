"""``python -m tetra_gradiometer locate BAG --params FILE --calibration CALIB.yaml --out DIR
[--raw] [--comparison] [--false-alarms-per-hour F] [--no-plots] [--force]``.

Finds and locates magnetic targets along a recorded survey: the bag's tensor, compensated
with the calibration (eq. 19), is searched for anomalies at the stated false-alarm rate on
the straight legs of the ``/odom`` track, and each is fitted with a point dipole plus a
background per pass (:func:`tetra_gradiometer.core.targets.locate`). ``--raw`` searches the
uncompensated tensor instead (no calibration needed).

``DIR`` (written as one atomic folder; :mod:`tetra_gradiometer.reports.targets`)::

    targets.json       {"targets": [{"position_m", "position_sigma_m", "moment_Am2",
                        "moment_sigma_Am2", "first_seen_s", "last_seen_s",
                        "fit_rms_nT_per_m", ...}], "frame": "odom", ...}
    targets_raw.json   with --comparison: the same search on the uncompensated tensor
                       (slow on long surveys: its interference residual makes many
                       spurious detections, each one a fit — 12 min for 1 h at 10 Hz)
    map.png            track, detections, targets with 3-sigma ellipses; the statistic
    report.md          both tables

Positions in the odom frame (ENU, m), moments A m^2, 1-sigma from the fit; times in seconds
from the first sample (``t0_stamp_s`` is its absolute stamp).
"""

from __future__ import annotations

import argparse
import sys
import time

from ..core.targets import DetectorSettings, LocatorSettings
from ..errors import InputError
from ..io.calibration import check_positions, load_calibration
from ..io.outputs import TARGETS, check_output
from ..io.params import earth_field_from_params, geometry_from_params, load_params
from ..pipelines.compensation import health_recorder, load_compensation
from ..pipelines.targets import Search, locate_bag
from ..pipelines.tracking import learn_after_ns
from ..reports.targets import write_locate_report
from ._args import (
    MAX_FALSE_ALARMS_PER_HOUR,
    add_bag_arguments,
    add_force_argument,
    add_progress_arguments,
    add_tracking_arguments,
    bag_from_args,
    positive_float,
    say_forced,
    say_health,
    timebase_from_args,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bag_arguments(parser)
    parser.add_argument(
        '--calibration',
        default=None,
        help='calibration YAML (from "calibrate"); required unless --raw',
    )
    parser.add_argument(
        '--out',
        required=True,
        help='output folder: targets.json, targets_raw.json, map.png, report.md',
    )
    parser.add_argument(
        '--raw', action='store_true', help='search the uncompensated tensor only (no calibration)'
    )
    parser.add_argument(
        '--comparison',
        action='store_true',
        help='also search the uncompensated tensor (targets_raw.json, beside on the map); '
        'slow on long surveys',
    )
    parser.add_argument(
        '--false-alarms-per-hour',
        type=positive_float(MAX_FALSE_ALARMS_PER_HOUR, '/h'),
        default=DetectorSettings.false_alarms_per_hour,
        help="the detector's false-alarm rate on noise, per hour of straight legs, 0 < F <= "
        f'{MAX_FALSE_ALARMS_PER_HOUR:g} (default {DetectorSettings.false_alarms_per_hour:g})',
    )
    parser.add_argument('--no-plots', action='store_true', help='no map.png')
    parser.add_argument(
        '--allow-missing-channels',
        action='store_true',
        help='as compensate: a channel the calibration terms read that the bag lacks holds '
        'its terms at their calibration-window mean (report.md and the output say so)',
    )
    add_force_argument(parser, 'a previous targets folder at --out')
    add_tracking_arguments(parser)
    add_progress_arguments(parser)


def depth_positive_down(search: Search) -> str:
    """'' or why the odom z looks like a depth (positive down): the whole track and every
    target above the odom origin, which on an underwater vehicle is at or above the sea
    surface in REP 103's z up."""
    z_track = search.survey.positions[:, 2]
    z_targets = [target.fit.position[2] for target in search.targets]
    if not z_targets or not (z_track.min() > 0 and min(z_targets) > 0):
        return ''
    return (
        f'/odom z looks like a depth (positive down): the track lies at z = '
        f'{z_track.min():+.1f} to {z_track.max():+.1f} m and every target above z = 0 '
        f'(lowest {min(z_targets):+.1f} m), above the odom origin; REP 103 odometry has z up '
        '(negate a depth), unless the odom origin lies below the whole survey'
    )


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    args.bag = bag_from_args(args)  # the folder and the topic names given for it
    if args.raw == (args.calibration is not None):
        raise InputError(
            'give --calibration (the compensated tensor is searched) or --raw (the raw one), '
            'not both'
            if args.raw
            else 'give --calibration CALIB.yaml (from "calibrate"), or --raw to search the '
            'uncompensated tensor'
        )
    inputs = [args.bag, args.params] + ([args.calibration] if args.calibration else [])
    check_output(args.out, TARGETS, force=args.force, inputs=inputs)  # refuse before the work
    params = load_params(args.params)
    geometry = geometry_from_params(params, str(args.params))
    parameters = None
    if args.calibration is not None:  # k, b only: locate needs no noise figure
        calibration = load_calibration(args.calibration)
        check_positions(
            calibration, geometry, source=str(args.calibration), target=str(args.params)
        )
        parameters = calibration.parameters
        say_forced(args.calibration, calibration.forced_warnings())
    settings = LocatorSettings(DetectorSettings(false_alarms_per_hour=args.false_alarms_per_hour))
    health = None  # the compensated tensor checks itself (the file's noise figure needed)
    if args.calibration is not None and calibration.sensor_noise_t is not None:
        compensation = load_compensation(args.calibration, geometry, target=str(args.params))
        health = health_recorder(geometry, compensation)
    result = locate_bag(
        args.bag,
        geometry,
        parameters,
        settings=settings,
        comparison=args.comparison,
        timebase=timebase_from_args(args),
        progress=args.progress,
        on_stage=lambda text: print(f'{text} ...', file=sys.stderr, flush=True),
        allow_missing_channels=args.allow_missing_channels,
        earth_field_enu=earth_field_from_params(params, str(args.params)),
        health=health,
        tracking=(
            None if args.calibration is None else calibration.sensor_noise_t,
            args.track,
            None if args.calibration is None else learn_after_ns(calibration.diagnostics),
        ),
    )
    out = write_locate_report(
        result, args.out, plots=not args.no_plots, force=args.force, inputs=inputs
    )
    for search in (result.main, result.comparison):
        if search is None:
            continue
        print(
            f'{search.tensor}: {len(search.detected.detections)} detections, '
            f'{len(search.targets)} targets '
            f'({sum(not t.dipolar for t in search.targets)} not dipolar)'
        )
    if result.held_summary:
        print(result.held_summary)
    if health is not None:
        say_health(health.document())
    depth = depth_positive_down(result.main)
    if depth:
        print(f'warning: {depth}', file=sys.stderr)
    print(f'{time.perf_counter() - started:.1f} s; targets in {out}')
    return 0
