"""``python -m tetra_gradiometer compensate BAG --params FILE --calibration CALIB.yaml
--csv OUT.csv [--raw] [--sensor-noise-nt S] [--out-bag DIR] [--report DIR]``.

Streams the bag's matched magnetometer sets, forms the tensor (eq. 7) and compensates it
(eq. 19) with the calibration's ``k``, ``b``; ``--raw`` skips the compensation. The work is
:func:`tetra_gradiometer.pipelines.compensation.compensate_bag`.

CSV (written to a temporary file, renamed into place at the end)::

    stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz,sigma_gxx,sigma_gxy,...,sigma_gzz

one row per matched set (sets with a non-finite or implausible reading are skipped and
counted); ``stamp_s`` is the **absolute** header stamp of sensor 1 in
seconds since the Unix epoch, printed exactly from the integer nanoseconds (9 decimals);
``gij = G_ij = dB_i/dx_j`` in **nT/m** (6 decimals), body frame; ``sigma_gij`` is its
standard uncertainty (1-sigma, nT/m, 6 decimals): the sensor noise propagated through the
geometry and the compensation, plus the calibration parameters' covariance when the file
has one (core/uncertainty.py). The noise is ``--sensor-noise-nt`` when given, else the
calibration's own estimate (``sensor_noise_T``); a calibration without one (older files,
``constraint_lstsq``, ``paper_ga``) needs the option. ``--raw`` writes the sigma columns
(sensor noise only) with ``--sensor-noise-nt``, and leaves them out without it.

``--out-bag DIR`` writes the tensors into a new rosbag2 folder (``--out-storage``, default
the input's storage) as ``/tetra/gradient/compensated`` (``/tetra/gradient/raw`` with
``--raw``): ``tetra_gradiometer_msgs/GradientTensor`` as the nodes publish it (the tensor
and its 1-sigma in T/m, ``B_1'``, the state and calibration; header stamp = the set's stamp).

``--allow-missing-channels``: a channel the calibration's terms read (a current, the
temperature) that the bag lacks altogether is otherwise refused by name (never taken as
zero); with the option the bag is compensated without it: each regressor column of the
absent channel is held at its mean over the calibration window (the constant part ``b`` was
fitted with stays), and the sigma columns are widened, in quadrature, by what those columns
contributed over that window: ``sqrt(diag(L C L^T))`` per component, ``C`` their covariance
on the window (stored in the calibration file's ``terms[].window``), ``L`` their map onto the
component (the term's coefficients times ``a^-1``). This assumes the absent channel varies in
the survey as it did on the calibration window. The CSV then starts with one ``#`` comment
line saying so, and so does the summary. A channel that is recorded but stale in places
still drops those sets (counted), with or without the option.

``--report DIR`` runs the health monitor (core/health.py) over the compensated sets and
writes ``DIR/report.json`` (``alarms``: ``t_s`` seconds since the bag's first message,
``kind``, ``sensors`` 1-based, ``statistic``, ``threshold``; reports/health.py) and
``DIR/health.png``; ``--false-alarms-per-hour`` sets its threshold.

The calibration's change along the survey is followed (``--track-calibration``, the
default; pipelines/tracking.py, core/tracking.py): the tensors and their sigma are the
tracked ones, the CSV gains nine ``db_<s>1<axis>`` columns (the pair offsets' change
removed, nT), the health monitor watches the tracked tensor and hands it the steps it
finds, and ``--report DIR`` holds ``tracking.json`` (every update, gate and step).
``--freeze-calibration`` compensates with the calibration as fitted: re-run with it to
compare.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ..core.geometry import TetraGeometry
from ..core.health import HealthConfig
from ..core.timebase import clocks_text
from ..core.units import NT_PER_T
from ..errors import InputError
from ..io.bag import STORAGES
from ..io.outputs import HEALTH_REPORT, check_output
from ..io.params import earth_field_from_params, geometry_from_params, load_params
from ..pipelines.compensation import (
    Compensation,
    check_outputs,
    compensate_bag,
    health_recorder,
    load_compensation,
)
from ..pipelines.health import HealthRecorder
from ..pipelines.tracking import TrackedStream, tracked_stream
from ..reports.health import write_health_report
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

#: ``--sensor-noise-nt`` range: the calibration file's bound on ``sensor_noise_T`` (1e-6 T).
MAX_SENSOR_NOISE_NT = 1000.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bag_arguments(parser)
    parser.add_argument(
        '--calibration',
        default=None,
        help='calibration YAML (from "calibrate"); required unless --raw',
    )
    parser.add_argument(
        '--csv',
        default=None,
        help='CSV to write (stamp_s, 9 components and their 9 sigma, nT/m)',
    )
    parser.add_argument(
        '--raw', action='store_true', help='write the uncompensated tensor (eq. 7)'
    )
    parser.add_argument(
        '--sensor-noise-nt',
        type=positive_float(MAX_SENSOR_NOISE_NT, 'nT'),
        default=None,
        help='white noise per sensor axis (nT RMS) for the sigma columns; default: the '
        "calibration's estimate (required when it has none; --raw: no sigma without it)",
    )
    parser.add_argument(
        '--out-bag', default=None, help='also write the tensor topic into this new bag'
    )
    add_force_argument(parser, 'a previous CSV at --csv and a previous bag of ours at --out-bag')
    parser.add_argument(
        '--out-storage',
        choices=sorted(STORAGES),
        default=None,
        help="storage of --out-bag (default: the input's)",
    )
    parser.add_argument(
        '--generic-reader',
        action='store_true',
        help='decode with rosbags and match message by message (slower; same result)',
    )
    parser.add_argument(
        '--report',
        default=None,
        metavar='DIR',
        help='health report folder (report.json, health.png); the monitor runs without it too '
        'and its verdict is printed',
    )
    parser.add_argument(
        '--false-alarms-per-hour',
        type=positive_float(MAX_FALSE_ALARMS_PER_HOUR, 'per hour'),
        default=HealthConfig.false_alarms_per_hour,
        help='health monitor: design false-alarm rate (default %(default)g per hour)',
    )
    parser.add_argument(
        '--allow-missing-channels',
        action='store_true',
        help='compensate even when a channel the calibration terms read (a current, the '
        'temperature) is absent from the bag: its terms held at their calibration-window mean, '
        'the sigma widened by their spread there, the CSV and summary saying so',
    )
    add_tracking_arguments(
        parser, '; the CSV gains the db_* columns, --report DIR a tracking.json'
    )
    add_progress_arguments(parser)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    args.bag = bag_from_args(args)  # the folder and the topic names given for it
    if args.csv is None and args.out_bag is None and args.report is None:
        raise InputError('nothing to write: give --csv OUT.csv, --out-bag DIR and/or --report DIR')
    if args.raw and args.report is not None:
        raise InputError('--report monitors a calibration: it needs --calibration, not --raw')
    if not args.raw and args.calibration is None:
        raise InputError('--calibration is required (or --raw for the uncompensated tensor)')
    inputs = tuple(p for p in (args.bag, args.params, args.calibration) if p is not None)
    # Refuse before any work: nothing is read or written when an output is not ours to replace.
    check_outputs(args.csv, args.out_bag, force=args.force, inputs=inputs)
    if args.report is not None:
        check_output(args.report, HEALTH_REPORT, force=args.force, inputs=inputs)
    params = load_params(args.params)
    geometry = geometry_from_params(params, source=args.params)
    earth = earth_field_from_params(params, str(args.params))
    compensation = load_compensation(
        None if args.raw else args.calibration,
        geometry,
        target=str(args.params),
        sensor_noise_nt=args.sensor_noise_nt,
    )
    health = _health_recorder(args, geometry, compensation)
    say_forced(args.calibration, compensation.forced)
    tracking = _tracking(args, geometry, compensation, health)
    counts = compensate_bag(
        args.bag,
        geometry,
        compensation,
        health=health,
        tracking=tracking,
        csv=args.csv,
        out_bag=args.out_bag,
        out_storage=args.out_storage,
        timebase=timebase_from_args(args),
        fast=not args.generic_reader,
        progress=args.progress,
        force=args.force,
        inputs=inputs,
        allow_missing_channels=args.allow_missing_channels,
        earth_field_t=None if earth is None else float(np.linalg.norm(earth)),
    )
    elapsed = time.perf_counter() - started
    kind = 'raw' if args.raw else 'compensated'
    counters = counts.counters
    print(
        f'{kind} {counts.n_sets} sets from {Path(args.bag)} ({counts.span_s:.1f} s of data; '
        f'{counters.text()}, '
        f'implausible sets dropped: {counts.dropped.text()}) '
        f'in {elapsed:.1f} s ({counts.n_sets / max(elapsed, 1e-9):.0f} sets/s)'
    )
    if counts.clocks is not None:
        print(f'  {clocks_text(counts.clocks)}')
    if counts.skipped_summary:
        print(counts.skipped_summary)
    if counts.channel_summary:
        print(f'  {counts.channel_summary}')
    if counts.held_summary:
        print(f'  {counts.held_summary}')
    for warning in (counts.extrapolated, counts.conventions):
        if warning:
            print(f'warning: {warning}', file=sys.stderr)
    if args.csv is not None:
        print(f'csv: {args.csv} (stamp_s absolute, nT/m; {_sigma_text(compensation)})')
    if args.out_bag is not None:
        print(f'bag: {args.out_bag} ({counts.topic}, T/m)')
    if tracking is not None:
        print(f'  {tracking.text()}')
    if health is not None:
        _health_verdict(health, args, inputs, tracking)
    return 0


def _tracking(
    args: argparse.Namespace,
    geometry: TetraGeometry,
    compensation: Compensation,
    health: HealthRecorder | None,
) -> TrackedStream | None:
    """The calibration tracker, unless frozen (never on the raw tensor)."""
    if args.raw:
        return None
    tracking, note = tracked_stream(
        args.bag,
        geometry,
        compensation.parameters,
        compensation.sensor_noise_t,
        health,
        asked=args.track,
        fitted=compensation.fitted,
    )
    if tracking is None and note:  # else its summary line says how it tracked
        print(f'note: {note}', file=sys.stderr)
    return tracking


def _health_verdict(
    health: HealthRecorder,
    args: argparse.Namespace,
    inputs: tuple[str, ...],
    tracking: TrackedStream | None = None,
) -> None:
    """The health monitor's verdict, always (a warning on stderr when it alarms); its
    folder with ``--report`` (and the tracker's audit trail, ``tracking.json``)."""
    document = health.document()
    where = ''
    if args.report is not None:
        extra = None if tracking is None else {'tracking.json': tracking.document()}
        write_health_report(health, args.report, force=args.force, inputs=inputs, extra=extra)
        where = f'; report: {args.report}'
    if tracking is not None and document['alarms']:
        where += ' (watching the tracked tensor: the offset changes were handed to the tracker)'
    say_health(document, where)


def _health_recorder(
    args: argparse.Namespace, geometry: TetraGeometry, compensation: Compensation
) -> HealthRecorder | None:
    """The monitor of every compensation that has a sensor noise (its verdict is printed;
    ``--report`` writes its folder)."""
    config = HealthConfig(false_alarms_per_hour=args.false_alarms_per_hour)
    recorder = health_recorder(geometry, compensation, config)
    if recorder is None and args.report is not None:
        raise InputError('--report needs a calibration and a sensor noise')
    return recorder


def _sigma_text(compensation: Compensation) -> str:
    """What the sigma columns hold, for the summary line."""
    if compensation.sigma is None:
        return 'no sigma columns: give --sensor-noise-nt for them'
    noise_nt = (compensation.sensor_noise_t or 0.0) * NT_PER_T
    terms = (
        'sensor noise and calibration covariance'
        if compensation.with_covariance
        else 'sensor noise only'
        + ('' if compensation.parameters is None else ': the calibration has no covariance')
    )
    return f'sigma from {terms}, noise {noise_nt:.3g} nT from {compensation.noise_source}'
