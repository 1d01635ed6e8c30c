"""``python -m tetra_gradiometer compensate BAG --params FILE --calibration CALIB.yaml
--csv OUT.csv [--raw] [--out-bag DIR]``.

Streams the bag's matched magnetometer sets, forms the tensor (eq. 7) and compensates it
(eq. 19) with the calibration's ``k``, ``b``; ``--raw`` skips the compensation. The work is
:func:`tetra_gradiometer.io.bag_compensation.compensate_bag`.

CSV (written to a temporary file, renamed into place at the end)::

    stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz

one row per matched set (sets with a non-finite reading are skipped and counted);
``stamp_s`` is the **absolute** header stamp of sensor 1 in
seconds since the Unix epoch, printed exactly from the integer nanoseconds (9 decimals);
``gij = G_ij = dB_i/dx_j`` in **nT/m** (6 decimals), body frame.

``--out-bag DIR`` writes the tensors into a new rosbag2 folder (``--out-storage``, default
the input's storage) as ``/tetra/gradient/compensated`` (``/tetra/gradient/raw`` with
``--raw``): ``sensor_msgs/JointState`` named ``gxx..gzz``, positions in T/m, header stamp =
the set's stamp (``conversions.tensor_msg``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..core.units import S_PER_MS
from ..errors import InputError
from ..io.bag import STORAGES
from ..io.bag_compensation import (
    calibration_parameters,
    check_outputs,
    compensate_bag,
)
from ..io.params import geometry_from_params, load_params
from ._args import add_bag_arguments, add_force_argument, add_progress_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bag_arguments(parser)
    parser.add_argument(
        '--calibration',
        default=None,
        help='calibration YAML (from "calibrate"); required unless --raw',
    )
    parser.add_argument('--csv', default=None, help='CSV to write (stamp_s + 9 components, nT/m)')
    parser.add_argument(
        '--raw', action='store_true', help='write the uncompensated tensor (eq. 7)'
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
    add_progress_arguments(parser)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    if args.csv is None and args.out_bag is None:
        raise InputError('nothing to write: give --csv OUT.csv and/or --out-bag DIR')
    if not args.raw and args.calibration is None:
        raise InputError('--calibration is required (or --raw for the uncompensated tensor)')
    inputs = tuple(p for p in (args.bag, args.params, args.calibration) if p is not None)
    # Refuse before any work: nothing is read or written when an output is not ours to replace.
    check_outputs(args.csv, args.out_bag, force=args.force, inputs=inputs)
    geometry = geometry_from_params(load_params(args.params), source=args.params)
    parameters = (
        None
        if args.raw
        else calibration_parameters(args.calibration, geometry, target=str(args.params))
    )
    counts = compensate_bag(
        args.bag,
        geometry,
        parameters,
        csv=args.csv,
        out_bag=args.out_bag,
        out_storage=args.out_storage,
        tolerance_s=args.tolerance_ms * S_PER_MS,
        fast=not args.generic_reader,
        progress=args.progress,
        force=args.force,
        inputs=inputs,
    )
    elapsed = time.perf_counter() - started
    kind = 'raw' if args.raw else 'compensated'
    counters = counts.counters
    print(
        f'{kind} {counts.n_sets} sets from {Path(args.bag)} ({counts.span_s:.1f} s of data; '
        f'{counters.dropped_messages} messages unmatched '
        f'({counters.evicted_messages} evicted from a full queue), '
        f'{counters.out_of_order} out of order, '
        f'implausible sets dropped: {counts.dropped.text()}) '
        f'in {elapsed:.1f} s ({counts.n_sets / max(elapsed, 1e-9):.0f} sets/s)'
    )
    if counts.skipped_summary:
        print(counts.skipped_summary)
    if args.csv is not None:
        print(f'csv: {args.csv} (stamp_s absolute, nT/m)')
    if args.out_bag is not None:
        print(f'bag: {args.out_bag} ({counts.topic}, T/m)')
    return 0
