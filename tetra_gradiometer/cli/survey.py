"""``python -m tetra_gradiometer survey BAG --params FILE --calibration CALIB --out DIR
(--origin LAT,LON[,ALT] | --navsat-topic TOPIC) [--crs EPSG:NNNN] [--cell-m C]
[--max-distance-m D] [--all-samples] [--sensor-noise-nt S] [--false-alarms-per-hour F]
[--vehicle NAME] [--force]``.

Survey products of a recorded survey: the compensated tensor along the ``/odom`` track in
the world frame (E, N, U), placed on the Earth (``--origin``: the odom frame is ENU at that
point; ``--navsat-topic``: fitted to the bag's surface fixes, residual reported), gridded
in the survey's UTM zone (``--crs`` for any other) with verde, the targets located, and
written as one folder (:mod:`tetra_gradiometer.reports.survey`): ``survey.nc`` (CF),
``geotiff/<var>.tif``, ``targets.json``, ``targets.geojson``, ``targets.csv``,
``track.geojson``, ``report.html`` (self-contained) and ``survey.json``.

The default cell is a quarter of the line spacing (never below the array's size); cells
farther than ``--max-distance-m`` (default 0.75 line spacing, at least 3 cells) from every
sample are masked, never extrapolated. The 1-sigma of each cell is propagated from each
sample's (the calibration's sensor noise, or ``--sensor-noise-nt``, and its covariance).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from ..core.targets import DetectorSettings
from ..errors import InputError
from ..io.bag import MagneticBag
from ..io.calibration import load_calibration
from ..io.geo import igrf_at, origin_earth_check, parse_origin
from ..io.outputs import SURVEY, check_output
from ..io.params import earth_field_from_params, geometry_from_params, load_params
from ..pipelines.compensation import load_compensation
from ..pipelines.survey import survey_bag
from ..pipelines.survey_grid import GridSettings
from ..reports.survey import residual_table, write_survey
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


def origin_arg(text: str) -> tuple[float, float, float]:
    """``--origin``'s type: :func:`~tetra_gradiometer.io.geo.parse_origin`, its error as a
    usage error."""
    try:
        return parse_origin(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bag_arguments(parser)
    parser.add_argument('--calibration', required=True, help='calibration YAML (from "calibrate")')
    parser.add_argument('--out', required=True, help='output folder (survey.nc, report.html, ...)')
    place = parser.add_mutually_exclusive_group(required=True)
    place.add_argument(
        '--origin',
        type=origin_arg,
        help='LAT,LON[,ALT]: the odom origin (odom axes E, N, U there)',
    )
    place.add_argument(
        '--navsat-topic', help='sensor_msgs/NavSatFix topic of surface fixes to fit odom to'
    )
    parser.add_argument(
        '--crs', default=None, help="the grids' projected CRS (default: the survey's UTM zone)"
    )
    parser.add_argument(
        '--cell-m',
        type=positive_float(10_000.0, 'm'),
        default=None,
        help='grid cell, m (default: line spacing / 4, at least the array size)',
    )
    parser.add_argument(
        '--max-distance-m',
        type=positive_float(100_000.0, 'm'),
        default=None,
        help='mask cells farther than this from every sample, m (default: 0.75 line spacing)',
    )
    parser.add_argument(
        '--all-samples',
        action='store_true',
        help='grid every sample, not only the straight legs (turns, trim and transits)',
    )
    parser.add_argument(
        '--sensor-noise-nt',
        type=positive_float(1000.0, 'nT'),
        default=None,
        help="per-axis sensor noise for the 1-sigma (default: the calibration's estimate)",
    )
    parser.add_argument(
        '--false-alarms-per-hour',
        type=positive_float(MAX_FALSE_ALARMS_PER_HOUR, '/h'),
        default=DetectorSettings.false_alarms_per_hour,
        help="the target detector's false-alarm rate on noise, per hour of straight legs",
    )
    parser.add_argument(
        '--vehicle', default='', help="the vehicle's name for report.html (default: not named)"
    )
    add_force_argument(parser, 'a previous survey folder at --out')
    add_tracking_arguments(parser)
    add_progress_arguments(parser)


def _start_ns(bag: str | os.PathLike[str]) -> int:
    """The bag's first log time, ns since the epoch."""
    with MagneticBag(bag) as reader:
        return int(reader.reader.start_time)


def _earth_field(args: argparse.Namespace, earth: np.ndarray | None) -> np.ndarray | None:
    """The Earth field (3,) T ENU the odometry's world frame is tested against: the params
    file's, checked against IGRF at ``--origin`` (io/geo.origin_earth_check: an origin given as
    LON,LAT is refused, another mismatch is a warning), or else IGRF at ``--origin``."""
    if args.origin is None:
        return earth
    start_ns = _start_ns(args.bag)
    if earth is None:
        return igrf_at(args.origin, start_ns)
    line, swapped = origin_earth_check(args.origin, earth, start_ns)
    if swapped:
        raise InputError(str(line))
    if line:
        print(f'warning: {line}', file=sys.stderr)
    return earth


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    args.bag = bag_from_args(args)  # the folder and the topic names given for it
    inputs = [args.bag, args.params, args.calibration]
    check_output(args.out, SURVEY, force=args.force, inputs=inputs)  # refuse before the work
    params = load_params(args.params)
    geometry = geometry_from_params(params, str(args.params))
    earth = _earth_field(args, earth_field_from_params(params, str(args.params)))
    compensation = load_compensation(
        args.calibration, geometry, target=str(args.params), sensor_noise_nt=args.sensor_noise_nt
    )
    calibration = load_calibration(args.calibration)
    say_forced(args.calibration, compensation.forced)
    result = survey_bag(
        args.bag,
        geometry,
        compensation,
        origin=args.origin,
        navsat_topic=args.navsat_topic,
        crs=args.crs,
        grid=GridSettings(args.cell_m, args.max_distance_m, all_samples=args.all_samples),
        detector=DetectorSettings(false_alarms_per_hour=args.false_alarms_per_hour),
        timebase=timebase_from_args(args),
        progress=args.progress,
        on_stage=lambda text: print(f'{text} ...', file=sys.stderr, flush=True),
        earth_field_enu=earth,
        tracked=args.track,
    )
    print('writing the products ...', file=sys.stderr, flush=True)
    metadata = {
        'calibration': args.calibration,
        'calibration_method': calibration.method,
        'effects': ','.join(term.effect for term in calibration.parameters.terms) or 'none',
        'sensor_noise': compensation.noise_source,
        'bag': str(args.bag),
        'params': str(args.params),
        'vehicle': args.vehicle,
        'command': getattr(args, 'command_line', ''),
    }
    out = write_survey(
        result,
        args.out,
        metadata=metadata,
        force=args.force,
        inputs=inputs,
        calibration=calibration,
    )
    grids = result.grids
    print(result.georeference.describe())
    if args.navsat_topic and earth is not None:  # the fixes' place against the params' field
        line, _ = origin_earth_check(result.georeference.origin, earth, _start_ns(args.bag))
        if line:
            print(f'warning: {line.replace("--origin", "the fixes at")}', file=sys.stderr)
    print(
        f'{result.crs}: {grids.mask.shape[1]} x {grids.mask.shape[0]} cells of '
        f'{grids.cell_m:.2f} m '
        f'({int(grids.mask.sum())} gridded, masked beyond {grids.max_distance_m:.1f} m); '
        f'{len(result.targets)} targets; {len(result.health["alarms"])} health alarms'
    )
    print(residual_table(result))
    say_health(result.health)
    print(f'{time.perf_counter() - started:.1f} s; survey in {out}')
    return 0
