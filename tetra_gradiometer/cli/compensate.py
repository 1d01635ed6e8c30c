"""``python -m tetra_gradiometer compensate BAG --params FILE --calibration CALIB.yaml --csv OUT.csv [--raw] [--out-bag DIR]``.

Streams the bag's matched magnetometer sets, forms the tensor (eq. 7) and compensates it
(eq. 19) with the calibration's ``k``, ``b``; ``--raw`` skips the compensation.

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
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from ..core import compensate, difference_tensor
from ..core.units import NS_PER_S, NT_PER_T, S_PER_MS, S_PER_NS
from ..errors import InputError
from ..io import conversions as cv
from ..io.bag import STORAGES, BagError, BagWriter, MagneticBag
from ..io.calibration import check_positions, load_calibration
from ..io.outputs import BAG, CSV, OutputError, atomic_output, check_output
from ..io.params import geometry_from_params, load_params

CSV_HEADER = 'stamp_s,' + ','.join(cv.TENSOR_NAMES)
COMPENSATED_TOPIC = f'{cv.NAMESPACE}/gradient/compensated'
RAW_TOPIC = f'{cv.NAMESPACE}/gradient/raw'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='rosbag2 folder (sqlite3 or mcap) following the data contract')
    parser.add_argument('--params', required=True, help='ROS 2 params YAML with sensor_positions')
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
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous CSV at --csv and a previous bag of ours at --out-bag '
        '(anything else there is refused)',
    )
    parser.add_argument(
        '--out-storage',
        choices=sorted(STORAGES),
        default=None,
        help="storage of --out-bag (default: the input's)",
    )
    parser.add_argument(
        '--tolerance-ms',
        type=float,
        default=2.0,
        help='largest spread of the four header stamps in one set (default 2 ms)',
    )
    parser.add_argument(
        '--generic-reader',
        action='store_true',
        help='decode with rosbags and match message by message (slower; same result)',
    )
    progress = parser.add_mutually_exclusive_group()
    progress.add_argument('--progress', dest='progress', action='store_true', default=None)
    progress.add_argument('--no-progress', dest='progress', action='store_false')


def format_rows(stamps_ns: np.ndarray, tensors_t_per_m: np.ndarray) -> str:
    """CSV rows (with trailing newline) for stamps (n,) ns and tensors (n, 3, 3) T/m."""
    seconds, nanoseconds = np.divmod(np.asarray(stamps_ns, dtype=np.int64), NS_PER_S)
    values = tensors_t_per_m.reshape(len(stamps_ns), 9) * NT_PER_T
    row = '%d.%09d,' + ','.join(['%.6f'] * 9)
    table = np.column_stack([seconds, nanoseconds]).astype(object)
    return ''.join(row % (s, ns, *v) + '\n' for (s, ns), v in zip(table, values.tolist()))


def _input_storage(bag: Path) -> str:
    return 'mcap' if any(bag.glob('*.mcap')) else 'sqlite3'


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    if args.csv is None and args.out_bag is None:
        raise InputError('nothing to write: give --csv OUT.csv and/or --out-bag DIR')
    if not args.raw and args.calibration is None:
        raise InputError('--calibration is required (or --raw for the uncompensated tensor)')
    inputs = tuple(p for p in (args.bag, args.params, args.calibration) if p is not None)
    if (
        args.csv is not None
        and args.out_bag is not None
        and Path(args.csv).resolve() == Path(args.out_bag).resolve()
    ):
        raise OutputError('--csv and --out-bag name the same path')
    # Refuse before any work: nothing is read or written when an output is not ours to replace.
    if args.csv is not None:
        check_output(args.csv, CSV, force=args.force, inputs=inputs)
    if args.out_bag is not None:
        check_output(args.out_bag, BAG, force=args.force, inputs=inputs)
    geometry = geometry_from_params(load_params(args.params), source=args.params)
    parameters = None
    if not args.raw:
        calibration = load_calibration(args.calibration)
        check_positions(
            calibration, geometry, source=str(args.calibration), target=str(args.params)
        )
        parameters = calibration.parameters
    bag_path = Path(args.bag)
    topic = RAW_TOPIC if args.raw else COMPENSATED_TOPIC
    n_sets = non_finite = 0
    first = last = None
    with ExitStack() as stack:
        bag = stack.enter_context(MagneticBag(bag_path))
        bag.check_contract()
        handle = writer = None
        if args.csv is not None:
            tmp = stack.enter_context(
                atomic_output(args.csv, CSV, force=args.force, inputs=inputs)
            )
            handle = stack.enter_context(open(tmp, 'w', encoding='ascii', newline='\n'))
            handle.write(CSV_HEADER + '\n')
        if args.out_bag is not None:
            writer = stack.enter_context(
                BagWriter(
                    args.out_bag,
                    storage=args.out_storage or _input_storage(bag_path),
                    force=args.force,
                    inputs=inputs,
                    command='compensate',
                )
            )
        for stamps, fields in bag.iter_sets(
            tolerance_s=args.tolerance_ms * S_PER_MS,
            progress=args.progress,
            fast=not args.generic_reader,
        ):
            finite = np.isfinite(fields).all(axis=(1, 2))
            if not finite.all():  # a NaN/inf reading: drop the set, count it
                non_finite += int((~finite).sum())
                stamps, fields = stamps[finite], fields[finite]
                if not len(stamps):
                    continue
            tensors = difference_tensor(fields, geometry)
            if parameters is not None:
                tensors = compensate(tensors, fields[:, 0, :], parameters, geometry)
            if handle is not None:
                handle.write(format_rows(stamps, tensors))
            if writer is not None:
                writer.write_tensors(topic, stamps, tensors)
            n_sets += len(stamps)
            first = int(stamps[0]) if first is None else first
            last = int(stamps[-1])
        counters = bag.counters
        if n_sets == 0:
            raise BagError(
                f'{bag_path}: every matched set has a non-finite reading ({non_finite} sets)'
            )
    elapsed = time.perf_counter() - started
    kind = 'raw' if args.raw else 'compensated'
    print(
        f'{kind} {n_sets} sets from {bag_path} ({(last - first) * S_PER_NS:.1f} s of data; '
        f'{counters.dropped_messages} messages unmatched, {counters.out_of_order} out of order, '
        f'{non_finite} sets with a non-finite reading skipped) '
        f'in {elapsed:.1f} s ({n_sets / max(elapsed, 1e-9):.0f} sets/s)'
    )
    if args.csv is not None:
        print(f'csv: {args.csv} (stamp_s absolute, nT/m)')
    if args.out_bag is not None:
        print(f'bag: {args.out_bag} ({topic}, T/m)')
    return 0
